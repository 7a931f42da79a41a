"""Presses straight down through the flange against loads centred below it (the same to the joint torques): a press
is held and never applied, a centred load is compensated once it has lasted or when the task says it is coming
(RME.expect_change), a held change whose level has moved on is dropped; against the simulated plant's truth."""
import numpy as np
import pytest

from cpic import CPIC, Attractor
from dynamics import Q_READY
from experiments.runner import PayloadChange, Push, run
from rme import RME
from sim import Plant, PlantConfig
from tests.helpers import SYNC, found_episode, hold, synthetic_stream, within


@pytest.mark.slow
def test_a_downward_push_through_the_flange_is_held_and_never_applied():
    """Pressing straight down on the hand for 1.8 s: to the joint torques a load centred below the flange. RME holds
    such a change for hold_axial (2.5 s) and the push ends first: nothing is estimated or applied. Without the hold
    the same push is compensated as a load while it lasts (the test's control)."""
    from dataclasses import replace
    push = [Push(1.0, (0.0, 0.0, -20.0), 1.8, body="link7", offset=(0.0, 0.0, 0.107))]
    rec, est = hold(5, 5.0, push)
    assert not est.history and est.changes_held >= 1, [(e.t, e.kind, e.mean.round(2)) for e in est.history]
    assert np.abs(rec.theta_hat[:, 0]).max() == 0.0
    rec_off, _ = hold(5, 5.0, push, settings=replace(SYNC, hold_axial=0.0))
    assert rec_off.theta_hat[:, 0].max() > 1.5                       # 20 N read as about 2 kg


@pytest.mark.slow
def test_a_load_centred_below_the_flange_is_compensated_once_it_has_lasted():
    """The other side of that hold: 1 kg hanging 10 cm straight below the flange at the ready pose (ee z down) waits
    hold_axial, then the monitor compensates it. A load 5 cm off that line is compensated at the detection."""
    rec, est = hold(5, 6.0, [PayloadChange(1.0, 1.0, (0.0, 0.0, 0.1))])
    assert rec.theta_hat[rec.at(1.0 + 2.4), 0] == 0.0                # held while a push could still end
    applied = [e for e in est.history if e.accepted]
    assert applied and 1.0 + 2.5 <= applied[0].t < 1.0 + 3.5, [(e.t, e.kind, e.accepted) for e in est.history]
    assert within(rec.theta_hat[-1, 0], 1.0) and np.linalg.norm(rec.p[-1] - rec.target[-1]) < 0.01
    rec, est = hold(5, 3.0, [PayloadChange(1.0, 1.0, (0.05, 0.0, 0.1))])
    assert est.changes_held == 0 and est.history[0].accepted and est.history[0].t < 1.0 + 0.4
    assert within(rec.theta_hat[-1, 0], 1.0)


@pytest.mark.slow
def test_a_centred_load_the_task_expects_is_compensated_at_its_detection():
    """The same centred 1 kg, with the task telling RME 0.1 s before that it grasps (RME.expect_change): not held,
    compensated at its detection, within 0.4 s and 10 %. The same call while a held change waits (told 0.5 s after
    the load came) has it estimated then, not 2.5 s after it came. Bad input is a ValueError naming seconds."""
    rng = np.random.default_rng(5)
    plant = Plant(PlantConfig.realistic(rng), rng=rng)
    est = RME(plant.robot, settings=SYNC, rng=np.random.default_rng(6))
    tell = lambda at: (lambda k, sample: k == int(round(at / plant.dt)) and est.expect_change(1.0))
    rec = run(plant, CPIC(plant.robot, Attractor(*plant.robot.ee_pose(Q_READY))), 3.0, est,
              [PayloadChange(1.0, 1.0, (0.0, 0.0, 0.1))], q0=Q_READY, before_step=tell(0.9))
    applied = [e for e in est.history if e.accepted]
    assert est.changes_held == 0 and applied and applied[0].applied < 1.0 + 0.4, [(e.t, e.kind) for e in est.history]
    assert within(rec.theta_hat[-1, 0], 1.0)
    rng = np.random.default_rng(5)
    plant = Plant(PlantConfig.realistic(rng), rng=rng)
    est = RME(plant.robot, settings=SYNC, rng=np.random.default_rng(6))
    rec = run(plant, CPIC(plant.robot, Attractor(*plant.robot.ee_pose(Q_READY))), 3.0, est,
              [PayloadChange(1.0, 1.0, (0.0, 0.0, 0.1))], q0=Q_READY, before_step=tell(1.5))
    applied = [e for e in est.history if e.accepted]
    assert est.changes_held == 1 and applied and applied[0].applied < 1.5 + 0.1, [(e.t, e.kind) for e in est.history]
    assert within(rec.theta_hat[-1, 0], 1.0)
    for bad in (-1.0, np.inf, np.nan, "1", True):
        with pytest.raises(ValueError, match=r"seconds: expected a number in \[0, 3600\] s"):
            est.expect_change(bad)


