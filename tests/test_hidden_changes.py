"""Changes a push hides from the detector (made while it holds the arm, or read against its level), healed once the
arm rests: a load changed or removed under a push, a small load left after a partial removal; against the simulated
plant's truth and the randomised episodes they were found in (tests.helpers.found_episode)."""
import pytest

from experiments.runner import PayloadChange, Push
from tests.helpers import SYNC, found_episode, hold, within


@pytest.mark.slow
def test_changes_during_a_long_push_are_healed_once_the_arm_rests():
    """The randomised episode of seed 93: 1.66 kg attached, then 0.38 kg and 2.01 kg while a 41 N push
    holds the arm aside for 1.6 s. The first level was never seen at rest before the first load; the level the
    compensation should leave (the one before the change) must still be known, so that after the push the monitor
    finds the compensated 1.62 kg inconsistent and heals it to the 2.01 kg carried."""
    ep = found_episode(93)
    last = ep["scored"][-1]
    assert within(last["m_hat"], last["m"]), ep["changes"]
    assert ep["final_error_mm"] < 10.0


@pytest.mark.slow
def test_a_removal_after_a_misread_load_is_healed_once_the_arm_rests():
    """The randomised episode of seed 6: a 2.39 kg load is read 1.51 kg at rest and then removed; no
    level had been seen at rest before, so the monitor's first level is judged against the compensation it has (not
    only the strict test for an unloaded start) and the phantom 1.5 kg is withdrawn."""
    ep = found_episode(6)
    assert within(ep["scored"][-1]["m_hat"], 0.0), ep["scored"]
    assert ep["final_error_mm"] < 10.0


@pytest.mark.slow
@pytest.mark.parametrize("seed", [39, 100_046])
def test_a_load_removed_under_a_push_is_withdrawn_at_rest(seed):
    """Randomised episodes (seeds 39 and 100046): a load attached (39: read 0.36 kg against the
    level of a 21 N push holding the arm) and removed under a push. At rest tau_ext is the sensor's bias (46: and a
    5 N upward push until 4 s): the compensation is withdrawn, and the level known from before the load is kept, so
    the upward push's release is not read as a 0.56 kg load centred below the flange."""
    ep = found_episode(seed, settings=SYNC)
    assert ep["scored"][0]["m_hat"] > 0.3 and within(ep["scored"][-1]["m_hat"], 0.0), ep["scored"]
    assert ep["final_error_mm"] < 10.0


@pytest.mark.slow
def test_a_small_load_left_after_a_partial_removal_under_a_push_is_not_withdrawn():
    """1.2 kg goes to 0.3 kg under a 30 N push, the check of a slow arm off: at rest the residual is far from the
    level known, tau_ext small as a bias, yet the estimate against no payload explains 81 %: not withdrawn (0 kg for
    1.3 s), but estimated against the level known, 0.3 s later."""
    from dataclasses import replace
    events = [PayloadChange(1.0, 1.2, (0.02, -0.01, 0.05)), Push(2.6, (30.0, 0.0, 0.0), 1.6, body="link7",
                                                                 offset=(0.0, 0.0, 0.107)),
              PayloadChange(3.0, 0.3, (0.02, -0.01, 0.05))]
    rec, est = hold(3, 7.0, events, settings=replace(SYNC, monitor_slow=(0.0, 0.6)))
    assert not any(e.kind == "withdrawn" for e in est.history), [(e.t, e.kind, e.mean[0]) for e in est.history]
    assert rec.theta_hat[rec.at(4.5):, 0].min() > 0.25 and within(rec.theta_hat[-1, 0], 0.3)
