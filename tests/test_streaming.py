"""Streaming RME in closed loop against the simulated plant's truth: removals right after an estimate, heavy loads on a
slowly settling arm, pushes and their releases, a phantom corrected, a limit cycle, a person holding the arm at
start-up, a load hung on during a push, a press; fresh episodes of each plant with stated bounds."""
import numpy as np
import pytest

from cpic import CPIC, Attractor
from dynamics import Q_READY, Robot
from experiments.reliability import ReliabilityConfig, reliability
from experiments.runner import PayloadChange, Push, run
from nn_train import DataConfig, random_pose
from rme import RME
from sim import Plant, PlantConfig
from tests.helpers import SYNC, hold, within



@pytest.mark.slow
def test_removal_right_after_the_estimate_at_rest_is_compensated():
    load = PayloadChange(1.0, 1.0, (0.03, -0.02, 0.1))
    _, est = hold(3, 3.5, [load])
    t_rest = next(e.t for e in est.history if e.kind == "at rest")
    rec, est = hold(3, t_rest + 3.0, [load, PayloadChange(t_rest + 0.3, 0.0)])
    assert within(rec.theta_hat[rec.at(t_rest + 0.25), 0], 1.0)            # the load was compensated ...
    assert within(rec.theta_hat[-1, 0], 0.0)                               # ... and its removal is too
    assert np.linalg.norm(rec.p[-1] - rec.target[-1]) < 0.01


@pytest.mark.slow
def test_heavy_load_on_a_slowly_settling_arm_is_compensated():
    """2.5 kg at a pose where the compliant arm settles for seconds: estimated as the level settles, again at rest."""
    q0 = random_pose(Robot.panda(), np.random.default_rng(28), DataConfig())
    rec, est = hold(28, 6.0, [PayloadChange(1.5, 2.5, (0.07, -0.1, 0.01))], q0=q0)
    assert within(rec.theta_hat[-1, 0], 2.5), [(e.kind, e.mean.round(3).tolist()) for e in est.history]
    assert 1e3 * np.linalg.norm(rec.p[-1] - rec.target[-1]) < 10.0


@pytest.mark.slow
@pytest.mark.parametrize("force", [(0.0, 0.0, 25.0), (0.0, 0.0, 40.0)])
def test_release_of_an_upward_push_is_not_applied(force):
    """An upward push lifts the arm; its release drops tau_ext back to where it was before the push, which a detector
    referred to the pushed state reads as a new load. RME must not compensate anything."""
    rec, est = hold(5, 4.0, [Push(1.0, force, 1.0, body="link7", offset=(0.0, 0.0, 0.107))])
    applied = [e for e in est.history if e.accepted and e.mean[0] > 0.05]
    assert not applied, [(e.t, e.kind, e.mean.round(3).tolist()) for e in applied]
    assert np.abs(rec.theta_hat[:, 0]).max() <= 0.05
    # a lift needs a negative mass: the push is not even estimated, nor is its release
    assert not est.history, [(e.t, e.kind, e.reason) for e in est.history]


@pytest.mark.slow
def test_a_push_tilted_from_vertical_is_not_a_payload():
    """Gravity pulls straight down: a push 15-25 deg off vertical, held 1.5 s at the flange, is judged a wrench, not
    estimated."""
    _, est = hold(5, 4.0, [Push(1.0, (-2.5, 3.0, -20.0), 1.5, body="link7", offset=(0.0, 0.0, 0.107))])
    assert not est.history and est.changes_not_payload >= 1, [(e.t, e.kind, e.mean.round(2)) for e in est.history]


@pytest.mark.slow
def test_a_wrong_compensation_is_corrected_at_rest():
    """A phantom estimate of 1.5 kg forced in while nothing is attached: the level it leaves is the return to no
    payload, which the model restores."""
    rng = np.random.default_rng(99)
    plant = Plant(PlantConfig.realistic(rng), rng=rng)
    est2 = RME(plant.robot, settings=SYNC, rng=np.random.default_rng(1))
    ctrl = CPIC(plant.robot, Attractor(*plant.robot.ee_pose(Q_READY)))
    rec = run(plant, ctrl, 1.0, est2, [], q0=Q_READY)                 # learns the unloaded level at rest
    est2.theta, est2._phi = np.array([1.5, 0.0, 0.0, 0.1]), np.array([1.5, 0.0, 0.0, 0.15])
    rec = run(plant, ctrl, 3.0, est2, first=rec.last)
    assert within(rec.theta_hat[-1, 0], 0.0), [(e.kind, e.mean.round(3).tolist()) for e in est2.history]


