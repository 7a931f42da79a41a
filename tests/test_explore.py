"""Active exploration (experiments/explore.py): the motion stays inside the joint and torque limits and its speed
bound, a push abandons it with nothing applied, it makes rz observable, and the moving target keeps the loop passive."""
import math

import numpy as np
import pytest

from diagnosis.excite import HoldsConfig
from dynamics import Q_READY, Robot
from experiments.bias_map import calibrate, trial_plant
from experiments.explore import ExploreSettings, Explorer
from experiments.explore_demo import explore_trial, limits_touched, storage_check
from experiments.runner import PayloadChange, Push
from rme_settings import RMESettings

THETA = np.array([0.9, 0.05, -0.03, 0.13])          # Table 5 payload 4
SEED = 4004


@pytest.fixture(scope="module")
def realistic():
    return explore_trial(THETA, SEED, seconds=6.0)      # the arm settled again after the exploration


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
    assert x.angle[-1][1] == 0.0 and np.abs(rec.dq[-1]).max() < 0.01   # back at the task's target, at rest,
    k = np.searchsorted(rec.t, x.start)                                 # where the arm held before the motion
    assert abs(rec.ee_error[-1] - rec.ee_error[k]) < 0.002              # (the plant's links are not the model's)
    turned = math.acos(min(1.0, (np.trace(rec.R[-1] @ rec.R[k].T) - 1) / 2))
    assert turned < 0.1 * s.tilt                                        # the hand turned back from its tilt


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


def test_both_windows_refer_to_rmes_reference_level(realistic):
    """The baseline is RME's own reference level: the mean over 2 changes.short consecutive samples of what the
    compensation left, tau_ext - Y(q) phi_hat (recomputed here from the record with the nominal model), taken before
    the exploration started and after the load was compensated, or the raw tau_ext before the attach (0.75 s)."""
    rec, _ = realistic
    (x,), L = rec.exploration, 2 * RMESettings().changes.short
    robot = Robot.panda()
    left = rec.tau_ext - np.array([robot.payload_torque(q, th) for q, th in zip(rec.q, rec.theta_hat)])
    c = np.cumsum(np.vstack([np.zeros(7), left]), axis=0)
    gap = np.abs((c[L:] - c[:-L]) / L - x.base).max(axis=1)     # each window's mean against the baseline
    (k,) = np.flatnonzero(gap < 1e-9)[:1]
    end = rec.t[k + L - 1]
    assert end <= x.t0 and (end < 0.75 or np.all(rec.theta_hat[k:k + L, 0] > 0))


@pytest.mark.slow
def test_the_map_predicts_the_plants_joint_friction_at_creeping_speeds():
    """The map fitted on the load-free holds with friction: at poses near the ready pose and joint speeds of +-0.02 rad/s
    (the arm creeping back to its target), its velocity part is the plant's own Gaz friction (tau_ext sign: -tau_f)
    within 0.01 Nm and a quarter of that friction."""
    plant = trial_plant(SEED)
    model = calibrate(plant, config=HoldsConfig(poses=30, hold=0.35), rng=np.random.default_rng(SEED + 2))
    rng = np.random.default_rng(5)
    q = Q_READY + rng.uniform(-0.03, 0.03, size=(50, 7))
    dq = rng.uniform(-0.02, 0.02, size=(50, 7))
    want = -np.array([plant._friction(v) for v in dq])
    err = model.correction(q, dq) - model.correction(q) - want
    assert np.abs(err).max() < 0.01 and np.sqrt((err ** 2).mean()) < 0.25 * np.sqrt((want ** 2).mean())


def test_settings_are_checked():
    for kwargs in ({"tilt": 1.2}, {"speed": 0.0}, {"axis": (0.0, 0.0, 1.0)}, {"window": 5}, {"pivot": "elbow"},
                   {"reference": 0}, {"reference_tilt": 1}, {"reference_tolerance": 0.0}, {"reference_limit": True},
                   {"reference_attempts": 0}):
        with pytest.raises(ValueError, match=next(iter(kwargs))):
            ExploreSettings(**kwargs)
    with pytest.raises(ValueError, match="settings"):
        Explorer(settings={"tilt": 0.4})


