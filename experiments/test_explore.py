"""Active exploration (experiments/explore.py): the motion stays inside the joint and torque limits and its speed
bound, a push abandons it with nothing applied, it makes rz observable, and the moving target keeps the loop passive."""
import math

import numpy as np
import pytest

from diagnosis.excite import HoldsConfig
from experiments.bias_map import calibrate, trial_plant
from experiments.explore import (ExploreSettings, Explorer, explore_trial, limits_touched, storage_check)
from experiments.runner import Push

THETA = np.array([0.9, 0.05, -0.03, 0.13])          # Table 5 payload 4
SEED = 4004


@pytest.fixture(scope="module")
def realistic():
    return explore_trial(THETA, SEED, seconds=4.5)


def test_the_exploration_stays_inside_the_joint_and_torque_limits_and_its_speed_bound(realistic):
    rec, ctrl = realistic
    s = ExploreSettings()
    (x,) = rec.exploration
    assert x.status == "applied" and x.end - x.start < 2.0
    margin, ratio = limits_touched(rec, ctrl, x.start, x.end)
    assert margin > 0.05 and ratio < 1.0
    t, angle = np.array(x.angle).T
    assert np.abs(angle).max() == pytest.approx(s.tilt, rel=1e-9)        # it reached the tilt and no further
    assert np.abs(np.diff(angle) / np.diff(t)).max() <= s.speed * (1 + 1e-6)   # the target's speed bound
    sel = (rec.t >= x.start) & (rec.t <= x.end)
    # the ee's own rotation rate stays near the target's (the DS follows it at 8 /s): no jerk beyond the bound
    R = rec.R[sel][::10]                                               # every 10 ms (the realistic q is noisy)
    rate = [math.acos(min(1.0, (np.trace(R[k + 1] @ R[k].T) - 1) / 2)) / 0.01 for k in range(len(R) - 1)]
    assert max(rate) < 1.5 * s.speed
    assert rec.ee_error[-1] < 0.005 and x.angle[-1][1] == 0.0          # back at the task's target


def test_a_push_during_the_exploration_abandons_it_and_applies_nothing(realistic):
    rec0, _ = realistic
    start = rec0.exploration[0].start
    rec, _ = explore_trial(THETA, SEED, pushes=[Push(start + 0.4, (0.0, 20.0, 0.0), 0.3)], seconds=4.5)
    (x,) = rec.exploration
    assert x.status.startswith("abandoned") and x.after is None
    assert x.end - x.start < 1.0                                   # the target turned back at once
    np.testing.assert_array_equal(rec.theta_hat[-1], x.before.mean)  # RME's estimate, nothing from the exploration
    assert x.angle[-1][1] == 0.0


def test_a_second_pose_brings_rz_below_the_target_and_below_the_single_pose_error():
    """On the ideal plant (no sensor bias, the nominal links): the payload's rz from the tilt alone."""
    rec, _ = explore_trial(THETA, SEED, preset="ideal", seconds=4.5)
    (x,) = rec.exploration
    before, after = abs(x.before.mean[3] - THETA[3]), abs(x.after.mean[3] - THETA[3])
    assert after < 0.015 and after < 0.5 * before
    assert x.after.std[3] < 0.5 * x.before.std[3]
    np.testing.assert_array_equal(rec.theta_hat[-1], x.after.mean)


def test_the_moving_target_keeps_the_storage_function_from_rising():
    """Prop. 4.1 with exact compensation on the ideal plant: over every 1 ms step at that step's target, S does not
    increase; energy enters only through the target's motion (positive work)."""
    res = storage_check(THETA)
    assert res["max_rise"] <= 1e-9 and res["target_work"] > 0


def test_settings_are_checked():
    for kwargs in ({"tilt": 1.2}, {"speed": 0.0}, {"axis": (0.0, 0.0, 1.0)}, {"window": 5}, {"pivot": "elbow"}):
        with pytest.raises(ValueError, match=next(iter(kwargs))):
            ExploreSettings(**kwargs)
    with pytest.raises(ValueError, match="settings"):
        Explorer(settings={"tilt": 0.4})


def test_a_calibrated_bias_map_brings_the_explored_rz_below_the_error_without_it():
    """A realistic plant (seed 4000, payload 4 of `python sim.py explore`), its load-free torque map fitted on a separate
    hold log without payload (experiments/bias_map.py) and given to RME: the exploration's rz error falls below half
    of the one without the map."""
    seed = 4000
    rec0, _ = explore_trial(THETA, seed, seconds=4.5)
    model = calibrate(trial_plant(seed), config=HoldsConfig(poses=30, hold=0.35), rng=np.random.default_rng(seed + 2))
    rec, _ = explore_trial(THETA, seed, settings=ExploreSettings(offset_std=None), seconds=4.5, correction=model)
    (x0,), (x,) = rec0.exploration, rec.exploration
    plain, mapped = abs(x0.after.mean[3] - THETA[3]), abs(x.after.mean[3] - THETA[3])
    assert x.status == "applied" and mapped < 0.5 * plain and mapped < 0.01