@pytest.mark.slow
def test_small_reliability_run_is_safe_and_compensates_what_rests():
    """Three load and three push-only tuning episodes of the reliability benchmark, RME applying each estimate on its
    sample (SyncRME: with RME's default, an estimate waits for its own wall time, so a run depends on the machine)."""
    res = reliability(episodes=3, split="tuning", estimator="tests.helpers:SyncRME", cfg=ReliabilityConfig(),
                      log=lambda *a: None)
    s = res["summary"]
    assert s["nan"] == 0 and s["torque_over_limit"] == 0 and s["joint_limit_violations"] == 0
    assert s["compensated"]["all"]["yes"] == s["compensated"]["all"]["count"], s["compensated"]
    assert s["final_error_over_target"] == 0, res["episodes"]


@pytest.mark.slow
def test_limit_cycle_with_a_load_recovers_on_the_default_seed():
    """The demo's case (`python sim.py limit-cycle`, realistic preset, seed 0): 2 kg attached while the arm cycles:
    the mass is compensated and the arm cycles again."""
    from experiments.scenarios import Args, limit_cycle_policy
    from experiments.scenarios import run as scenario
    cycle = limit_cycle_policy()
    rec = scenario(Args(seed=0), 12.0, [(4.0, np.array([2.0, 0.04, 0.0, 0.10]), None)], policies=[(0.0, cycle)])
    assert within(rec.theta_hat[-1, 0], 2.0)
    late = rec.t >= 10.0
    u = rec.p[late] - cycle.center
    turns = np.ptp(np.unwrap(np.arctan2(u[:, 2], u[:, 1]))) / (2 * np.pi)
    assert turns > 0.2                                               # 2 s at 1/6 turn/s: about a third of a turn
    radius = np.hypot(u[:, 1], u[:, 2])
    assert np.sqrt(np.mean((radius - cycle.radius) ** 2)) < 0.005


@pytest.mark.slow
def test_a_load_on_a_cycling_arm_is_compensated_within_half_a_second():
    """On fresh sensor seeds (never used by a benchmark or the design) and fresh loads, the cycling arm's level
    never settles (friction drifts with the speed): the load is still compensated, within 10 %, 0.5 s after it
    arrives, at the latest, on every seed."""
    from experiments.scenarios import Args, limit_cycle_policy
    from experiments.scenarios import run as scenario
    cycle, rng = limit_cycle_policy(), np.random.default_rng(77)
    for seed in (77, 78):
        load = np.array([rng.uniform(1.0, 2.5), *rng.uniform(-0.05, 0.05, 2), rng.uniform(0.0, 0.12)])
        rec = scenario(Args(seed=seed), 5.0, [(4.0, load, None)], policies=[(0.0, cycle)])
        assert within(rec.theta_hat[rec.at(4.5), 0], load[0]), (seed, load, rec.theta_hat[rec.at(4.5)])


def first_applied(est):
    return min((e.applied for e in est.history if e.accepted and e.applied is not None), default=np.inf)


@pytest.mark.slow
def test_a_person_holding_the_arm_from_start_up_is_not_taken_for_the_sensors_bias():
    """A person holds the hand aside with 34 N from 0.3 s to 2.5 s, so the first level RME sees at rest is that push's
    (about 17 Nm, no payload) and is taken for the bias; 2 kg is hung on just before the release. Against the push's
    level the load is no payload either, but against none at all it is a clear one, and no sensor's bias lies
    monitor_far from zero: the load is compensated (read light: the bias is in its level) and the hand holds its
    target. Before, it was never compensated (40 mm off)."""
    events = [Push(0.3, (-10.0, -26.0, 20.0), 2.2, body="link7", offset=(0.0, 0.0, 0.107)),
              PayloadChange(2.4, 2.0, (0.05, 0.03, 0.08))]
    rec, est = hold(5, 6.0, events)
    applied = [(round(e.t, 2), e.kind, round(e.mean[0], 3)) for e in est.history if e.accepted]
    assert applied and 1.6 < rec.theta_hat[-1, 0] < 2.2, applied
    assert np.linalg.norm(rec.p[-1] - rec.target[-1]) < 0.01


@pytest.mark.slow
def test_a_load_hung_on_during_a_push_is_compensated_soon_after_the_release():
    """A person pushes the hand aside with 36 N for 1.5 s and a 1.5 kg load is hung on it meanwhile: judged a
    wrench while the push lasts, the load is compensated within a second of the release and refined at rest."""
    release = 2.5
    events = [Push(1.0, (35.0, -10.0, 0.0), release - 1.0, body="link7", offset=(0.0, 0.0, 0.107)),
              PayloadChange(1.3, 1.5, (0.08, -0.03, 0.05))]
    rec, est = hold(3, 5.0, events)
    assert first_applied(est) - release < 1.0, [(e.t, e.kind, e.mean.round(3)) for e in est.history]
    assert abs(rec.theta_hat[-1, 0] - 1.5) < 0.075


