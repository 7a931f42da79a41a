"""Streaming RME fed synthetic streams whose truth is known, no plant: an absurd sample, an estimate failing beside
the loop, states to return to, arms that creep, move steadily or never rest, levels on their way, friction against
the motion, corrections of a compensation the level says is off."""
import numpy as np
import pytest

from detector import Detector
from dynamics import Q_READY, Robot
from rme import RME
from tests.helpers import SYNC, gaz_friction, sensor_bias, within


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


class _Done:
    """A finished job: its value, or the error its result() raises."""

    def __init__(self, value=None, error=None):
        self.value, self.error = value, error

    def done(self):
        return True

    def result(self):
        if self.error is not None:
            raise self.error
        return self.value


class _FailingFirst:
    """An executor whose first `failures` jobs fail (as a worker's estimate that raised), the rest run at once."""

    def __init__(self, failures):
        self.failures, self.jobs = failures, 0

    def submit(self, fn, *args):
        self.jobs += 1
        if self.jobs <= self.failures:
            return _Done(error=RuntimeError("the estimate failed in the worker: ValueError: test"))
        return _Done(fn(*args))


@pytest.mark.parametrize("failures", [1, 10_000])
def test_an_estimate_that_fails_beside_the_loop_is_counted_and_the_change_judged_again(failures):
    """Synthetic stream at the ready pose, 0.9 kg hung on at 1 s: the executor's first job fails (or every job).
    update never raises and returns finite torques within the limits; each failure is counted with its message;
    after one failure the change is estimated again and compensated, after nothing but failures nothing is."""
    robot = Robot.panda()
    ex = _FailingFirst(failures)
    est = RME(robot, weights=None, settings=SYNC, rng=np.random.default_rng(0), executor=ex)
    noise, theta, limit = np.random.default_rng(2), np.array([0.9, 0.03, -0.02, 0.1]), robot.torque_limits()
    for k in range(2500):
        tau = robot.payload_torque(Q_READY, theta) if k >= 1000 else np.zeros(7)
        comp = est.update(Q_READY, np.zeros(7), tau + 0.01 * noise.normal(size=7))
        assert np.all(np.isfinite(comp)) and np.all(np.abs(comp) <= limit)
    assert est.failed == 1 if failures == 1 else ex.jobs - 1 <= est.failed <= ex.jobs   # (the last may be out)
    assert "ValueError: test" in est.failure
    assert within(est.theta[0], 0.9) if failures == 1 else est.theta[0] == 0.0, est.history


@pytest.mark.parametrize("held", [0.3, 1.5])
def test_a_payload_becomes_a_state_to_return_to_once_its_level_held(held):
    """Synthetic stream at the ready pose, the arm still: 0.8 kg hung on, swapped for 1.6 kg `held` seconds later. Its
    level held at the compensation's own for patience (0.3 s) and more, 0.8 kg is an earlier payload to return to
    once the swap is compensated; swapped before its level could hold that long after its estimate (detected 0.05-0.1
    s after the change), it is not kept (an estimate the next one corrected: no state the arm held)."""
    robot = Robot.panda()
    est = RME(robot, weights=None, settings=SYNC, rng=np.random.default_rng(0))
    noise = np.random.default_rng(1)
    first, second = np.array([0.8, 0.02, 0.0, 0.1]), np.array([1.6, -0.03, 0.01, 0.08])
    swap = 1000 + int(held * 1000)
    for k in range(swap + 1500):
        theta = first if 1000 <= k < swap else second if k >= swap else None
        tau = np.zeros(7) if theta is None else robot.payload_torque(Q_READY, theta)
        est.update(Q_READY, np.zeros(7), tau + 0.01 * noise.normal(size=7))
    assert within(est.theta[0], 1.6), [(e.kind, e.mean.round(3).tolist()) for e in est.history]
    kept = [p[0] for p in est.payloads.earlier]
    assert any(within(m, 0.8) for m in kept) == (held > 1.0), (kept, [(e.t, e.kind) for e in est.history])


