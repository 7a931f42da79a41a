"""Streaming RME in closed loop: the consistency monitor heals what the detector misses, removals right after an
estimate, heavy loads on a slowly settling arm, push releases, absurd samples; against the simulated plant's truth."""
import numpy as np
import pytest

from cpic import CPIC, Attractor
from detector import Detector, DetectorSettings
from dynamics import Q_READY, Robot
from experiments.reliability import ReliabilityConfig, reliability
from experiments.runner import PayloadChange, Push, run
from nn_train import DataConfig, random_pose
from rme import RME, RMESettings
from sim import Plant, PlantConfig
from tests.helpers import SYNC, found_episode, hold, synthetic_stream, within


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
    """2.5 kg at a pose where the compliant arm settles for seconds: no settled window for the detector, so the
    monitor must catch it once the arm is calm."""
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
    """Gravity pulls straight down: a push 15-25 deg off vertical, held 1.5 s at the flange, is not estimated, even
    where its torques are explained to 97 % by a point mass (the randomised push-only episode of seed 50028: a push
    (1.8, 3.9, -10.9) N was applied as 0.92 kg when only that share was tested)."""
    _, est = hold(5, 4.0, [Push(1.0, (-2.5, 3.0, -20.0), 1.5, body="link7", offset=(0.0, 0.0, 0.107))])
    # the push, and its release if the arm swinging back has not yet returned the level to the one before it
    assert not est.history and est.changes_not_payload in (1, 2), [(e.t, e.kind, e.mean.round(2)) for e in est.history]
    history = found_episode(50_028, loads=False)["est"].history
    assert not history, [(e.t, e.kind, e.mean.round(2)) for e in history]


def test_a_heavy_load_missed_during_pushes_is_healed_although_its_sag_moved_the_bias():
    """The randomised episode of seed 42 (tests.helpers.found_episode): 2.6 kg attached, two pushes before the arm settles, so the detector never
    fires; at rest the monitor's estimate leaves 0.41 Nm of a 9.4 Nm gap (the load's sag moved the arm within the
    same pose tolerance, and the sensor bias with it). That is consistent; refusing it kept the load uncompensated."""
    last = found_episode(42)["scored"][-1]
    assert last["m"] > 2.5 and within(last["m_hat"], last["m"]), last


def test_a_load_read_light_on_a_creeping_arm_is_estimated_again_once_calm():
    """The randomised episode of seed 100061: 1.33 kg read 1.18 kg at the detection; the arm then creeps at 0.01-0.02
    rad/s for seconds, never still (< 0.01 rad/s) for a whole window, and the 0.15 kg left stays below the monitor's
    0.3 Nm there. In the last 0.5 s before the estimate at rest expires, an arm calm below 0.02 rad/s will do."""
    last = found_episode(100_061)["scored"][-1]
    assert abs(last["m"] - 1.33) < 0.01 and within(last["m_hat"], last["m"]), last


@pytest.mark.slow
def test_a_load_read_light_in_motion_is_estimated_again_after_a_push_kept_the_arm_from_resting():
    """The randomised episode of seed 100019: 0.975 kg read 0.844 kg at the detection (the arm moving at 0.1 rad/s, joint
    friction holding part of it); a 32 N push starts just before the arm has rested for a whole window and lasts
    until after the estimate at rest would expire; the 0.13 kg left is under the monitor's 0.3 Nm at that pose. The
    push's release lets the arm rest only after the 2 s refine_within: the estimate at rest waits for it (up to 6 s).
    Seed 100030: a removal read as 0.09 kg left, then a 33 N push for 1.3 s: healed the same way."""
    for seed, m in ((100_019, 0.975), (100_030, 0.0)):
        change = found_episode(seed)["scored"][-1]
        assert abs(change["m"] - m) < 0.01 and within(change["m_hat"], m), (seed, change)


@pytest.mark.slow
def test_a_change_the_detector_misses_is_healed_once_the_arm_rests():
    blind = RMESettings(asynchronous=False, detector=DetectorSettings(activation_threshold=1e6))   # never fires
    rec, est = hold(7, 4.0, [PayloadChange(1.0, 0.9, (0.05, -0.03, 0.13))], settings=blind)
    healed = [e for e in est.history if e.kind == "monitor" and e.accepted]
    assert healed and healed[0].t < 1.0 + 1.5                      # within about 1 s of the arm coming to rest
    assert within(rec.theta_hat[-1, 0], 0.9)
    off = RMESettings(asynchronous=False, monitor=False, detector=blind.detector)
    rec_off, _ = hold(7, 4.0, [PayloadChange(1.0, 0.9, (0.05, -0.03, 0.13))], settings=off)
    assert rec_off.theta_hat[-1, 0] == 0.0                           # without the monitor the load stays missed