@pytest.mark.slow
def test_a_press_straight_down_is_taken_for_a_load_and_withdrawn_at_its_release():
    """To the torques a 25 N press straight down at the flange is a 2.5 kg load centred below it: compensated as one
    while it lasts, withdrawn within 200 ms of its release, the hand rising less than 10 mm meanwhile."""
    release = 2.5
    rec, est = hold(2, 4.0, [Push(1.0, (0.0, 0.0, -25.0), release - 1.0, body="link7", offset=(0.0, 0.0, 0.107))])
    back = [e for e in est.history if e.kind == "back" and e.t > release]
    assert back and back[0].applied - release < 0.2 and within(rec.theta_hat[-1, 0], 0.0), \
        [(e.t, e.kind, e.mean.round(3)) for e in est.history]
    after = (rec.t > release) & (rec.t < release + 0.5)
    assert 1e3 * (rec.p[after, 2] - rec.target[after, 2]).max() < 10.0


@pytest.mark.slow
@pytest.mark.parametrize("plant", ["realistic", "harsh"])
def test_fresh_episodes_of_each_plant_meet_stated_bounds(plant):
    """Six load and six push-only episodes of each plant, drawn from seeds no benchmark report or design used
    (the test split's indices from 1000 on): every change the arm rested after is compensated but at most one, at
    most one sideways push in ten is (the benchmark's test split: 0-8 %, docs/benchmarks.md), no load is ignored on
    a calm arm for more than 1.5 s, no episode with more than 5 estimates per change or push (the detection, again
    as the arm sags, at rest; not the same level estimated again every few milliseconds), nothing unsafe."""
    from experiments.reliability import run_episode, summarise
    cfg = ReliabilityConfig()
    loads = [run_episode(("test", plant, "load", 1000 + i, cfg, "tests.helpers:SyncRME")) for i in range(6)]
    pushes = [run_episode(("test", plant, "push", 1000 + i, cfg, "tests.helpers:SyncRME")) for i in range(6)]
    s = summarise(loads, pushes, cfg)
    done = s["compensated"]["all"]
    assert done["count"] - done["yes"] <= 1, s["compensated"]
    side = s["pushes"]["sideways"]
    assert side["yes"] <= 0.1 * side["count"] and s["ignored_load"]["over_target"] == 0, s
    assert s["nan"] == 0 and s["torque_over_limit"] == 0 and s["joint_limit_violations"] == 0
    assert s["estimates_per_event_max"] <= 5, s               # (each change estimated a few times, never in a loop)


@pytest.mark.slow
def test_the_estimate_at_rest_waits_for_a_push_holding_the_arm_still():
    """A load (0.5-2.5 kg) is estimated at its detections on a short window and owed an estimate on the full one at
    rest; a sideways push (20-30 N) holding the hand from just after the last detection for 3 s makes the arm still
    under it, but that level is the push's: nothing is estimated while it acts, and the load is right after."""
    rng = np.random.default_rng(2028)
    for seed in range(2):
        m, r = rng.uniform(0.5, 2.5), rng.uniform(-0.08, 0.08, 3)
        side = rng.uniform(20.0, 30.0) * np.array([np.cos(a := rng.uniform(0, 2 * np.pi)), np.sin(a), 0.0])
        _, est = hold(50 + seed, 1.5, [PayloadChange(1.0, m, tuple(r))])
        t0 = max(e.t for e in est.history if e.kind == "detection") + 0.03   # (the same draws: the same detections)
        events = [PayloadChange(1.0, m, tuple(r)), Push(t0, tuple(side), 3.0, body="link7", offset=(0.0, 0.0, 0.107))]
        rec, est = hold(50 + seed, t0 + 5.0, events)
        assert np.abs(rec.dq[rec.at(t0 + 2.4):rec.at(t0 + 3.0)]).max() < 0.01      # the push holds the arm still
        during = [(round(e.t, 3), e.kind, e.mean.round(3).tolist()) for e in est.history if t0 + 0.03 < e.t < t0 + 3.0]
        assert not during, (m, side, during)
        assert within(rec.theta_hat[-1, 0], m), (m, [(round(e.t, 3), e.kind, e.mean.round(3).tolist())
                                                     for e in est.history])
