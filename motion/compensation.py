"""The payload's inertial torque compensated beside RME's static one: tau_comp = -tau_mm(q, theta_hat) -
(Y(q, dq, ddq_hat) - Y(q, 0, 0)) pi_hat, pi_hat fitted on windows in motion (motion/inertia.py), the arm's own
residual taken from the same motion without payload (Khalil, Gautier, Lemoine, ICRA 2007: loaded minus unloaded)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

import checks
from dynamics import phi_of, skew
from motion.inertia import FitInfo, FitSettings, fit_normal, fit_steps, inertia_of, rigid_body, savgol


@dataclass(frozen=True)
class InertiaSettings:
    rate: float = 1000.0            # Hz, the control loop
    filter_window: int = 41         # samples (41 ms) of the Savitzky-Golay filters on dq, the ee twist and tau_ext
    filter_order: int = 2           # their local polynomial: a causal derivative of order 2 has no lag on a parabola
    every: int = 10                 # samples between two rows kept for the fit (the filters overlap 4 rows)
    min_speed: float = 0.1          # rad/s: a row counts as motion when a joint moves faster (the rest tells nothing)
    window: int = 300               # rows of motion (3 s at every = 10) before a fit, and between two fits
    max_rows: int = 1200            # rows of one load fitted: the newest max_rows // window windows (12 s of motion)
    reference_rows: int = 3000      # rows of unloaded motion kept as the arm's own residual (30 s)
    min_reference: int = 200        # rows: with fewer, fit the absolute residual (offsets only)
    scale: tuple = (0.2, 1.0, 0.05)  # Nm per rad, per rad/s, per rad/s^2: how fast the arm's own residual changes
                                    #   with q (the pose bias), dq (friction's slope) and ddq (rotor inertia); the
                                    #   state distance of a reference row is in Nm through these (ours)
    max_distance: float = 0.1       # Nm: a loaded row further from every reference row is not used
    observer_gain: float | None = None   # 1/s: tau_ext from a first-order observer; its lag undone as
                                         #   tau + dtau/dt / K (None: tau_ext has no lag)
    unloaded_mass: float = 0.05     # kg: RME's estimate below this is no payload (its motion is the reference)
    max_torque: float = 5.0         # Nm per joint: the inertial part never asks for more (a payload's is < 1 Nm)
    max_relative_std: float = 0.1   # a fit is applied only when every diagonal inertia's std is below this share
                                    #   of it (an overestimate cancels more inertia than the light wrist has)
    max_acceleration: float = 50.0  # m/s^2 and rad/s^2: the ee acceleration used is clipped to this
    jolt: float = 0.05              # Nm on any joint: a step this large of RME's compensation in one sample (it
                                    #   switching on) or of the inertial part when a fit is applied jolts the arm;
                                    #   smooth motion changes the static one by < 0.01 Nm per sample (7 Nm/rad at
                                    #   1 rad/s) (ours)
    settle: float = 0.3             # s: rows whose filter window starts within this of such a step or of a new
                                    #   estimate are not used (measured: their residual is 10-80 x the settled one
                                    #   for 0.3 s, docs/inertia.md) (ours)
    fit: FitSettings = field(default_factory=FitSettings)

    def __post_init__(self):
        """Every field checked (checks.py), with finite bounds far beyond use (a kHz loop, 1e3 Nm, 1e6 rows)."""
        number = checks.number
        number("settings.rate", self.rate, "[10, 1e4]", "Hz")
        number("settings.filter_order", self.filter_order, "0..10")
        if number("settings.filter_window", self.filter_window, f"{self.filter_order + 3}..1001", "samples") % 2 == 0:
            raise ValueError(f"settings.filter_window: expected an odd number of samples, found {self.filter_window}")
        for name, interval in (("every", "1..1000"), ("min_speed", "[0, 10]"), ("max_rows", "20..1000000"),
                               ("window", f"20..{self.max_rows}"), ("reference_rows", "1..1000000"),
                               ("min_reference", f"0..{self.reference_rows}"), ("max_distance", "(0, 1e3]"),
                               ("unloaded_mass", "[0, 50]"), ("max_torque", "(0, 1e3]"),
                               ("max_relative_std", "(0, 10]"), ("max_acceleration", "(0, 1e3]"), ("jolt", "(0, 1e3]"),
                               ("settle", "[0, 60]")):
            number(f"settings.{name}", getattr(self, name), interval)
        checks.array("settings.scale", self.scale, (3,), "(0, 1e3]", "(Nm per rad, rad/s, rad/s^2)")
        None if self.observer_gain is None else number("settings.observer_gain", self.observer_gain, "(0, 1e4]", "1/s")
        checks.instance("settings.fit", self.fit, FitSettings)


def _cross(a, b):
    """a x b for (3,) arrays, without np.cross's overhead (the 1 kHz path)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def motion_wrench(pi, w, al, a, I=None):
    """The ee-frame wrench (f (3,), n (3,)) that moves the payload pi (10,) with angular velocity w, acceleration al
    and origin acceleration a (3,) each (ee frame, gravity not in a): Newton-Euler, h = m c,
    f = m a + al x h + w x (w x h),  n = I al + w x (I w) + h x a.  I: inertia_of(pi) if already formed."""
    h, I = pi[1:4], inertia_of(pi) if I is None else I
    f = pi[0] * a + _cross(al, h) + _cross(w, _cross(w, h))
    n = I @ al + _cross(w, I @ w) + _cross(h, a)
    return f, n