@pytest.mark.slow
def test_a_heavy_load_swapped_for_one_close_to_none_is_withdrawn_at_once():
    """Synthetic stream at the ready pose, the arm still: 1.5-3 kg compensated, then swapped for 20-60 g, which a
    return to no payload and a new light payload explain about as well. Every hypothesis but those keeping the
    compensation says it is 1.4-3 kg off, so the heavy load's compensation goes at the first judgement that sees
    the level (within 0.1 s: the 40-sample level and a 5 ms judgement), whichever of the two it takes; and the mass
    ends right."""
    robot = Robot.panda()
    draws = np.random.default_rng(2041)
    for _ in range(8):
        heavy = np.array([draws.uniform(1.5, 3.0), *draws.uniform(-0.08, 0.08, 2), draws.uniform(0, 0.1)])
        light = np.array([draws.uniform(0.02, 0.06), *draws.uniform(-0.05, 0.05, 2), draws.uniform(0, 0.1)])
        est = RME(robot, weights=None, settings=SYNC, rng=np.random.default_rng(0))
        noise = np.random.default_rng(1)
        gone = None
        for k in range(4000):
            theta = None if k < 1000 else heavy if k < 2500 else light
            tau = np.zeros(7) if theta is None else robot.payload_torque(Q_READY, theta)
            est.update(Q_READY, np.zeros(7), tau + 0.01 * noise.normal(size=7))
            if k == 2499:
                assert within(est.theta[0], heavy[0])
            if k >= 2500 and gone is None and not within(est.theta[0], heavy[0]):
                gone = (k - 2500) / 1000
        story = (heavy[0], light[0], [(e.t, e.kind, round(e.mean[0], 3)) for e in est.history])
        assert gone is not None and gone <= 0.1, (gone, story)
        assert within(est.theta[0], light[0]), story


def _creeping_hold(draws, samples, friction, stop=None):
    """A synthetic stream at the ready pose: m of 0.5-2.5 kg (its CoM within 8 cm; drawn from `draws`) hung on at
    sample 1000 as the joints start creeping at 0.2-0.3 rad/s (random signs), slowing with a time constant of 0.7 s,
    until sample `stop` (None: never), tau_ext holding `friction` x the friction changes.py's model says, against the
    motion (the paper's sign, the plant's: tests/test_changes.py); RME (no network, estimates on their sample) fed
    `samples` samples. Returns (m, the estimator, its mass per sample)."""
    robot = Robot.panda()
    model = RME(robot, weights=None).model
    m, r = draws.uniform(0.5, 2.5), draws.uniform(-0.08, 0.08, 3)
    speed, sign = draws.uniform(0.2, 0.3, 7), draws.choice([-1.0, 1.0], 7)
    est = RME(robot, weights=None, settings=SYNC, rng=np.random.default_rng(0))
    noise = np.random.default_rng(1)
    load = robot.payload_torque(Q_READY, np.array([m, *r]))
    masses = []
    for k in range(samples):
        moving = 1000 <= k and (stop is None or k < stop)
        dq = sign * speed * np.exp(-(k - 1000) / 700.0) if moving else np.zeros(7)
        tau = np.zeros(7) if k < 1000 else load - friction * sign * model.friction(np.abs(dq))   # (against dq)
        est.update(Q_READY, dq, tau + 0.01 * noise.normal(size=7))
        masses.append(est.theta[0])
    return m, est, masses


@pytest.mark.slow
def test_a_load_hung_on_a_creeping_arm_is_right_before_the_arm_comes_to_rest():
    """Synthetic stream at the ready pose: the joints creep at 0.2-0.3 rad/s, slowing with a time constant of 0.7 s
    (still, below rest_speed, only about 2.3 s later), and tau_ext holds 1.5 x the friction changes.py's model says
    (random signs; the harsh plant's); 0.5-2.5 kg hung on as the creep starts. The mass is right, and stays right,
    within 0.7 s: the full window is estimated again as motion's share of its error shrinks, not only at rest."""
    draws = np.random.default_rng(2032)
    for _ in range(4):
        m, est, masses = _creeping_hold(draws, 3500, friction=1.5)
        assert all(within(x, m) for x in masses[1700:]), [(e.t, e.kind, e.mean.round(3).tolist())
                                                           for e in est.history]


@pytest.mark.slow
def test_an_estimate_made_in_motion_is_made_again_once_the_arm_is_still():
    """Synthetic stream at the ready pose: 0.5-2.5 kg hung on as the joints start creeping at 0.2-0.3 rad/s, slowing
    with a time constant of 0.7 s, tau_ext holding the friction changes.py's model says (random signs); the joints
    stop 1.6 s after the load. The full window is estimated in motion, friction in it; once the arm has been still for
    a full window it is estimated there without it: the mass kept is within 0.5 % (the noise's share is grams)."""
    draws = np.random.default_rng(2033)
    for _ in range(4):
        m, est, _ = _creeping_hold(draws, 3200, friction=1.0, stop=2600)
        kinds = [(e.t, e.kind, e.mean.round(3).tolist()) for e in est.history]
        assert any(kind == "at rest" and t < 2.6 for t, kind, _ in kinds), kinds
        assert abs(est.theta[0] - m) <= 0.005 * m, (m, kinds)


