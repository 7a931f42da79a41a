"""The physical effects a robot model is made of (Eq. 1 split into parts, the paper's payload Eqs. 4-5, and
the Sec. 6 limitations: friction, offsets, rotor inertia, a tilted base). Each is a regressor block linear in its
parameters, in the sign of the measured joint torque tau_J, so masses and friction coefficients come out positive."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.optimize import least_squares
from scipy.signal import savgol_filter
from scipy.special import expit

from diagnosis.batch_dynamics import BatchDynamics
from dynamics import Robot
from diagnosis.logs import Log


@dataclass(frozen=True)
class EffectConfig:
    """Shape constants of the library's nonlinear friction terms."""
    coulomb_width: float = 0.05              # rad/s, tanh(dq / width): sharp beside Gaz's 0.1-0.4 rad/s sigmoids
    sigmoid_p2: tuple = (0.5, 200.0)         # s/rad, bounds of Gaz p2 (fitted values 5-17, Gaz et al. 2019)
    sigmoid_p3: tuple = (-0.3, 0.3)          # rad/s, bounds of Gaz p3 (fitted |p3| < 0.05, Gaz et al. 2019)
    sigmoid_rows: int = 2000                 # samples per joint used for the nonlinear fit (every k-th row)


class Signals:
    """What regressors read: the log's t (T,), q, dq, ddq (T, n), the robot, and the nominal rigid-body terms computed
    once per log with BatchDynamics: gravity G (T, n), motion M ddq + C dq (T, n), the gravity map W (T, n, 3) with
    G(q; v) = -W v, and the end-effector regressors (paper sign). Cached: each is computed on first use."""

    def __init__(self, log: Log, robot: Robot, batch: BatchDynamics | None = None):
        if log.n != robot.n:
            raise ValueError(f"log: expected {robot.n} joints for this robot, found {log.n}")
        self.log, self.robot = log, robot
        self.t, self.q, self.dq, self.ddq = log.t, log.q, log.dq, log.ddq
        self.batch = batch if batch is not None else BatchDynamics(robot)
        self.smoothing = log.info.get("smoothing")        # (window, order) applied to the log's torques, or None
        self._k, self._cache = None, {}

    @property
    def n(self) -> int:
        return self.robot.n

    def __len__(self) -> int:
        return len(self.t)

    def _kin(self):
        if self._k is None:
            self._k = self.batch.forward(self.q, self.dq, self.ddq, self.robot.g)
        return self._k

    def cached(self, name: str, fn: Callable[[], np.ndarray]) -> np.ndarray:
        """fn() computed once per log under `name` (for expensive user-defined regressors)."""
        if name not in self._cache:
            self._cache[name] = fn()
        return self._cache[name]

    @property
    def gravity(self):                       # G(q) (T, n): the torque that holds the arm still
        return self.cached("gravity", lambda: -self._kin()["W"] @ self.robot.g)

    @property
    def inverse_dynamics(self):              # M ddq + C dq + G (T, n), the nominal model of Eq. 1
        return self._kin()["tau"]

    @property
    def motion(self):                        # M(q) ddq + C(q, dq) dq (T, n)
        return self.cached("motion", lambda: self._kin()["tau"] - self.gravity)

    @property
    def gravity_map(self):                   # W (T, n, 3): G(q; v) = -W v for a gravity vector v
        return self._kin()["W"]

    @property
    def payload(self):                       # (T, n, 4): tau_mm = Y phi (paper sign, Eqs. 4-5)
        return self.cached("payload", lambda: self.batch.payload_regressor(self._kin(), self.robot.g))

    @property
    def body(self):                          # (T, n, 10): rigid payload under motion (paper sign)
        return self.cached("body", lambda: self.batch.body_regressor(self._kin()))

    def smooth(self, Y: np.ndarray) -> np.ndarray:
        """Y (T, ...) through the same Savitzky-Golay filter as the log's torques ("parallel filtering": tau_J and the
        regressors stay consistent, e.g. at the steps of Coulomb friction); only non-zero columns are filtered."""
        if self.smoothing is None or len(Y) <= self.smoothing[0]:
            return Y
        flat = Y.reshape(len(Y), -1)
        cols = np.flatnonzero(np.any(flat != 0, axis=0))
        out = flat.copy()
        out[:, cols] = savgol_filter(np.ascontiguousarray(flat[:, cols].T), self.smoothing[0], self.smoothing[1],
                                     axis=-1, mode="interp").T
        return out.reshape(Y.shape)

    def measured(self) -> np.ndarray:
        """tau_J (T, n); for a log without it, tau_J = nominal model - tau_ext (Eq. 1, tau_ext in the paper's sign)."""
        if self.log.tau_J is not None:
            return self.log.tau_J
        return self.inverse_dynamics - self.log.tau_ext