@pytest.mark.slow
def test_a_calibrated_bias_map_brings_the_explored_rz_below_the_error_without_it():
    """A realistic plant (seed 4000, payload 4 of `python sim.py explore`), its load-free torque map (with its joint
    friction) fitted on a separate hold log without payload (experiments/bias_map.py) and given to RME: the
    exploration's rz error falls below half of the one without the map and below 10 mm, its m error below 5 g. The
    load comes at 1.25 s, once the arm has settled from the start: both windows are referred to the still stretch
    before it, and at 0.75 s the arm has not yet been still (a 30-sample reference: 5-10 g of noise in m)."""
    seed, late = 4000, dict(t_attach=1.25, seconds=5.0)
    rec0, _ = explore_trial(THETA, seed, **late)
    model = calibrate(trial_plant(seed), config=HoldsConfig(poses=30, hold=0.35), rng=np.random.default_rng(seed + 2))
    rec, _ = explore_trial(THETA, seed, settings=ExploreSettings(offset_std=None), correction=model, **late)
    (x0,), (x,) = rec0.exploration, rec.exploration
    plain, mapped = abs(x0.after.mean[3] - THETA[3]), abs(x.after.mean[3] - THETA[3])
    assert x.status == "applied" and mapped < 0.5 * plain and mapped < 0.01
    assert abs(x.after.mean[0] - THETA[0]) < 0.005


@pytest.mark.slow
def test_a_load_free_reference_tilt_brings_rz_below_5_mm_where_the_links_errors_hide_it():
    """A realistic plant (seed 4001, payload 4 of `python sim.py explore --seed 1`) whose links' model errors read as
    rz: no second window tells them from the payload's (docs/exploration.md). With reference_tilt the explorer
    first makes the same tilt load-free, once the arm is still, and keeps how tau_ext changed over it; the loaded
    tilt's window is referred to that. The truth is the plant's payload; the control: the same plant without it."""
    seed, late = 4001, dict(t_attach=4.0, seconds=8.5)
    rec0, _ = explore_trial(THETA, seed, seconds=4.5)
    rec, _ = explore_trial(THETA, seed, settings=ExploreSettings(reference_tilt=True), **late)
    (x0,), (ref, x) = rec0.exploration, rec.exploration
    assert ref.reference and ref.status == "recorded" and ref.after is None and ref.end < 4.0
    np.testing.assert_array_equal(rec.theta_hat[rec.t < 4.0], 0.0)        # the reference tilt applies nothing
    assert x.referred and x.status == "applied" and x.end - x.start < 2.0
    plain, referred = abs(x0.after.mean[3] - THETA[3]), abs(x.after.mean[3] - THETA[3])
    assert plain > 0.015 and referred < 0.005, (plain, referred)
    assert abs(x.after.mean[0] - THETA[0]) < 0.01 and np.abs(x.after.mean[1:3] - THETA[1:3]).max() < 0.003


@pytest.mark.slow
def test_a_push_abandons_the_reference_tilt_and_it_is_made_again_once_the_arm_is_still():
    """A push 0.4 s into the reference tilt abandons it with nothing kept; the tilt is made again once all is still,
    and only that one is recorded."""
    seed = 4001
    probe, _ = _referring(seed, [], 2.0)
    start = probe.exploration[0].start
    rec, explorer = _referring(seed, [Push(start + 0.4, (0.0, 20.0, 0.0), 0.3)], 6.0)
    first, again = rec.exploration
    assert first.reference and first.status.startswith("abandoned") and first.end - first.start < 1.0
    assert again.reference and again.status == "recorded" and again.start > first.end
    (q0, _), = explorer.references                                  # the second tilt's, from its window a
    np.testing.assert_array_equal(q0, again.windows[0][0].mean(axis=0))
    np.testing.assert_array_equal(rec.theta_hat, 0.0)


def _referring(seed, events, seconds, switch=None):
    """The realistic plant `seed` held at the ready pose with RME and an Explorer(reference_tilt=True); events: payload
    changes; switch (t, q): at t the task's target becomes the ee pose at q. (Record, Explorer)."""
    from cpic import CPIC, Attractor
    from experiments.runner import run
    from rme import RME
    plant = trial_plant(seed)
    robot = plant.robot
    ctrl, explorer = CPIC(robot, Attractor(*robot.ee_pose(Q_READY))), Explorer(ExploreSettings(reference_tilt=True))

    def step(k, sample):
        if switch is not None and k == int(round(switch[0] / plant.dt)):
            ctrl.policy = Attractor(*robot.ee_pose(switch[1]))
    rec = run(plant, ctrl, seconds, estimator=RME(robot, rng=np.random.default_rng(seed + 1)), events=events,
              q0=Q_READY, explorer=explorer, before_step=step)
    return rec, explorer