def regressor_rows(J, R, w, al, a):
    """Y (n, 10) with tau = Y pi the torque the payload applies (paper sign, as dynamics.Robot.body_regressor) from
    the ee's J (6, n), R (3, 3) and ee-frame w, al, a (3,) (a = origin acceleration - g, in the ee frame)."""
    x, y, z = al
    La = np.array([[x, y, 0, z, 0, 0], [0, x, y, 0, z, 0], [0, 0, 0, x, y, z]])      # I al = La (Ixx, ..., Izz)
    x, y, z = w
    Lw = np.array([[x, y, 0, z, 0, 0], [0, x, y, 0, z, 0], [0, 0, 0, x, y, z]])
    W = skew(w)
    Af = np.zeros((3, 10))
    Af[:, 0], Af[:, 1:4] = a, skew(al) + W @ W
    An = np.zeros((3, 10))
    An[:, 1:4], An[:, 4:] = -skew(a), La + W @ Lw
    return -(J[:3].T @ (R @ Af) + J[3:].T @ (R @ An))


class InertialCompensation:
    """Wraps an RME for the runner: update(q, dq, tau_ext) passes the sample to rme.update and adds the payload's
    inertial torque, never NaN nor beyond the torque limits. While RME compensates no payload and the arm moves,
    rows of that motion are kept as the arm's own residual; once it compensates one, each row of motion (less its
    nearest unloaded row) is added to running normal equations, and every settings.window rows pi is refitted from
    them (its first four from RME's (m, m r) as the prior); a change of RME's estimate (a new load) starts again from
    a point mass at that estimate. A sample's own work is bounded: one row (every settings.every samples) or one
    step of a refit in flight (motion.inertia.fit_steps; both with every = 1), or, with an executor (submit(fn,
    *args) -> a future with done()), the refit runs there and is polled, never waited on. fits: [(t, pi, FitInfo)],
    t when applied."""

    def __init__(self, rme, settings: InertiaSettings = InertiaSettings(), executor=None):
        checks.instance("settings", settings, InertiaSettings), checks.has_methods("rme", rme, "update")
        None if executor is None else checks.has_methods("executor", executor, "submit")
        if not hasattr(rme, "robot"):
            raise ValueError(f"rme: expected an RME (update, robot, theta), found {type(rme).__name__}")
        self.rme, self.settings, self.executor, s = rme, settings, executor, settings
        self.robot, n, W = rme.robot, rme.robot.n, settings.filter_window
        dt = 1.0 / s.rate
        order = lambda c: np.stack([c[(np.arange(W) - k - 1) % W] for k in range(W)])   # (W, W): row k for
        self._causal_d = order(savgol(W, s.filter_order, 1, dt, causal=True))           #   the newest at slot k
        self._smooth = order(savgol(W, s.filter_order, 0, dt, causal=False))
        self._deriv = order(savgol(W, s.filter_order, 1, dt, causal=False))
        self._twist, self._J, self._R = np.zeros((W, 6)), np.zeros((W, 6, n)), np.zeros((W, 3, 3))
        self._q, self._dq, self._tau = np.zeros((W, n)), np.zeros((W, n)), np.zeros((W, n))
        self._k, self._limit, self._gR = 0, self.robot.torque_limits(), self.robot.g
        self._settle, self._last, self._state = int(round(s.settle * s.rate)), None, None   # RME's last output,
                                                             #   the last (J, R, V, acc) of the inertial torque
        R = s.reference_rows                                 # the unloaded motion, a ring: features (R, 3n),
        self._ref_x, self._ref_sq, self._ref_tau, self._ref_n = np.zeros((R, 3 * n)), np.zeros(R), np.zeros((R, n)), 0
        self._seen, self.pi, self._I, self.fits = None, np.zeros(10), np.zeros((3, 3)), []   # |x|^2 (R,), tau (R, n)
        self.inertial = np.zeros(n)                          # the inertial part of the last output (n,)
        self._reset(np.zeros(4))

    @property
    def theta(self):
        return self.rme.theta

    @property
    def history(self):
        return self.rme.history

    @property
    def info(self) -> FitInfo | None:
        """The last applied fit's FitInfo (None before the first fit of the current load)."""
        return self._info

    @property
    def busy(self) -> bool:
        """A refit is in flight."""
        return self._job is not None

    def _reset(self, theta):
        n = self.robot.n
        self._seen, self._info, self._step_at = theta.copy(), None, self._k       # a new estimate: a step
        self._blocks, self._S, self._new = [], np.zeros((n, 12, 12)), 0            # closed windows, the open one
        self._job, self._queued, self._prior = None, None, self._prior_cov()        # a refit in flight: dropped
        loaded = theta[0] >= self.settings.unloaded_mass
        self._set(rigid_body(theta[0], theta[1:]) if loaded else np.zeros(10))   # a point mass until fitted

    def _set(self, pi):
        self.pi, self._I = pi, inertia_of(pi)

    def update(self, q, dq, tau_ext) -> np.ndarray:
        """One 1 kHz sample: RME's compensation (n,) plus the inertial part, clipped to the torque limits."""
        comp = self.rme.update(q, dq, tau_ext)
        q, dq, tau = (np.asarray(v, dtype=float) for v in (q, dq, tau_ext))
        n, W = self.robot.n, self.settings.filter_window
        if q.shape != (n,) or dq.shape != q.shape or tau.shape != q.shape or not np.isfinite(q.sum() + dq.sum()
                                                                                            + tau.sum()):
            return comp                                      # RME dropped it: so does the inertial part
        if np.any(self.rme.theta != self._seen):
            self._reset(self.rme.theta)
        _, R, J = self.robot.kinematics(q)
        k = self._k % W
        self._twist[k], self._J[k], self._R[k] = J @ dq, J, R
        self._q[k], self._dq[k], self._tau[k] = q, dq, tau
        self._k += 1
        if self._k >= W:
            acc = np.clip(self._causal_d[k] @ self._twist, -self.settings.max_acceleration,
                          self.settings.max_acceleration)
            self._state = (J, R, self._twist[k], acc)
            self.inertial = self._torque(*self._state) if self.pi[0] > 0 else np.zeros(n)
        rowed = self._k >= W and self._k % self.settings.every == 0 and self._row(k)
        if not rowed or self.settings.every == 1:             # a refit's step on a sample without a row
            self._advance()
        if self._last is not None and np.abs(comp - self._last).max() > self.settings.jolt:
            self._step_at = self._k                          # RME's part stepped: the arm jolts
        self._last = comp
        return np.clip(comp + self.inertial, -self._limit, self._limit)

    def _torque(self, J, R, V, acc):
        """-(Y(q, dq, ddq_hat) - Y(q, 0, 0)) pi_hat (n,) from the world twist V (6,) and its derivative acc (6,)."""
        Rt = R.T
        f, m = motion_wrench(self.pi, Rt @ V[3:], Rt @ acc[3:], Rt @ acc[:3], self._I)
        tau = J.T @ np.concatenate([R @ f, R @ m])
        return np.clip(tau, -self.settings.max_torque, self.settings.max_torque) if np.isfinite(tau.sum()) else 0 * tau

    def _row(self, k) -> bool:
        """One row at the centre of the filter window: smoothed q-state, tau_ext and the regressor, filtered alike;
        none while the window starts within settings.settle of a step. O(reference_rows n + n 12^2) operations.
        True when it kept the row."""
        s, W = self.settings, self.settings.filter_window
        c = (k + 1 + W // 2) % W                             # the centre sample's slot
        S, D = self._smooth[k], self._deriv[k]
        dq, ddq, tau = S @ self._dq, D @ self._dq, S @ self._tau
        if s.observer_gain:
            tau = tau + (D @ self._tau) / s.observer_gain     # tau_ext lags the torque by 1/K
        if np.abs(dq).max() < s.min_speed or self._k - W < self._step_at + self._settle:
            return False
        x = np.concatenate([self._q[c] * s.scale[0], dq * s.scale[1], ddq * s.scale[2]])
        if self.pi[0] <= 0:                                   # no payload: the arm's own residual
            i = self._ref_n % len(self._ref_x)
            self._ref_x[i], self._ref_sq[i], self._ref_tau[i], self._ref_n = x, x @ x, tau, self._ref_n + 1
            return True
        J, R, V, acc = self._J[c], self._R[c], S @ self._twist, D @ self._twist
        Y = regressor_rows(J, R, R.T @ V[3:], R.T @ acc[3:], R.T @ (acc[:3] - self._gR))
        found = True
        if self._ref_n >= s.min_reference:                    # loaded minus unloaded: the nearest reference row
            m = min(self._ref_n, len(self._ref_x))
            d2 = self._ref_sq[:m] - 2.0 * (self._ref_x[:m] @ x)  # |r - x|^2 - |x|^2 (m,)
            i = int(np.argmin(d2))
            found, tau = d2[i] + x @ x <= s.max_distance ** 2, tau - self._ref_tau[i]
        z = np.concatenate([Y, tau[:, None], np.ones((len(tau), 1))], axis=1)       # (n, 12): (Y_j, tau_j, 1)
        zz = np.einsum("ji,jk->jik", z, z)
        if found and np.isfinite(zz).all():
            self._S += zz
        self._new += 1
        if self._new >= s.window:                             # a window closes: refit on the newest ones
            self._blocks = (self._blocks + [self._S])[-max(s.max_rows // s.window, 1):]
            self._S, self._new = np.zeros_like(self._S), 0
            self._start(sum(self._blocks))
        return True

    def _start(self, S):
        """A refit on the statistics S (n, 12, 12): on the executor, or as steps run one per sample."""
        if self._job is not None:
            self._queued = S                                  # after the one in flight
            return
        args = (S, phi_of(self._seen), self._prior, self.settings.fit)
        self._job = fit_steps(*args) if self.executor is None else self.executor.submit(fit_normal, *args)

    def _advance(self):
        """One step of the refit in flight (inline), or a look whether the executor's is done; applies a result."""
        job = self._job
        if job is None:
            return
        try:
            if self.executor is not None:
                if not job.done():
                    return
                result = job.result()
            else:
                next(job)
                return
        except StopIteration as done:
            result = done.value
        except (np.linalg.LinAlgError, ValueError):
            result = None                                     # a degenerate fit: nothing to apply
        self._job = None
        if result is not None:
            self._apply(*result)
        if self._queued is not None:
            S, self._queued = self._queued, None
            self._start(S)

    def _apply(self, pi, info):
        """Applied when the diagonal inertia is determined (max_relative_std) and pi is finite."""
        s, d = self.settings, np.diag(inertia_of(pi))
        if (info.status != "no data" and np.all(np.isfinite(pi))
                and np.all(info.std[[4, 6, 9]] <= s.max_relative_std * np.maximum(d, 1e-4))):
            self._info = info
            self._set(pi)
            self.fits.append((self._k / s.rate, pi.copy(), info))
            if self._state is not None and np.abs(self._torque(*self._state) - self.inertial).max() > s.jolt:
                self._step_at = self._k                       # the inertial part steps: the arm jolts

    def refit(self):
        """Fit pi now, within this call (a few ms: not for the 1 kHz loop), on the newest windows and the open one;
        applied as in the loop. Returns the FitInfo (None without rows)."""
        keep = max(self.settings.max_rows // self.settings.window, 1)
        S = sum(self._blocks[max(len(self._blocks) - keep + 1, 0):] + [self._S])
        if S[0, 11, 11] < 1:
            return None
        pi, info = fit_normal(S, phi_of(self._seen), self._prior, self.settings.fit)
        self._apply(pi, info)
        return info

    def _prior_cov(self):
        """RME's covariance of the compensated estimate carried to phi = (m, m r) (4, 4); None if it has none."""
        theta = self._seen
        e = next((e for e in reversed(getattr(self.rme, "history", [])) if e.accepted
                  and np.allclose(e.mean, theta)), None)
        if e is None or not np.all(np.isfinite(e.cov)):
            return None
        Jt = np.eye(4)
        Jt[1:, 0], Jt[1:, 1:] = theta[1:], theta[0] * np.eye(3)       # d(m, m r) / d(m, r)
        return Jt @ e.cov @ Jt.T