@pytest.mark.slow
def test_a_wrong_compensation_is_corrected_at_rest():
    """A phantom estimate of 1.5 kg forced in while nothing is attached is withdrawn by the monitor."""
    rng = np.random.default_rng(99)
    plant = Plant(PlantConfig.realistic(rng), rng=rng)
    est2 = RME(plant.robot, settings=SYNC, rng=np.random.default_rng(1))
    ctrl = CPIC(plant.robot, Attractor(*plant.robot.ee_pose(Q_READY)))
    rec = run(plant, ctrl, 1.0, est2, [], q0=Q_READY)                 # learns the unloaded level at rest
    est2.theta, est2._phi = np.array([1.5, 0.0, 0.0, 0.1]), np.array([1.5, 0.0, 0.0, 0.15])
    rec = run(plant, ctrl, 3.0, est2, first=rec.last)
    assert within(rec.theta_hat[-1, 0], 0.0), [(e.kind, e.mean.round(3).tolist()) for e in est2.history]


def test_an_absurd_sample_is_dropped_and_detection_goes_on():
    robot = Robot.panda()
    est = RME(robot, weights=None, settings=SYNC, rng=np.random.default_rng(0))
    noise = np.random.default_rng(1)
    theta = np.array([0.8, 0.02, 0.0, 0.1])
    for k in range(3000):
        tau = robot.payload_torque(Q_READY, theta) if k >= 1500 else np.zeros(7)
        tau = tau + 0.01 * noise.normal(size=7)
        if k in (700, 701):
            tau = np.full(7, 1e200) if k == 700 else np.full(7, np.nan)
        comp = est.update(Q_READY, np.zeros(7), tau)
        assert np.all(np.isfinite(comp))
    assert est.dropped == 2
    assert within(est.theta[0], 0.8) and any(e.kind == "detection" for e in est.history)
    with pytest.raises(ValueError, match="tau_ext"):
        Detector().update(np.full(7, 1e200), force=np.zeros(3))


@pytest.mark.parametrize("algorithm", ["referred", "as_printed"])
@pytest.mark.parametrize("before", [700, 300, 1001, 1002])    # full, partly filled, around a re-basing of the sums
def test_detector_shift_equals_a_detector_fed_the_shifted_samples(before, algorithm):
    rng = np.random.default_rng(4)
    tau, F = 0.01 * rng.normal(size=(before, 7)), rng.normal(size=(before, 3))   # quiet: no status kept
    shifts = [(rng.normal(size=7), rng.normal(size=3)) for _ in range(2)]
    a, b, unshifted = (Detector(DetectorSettings(algorithm=algorithm)) for _ in range(3))
    for k in range(before):
        a.update(tau[k], force=F[k])
        unshifted.update(tau[k], force=F[k])
        b.update(tau[k] - sum(s[0] for s in shifts), force=F[k] - sum(s[1] for s in shifts))
    for d_tau, d_F in shifts:                      # twice: the second on sums the first already changed
        a.shift(d_tau, d_F)
    if a.count >= a.settings.window:               # status: the last evaluation, on the samples as they were
        for key in ("rapid", "stabilisation", "force_change"):
            np.testing.assert_array_equal(a.status[key], unshifted.status[key])
    new_tau, new_F = rng.normal(size=(600, 7)), rng.normal(size=(600, 3))
    for k in range(600):
        assert a.update(new_tau[k], force=new_F[k]) == b.update(new_tau[k], force=new_F[k])
        if a.count >= a.settings.window:
            for key in ("rapid", "stabilisation", "force_change"):
                np.testing.assert_allclose(a.status[key], b.status[key], rtol=1e-9, atol=1e-9)


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
    """The demo's case (`python sim.py limit-cycle`, realistic preset, seed 0): 2 kg attached while the arm cycles.
    The detector misses it in motion; the arm sags towards a spurious attractor, slows, and once it is calm the
    monitor estimates the load: the mass is compensated and the arm cycles again."""
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


def first_applied(est):
    return min((e.applied for e in est.history if e.accepted and e.applied is not None), default=np.inf)


@pytest.mark.slow
def test_a_load_added_during_a_push_is_compensated_while_the_arm_returns():
    """A person pushes the hand aside with 36 N for 1.5 s and a 1.5 kg load is hung on it meanwhile. After the
    release the arm swings back for about a second; the monitor checks it once it is slower than 0.1 rad/s, not
    only once calm, and compensates the load about 0.5 s sooner, then refines at rest. The control: the same run
    with that check off (monitor_slow speed 0) compensates only once the arm is calm."""
    from dataclasses import replace
    release = 2.5
    events = [Push(1.0, (35.0, -10.0, 0.0), release - 1.0, body="link7", offset=(0.0, 0.0, 0.107)),
              PayloadChange(1.3, 1.5, (0.08, -0.03, 0.05))]
    rec, est = hold(3, 5.0, events)
    _, off = hold(3, 5.0, events, settings=replace(SYNC, monitor_slow=(0.0, 0.6)))
    t, t_off = first_applied(est), first_applied(off)
    assert t - release < 1.1 and t_off - t > 0.3, (t, t_off)
    kinds = [e.kind for e in est.history if e.accepted]
    assert kinds[0] == "monitor" and "at rest" in kinds, [(e.t, e.kind, e.mean.round(3)) for e in est.history]
    assert abs(rec.theta_hat[-1, 0] - 1.5) < 0.05