@pytest.mark.slow
@pytest.mark.parametrize("force, seconds", [(8.0, 0.8), (14.0, 1.5)])
def test_a_lift_by_the_hand_read_as_part_of_the_load_gone_is_undone_at_its_release(force, seconds):
    """A person lifts the hand from below under a compensated 2 kg load off the flange's line: to the torques part
    of the load has gone, and it is compensated so. At the release the load's weight comes back through the
    flange's line, as a press would; that change takes the compensation back to the estimate before the lift, so it
    is estimated at its detection, not held: 2 kg within 0.6 s of the release (held, it took 2.6-2.8 s)."""
    lift = Push(2.5, (0.0, 0.0, force), seconds, body="link7", offset=(0.0, 0.0, 0.107))
    rec, est = hold(5, 2.5 + seconds + 0.7, [PayloadChange(1.0, 2.0, (0.03, -0.02, 0.1)), lift])
    assert rec.theta_hat[rec.at(2.5 + seconds), 0] < 1.6              # the lift read as part of the load gone
    assert est.changes_held == 0, [(e.t, e.kind, e.mean.round(2).tolist()) for e in est.history]
    assert within(rec.theta_hat[rec.at(2.5 + seconds + 0.6), 0], 2.0)


@pytest.mark.slow
@pytest.mark.parametrize("first", ["removal", "press"])
def test_a_press_like_the_load_just_gone_is_still_held(first):
    """Taking a lift's release back to the load before it must not let a press pass for a load coming back: after a
    2 kg load 3.6 cm off the flange's line is removed, or after a 20 N press held 3.5 s (compensated once it lasted)
    is released, a 20 N press through the flange 2 s later is held and never applied."""
    load = [PayloadChange(1.0, 2.0, (0.03, -0.02, 0.1)), PayloadChange(3.0, 0.0, (0.0, 0.0, 0.0))]
    before = load if first == "removal" else [Push(1.0, (0.0, 0.0, -20.0), 3.5, body="link7", offset=(0.0, 0.0, 0.107))]
    t = 5.0 if first == "removal" else 6.5
    rec, est = hold(5, t + 2.5, before + [Push(t, (0.0, 0.0, -20.0), 1.8, body="link7", offset=(0.0, 0.0, 0.107))])
    assert rec.theta_hat[rec.at(t):, 0].max() < 0.05, [(e.t, e.kind, e.mean[0]) for e in est.history]


@pytest.mark.slow
def test_the_estimate_at_rest_waits_while_a_push_holds_the_resting_arm():
    """A 2 kg load read 1.87 kg at its detection, then a 14 N push, down and 6 N sideways, from before the arm rests
    until 3.5 s: the change from before the load is then no payload (its force is not vertical), so the estimate at
    rest waits for the push's end and reads 2.0 kg. Made during the push it read 3.07 kg and was applied for 1.5 s."""
    push = Push(1.5, (-5.0, 3.6, -12.7), 2.0, body="link7", offset=(0.0, 0.0, 0.107))
    rec, est = hold(5, 5.0, [PayloadChange(1.0, 2.0, (0.03, -0.02, 0.1)), push])
    assert rec.theta_hat[rec.at(1.5):rec.at(3.5), 0].max() < 2.0, [(e.t, e.kind, e.mean[0]) for e in est.history]
    (e,) = [e for e in est.history if e.kind == "at rest"]
    assert e.accepted and e.t > 3.5 and abs(e.mean[0] - 2.0) < 0.05


