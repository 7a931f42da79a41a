"""Active exploration for the CoM along gravity (ours, beyond the paper's Sec. 6 limitation): when the estimate at rest
leaves a CoM component uncertain, a small, speed-limited reorientation through a moving Attractor target (Eq. 6), a
second window there, one posterior from both poses (RME.estimate on lists, vi.combine), and back to the task."""
from __future__ import annotations

import copy
import dataclasses
import math
from dataclasses import dataclass, field

import mujoco
import numpy as np

import checks
from cpic import Attractor


@dataclass(frozen=True)
class ExploreSettings:
    std_threshold: float = 0.02    # m: explore when a CoM component's posterior std after the estimate at rest is above
    #                                this (from one pose rz keeps about the prior's 0.05 m; rx, ry reach a few mm)
    tilt: float = math.radians(25)  # rad: the reorientation, about a horizontal world axis through the ee origin
    axis: tuple = (0.0, 1.0, 0.0)  # that axis (world, horizontal); at the ready pose it is joint 6's
    pivot: str = "wrist"           # the axis passes through "wrist" (joint 6's anchor: only the wrist need turn,
    #                                the upper links stay where their model errors were referred) or "ee"
    offset_std: float | None = 0.1  # Nm, each window's marginalised offset (vi.precompute; None: RME's 0.005): the
    #                                realistic sensor's bias and the links' model errors change by 0.05-0.15 Nm
    speed: float = 1.5             # rad/s: peak angular speed of the target (cosine profile; ours; joint 6 may
    #                                turn at 2.61 rad/s, panda_facts.md)
    settle: float = 0.2            # s at the tilted target before the window may end (the DS converges at 8 /s)
    window: int = 200              # samples of each pose's window (RME's own, Sec. 4)
    reference: int = 400           # samples, at most, of the still stretch before the change both windows refer to
    still_speed: float = 0.04      # rad/s: every joint slower than this counts as still (the DS still creeps
    #                                back at 0.02-0.04 rad/s for 0.5 s after the tilt; friction then < 0.1 Nm)
    rest_before: float = 0.25      # s the arm must have been still, with the estimate applied, before exploring
    push_threshold: float = 1.5    # Nm: |tau_ext - the torque the estimate predicts| beyond this abandons the
    #                                exploration (a person); moving the wrist at 1.2 rad/s leaves < 0.6 Nm (measured)
    reference_tilt: bool = False   # at start-up, the hand empty (nothing compensated or ever estimated, RME settled)
    #                                and the arm still, make the same tilt load-free and keep how tau_ext changed
    #                                over it (the sensor's pose bias, the links' model errors); a later exploration
    #                                from within reference_tolerance of that start pose refers its tilted window to
    #                                it and keeps RME's offset prior: a 2 s calibration of this one motion, made by
    #                                the explorer itself, once per Explorer
    reference_tolerance: float = 0.05   # rad, on every joint
    reference_limit: float = 0.5   # Nm: a change over the tilt beyond this is not kept, and no reference is made (load-
    #                                free: 0.1-0.3 Nm; a tool held from the start, which RME takes for bias, shows more)
    reference_attempts: int = 3    # reference tilts begun, at most (a push or a load change abandons one)

    def __post_init__(self):
        """Every field checked (checks.py); finite bounds far beyond use (a 10 s settle, 100 Nm, 1000 attempts)."""
        a = checks.array("settings.axis", self.axis, (3,), "[-1e3, 1e3]", "(x, y, 0): a horizontal world axis")
        if np.linalg.norm(a) < 1e-9 or abs(a[2]) > 1e-9:
            raise ValueError(f"settings.axis: expected a horizontal world axis (x, y, 0), found {self.axis!r}")
        if not 0 < abs(checks.number("settings.tilt", self.tilt, "[-0.7854, 0.7854]", "rad (45 deg)")):
            raise ValueError("settings.tilt: expected an angle other than 0 in [-0.7854, 0.7854] rad, found 0")
        for name, interval in (("std_threshold", "(0, 10]"), ("speed", "(0, 2]"), ("settle", "[0, 10]"),
                               ("rest_before", "[0, 10]"), ("window", "20..1000"), ("reference", "1..2000"),
                               ("still_speed", "(0, 10]"), ("push_threshold", "(0, 100]"),
                               ("reference_tolerance", "(0, 3.1416]"), ("reference_limit", "(0, 100]"),
                               ("reference_attempts", "1..1000")):
            checks.number(f"settings.{name}", getattr(self, name), interval)
        checks.flag("settings.reference_tilt", self.reference_tilt)
        checks.choice("settings.pivot", self.pivot, ("wrist", "ee"))
        None if self.offset_std is None else checks.number("settings.offset_std", self.offset_std, "[0, 10]", "Nm")

    def profile(self, t):
        """Angle (rad) of the target along the tilt t [s] after it starts moving: a/2 (1 - cos(pi t / T)),
        T = pi |a| / (2 speed), so the peak angular speed is `speed`; (angle, T)."""
        T = math.pi * abs(self.tilt) / (2.0 * self.speed)
        s = min(max(t / T, 0.0), 1.0)
        return 0.5 * self.tilt * (1.0 - math.cos(math.pi * s)), T