def per_joint(x: np.ndarray) -> np.ndarray:
    """A per-joint signal x (T, n) as a regressor block (T, n, n): joint j's torque = p_j x[:, j]."""
    T, n = x.shape
    Y = np.zeros((T, n, n))
    Y[:, np.arange(n), np.arange(n)] = x
    return Y


@dataclass(frozen=True)
class Effect:
    """One physical effect: tau (T, n) = regressor(signals) @ p, with p the parameters named `params` in `units`.

    per_joint: each name stands for n parameters, one per joint (fv -> fv per joint), block per_joint(x).
    nominal: parameter values the nominal model already assumes (1 for its own gravity and motion, else 0).
    signal: what to plot the residual against ("q", "dq", "ddq", "t"; "" = against the effect's own torque).
    payload: part of the load rather than of the robot (reported as theta = (m, r) when possible).
    smooth: filter the block like the log's torques (needed for sharp regressors such as Coulomb friction; the
    library's smooth effects skip it, since their content lies inside the filter's pass band anyway).
    Nonlinear effects also give nonlinear=(names, units, initial (n, k)) and fit_nonlinear(signals, z, nl) -> nl
    (signals: the training rows only, z (T', n) the residual they should explain, nl the start), and their regressor
    takes (signals, nl)."""
    name: str
    explanation: str
    regressor: Callable
    params: tuple
    units: tuple
    per_joint: bool = False
    nominal: float = 0.0
    signal: str = ""
    payload: bool = False
    nonlinear: tuple | None = None
    fit_nonlinear: Callable | None = None
    smooth: bool = True

    def size(self, n: int) -> int:
        return len(self.params) * (n if self.per_joint else 1)

    def block(self, s: Signals, nl=None) -> np.ndarray:
        """The checked regressor block (T, n, k), filtered like the log's torques if self.smooth. A per-joint effect
        with one parameter name may return its signal x (T, n) instead of per_joint(x). Linear effects are cached."""
        if not self.nonlinear:
            return s.cached(("block", self.name, id(self.regressor)), lambda: self._block(s, None))
        return self._block(s, nl)

    def _block(self, s, nl):
        Y = np.asarray(self.regressor(s, nl) if self.nonlinear else self.regressor(s), dtype=float)
        T, n = len(s), s.n
        diagonal = self.per_joint and len(self.params) == 1 and Y.shape == (T, n)
        want = (T, n) if diagonal else (T, n, self.size(n))
        if Y.shape != want:
            raise ValueError(f"effect {self.name!r}: regressor expected shape {want}, found {Y.shape}")
        if not np.all(np.isfinite(Y)):
            raise ValueError(f"effect {self.name!r}: regressor returned NaN/inf")
        Y = s.smooth(Y) if self.smooth else Y
        return per_joint(Y) if diagonal else Y

    def describe(self, p, nl=None, n: int = 7) -> str:
        """The parameters p (and nonlinear nl (n, k)) with their units as one line; theta = (m, r) for a payload."""
        p = np.asarray(p, dtype=float)
        lines = []
        k = n if self.per_joint else 1
        for i, (name, unit) in enumerate(zip(self.params, self.units)):
            vals = p[i * k:(i + 1) * k]
            lines.append(f"{name} = {_fmt(vals)} {unit}")
        if self.nonlinear and nl is not None:
            for i, (name, unit) in enumerate(zip(self.nonlinear[0], self.nonlinear[1])):
                lines.append(f"{name} = {_fmt(np.asarray(nl)[:, i])} {unit}")
        if self.payload and p[0] > 1e-6:
            lines.append(f"theta: m = {p[0]:.3f} kg, r = {_fmt(p[1:4] / p[0])} m (ee frame)")
        return "; ".join(lines)