@pytest.mark.slow
def test_a_still_window_far_from_the_pose_of_the_level_before_the_change_does_not_replace_the_estimate():
    """Synthetic stream at the ready pose: 1-2.5 kg hung on as the joints start creeping at 0.02 rad/s with the
    friction changes.py's model says (random signs); after 1 s they carry the load 0.5-0.7 rad away and rest there,
    where the sensors' pose-dependent offset has moved by twice its std at that distance (the change model's Gaussian
    process), each joint's sign the one that moves the mass most. A window there, referred to the level before the
    change, carries that offset into the mass: the estimate made in motion near the change's pose (its error from
    friction smaller) is kept and none is made after the carry began."""
    robot, draws = Robot.panda(), np.random.default_rng(2034)
    est0 = RME(robot, weights=None)
    absolute, length = np.asarray(est0.error_model.absolute), est0.settings.changes.bias_length
    for _ in range(3):
        m, r = draws.uniform(1.0, 2.5), draws.uniform(-0.08, 0.08, 3)
        sign = draws.choice([-1.0, 1.0], 7)
        step = draws.uniform(0.5, 0.7) * draws.normal(size=7) / np.sqrt(7)             # the carry (7,) [rad]
        far = Q_READY + step * draws.uniform(0.5, 0.7) / np.linalg.norm(step)
        step = far - Q_READY
        std = absolute * np.sqrt(2 * -np.expm1(-0.5 * (step @ step) / length ** 2))
        offset = 2 * std * np.sign(np.linalg.pinv(robot.payload_regressor(far))[0])
        est = RME(robot, weights=None, settings=SYNC, rng=np.random.default_rng(0))
        noise = np.random.default_rng(1)
        for k in range(4200):
            s = min(max((k - 2000) / 1000, 0.0), 1.0)                                  # the carry: 2 s to 3 s
            q = Q_READY + step * (3 * s * s - 2 * s * s * s)
            dq = step * 6 * s * (1 - s) if 2000 <= k < 3000 else 0.02 * sign if 1000 <= k < 2000 else np.zeros(7)
            tau = robot.payload_torque(q, np.array([m, *r])) + s * offset if k >= 1000 else np.zeros(7)
            tau = tau - sign * est0.model.friction(np.abs(dq)) if k < 2000 else tau
            est.update(q, dq, tau + 0.01 * noise.normal(size=7))
        kinds = [(e.t, e.kind, e.mean.round(3).tolist()) for e in est.history]
        assert any(kind == "at rest" and t < 2.0 for t, kind, _ in kinds), kinds
        assert not any(kind == "at rest" and t > 2.0 for t, kind, _ in kinds), kinds
        assert abs(est.theta[0] - m) <= 0.025 * m, (m, kinds)


@pytest.mark.slow
def test_a_load_estimated_against_a_level_taken_in_motion_leaves_nothing_behind_at_its_removal():
    """Synthetic stream at the ready pose: the joints move at 0.15-0.3 rad/s (random signs) from the start, tau_ext
    holding the friction changes.py's model says, so every level the stream is referred to is taken in motion;
    1-2.5 kg (CoM within 8 cm) hung on at 1 s, the joints stop at 2 s, the load is removed at 4 s with the arm still.
    An estimate at rest then holds the friction of the level it was referred to, and the level taken under it holds
    that error: the removal is a return to no payload, and nothing is compensated from 0.5 s after it to the end."""
    robot, draws = Robot.panda(), np.random.default_rng(2037)
    friction = RME(robot, weights=None).model.friction
    for _ in range(4):
        m, r = draws.uniform(1.0, 2.5), draws.uniform(-0.08, 0.08, 3)
        dq = draws.uniform(0.15, 0.3, 7) * draws.choice([-1.0, 1.0], 7)
        est = RME(robot, weights=None, settings=SYNC, rng=np.random.default_rng(0))
        noise = np.random.default_rng(1)
        load = robot.payload_torque(Q_READY, np.array([m, *r]))
        after = []
        for k in range(6000):
            moving = dq if k < 2000 else np.zeros(7)
            tau = -np.sign(moving) * friction(np.abs(moving)) + (load if 1000 <= k < 4000 else 0.0)
            est.update(Q_READY, moving, tau + 0.01 * noise.normal(size=7))
            after += [est.theta[0]] if k >= 4500 else []
        kinds = [(e.t, e.kind, e.mean.round(3).tolist()) for e in est.history]
        assert all(within(x, 0.0) for x in after), (m, kinds)