def axis_rotation(axis, angle):
    """Rodrigues: rotation (3, 3) by angle [rad] about the unit direction of axis (3,)."""
    k = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    K = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * K + (1.0 - math.cos(angle)) * K @ K


class MovingAttractor:
    """The Attractor DS (Eq. 6) toward a target the explorer moves: at each instant f = -grad V of
    Attractor(p_star, R_star), so with the target still the loop is the paper's; `move` sets R* = Rot(angle) R0."""

    def __init__(self, base: Attractor):
        self.base = self._now = base
        self.angle, self.axis, self.pivot = 0.0, np.array([0.0, 1.0, 0.0]), base.p_star

    p_star = property(lambda self: self._now.p_star)
    R_star = property(lambda self: self._now.R_star)

    def move(self, angle, axis=None, pivot=None):
        """Target pose turned by angle [rad] about the world axis (3,) through the point pivot (3,):
        R* = Rot R0, p* = pivot + Rot (p0 - pivot) (axis and pivot kept from the last call when None)."""
        self.axis = self.axis if axis is None else np.asarray(axis, dtype=float)
        self.pivot = self.pivot if pivot is None else np.asarray(pivot, dtype=float)
        if angle != self.angle:
            self.angle = float(angle)
            self._now = self.at(angle)

    def at(self, angle):
        """The Attractor of the target at `angle` about the current axis and pivot."""
        if angle == 0.0:
            return self.base
        Rot = axis_rotation(self.axis, angle)
        return dataclasses.replace(self.base, p_star=self.pivot + Rot @ (self.base.p_star - self.pivot),
                                   R_star=Rot @ self.base.R_star)

    __call__ = lambda self, p, R: self._now(p, R)                 # -> f (6,), (V_pos, V_rot)


@dataclass
class Exploration:
    """One exploration: times [s] (start: the target starts moving; end: it is back), status ("applied", "recorded"
    or "refused: <why>" (a reference tilt), or "abandoned: <why>"), the estimate it started from and the one from
    both poses (or None)."""
    start: float
    status: str = "running"
    end: float = float("nan")
    before: object = None          # rme.Estimate
    after: object = None           # rme.Estimate from both windows, or None
    deviation: float = 0.0         # Nm, largest |tau_ext - predicted| seen while exploring
    reference: bool = False        # the load-free reference tilt (ExploreSettings.reference_tilt): no estimate
    referred: bool = False         # its tilted window was referred to a reference tilt
    angle: list = field(default_factory=list)   # (t, target angle) of every step while exploring