def custom(name: str, explanation: str, regressor: Callable, params, units, per_joint_params: bool = False,
           signal: str = "") -> Effect:
    """A user-defined effect from one regressor function signals -> (T, n, k) block (or, with per_joint_params and
    one parameter name, its per-joint signal (T, n)); signals offers t, q, dq, ddq, robot, gravity, motion, ..."""
    params, units = tuple(params), tuple(units)
    if len(params) != len(units):
        raise ValueError(f"units: expected one unit per parameter ({len(params)}), found {len(units)}")
    return Effect(name, explanation, regressor, params, units, per_joint=per_joint_params, signal=signal)


def _fmt(v):
    v = np.atleast_1d(v)
    return f"{v[0]:.4g}" if len(v) == 1 else "[" + ", ".join(f"{x:.4g}" for x in v) + "]"


# --- the Gaz sigmoid friction: tau_f = p1 / (1 + exp(-p2 (dq + p3))) - p1 / (1 + exp(-p2 p3)) -------------
def _sigmoid_shape(dq, p2, p3):
    """(T, n) shape functions of the Gaz friction for p2, p3 (n,): tau_f = p1 * shape, shape(0) = 0."""
    return expit(p2 * (dq + p3)) - expit(p2 * p3)


def _fit_sigmoid(s: Signals, z: np.ndarray, nl: np.ndarray, cfg: EffectConfig = EffectConfig()) -> np.ndarray:
    """(p2, p3) per joint (n, 2) fitting z (T, n), the residual to explain, by z_j ~ p1 shape(dq_j; p2, p3) + c_j.
    The nuisance constant c_j keeps a sensor offset from bending the shape (an offset is its own effect). Per joint,
    scipy.optimize.least_squares (Levenberg-Marquardt, analytic Jacobian) over x = (p1, log p2, atanh(p3 / b), c),
    so p3 stays inside +-b, from the best p2 of a coarse grid (or the previous value)."""
    step = max(1, len(s) // cfg.sigmoid_rows)
    dq, z = s.dq[::step], z[::step]
    n, b = dq.shape[1], max(abs(cfg.sigmoid_p3[0]), abs(cfg.sigmoid_p3[1]))
    out = np.empty((n, 2))
    for j in range(n):
        v, zj = dq[:, j], z[:, j]

        def residual(x):
            return zj - x[0] * _sigmoid_shape(v, np.exp(min(x[1], 30.0)), b * np.tanh(x[2])) - x[3]

        def jacobian(x):
            p2, p3 = np.exp(min(x[1], 30.0)), b * np.tanh(x[2])
            sg, s0 = expit(p2 * (v + p3)), expit(p2 * p3)
            d, d0 = sg * (1 - sg), s0 * (1 - s0)
            dp3 = x[0] * p2 * (d - d0) * b * (1 - np.tanh(x[2]) ** 2)
            return -np.stack([sg - s0, x[0] * p2 * (d * (v + p3) - d0 * p3), dp3, np.ones_like(v)], axis=1)

        starts = [(p2, 0.0) for p2 in (2.0, 5.0, 10.0, 20.0, 50.0)] + [(nl[j, 0], np.clip(nl[j, 1], -0.9 * b, 0.9 * b))]
        best = None
        for p2, p3 in starts:                # p1, c in closed form for each start
            A = np.stack([_sigmoid_shape(v, p2, p3), np.ones_like(v)], axis=1)
            (p1, c), err = np.linalg.lstsq(A, zj, rcond=None)[:2]
            err = err[0] if len(err) else np.inf
            if best is None or err < best[0]:
                best = (err, np.array([p1, np.log(p2), np.arctanh(p3 / b), c]))
        x = best[1]
        if best[0] < 0.99 * np.sum((zj - zj.mean()) ** 2):     # a shape that explains nothing has no optimum
            x = least_squares(residual, x, jac=jacobian, method="lm", xtol=1e-6, ftol=1e-6, max_nfev=50).x
        out[j] = np.clip(np.exp(x[1]), *cfg.sigmoid_p2), b * np.tanh(x[2])
    return out


def library(config: EffectConfig = EffectConfig()) -> dict:
    """The built-in effects by name (regressors in the tau_J sign: the torque the drives add for the effect)."""
    w = config.coulomb_width

    def tilt(s):                             # dg = (ax e_x + ay e_y) x g, tau = G(q; dg) = -W dg
        W, g = s.gravity_map, s.robot.g
        return -np.stack([W @ np.cross([1.0, 0, 0], g), W @ np.cross([0, 1.0, 0], g)], axis=2)

    effects = [
        Effect("gravity", "the arm's own weight, G(q) of the nominal link masses and CoMs, scaled by k_G",
               lambda s: s.gravity[:, :, None], ("k_G",), ("(1 = nominal)",), nominal=1.0, smooth=False),
        Effect("motion", "the arm's inertial, Coriolis and centrifugal torques M(q) ddq + C(q, dq) dq, scaled by k_M",
               lambda s: s.motion[:, :, None], ("k_M",), ("(1 = nominal)",), nominal=1.0, signal="ddq", smooth=False),
        Effect("payload", "a load at the end-effector whose weight pulls on the arm (static: Eqs. 4-5, "
               "phi = (m, m r), r in the ee frame)", lambda s: -s.payload, ("m", "m_rx", "m_ry", "m_rz"),
               ("kg", "kg m", "kg m", "kg m"), payload=True, smooth=False),
        Effect("rigid_payload", "a rigid load at the end-effector: its weight and its inertia under motion "
               "(Newton-Euler; inertia about the ee origin)", lambda s: -s.body,
               ("m", "m_cx", "m_cy", "m_cz", "Ixx", "Ixy", "Iyy", "Ixz", "Iyz", "Izz"),
               ("kg", "kg m", "kg m", "kg m") + ("kg m^2",) * 6, payload=True, smooth=False),
        Effect("viscous", "friction growing in proportion to joint speed (lubricant shear in the gears), fv dq",
               lambda s: s.dq, ("fv",), ("Nm s/rad",), per_joint=True, signal="dq", smooth=False),
        Effect("coulomb", f"sliding friction of constant size opposing motion, fc sign(dq) (tanh(dq / {w} rad/s))",
               lambda s: np.tanh(s.dq / w), ("fc",), ("Nm",), per_joint=True, signal="dq"),
        Effect("sigmoid", "joint friction as a sigmoid of speed (Gaz et al. 2019): p1/(1+exp(-p2(dq+p3))) - "
               "p1/(1+exp(-p2 p3))", lambda s, nl: _sigmoid_shape(s.dq, nl[:, 0], nl[:, 1]),
               ("p1",), ("Nm",), per_joint=True, signal="dq",
               nonlinear=(("p2", "p3"), ("s/rad", "rad/s"), (10.0, 0.0)),
               fit_nonlinear=lambda s, z, nl: _fit_sigmoid(s, z, nl, config)),
        Effect("offset", "a constant bias of each joint torque sensor (calibration drift)",
               lambda s: np.ones_like(s.q), ("tau_0",), ("Nm",), per_joint=True, signal="t", smooth=False),
        Effect("rotor", "the motor rotor's inertia seen through the gearbox, I_a ddq, missing from a link-only model",
               lambda s: s.ddq, ("I_a",), ("kg m^2",), per_joint=True, signal="ddq", smooth=False),
        Effect("tilt", "the base is not level: gravity tilted by ax about world x and ay about world y "
               "(small angles; G(q; dg), dg = (ax e_x + ay e_y) x g)", tilt, ("ax", "ay"), ("rad", "rad"),
               smooth=False),
    ]
    return {e.name: e for e in effects}