def test_a_load_on_a_resting_arm_is_the_detectors_to_estimate():
    """The sag after a load is hung on a resting arm is slower than 0.1 rad/s: the check of a slow arm must leave
    a change still in the detector's window to the detector, whose window is referred to the torque before it."""
    rec, est = hold(7, 2.0, [PayloadChange(1.0, 0.6, (0.10, 0.05, 0.05))])
    assert est.history and est.history[0].kind == "detection", [(e.t, e.kind, e.mean.round(3)) for e in est.history]
    assert abs(est.history[0].mean[0] - 0.6) < 0.06


@pytest.mark.slow
def test_a_load_first_seen_at_the_first_rest_is_estimated_though_the_bias_bends_its_wrench():
    """The randomised episode of seed 100018: pushes keep the arm from resting until 1.06 kg hangs on
    it, so the first level RME sees is the load's plus the sensor's unknown bias, judged against no payload. That
    bias tilts the level's wrench by 2.1 N of side force for 7.8 N down, beyond the 0.5 N + 12 % a payload change
    may carry; at the first level the side test allows App. A's 2.5 N instead. Without that the load was taken for
    the bias and never compensated; with it, it is (read 12 % light: the bias is in the level)."""
    ep = found_episode(100018)
    assert 0.85 < ep["scored"][-1]["m_hat"] < 1.2, ep["scored"]


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
def test_after_a_start_up_hold_a_press_is_still_held_and_a_first_level_refused_is_doubtful_too():
    """The doubtful first level's two other sides. After the same start-up hold, a person presses 25 N down on the
    hand for 1.5 s: against no payload (the bias in it bends its wrench) it is still a press through the flange's
    line, held, never applied. And a start-up press 0.5 m out from the hand, whose first level is payload-like but its
    estimate refused (CoM beyond max_com), is doubtful as well: 2 kg hung on at its release is compensated."""
    hold_aside = Push(0.3, (-10.0, -26.0, 20.0), 2.2, body="link7", offset=(0.0, 0.0, 0.107))
    rec, est = hold(5, 7.0, [hold_aside, Push(3.5, (2.0, 0.0, -25.0), 1.5, body="link7", offset=(0.0, 0.0, 0.107))])
    assert not any(e.accepted for e in est.history) and np.all(rec.theta_hat[:, 0] == 0.0), \
        [(round(e.t, 2), e.kind, round(e.mean[0], 3)) for e in est.history]
    far_out = Push(0.3, (0.0, 0.0, -20.0), 2.2, body="link7", offset=(0.5, 0.0, 0.107))
    rec, est = hold(5, 6.0, [far_out, PayloadChange(2.4, 2.0, (0.05, 0.03, 0.08))])
    assert 1.6 < rec.theta_hat[-1, 0] < 2.2, [(round(e.t, 2), e.kind, e.accepted, round(e.mean[0], 3))
                                              for e in est.history]
    assert np.linalg.norm(rec.p[-1] - rec.target[-1]) < 0.01


@pytest.mark.slow
def test_a_level_refused_on_a_slow_arm_is_not_estimated_again_and_again():
    """A person presses down 20 N on a handle 0.55 m out from the hand for 4.5 s: to the torques a payload with its
    CoM 0.39 m out along the ee's x and y, beyond max_com, so every estimate of it is refused (one 0.45 m out lies
    within 0.02 m of max_com, which the estimate at the detection may not see). The arm, held aside, creeps slower than
    0.1 rad/s; the check of a slow arm tries that level once, not every 200 ms while it stays (the control: the
    same run with that check off)."""
    from dataclasses import replace
    push = [Push(1.0, (0.0, 0.0, -20.0), 4.5, body="link7", offset=(0.55, 0.0, 0.107))]
    _, est = hold(3, 6.0, push)
    _, off = hold(3, 6.0, push, settings=replace(SYNC, monitor_slow=(0.0, 0.6)))
    refused = [e for e in est.history if not e.accepted]
    assert not any(e.accepted for e in est.history)
    assert len(refused) <= len(off.history) + 1, [(round(e.t, 2), e.kind, e.reason) for e in est.history]