@pytest.mark.slow
def test_a_light_load_hung_on_an_arm_that_never_rests_is_found_where_the_pose_has_moved_far():
    """Synthetic stream: from 0.2 s to 4 s the arm travels 2.3-2.8 rad through joint space without a rest (joints
    1, 3, 5 and 7 at 0.25-0.45 rad/s, 2, 4 and 6 slower), tau_ext holding Gaz et al.'s friction against the motion
    (the plant's; every level it sets out from is taken in motion, its friction in it) and the sensors' pose-dependent
    offset drawn from the change model's Gaussian process (random Fourier features, the
    error model's std). 0.3-0.6 kg (CoM within 5 cm) hung on 2.5 s in, 1-1.5 rad from the first level's pose, where
    a level referred to the pose the arm set out from carries the offset's change over that distance (tenths of a
    Nm): the load is estimated within 0.5 s, and its mass is right once the arm has rested 1.5 s."""
    robot, draws = Robot.panda(), np.random.default_rng(2036)
    est0 = RME(robot, weights=None)
    sigma, length = np.asarray(est0.error_model.absolute), est0.settings.changes.bias_length
    for _ in range(3):
        m, r = draws.uniform(0.3, 0.6), draws.uniform(-0.05, 0.05, 3)
        rate = draws.uniform(0.25, 0.45, 7) * draws.choice([-1.0, 1.0], 7) * np.array([1, 0.2, 1, 0.2, 1, 0.2, 1])
        offset = sensor_bias(draws, sigma, length)
        est = RME(robot, weights=None, settings=SYNC, rng=np.random.default_rng(0))
        noise = np.random.default_rng(1)
        for k in range(5500):
            t = min(max(k - 200, 0), 3800) / 1000
            q, dq = Q_READY + rate * t, rate if 200 <= k < 4000 else np.zeros(7)
            tau = offset(q) - gaz_friction(dq) + 0.01 * noise.normal(size=7)
            if k >= 2500:
                tau = tau + robot.payload_torque(q, np.array([m, *r]))
            est.update(q, dq, tau)
            if k == 3000:
                kinds = [(e.t, e.kind, e.accepted, e.mean.round(3).tolist()) for e in est.history]
                assert any(e.accepted and 2.5 <= e.t for e in est.history), (m, kinds)
        assert within(est.theta[0], m), (m, [(e.t, e.kind, e.mean.round(3).tolist()) for e in est.history])


@pytest.mark.slow
def test_a_return_to_a_payload_whose_estimate_at_rest_was_owed_owes_it_again():
    """Synthetic stream at the ready pose with the joints moving at 0.2-0.4 rad/s, Gaz et al.'s friction in tau_ext
    against the motion (the estimate at rest on the full window waits): 0.5-1.5 kg hung on, a press straight down (a
    centred 1.5-2.5 kg to the torques) from 1 s after it for 0.5 s, then the joints stop. The release is a return to the payload, whose estimate at rest
    was still owed: made once the arm is still, after the return."""
    robot, draws = Robot.panda(), np.random.default_rng(2031)
    for _ in range(2):
        m, r, press = draws.uniform(0.5, 1.5), draws.uniform(-0.05, 0.05, 3), draws.uniform(1.5, 2.5)
        dq = draws.uniform(0.2, 0.4, 7) * draws.choice([-1.0, 1.0], 7)
        est = RME(robot, weights=None, settings=SYNC, rng=np.random.default_rng(0))
        noise = np.random.default_rng(1)
        load = robot.payload_torque(Q_READY, np.array([m, *r]))
        pressed = robot.payload_torque(Q_READY, np.array([m + press, *(m * r / (m + press))]))
        for k in range(4500):
            tau = np.zeros(7) if k < 1000 else pressed if 2000 <= k < 2500 else load
            moving = dq if k < 3000 else np.zeros(7)
            est.update(Q_READY, moving, tau - gaz_friction(moving) + 0.01 * noise.normal(size=7))
        kinds = [(e.t, e.kind) for e in est.history]
        back = [t for t, kind in kinds if kind == "back" and t >= 2.5]
        assert back and any(kind == "at rest" and t > back[0] for t, kind in kinds), kinds
        assert within(est.theta[0], m), kinds