@pytest.mark.slow
def test_a_press_while_a_loads_estimate_at_rest_is_pending_keeps_that_estimate():
    """An off-axis 1 kg load read 7 % light at its detection, then a 20 N press through the flange for 1 s before the
    arm rests: the press is held and released, and the load's estimate at rest still comes (without the press it
    reads 1.003 kg); a press that superseded it had thrown it away, leaving 0.932 kg."""
    load = PayloadChange(1.0, 1.0, (0.03, -0.02, 0.1))
    rec, est = hold(5, 6.0, [load, Push(1.7, (0.0, 0.0, -20.0), 1.0, body="link7", offset=(0.0, 0.0, 0.107))])
    assert est.changes_held >= 1 and any(e.kind == "at rest" and e.accepted for e in est.history), \
        [(e.t, e.kind, e.accepted, e.mean.round(3).tolist()) for e in est.history]
    assert abs(rec.theta_hat[-1, 0] - 1.0) < 0.03 and rec.theta_hat[:, 0].max() < 1.2   # the press never applied


@pytest.mark.slow
def test_on_a_cycling_arm_a_centred_load_is_compensated_once_it_has_lasted_and_a_later_press_is_not():
    """The arm never rests on the limit cycle: a load centred below the flange is estimated once it has lasted
    hold_axial, on the window of its detection (the pose before it is long gone), and a 20 N press through the
    flange 6 s later is held afresh and, released while the arm still moves, never applied."""
    from cpic import LimitCycle
    rng = np.random.default_rng(5)
    plant = Plant(PlantConfig.realistic(rng), rng=rng)
    p0, R0 = plant.robot.ee_pose(Q_READY)
    cycle = LimitCycle(p0 - np.array([0.0, 0.0, 0.05]), R0, radius=0.05)
    est = RME(plant.robot, settings=SYNC, rng=np.random.default_rng(6))
    events = [PayloadChange(2.0, 1.0, (0.0, 0.0, 0.1)), Push(8.0, (0.0, 0.0, -20.0), 1.5, body="link7",
                                                              offset=(0.0, 0.0, 0.107))]
    rec = run(plant, CPIC(plant.robot, cycle), 11.0, est, events, q0=Q_READY)
    applied = [e for e in est.history if e.accepted]
    assert len(applied) == 1 and 2.0 + 2.5 <= applied[0].applied < 2.0 + 3.0, [(e.t, e.kind) for e in est.history]
    assert applied[0].t < 2.0 + 0.5                      # its time: the detection's, whose window it estimates on
    assert within(applied[0].mean[0], 1.0) and est.changes_held == 2
    assert np.abs(rec.theta_hat[rec.t >= 5.0, 0] - applied[0].mean[0]).max() < 1e-12   # the press: nothing applied


@pytest.mark.slow
def test_a_held_change_whose_level_has_moved_on_is_not_estimated_on_its_old_window():
    """The randomised episode of seed 75: the arm creeps from its start and is never calm; 1.69 kg hung
    on at 1.84 s is held as a possible press, three pushes follow, the load is removed at 2.79 s and 2.99 kg hung on at
    3.37 s. Once the residual has moved far from the held level, that change is gone: no estimate of its window (about
    1.65 kg) is applied, and the 2.99 kg load is compensated within 10 % by the check of a slow arm, at a pose where
    no level was ever explained."""
    ep = found_episode(75, settings=SYNC)
    assert [round(m, 2) for _, m, _ in ep["changes"]] == [1.69, 0.0, 2.99]
    rec, est = ep["rec"], ep["est"]
    applied = [(round(e.t, 3), e.kind, round(e.mean[0], 3)) for e in est.history if e.accepted]
    assert est.changes_held >= 1 and not any(abs(m - 1.69) < 0.2 for *_, m in applied), applied
    assert within(rec.theta_hat[-1, 0], 2.99), applied