@pytest.mark.slow
def test_a_change_while_the_arm_still_creeps_after_the_last_estimate_is_not_left_until_it_rests():
    """The randomised episode of seed 86: 2.73 kg is compensated at once, and the heavily loaded arm
    then creeps back at 0.04 rad/s, so the estimate at rest it scheduled stays due. At 3.71 s the load drops to
    1.16 kg while a person pushes for 0.29 s; the detector's window holds the push, so it refuses the change. The
    check of a slow arm runs while such an estimate is due too: the new load is compensated within a second, not
    once the arm is still (1.5 s after the change)."""
    change = found_episode(86)["scored"][1]
    assert within(change["m_hat"], change["m"]) and change["latency_ms"] < 1000, change


def test_the_creep_after_a_compensation_is_left_to_the_estimate_at_rest_it_scheduled():
    """While an estimate at rest is due, the check of a slow arm estimates only a level monitor_far (2 Nm) or more
    from the one explained there. 1 kg is hung on at 0.8 s; from 1.0 s joint 1 creeps at 0.05 rad/s for 1.5 s while
    tau_ext drifts by a payload-shaped 0.75 Nm (friction letting go of part of the load, say; too small for the
    detector: 0.56 Nm^2 against its 0.7), off the flange's line: that is the estimate at rest's to judge, once the
    arm stops, not a new change to estimate on the moving arm. The control: with monitor_far at 0.7 Nm the same
    stream is estimated by that check while the arm creeps."""
    from dataclasses import replace
    kinds = lambda est: [(round(e.t, 3), e.kind) for e in est.history]
    creep = lambda settings: synthetic_stream(settings, None, 3.0, load=np.array([1.0, 0.03, -0.02, 0.05]), t_load=0.8,
                                        move=(0, 0.05, 1.0, 2.5), drift=(np.array([1.0, 0.08, -0.05, 0.05]), 0.75, 1.0),
                                        seed=7)
    est, low = creep(SYNC), creep(replace(SYNC, monitor_far=0.7))
    assert [k for _, k in kinds(est)] == ["detection", "at rest"] and est.history[1].t >= 2.5, kinds(est)
    assert any(k == "monitor" and 1.0 < t < 2.5 for t, k in kinds(low)), kinds(low)


def test_a_payload_shaped_sensor_bias_at_start_up_is_not_taken_for_a_load_before_the_arm_is_calm():
    """A sensor bias of 2.7 Nm, 96 % of it payload-shaped (0.45 kg), there from the first sample on an arm that is
    still: until it has been calm for monitor_window the arm counts as slow, and the check of a slow arm judges a
    level against no payload with the first level's gate (97 %), as the check at rest does: nothing is applied, and
    the level becomes the bias explained there."""
    from dynamics import phi_of
    robot = Robot.panda()
    Y0 = robot.payload_regressor(Q_READY)
    pay = Y0 @ phi_of(np.array([0.45, 0.02, 0.0, 0.03]))
    J = robot.jacobian(Q_READY)
    other = J.T @ np.array([0.0, 0.0, 0.0, 0.0, 0.0, 1.0])      # a moment about the world z: no payload's
    other -= Y0 @ np.linalg.lstsq(Y0, other, rcond=None)[0]
    bias = pay + 0.2 * np.linalg.norm(pay) / np.linalg.norm(other) * other
    est = synthetic_stream(SYNC, bias, 1.0)
    assert not est.history and np.all(est.theta == 0.0) and len(est._lv.explained) == 1


@pytest.mark.slow
def test_a_load_on_a_resting_arm_is_compensated_within_200_ms_on_the_samples_after_it():
    """The detector's stabilisation checks span the last 150 ms and the estimate at the detection takes those 150
    samples, all after the change: a 0.9 kg load is compensated within 0.2 s and read within 10 %. The control:
    Algorithm 1's 230 ms checks (and a 200 ms window) on the same plant take over 0.25 s."""
    from dataclasses import replace
    from detector import ALGORITHM_1_CHECKS
    events = [PayloadChange(1.0, 0.9, (0.05, -0.03, 0.13))]
    _, est = hold(0, 2.0, events)
    _, alg1 = hold(0, 2.0, events, settings=replace(SYNC, detector=DetectorSettings(check_windows=ALGORITHM_1_CHECKS)))
    assert SYNC.detection_window == 150 and alg1.settings.detection_window == 200
    t, t_alg1 = first_applied(est) - 1.0, first_applied(alg1) - 1.0
    assert t < 0.2 and t_alg1 > 0.25, (t, t_alg1)
    assert est.history[0].kind == "detection" and within(est.history[0].mean[0], 0.9)
    with pytest.raises(ValueError, match="detector.check_windows"):
        RMESettings(detector=DetectorSettings(check_windows=((491, 495),)))