def test_a_load_hung_on_an_arm_moving_steadily_is_first_estimated_once_its_level_has_arrived():
    """Synthetic stream at the ready pose with the joints moving at a steady 0.2-0.4 rad/s (their friction's size
    hides a level on its way): 0.5-2 kg hung on. The first estimate waits until the payload's mass is pinned down or
    the level has arrived (its move within the noise and the friction's change), and is right (within 10 %) within
    0.5 s of the change; one made as soon as the level moves less than the friction's size would read a level still
    on its way (23-32 % low, on these draws)."""
    robot, draws = Robot.panda(), np.random.default_rng(2113)
    for _ in range(3):
        m, r = draws.uniform(0.5, 2.0), draws.uniform(-0.05, 0.05, 3)
        dq = draws.uniform(0.2, 0.4, 7) * draws.choice([-1.0, 1.0], 7)
        est = RME(robot, weights=None, settings=SYNC, rng=np.random.default_rng(0))
        noise = np.random.default_rng(1)
        load = robot.payload_torque(Q_READY, np.array([m, *r]))
        for k in range(1500):
            est.update(Q_READY, dq, (np.zeros(7) if k < 1000 else load) + 0.01 * noise.normal(size=7))
        first = [e for e in est.history if e.accepted]
        assert first and first[0].t < 1.5 and within(first[0].mean[0], m), \
            (m, [(e.t, e.kind, e.mean.round(3)) for e in est.history])


def test_a_first_estimate_read_before_its_level_arrived_is_made_again_at_rest_wherever_the_rest_sits():
    """Synthetic stream, the arm still at the ready pose, 0.05 Nm white noise per sample (the noisy plant's): 0.5-2.5
    kg hung on, 93-99.5 % of its torque for 150 ms (the first estimate reads that), then all of it. Whatever is left
    after the first estimate, above the departure's bar, below it or on it (then it crosses it from one judgement to
    the next), the estimate at rest owed for the change is made within 0.75 s, and the compensated mass is right within
    1 %."""
    robot, draws = Robot.panda(), np.random.default_rng(1)
    for i in range(16):
        m, r, p = draws.uniform(0.5, 2.5), draws.uniform(-0.05, 0.05, 3), draws.uniform(0.93, 0.995)
        load = robot.payload_torque(Q_READY, np.array([m, *r]))
        est, noise = RME(robot, weights=None, settings=SYNC, rng=np.random.default_rng(0)), np.random.default_rng(i)
        for k in range(1900):
            share = 0.0 if k < 1000 else p if k < 1150 else 1.0
            est.update(Q_READY, np.zeros(7), share * load + 0.05 * noise.normal(size=7))
        at_rest = [e for e in est.history if e.kind == "at rest" and e.t > 1.15]
        assert at_rest and abs(est.theta[0] - m) < 0.01 * m, \
            (m, p, [(e.t, e.kind, e.mean.round(3)) for e in est.history])


def test_a_load_that_sets_the_still_arm_moving_is_estimated_without_the_friction_that_resists_the_motion():
    """Synthetic stream: the arm still at the ready pose, then 0.5-2.5 kg hung on and each joint set moving at 0.05-0.3
    rad/s the way the load's torque turns it (an arm sagging under it), Gaz et al.'s friction in tau_ext against the
    motion (with its offset p3, which the model leaves out), 0.01 Nm noise. The first estimate, made in motion on a
    window that holds the friction and referred to a level taken at rest that does not, is right within 4 % of the
    mass; with the friction left in the window it reads 2-9 % low on these draws (5 of 10 beyond 4 %)."""
    robot, draws = Robot.panda(), np.random.default_rng(7)
    for i in range(10):
        m, r = draws.uniform(0.5, 2.5), draws.uniform(-0.05, 0.05, 3)
        v = draws.uniform(0.05, 0.3, 7) * np.sign(robot.payload_torque(Q_READY, np.array([m, *r])))
        friction = -gaz_friction(v)                                     # in tau_ext: against the motion
        est, noise = RME(robot, settings=SYNC, rng=np.random.default_rng(0)), np.random.default_rng(i)
        for k in range(1500):
            moving = k >= 1000
            q = Q_READY + (v * (k - 1000) / 1000 if moving else 0.0)
            tau = robot.payload_torque(q, np.array([m, *r])) + friction if moving else np.zeros(7)
            est.update(q, v if moving else np.zeros(7), tau + 0.01 * noise.normal(size=7))
        first = [e for e in est.history if e.accepted]
        assert first and abs(first[0].mean[0] - m) < 0.04 * m, \
            (m, [(e.t, e.kind, e.mean.round(3)) for e in est.history])


