"""The tool-identification motion about the start pose: a slow cone of the flange's axis (gravity seen from every side:
all three CoM axes), then small wrist oscillations (inertia), within joint limits and a speed limit, tracked by a
joint-space spring-damper; a push (tau_ext leaving the tool's weight) abandons it at once."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dynamics import Robot, as_states
from motion.inertia import rigid_body

WRIST = (4, 5, 6)                  # joints 5, 6, 7 (0-based): they turn the flange; the upper arm stays still


@dataclass(frozen=True)
class MotionSettings:
    rate: float = 1000.0           # Hz, the torque loop
    max_speed: float = 0.4         # rad/s, peak reference speed of any joint (the target is < 0.5 rad/s measured,
    #                                with room for tracking overshoot)
    margin: float = 0.2            # rad kept from every joint limit by the reference (the target)
    tilt: float = 0.5              # rad: the cone's half-angle in joints 5 and 6 (29 deg: gravity's part across
    #                                the flange axis reaches sin 0.5 = 0.48 g, so the CoM along that axis is seen)
    rest: float = 0.75             # s at rest at the start (the push watch's first rows, its compensation fading
    #                                in) and at the end
    ramp: float = 0.25             # share of the cone over which its amplitude rises (and falls: cosine ramps)
    turns: float = 1.0             # cone turns
    shake: float = 8.0             # s of wrist oscillations after the cone
    shake_hz: tuple = (1.1, 1.3, 1.5)   # Hz, joints 5, 6, 7: distinct, so the three axes' accelerations differ
    #                                (ours: 2-3 rad/s^2, a 5e-3 kg m^2 inertia 0.01-0.015 Nm; at 2-3 Hz the arm
    #                                tracks less alike with and without the tool: one realistic tool's diagonal came
    #                                out 18-26 % low there, 2-6 % at 1.1-1.5 Hz, docs/tool_identification.md)
    max_duration: float = 20.0     # s: the whole motion at most (the target)
    max_shift: float = 0.05        # rad: how far the start pose may lie from the motion's centre on any joint (the
    #                                tool run is made about the reference's start: a robot holding a tool it does not
    #                                know sags before control starts, 1.6 mrad on joint 2 on franky-sim for 1.4 kg);
    #                                the fit's reference_tolerance: beyond it the two runs are not the same motion
    kp: tuple = (600.0,) * 4 + (50.0, 50.0, 150.0)   # Nm/rad: cpic.JointHold's gains (a 3 kg load moves the arm
    kd: tuple = (40.0,) * 4 + (4.0, 4.0, 7.0)        # Nm s/rad   by a few mrad), joint 7 three times stiffer (the
    #                                same damping ratio, kd ~ sqrt(kp)): the tool's inertia then changes joint 7's
    #                                tracking 3 times less, and with it the drives' friction and rotor-inertia torque
    #                                of the two runs' difference, which read Izz 5.7 % low at 50 (1.7 % at 150; the
    #                                whole wrist at 150 read Ixx, Iyy 4.5 % high: docs/tool_identification.md)
    soft: float = 0.1              # after a push the spring is kp x soft about where the arm is (a person moves it)
    stop_after: float = 0.2        # s from the push to the run's end (`finished`): the soft spring and the full
    #                                dampers take the arm's speed off meanwhile (the wrist's time constant I / kd is
    #                                10-20 ms, joints 1-4's 30-80 ms); the loop then ramps the command to zero and
    #                                hands the arm back to the robot (franka.run_loop's end)
    push: tuple = (2.5,) * 4 + (1.5,) * 3   # Nm per joint: |tau_ext - predicted| above this is a push (PushWatch:
    #                                with nobody touching, 0.22-0.85 Nm measured on the realistic plant; a force at
    #                                the flange of 7-14 N, by its direction, crosses them at the ready pose)
    push_samples: int = 10         # consecutive samples (10 ms) above it (a single stale or noisy sample is not one)
    compensate: bool = True        # the watch's static fit Y phi + b is compensated: the arm follows the reference
    #                                alike with and without the tool (a 1 kg tool's weight otherwise sags joint 6 by
    #                                0.025 rad, and the arm's own pose-dependent error differs by that much)
    feedforward: bool = True       # with the compensation, the watch's point mass's inertial torque along the
    #                                reference (Y(q, dq, ddq_d) pi less its weight): the tool run then tracks the
    #                                reference as the run without the tool does, so the drives' torques of the two
    #                                runs' difference shrink (the tool's m d^2 about the wrist axes is most of what it
    #                                adds to their inertia)
    settle: float = 0.25           # s: the watch starts after this (a momentum observer, K = 100 /s, and the first
    #                                commands settle; the reference is at rest until settings.rest)
    fade: float = 0.45             # s over which the compensation then fades in (the arm's whole static torque:
    #                                the arm, sagged under the tool's weight at first, 3-8 mrad on joint 2 on the
    #                                realistic plant, is lifted back within the rest, slowly: what the arm's model
    #                                gets wrong of the lift's inertial torque stays in the watch's residual)


def excitation(robot: Robot, q0, settings: MotionSettings = MotionSettings(), center=None):
    """The reference q_d, dq_d, ddq_d (T, n) at settings.rate about `center` (n,) (default q0): rest (from q0 to
    the centre by a cosine ramp), the cone (joints 5, 6 of amplitude a e(t), e a cosine ramp), the oscillations of
    joints 5-7 (each A sin(2 pi f t) under a ramp, A = v / (2 pi f)), rest. Each joint's amplitude is cut to stay
    settings.margin from its limits; the time is scaled so no joint exceeds settings.max_speed. ValueError if q0 or
    the centre is already within the margin of a limit, they lie more than settings.max_shift apart, or the motion
    is too long."""
    s, n = settings, robot.n
    q0 = as_states("q0", q0, n, allow_window=False)[0][0]
    c = q0 if center is None else as_states("center", center, n, allow_window=False)[0][0]
    lo, hi = robot.model.jnt_range[:, 0] + s.margin, robot.model.jnt_range[:, 1] - s.margin
    for name, p in (("q0", q0), ("center", c)):
        if np.any(p < lo) or np.any(p > hi):
            j = int(np.argmax((p < lo) | (p > hi)))
            raise ValueError(f"{name}: expected every joint at least {s.margin} rad inside its limits, found joint "
                             f"{j + 1} at {p[j]:.3f} rad (limits {lo[j] - s.margin:.3f}..{hi[j] + s.margin:.3f})")
    if np.abs(c - q0).max() > s.max_shift:
        j = int(np.argmax(np.abs(c - q0)))
        raise ValueError(f"center: expected within {s.max_shift} rad of the start pose q0 on every joint (the same "
                         f"motion as the reference's), found joint {j + 1} {c[j] - q0[j]:+.3f} rad away: move the arm "
                         f"to the reference's start pose or record the reference again here")
    room = np.minimum(c - lo, hi - c)                           # (n,) what each joint may swing
    dt = 1.0 / s.rate
    a5, a6 = (min(s.tilt, room[j]) for j in WRIST[:2])
    tau = np.linspace(0.0, 1.0, 2001)                          # the cone in normalised time, then stretched so
    e1, th = _ramp(tau, s.ramp, 1.0), 2 * math.pi * s.turns * tau   # its fastest joint moves at max_speed
    v1 = max(np.abs(np.gradient(a5 * e1 * np.sin(th), tau)).max(), np.abs(np.gradient(a6 * e1 * np.cos(th), tau)).max())
    t1 = np.arange(0.0, v1 / s.max_speed, dt)
    e1, th = _ramp(t1 / t1[-1], s.ramp, 1.0), 2 * math.pi * s.turns * t1 / t1[-1]
    d = np.zeros((len(t1), n))
    d[:, WRIST[0]], d[:, WRIST[1]] = a5 * e1 * np.sin(th), a6 * e1 * np.cos(th)
    t2 = np.arange(0.0, s.shake, dt)
    e2 = _ramp(t2 / s.shake, 1.0 / s.shake, 1.0)
    d2 = np.zeros((len(t2), n))
    for j, f in zip(WRIST, s.shake_hz):
        A = min(s.max_speed / 1.3 / (2 * math.pi * f), room[j])   # 1.3: the ramp's share
        d2[:, j] = A * e2 * np.sin(2 * math.pi * f * t2)
    rest = np.zeros((int(round(s.rest * s.rate)), n))
    shift = 0.5 * (1 + np.cos(math.pi * np.linspace(0.0, 1.0, len(rest))))[:, None] * (q0 - c)   # q0 -> centre
    D = np.vstack([shift, d, d2, rest])
    if len(D) * dt > s.max_duration + 1e-9:
        raise ValueError(f"settings: the motion lasts {len(D) * dt:.1f} s, expected at most {s.max_duration} s")
    q = c + D
    dq = np.gradient(q, dt, axis=0)
    ddq = np.gradient(dq, dt, axis=0)
    return q, dq, ddq


def _ramp(t, ramp, end):
    """e(t) (T,): 0 -> 1 over [0, ramp] and 1 -> 0 over [end - ramp, end], cosine-shaped (zero slope at both ends)."""
    up = np.clip(t / ramp, 0.0, 1.0)
    down = np.clip((end - t) / ramp, 0.0, 1.0)
    return 0.25 * (1 - np.cos(math.pi * up)) * (1 - np.cos(math.pi * down))


def point_mass_inertial(robot: Robot, phi, q, dq, ddq) -> np.ndarray:
    """(n,) tau_ext's sign: the inertial torque a point mass phi = (m, m c) (4,) (ee frame) applies at q, dq, ddq (n,):
    the body regressor's less its weight's, Y(q, dq, ddq) pi - Y(q) phi, pi the point mass at c (none below 0.05 kg,
    where c = m c / m is not known)."""
    phi = np.asarray(phi, dtype=float)
    if phi[0] < 0.05:
        return np.zeros(robot.n)
    return robot.body_regressor(q, dq, ddq, gravity=False) @ rigid_body(phi[0], phi[1:] / phi[0])


class PushWatch:
    """Whether tau_ext (paper sign) has left what the tool's weight predicts. H0, no contact: tau_ext = Y(q) phi + b
    + friction + the arm's own model error + the tool's small inertial torque; H1, a person pushes with F at the
    hand: J^T F more. phi (4,) and the offsets b (n,) are least squares on the rows so far (one every 10 samples,
    refitted every 20), so the watch needs no tool known in advance; a push is |r_j| = |tau_ext_j - Y_j phi - b_j|
    above settings.push[j] on a joint for settings.push_samples samples in a row (the thresholds: the largest H0
    residual on the realistic plant over the motion with margin, docs/tool_identification.md)."""

    def __init__(self, robot: Robot, settings: MotionSettings = MotionSettings()):
        self.robot, self.settings, n = robot, settings, robot.n
        self._S = np.zeros((n, 6, 6))                       # per joint sum of z z^T, z = (Y_j (4), tau_j, 1)
        self._phi, self._b, self._k, self._over = np.zeros(4), None, 0, 0
        self.start = int(round(settings.settle * settings.rate))   # samples before the watch starts
        self.limit = np.asarray(settings.push, dtype=float)
        self._prior = np.diag(1.0 / np.square([10.0, 1.0, 1.0, 1.0]))   # kg, kg m: keeps phi finite at one pose
        self.residual = np.zeros(n)                         # the last r (n,) [Nm]
        self.predicted = np.zeros(n)                        # the last Y phi + b (n,) [Nm] (0 before the watch starts)
        self.peak = np.zeros(n)                             # its largest |r| per joint so far

    @property
    def phi(self) -> np.ndarray:
        """(4,) the fit's (m, m c) so far (ee frame, tau_ext's sign: the point mass whose weight it sees)."""
        return self._phi.copy()

    def update(self, q, tau_ext) -> bool:
        """Feed one sample; True from the sample the push is confirmed on."""
        self._k += 1
        if self._k <= self.start:
            return False
        Y = self.robot.payload_regressor(q)                 # (n, 4)
        tau = np.asarray(tau_ext, dtype=float)
        if self._k % 10 == 0 or self._b is None:
            z = np.concatenate([Y, tau[:, None], np.ones((len(tau), 1))], axis=1)   # (n, 6)
            self._S += z[:, :, None] * z[:, None, :]
        if self._k % 20 == 0 or self._b is None:
            self._refit()
        self.predicted = Y @ self._phi + self._b
        self.residual = tau - self.predicted
        self.peak = np.maximum(self.peak, np.abs(self.residual))
        self._over = self._over + 1 if np.any(np.abs(self.residual) > self.limit) else 0
        return self._over >= self.settings.push_samples

    def _refit(self):
        S = self._S
        N = S[0, 5, 5]
        mu = S[:, :5, 5] / N                                # (n, 5) means of (Y_j, tau_j)
        C = S[:, :5, :5] - N * mu[:, :, None] * mu[:, None, :]
        self._phi = np.linalg.solve(C[:, :4, :4].sum(axis=0) + self._prior, C[:, :4, 4].sum(axis=0))
        self._b = mu[:, 4] - mu[:, :4] @ self._phi


class ExcitationController:
    """Tracks excitation(robot, q0) with tau = ID(q, dq, ddq_d) + Kp (q_d - q) + Kd (dq_d - dq) (the nominal model's
    inverse dynamics, a spring-damper to the moving reference: at 0.4 rad/s a person meets a spring, never a fast
    arm), less the watch's fit of the static tau_ext and its point mass's inertial torque along the reference
    (settings.compensate, settings.feedforward). On a push (PushWatch) the motion is abandoned at once: the reference
    stops where the arm is, the spring drops to settings.soft of its stiffness and the compensation keeps the fit of
    the samples before the push; settings.stop_after later `finished` says the run is over (robot.loop.run_loop then
    ends it). step(q, dq, compensation, tau_ext) -> (tau (n,), None) as cpic's controllers; after the reference it
    holds its last point; center: excitation's. abandoned: the time [s] of the push or None; pushed_joint: the joint
    (1-based) furthest over its threshold when the push was confirmed, push_residual its r [Nm]."""

    def __init__(self, robot: Robot, q0, settings: MotionSettings = MotionSettings(), center=None):
        self.robot, self.settings = robot, settings
        self.q_d, self.dq_d, self.ddq_d = excitation(robot, q0, settings, center)
        self.kp, self.kd = np.asarray(settings.kp, float), np.asarray(settings.kd, float)
        self.watch = PushWatch(robot, settings)
        self.k, self.abandoned, self._hold = 0, None, None
        self.pushed_joint, self.push_residual = None, None

    @property
    def finished(self) -> str | None:
        """None while the run is to go on; once settings.stop_after has passed since a push, why it ends."""
        if self.abandoned is None or self.k < (self.abandoned + self.settings.stop_after) * self.settings.rate:
            return None
        return (f"push: the motion abandoned at {self.abandoned:.3f} s (joint {self.pushed_joint}, |tau_ext - "
                f"predicted| {abs(self.push_residual):.2f} Nm), the run ended {self.settings.stop_after} s later")

    @property
    def duration(self) -> float:
        return len(self.q_d) / self.settings.rate

    def step(self, q, dq, compensation=None, tau_ext=None):
        q, dq = np.asarray(q, dtype=float), np.asarray(dq, dtype=float)
        if self.abandoned is None and tau_ext is not None and self.watch.update(q, tau_ext):
            self.abandoned, self._hold = self.k / self.settings.rate, q.copy()
            over = np.abs(self.watch.residual) / self.watch.limit
            self.pushed_joint = int(np.argmax(over)) + 1
            self.push_residual = float(self.watch.residual[self.pushed_joint - 1])
        if self._hold is not None:
            tau = self.robot.gravity(q) + self.settings.soft * self.kp * (self._hold - q) - self.kd * dq
        else:
            i = min(self.k, len(self.q_d) - 1)
            tau = self.robot.inverse_dynamics(q, dq, self.ddq_d[i]) + self.kp * (self.q_d[i] - q) + \
                self.kd * (self.dq_d[i] - dq)
        if self.settings.compensate:                     # tau_ext's sign: the torque the tool applies, undone, faded
            fade = min(max((self.k - self.watch.start) / (self.settings.fade * self.settings.rate), 0.0), 1.0)
            tau = tau - fade * self.watch.predicted
            if self._hold is None and self.settings.feedforward and fade > 0.0:
                tau = tau - fade * point_mass_inertial(self.robot, self.watch.phi, q, dq,
                                                       self.ddq_d[min(self.k, len(self.q_d) - 1)])
        self.k += 1
        return (tau if compensation is None else tau + compensation), None