class Explorer:
    """Wraps RME in the loop (runner.run(..., explorer=...)): update(q, dq, tau_ext) feeds RME and returns the
    compensation; after an accepted estimate at rest whose CoM std exceeds settings.std_threshold it moves the
    controller's target (a MovingAttractor around its Attractor), estimates from both poses and compensates that
    estimate until RME's own estimate changes. A push (tau_ext departing from the estimate's prediction) or an
    RME detection abandons it at once: the target returns, nothing from it is applied."""

    def __init__(self, settings: ExploreSettings = ExploreSettings()):
        if not isinstance(settings, ExploreSettings):
            raise ValueError(f"settings: expected an ExploreSettings, found {type(settings).__name__}")
        self.settings, self.log = settings, []

    def attach(self, controller, rme):
        """Take over the controller's Attractor target and wrap the estimator rme (an RME); returns self."""
        if not isinstance(getattr(controller, "policy", None), Attractor):
            raise ValueError(f"controller.policy: expected a cpic.Attractor to move, found "
                             f"{type(getattr(controller, 'policy', None)).__name__}")
        if not all(hasattr(rme, a) for a in ("update", "estimate", "history", "theta", "settings", "robot", "dropped")):
            raise ValueError(f"estimator: expected an rme.RME to explore for, found {type(rme).__name__}")
        self.ctrl, self.rme, self.robot = controller, rme, rme.robot
        self.policy = MovingAttractor(controller.policy)
        controller.policy = self.policy
        keep = 4 * int(round(rme.settings.rate))                      # 4 s of samples
        self._q, self._dq, self._tau = (np.zeros((keep, self.robot.n)) for _ in range(3))
        self._k, self._still, self._seen, self._phase = 0, 0, 0, None
        self._theta, self._from, self._limit = None, None, self.robot.torque_limits()
        self.references = []       # (start pose q (n,), load-free change of tau_ext over the tilt (n,)), newest last
        self._attempts = 0         # reference tilts begun; the last one ended "recorded" or "refused": none more
        return self

    # --- what the runner reads ---------------------------------------------------------------------------
    @property
    def theta(self):
        """The compensated estimate (4,): the exploration's while it holds, else RME's."""
        return self.rme.theta if self._theta is None else self._theta

    history, t = property(lambda self: self.rme.history), property(lambda self: self._k / self.rme.settings.rate)

    # --- the loop ------------------------------------------------------------------------------------------
    def update(self, q, dq, tau_ext):
        dropped = self.rme.dropped
        comp = self.rme.update(q, dq, tau_ext)
        if self.rme.dropped > dropped:                                # a faulty sample RME dropped: not kept here
            return comp if self._theta is None else self._hold(q)     #   either (the sample counts stay RME's)
        i = self._k % len(self._q)
        self._q[i], self._dq[i], self._tau[i] = q, dq, tau_ext
        self._k += 1
        self._still = self._still + 1 if np.abs(dq).max() < self.settings.still_speed else 0
        if self.ctrl.policy is not self.policy:                      # the task switched policy: follow it
            if self._phase is not None:                              # at once: its new target is not turned
                x, self._phase, self.rme.paused = self._x, None, False
                done = ("recorded" if x.reference else "applied") if x.status == "returning" else x.status
                x.end, x.status = self.t, done if done != "running" else "abandoned: the task changed its target"
            if isinstance(self.ctrl.policy, Attractor):
                self.policy = MovingAttractor(self.ctrl.policy)
                self.ctrl.policy = self.policy
        if self._theta is not None and not np.array_equal(self.rme.theta, self._from):
            self._theta = None                                        # RME estimated a new payload: its turn
        if self._phase is None:
            self._maybe_start()
        else:
            self._advance(q, tau_ext)
        return comp if self._theta is None else self._hold(q)

    def _hold(self, q):
        """The compensation of the exploration's estimate at pose q (n,), within the torque limits."""
        return np.clip(-self.robot.payload_torque(q, self._theta), -self._limit, self._limit)

    def _maybe_start(self):
        """Explore after an accepted estimate that RME has applied and will not refine, once the arm is still."""
        s, rs, hist = self.settings, self.rme.settings, self.rme.history
        if self.ctrl.policy is not self.policy:
            return                                                    # the task's DS is no Attractor: not ours to move
        ended = self.log and self.log[-1].reference and not self.log[-1].status.startswith("abandoned")
        if s.reference_tilt and self._attempts < s.reference_attempts and not ended and not hist and \
                float(self.theta[0]) == 0.0 and self.rme.settled and \
                self.policy.angle == 0.0 and self._still >= max(s.window, int(s.rest_before * rs.rate)):
            if np.abs(self._window(s.window)[2]).max() < rs.rest_speed:   # still: no friction in window a
                self._attempts += 1
                return self._start(Exploration(self.t, reference=True), np.zeros(4))
        if len(hist) == self._seen or self.policy.angle != 0.0:
            return
        e = hist[-1]
        # final: no estimate at rest is owed after it (RME owes one for a change it estimated in motion)
        final = self.rme.settled
        if not (e.accepted and final and np.isfinite(e.applied) and e.applied <= self.t):
            if not e.accepted:
                self._seen = len(hist)
            return
        if self._still < max(s.window, int(s.rest_before * rs.rate)):
            return
        self._seen = len(hist)
        if np.max(e.std[1:]) <= s.std_threshold:
            return
        x = Exploration(self.t, before=e)
        x.base, x.base_q, x.base_dq = self._baseline(e)
        self._start(x, e.mean)

    def _start(self, x, theta0):
        """Window a now, then the target starts to turn; theta0 (4,): the payload the deviation test expects."""
        x.windows = [self._window(self.settings.window)]
        if x.reference:                                               # load-free: the level at the start pose
            x.base, x.base_q, x.base_dq = x.windows[0][1].mean(axis=0), x.windows[0][0], x.windows[0][2]
        x.theta0, x.t0, x.n_history = np.array(theta0, dtype=float), self.t, len(self.rme.history)
        self.policy.move(0.0, self.settings.axis, self._pivot(x.windows[0][0].mean(axis=0)))
        self.log.append(x)
        self._phase, self._x = "out", x
        self.rme.paused = True                                        # the tilt is ours: RME judges after it

    def _reference_at(self, q):
        """The load-free change over the tilt recorded from a start pose within reference_tolerance of q, or None."""
        near = [d for q0, d in self.references if np.abs(q0 - q).max() <= self.settings.reference_tolerance]
        return near[-1] if near else None

    def _level(self, window):
        """Mean tau_ext of a window (q, tau, dq), less RME's correction (the level RME's own windows see)."""
        q, tau, dq = window
        c = self.rme.correction
        return (tau if c is None else tau - c.correction(q, dq)).mean(axis=0)

    def _pivot(self, q):
        return self._pivot_of(self.robot, q, self.settings.pivot, self.policy.base.p_star)

    @staticmethod
    def _pivot_of(robot, q, pivot, p_star):
        """The point (3,) the target turns about: p_star ("ee") or joint 6's anchor at pose q (n,) ("wrist")."""
        if pivot == "ee":
            return np.asarray(p_star, dtype=float)
        d = mujoco.MjData(robot.model)
        d.qpos[:] = q
        mujoco.mj_kinematics(robot.model, d)
        return d.xanchor[5].copy()

    def _baseline(self, e):
        """(tau_ext level (n,), q, dq (1, n)) the estimate e was referred to: RME's reference level (what tau_ext held
        beyond the compensated payload before the change: the robot's bias; RME's correction added back, as the
        windows here are raw tau_ext) and the pose it was taken at."""
        ref = self.rme.model.reference
        if ref is None:
            q, tau, dq = self._window(self.settings.window)
            return (tau - self.robot.payload_torque(q, e.mean)).mean(axis=0), q, dq
        q, dq, c = ref.q[None].copy(), np.zeros((1, self.robot.n)), self.rme.correction
        return ref.level + (0.0 if c is None else c.correction(q, dq).mean(axis=0)), q, dq   # as tau_ext reads it

    def _window(self, T):
        """The last T samples, oldest first: q, tau_ext, dq (T, n)."""
        idx = (self._k - T + np.arange(T)) % len(self._q)
        return self._q[idx].copy(), self._tau[idx].copy(), self._dq[idx].copy()

    def _advance(self, q, tau_ext):
        s, x = self.settings, self._x
        dev = float(np.linalg.norm(tau_ext - x.base - self.robot.payload_torque(q, x.theta0)))
        x.deviation = max(x.deviation, dev)
        if self._phase != "back":
            if dev > s.push_threshold:
                self._abandon(f"tau_ext departed {dev:.2f} Nm from the estimate's prediction (a push)")
            elif len(self.rme.history) > x.n_history:
                self._abandon("RME detected a change")
        t = self.t - x.t0
        if self._phase == "out":
            angle, T = s.profile(t)
            self.policy.move(angle)
            if t >= T + s.settle and self._still >= s.window:
                x.windows.append(self._window(s.window))
                if x.reference:
                    a, b = x.windows
                    change = self._level(b) - self._level(a)
                    if np.linalg.norm(change) <= s.reference_limit:
                        self.references.append((a[0].mean(axis=0), change))
                        self._return(x, "returning")
                    else:                                             # something on the hand: not load-free
                        self._return(x, f"refused: tau_ext changed {np.linalg.norm(change):.2f} Nm over the tilt")
                else:
                    self._estimate(x)
        elif self._phase == "back":
            angle, T = s.profile(t - x.t_back)
            self.policy.move(x.angle_back - angle * x.angle_back / s.tilt)
            if t - x.t_back >= T:
                self.policy.move(0.0)
                self._phase, x.end, self.rme.paused = None, self.t, False
                x.status = ("recorded" if x.reference else "applied") if x.status == "returning" else x.status
        x.angle.append((self.t, self.policy.angle))

    def _estimate(self, x):
        """One posterior from the window at the start pose and the one at the tilted pose, each referred to the
        baseline, each with its own marginalised offset: the load-free level at the tilted pose is not known, unless
        a reference tilt from this start pose recorded how it changes (then RME's own offset prior)."""
        qs, taus, dqs = zip(*x.windows)
        corr = self.rme.correction                # RME subtracts it from the windows: refer to the corrected level
        base = x.base if corr is None else x.base - corr.correction(x.base_q, x.base_dq).mean(axis=0)
        taus = [tau - base for tau in taus]
        tilt = self._reference_at(qs[0].mean(axis=0))
        if tilt is not None:                                         # what the tilt changes with no load on
            taus[1] = taus[1] - tilt
            x.referred = True
        rme = self.rme
        if self.settings.offset_std is not None and tilt is None:   # the same estimator, its offset prior changed
            rme = copy.copy(rme)
            rme.settings = dataclasses.replace(rme.settings, vi=dataclasses.replace(
                rme.settings.vi, offset_std=self.settings.offset_std))
        e = rme.estimate(list(qs), taus, dq=list(dqs) if rme.correction is not None else None, referred=True)
        x.after, e.kind, e.t = e, "exploration", self.t
        if np.all(np.abs(e.mean[1:]) <= self.rme.settings.max_com) and np.isfinite(e.mean).all():
            self._theta, self._from, e.applied = e.mean.copy(), self.rme.theta.copy(), self.t
            self._return(x, "returning")
        else:
            self._return(x, "abandoned: the estimate from both poses is not a payload")

    def _abandon(self, why):
        self._x.after = self._return(self._x, f"abandoned: {why}")

    def _return(self, x, status):
        x.status, x.t_back, x.angle_back, self._phase = status, self.t - x.t0, self.policy.angle, "back"