def test_a_correction_is_made_only_when_the_payload_it_compensates_moves_the_mass():
    """The noise hypothesis' posterior of the payload held (Verdict.kept, phi (4,)) corrects the compensation only if
    the payload compensated from it (finite, mass in [0, max_mass]) differs in mass from the held one by more than
    half the tolerance (10 % or 50 g): a posterior the arm cannot carry, clipped back to the held mass, would leave
    the level where it is and be judged again every 5 ms."""
    from changes import Verdict
    est = RME(rng=np.random.default_rng(0))
    top = est.settings.max_mass

    def verdict(phi):
        return Verdict(np.zeros(7), {"noise": 1.0}, "noise", kept=np.asarray(phi, dtype=float))

    assert est._corrected(verdict([-0.3, 0.0, 0.0, 0.0])) is None            # below 0 kg: clipped to the 0 held
    assert est._corrected(verdict([np.nan, 0.0, 0.0, 0.0])) is None
    assert est._corrected(verdict([0.02, 0.0, 0.0, 0.0])) is None            # within 50 g of the 0 held
    np.testing.assert_allclose(est._corrected(verdict([0.3, 0.03, 0.0, -0.015])), [0.3, 0.1, 0.0, -0.05])
    est.theta = np.array([top, 0.0, 0.0, 0.0])
    assert est._corrected(verdict([top + 1.0, 0.0, 0.0, 0.0])) is None      # beyond max_mass: clipped to the held
    assert est._corrected(verdict([0.5 * top, 0.0, 0.0, 0.0]))[0] == 0.5 * top
    # a light "payload" whose CoM is beyond max_com (0.04 kg with 0.076 kg m: r = 1.9 m, clipped to 1 m, which
    # would not leave the level the posterior says): no payload a hand carries, no correction; at max_com it is one
    est.theta = np.zeros(4)
    R = est.settings.max_com
    assert est._corrected(verdict([0.04, -0.02, 0.026, -0.076])) is None
    assert est._corrected(verdict([0.3, 0.0, 0.0, 1.01 * R * 0.3])) is None
    np.testing.assert_allclose(est._corrected(verdict([0.3, 0.0, 0.0, 0.99 * R * 0.3])), [0.3, 0, 0, 0.99 * R])


def test_a_correction_carries_the_spread_of_theta_under_the_noise_hypothesis_posterior():
    """A correction's Estimate (std (4,), cov (4, 4) of theta = (m, r)) against theta_of over 20000 draws of phi from
    the posterior N(kept, kept_cov) it is made of: within 5 % (first order for a 2 % mass std); with no mass left,
    the mass's own std, nothing claimed of a CoM."""
    from changes import Verdict
    from dynamics import theta_of
    rng = np.random.default_rng(5)
    est = RME(rng=np.random.default_rng(0))
    A = rng.normal(size=(4, 4)) * np.array([0.02, 0.002, 0.002, 0.002])[:, None]
    P = A @ A.T + np.diag([0.02, 0.002, 0.002, 0.002]) ** 2
    for kept in (np.array([1.0, 0.05, -0.02, 0.08]), np.array([-0.1, 0.0, 0.0, 0.0])):
        v = Verdict(np.zeros(7), {"noise": 1.0}, "noise", kept=kept, kept_cov=P)
        est.theta, est._phi = np.array([0.5, 0.0, 0.0, 0.0]), np.array([0.5, 0.0, 0.0, 0.0])
        est._correct(v, est._corrected(v))
        e = est.history[-1]
        assert e.kind == "correction" and np.all(np.isfinite(e.std)) and np.all(np.isfinite(e.cov))
        if kept[0] > 0:
            draws = theta_of(rng.multivariate_normal(kept, P, 20000))
            np.testing.assert_allclose(e.std, draws.std(axis=0), rtol=0.05)
        else:
            np.testing.assert_allclose(e.std, [np.sqrt(P[0, 0]), 0.0, 0.0, 0.0])