@pytest.mark.parametrize("joint", [1, 5])
def test_a_held_load_on_an_arm_that_keeps_moving_is_compensated_once_it_has_lasted(joint):
    """1.5 kg centred below the flange (held as a possible press) while one joint sweeps 0.7 rad at 0.2 rad/s: its
    residual changes with the pose, yet it is the same change, carried there (not a level that has moved on), so
    it is estimated on its detection's window once it has lasted hold_axial, while the arm still moves."""
    est = synthetic_stream(SYNC, np.zeros(7), 4.5, load=np.array([1.5, 0.0, 0.0, 0.10]), t_load=1.2,
                     move=(joint, 0.2, 1.0, 4.5))
    applied = [e for e in est.history if e.accepted]
    assert est.changes_held == 1 and applied and applied[0].applied < 1.2 + 2.5 + 0.3, \
        [(e.t, e.kind, e.applied) for e in est.history]
    assert within(applied[0].mean[0], 1.5)


@pytest.mark.slow
def test_a_press_read_as_a_plausible_load_at_the_detection_is_withdrawn_once_the_arm_rests():
    """A person presses 20 N down on a handle 0.45 m out from the hand: to the torques 2 kg with its CoM 0.32 m out
    along the ee's x and y, just beyond max_com. The window at the detection, still in the arm's sag, reads it
    0.28-0.30 m out, a plausible load, and it is compensated; the estimate at rest reads it beyond max_com, so the
    compensation goes back to the estimate before the change (none) and stays there while the press lasts."""
    push = [Push(1.0, (0.0, 0.0, -20.0), 4.5, body="link7", offset=(0.45, 0.0, 0.107))]
    rec, est = hold(3, 6.0, push)
    kinds = [(e.kind, e.accepted) for e in est.history]
    assert ("detection", True) in kinds and ("at rest", False) in kinds, kinds
    (w,) = [e for e in est.history if e.kind == "withdrawn"]
    assert w.accepted and w.applied < 3.0 and np.all(w.mean == 0.0)
    assert np.all(rec.theta_hat[rec.t > w.applied + 0.002] == 0.0)


@pytest.mark.slow
def test_a_held_press_that_shifts_as_the_arm_yields_stays_held():
    """The randomised push-only episode of seed 350076: 34 N straight down for 1.3 s, held as a possible
    press. The arm yields to it at 0.3 rad/s and the detector fires again on that small shift (1.8 N). Referred to
    the press's own level that shift read as a 0.24 kg load 0.2 m out, and was applied until the rest; referred to
    the level before the press, the whole change is still the press through the flange: nothing is applied."""
    est = found_episode(350076, loads=False)["est"]
    assert not any(e.accepted for e in est.history) and est.changes_held >= 1, est.history


def test_a_centred_change_on_a_slow_arm_is_estimated_when_the_task_expects_it():
    """A centred load's worth of torque (0.75 Nm, too little for the detector) comes on while joint 1 turns at 0.05
    rad/s: the check of a slow arm leaves a change through the flange's line to the rest (a person may be pressing),
    so nothing is estimated while the arm moves, unless the task said a load is coming (RME.expect_change): then it
    is estimated there, as the load it is (mass within 10 %)."""
    from dynamics import Robot, phi_of
    theta = np.array([1.0, 0.0, 0.0, 0.1])                             # centred 0.1 m below the flange
    size = 0.75 / np.linalg.norm(Robot.panda().payload_regressor(Q_READY) @ phi_of(theta))   # kg: 0.75 Nm's worth
    runs = [synthetic_stream(SYNC, None, 3.0, move=(0, 0.05, 1.0, 3.0), drift=(theta, 0.75, 1.2), seed=7, expect=expect)
            for expect in (None, (1.1, 2.0))]
    assert runs[0].history == []
    (e,) = runs[1].history
    assert e.accepted and e.kind == "monitor" and 1.2 < e.t < 2.0 and within(e.mean[0], size), (e.t, e.mean, size)
