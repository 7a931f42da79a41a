"""How soon a change is compensated when the arm is slow to settle: a heavy load sagging a compliant arm far out;
against a randomised episode of the realistic plant (tests.helpers.found_episode)."""
import pytest

from tests.helpers import SYNC, found_episode, within


@pytest.mark.slow
def test_a_heavy_load_sagging_the_arm_is_compensated_within_300_ms():
    """The randomised episode of seed 28 (tests.helpers.found_episode): 2.91 kg attached far out, a 22 Nm change; the arm sags and
    creeps back for 0.4 s, so a drift of 3 % of the change is reached only after 420 ms. The allowance that grows with
    the change's square lets the detector estimate it within 300 ms, already within 10 % of the mass."""
    (change,) = found_episode(28, settings=SYNC)["scored"]
    assert change["m"] > 2.8 and within(change["m_hat"], change["m"]), change
    assert change["latency_ms"] < 300 and change["right_ms"] < 300, change
