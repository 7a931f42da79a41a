"""How soon a change is compensated when the arm is slow to settle: a heavy load sagging a compliant arm far out;
against the reliability benchmark's episodes on the realistic plant."""
import pytest

from experiments.reliability import ReliabilityConfig, run_episode
from tests.helpers import SYNC


@pytest.mark.slow
def test_a_heavy_load_sagging_the_arm_is_compensated_within_300_ms():
    """The reliability benchmark's episode of seed 28: 2.91 kg attached far out, a 22 Nm change; the arm sags and
    creeps back for 0.4 s, so a drift of 3 % of the change is reached only after 420 ms. The allowance that grows with
    the change's square lets the detector estimate it within 300 ms, already within 10 % of the mass."""
    (change,) = run_episode(28, ReliabilityConfig(), rme_settings=SYNC)["changes"]
    assert change["m"] > 2.8 and change["compensated"], change
    assert change["latency_ms"] < 300 and change["right_ms"] < 300, change