@pytest.mark.slow
def test_a_reference_tilt_is_made_once_and_serves_only_its_own_start_pose():
    """The reference is recorded at the ready pose; the task then moves its target 0.15 rad away on joints 2 and 4
    and a load is hung on there: no second reference tilt, and the load's exploration is not referred to the one
    from another pose (it keeps the wider offset prior)."""
    q1 = Q_READY + np.array([0.0, 0.15, 0.0, -0.15, 0.0, 0.0, 0.0])
    rec, explorer = _referring(4001, [PayloadChange(5.0, THETA[0], THETA[1:])], 9.0, switch=(3.0, q1))
    ref, *rest = rec.exploration
    assert ref.reference and ref.status == "recorded" and ref.end < 3.0 and len(explorer.references) == 1
    assert rest and not any(x.reference for x in rest) and rest[0].status == "applied" and not rest[0].referred


@pytest.mark.slow
def test_no_reference_tilt_with_a_load_on_the_hand():
    """A tool held from the start, which RME takes for the sensor's bias: the tilt's change (0.8 kg, 8 cm out) is
    beyond reference_limit, so nothing is kept and no tilt follows. A load hung on before the arm is first still is
    compensated at once: no reference tilt at all."""
    rec, explorer = _referring(5005, [PayloadChange(0.0, 0.8, (0.08, 0.0, 0.03))], 6.0)
    (x,) = rec.exploration
    assert x.reference and x.status.startswith("refused") and explorer.references == []
    rec, explorer = _referring(4001, [PayloadChange(0.3, THETA[0], THETA[1:])], 4.5)
    assert rec.exploration and not any(x.reference for x in rec.exploration) and explorer.references == []


@pytest.mark.slow
def test_a_policy_change_while_a_reference_tilt_returns_keeps_its_outcome():
    """The task switches to a new Attractor 0.2 s before a reference tilt is back: the tilt ends at once, still
    "recorded" (or "refused", with a tool on the hand), and no other reference tilt follows."""
    for seed, events, outcome in ((4001, [], "recorded"), (5005, [PayloadChange(0.0, 0.8, (0.08, 0.0, 0.03))], "refused")):
        probe, _ = _referring(seed, events, 3.5)
        end = probe.exploration[0].end
        rec, explorer = _referring(seed, events, end + 4.0, switch=(end - 0.2, Q_READY))
        (x,) = rec.exploration
        assert x.reference and x.status.startswith(outcome) and x.end == pytest.approx(end - 0.2, abs=2e-3), x.status
        assert len(explorer.references) == (outcome == "recorded")


@pytest.mark.slow
def test_a_faulty_sample_in_the_explorations_window_is_dropped_as_rme_drops_it():
    """A tau_ext sample that is not finite, 20 ms before the exploration starts (inside its window at the start pose):
    RME drops it and so does the explorer, whose sample count stays RME's; the exploration ends as it does without
    the fault (the same outcome, estimates within a millimetre and a gram; estimates applied on their sample)."""
    from cpic import CPIC, Attractor
    from experiments.runner import run
    from rme import RME, RMESettings
    from sim import Plant, PlantConfig

    def trial(fault):
        rng = np.random.default_rng(SEED)                           # explore_trial's plant
        plant = Plant(PlantConfig.preset("realistic", rng), rng=rng)
        robot = plant.robot
        ctrl = CPIC(robot, Attractor(*robot.ee_pose(Q_READY)))
        rme = RME(robot, settings=RMESettings(asynchronous=False), rng=np.random.default_rng(SEED + 1))
        explorer = Explorer(ExploreSettings())

        def step(k, sample):
            if k == fault:
                sample.tau_ext = np.full(robot.n, np.nan)
        rec = run(plant, ctrl, 4.5, estimator=rme, events=[PayloadChange(0.75, THETA[0], THETA[1:])], q0=Q_READY,
                  explorer=explorer, before_step=step)
        return rec, rme, explorer
    (clean,) = trial(None)[0].exploration
    rec, rme, explorer = trial(int(round((clean.start - 0.02) * 1000)))
    (x,) = rec.exploration
    assert rme.dropped == 1 and explorer.t == pytest.approx((len(rec.t) - 1) * 1e-3)
    assert x.status == clean.status == "applied" and x.start == pytest.approx(clean.start, abs=0.005)
    np.testing.assert_allclose(x.after.mean, clean.after.mean, rtol=0, atol=1e-3)
