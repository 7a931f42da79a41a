"""The physical effects a robot model is made of (Eq. 1 split into parts, the paper's payload Eqs. 4-5, and
the Sec. 6 limitations: friction, offsets, rotor inertia, a tilted base). Each is a regressor block linear in its
parameters, in the sign of the measured joint torque tau_J, so masses and friction coefficients come out positive."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.signal import savgol_filter

from diagnosis.batch_dynamics import BatchDynamics
from diagnosis.friction import fit_coulomb, fit_sigmoid, sigmoid_shape
from diagnosis.logs import Log
from diagnosis.physical import KINDS, Segment, tilt_columns
from dynamics import Robot


# A Panda's static torque error at a pose, per joint, measured: `python rme.py calibrate` on 36 real logs of a Panda
# holding a beam at 6 poses (docs/real_logs.md, load fitted): offset 0.117, -0.832, -0.324, -0.780, 0.100, -0.244,
# -0.070 Nm and absolute std 0.226, 0.103, 0.168, 0.130, 0.190, 0.092, 0.203 Nm; the bound is |offset| + 3 std
# (offset_bounds). Franka's own figure, "a few tenths, up to about 1 Nm on J1-J4" (panda_facts.md), agrees.
PANDA_OFFSET_MAX = (0.80, 1.14, 0.83, 1.17, 0.67, 0.52, 0.68)
PANDA_OFFSET_SOURCE = ("|offset| + 3 std of a real Panda's static error at a pose, calibrated on 36 beam logs "
                       "(docs/real_logs.md)")
BOUND_SIGMAS = 3.0          # stds of a pose's static error the offset bound allows (0.3 % of poses beyond, Gaussian)


def offset_bounds(error_model, gravity=None, links=None) -> tuple[tuple, str]:
    """(bound (n,) [Nm], source) of |tau_0| per joint from an error_model.ErrorModel (a calibration of this robot):
    |offset_j| + BOUND_SIGMAS sqrt(C_jj), C the absolute error's covariance at the log's poses (gravity (P, n): their
    gravity torques; beyond the calibrated range it grows, ErrorModel.absolute_cov_at; for a model of link errors,
    links (P, n, 4 L): the poses' link gravity regressors, ErrorModel.pose_error_at), the largest over them."""
    stds = lambda C: np.sqrt(np.diag(C)) if C.ndim == 2 else C    # absolute_cov_at: (n, n) or stds (n,)
    if error_model.links is not None and links is not None:
        covs = [error_model.pose_error_at(A)[1] for A in links]
    else:
        poses = [None] if gravity is None else np.atleast_2d(gravity)
        covs = [np.asarray(error_model.absolute_cov_at(g)) for g in poses]
    std = np.max([stds(C) for C in covs], axis=0)
    bound = np.abs(np.asarray(error_model.offset)) + BOUND_SIGMAS * std
    return tuple(float(x) for x in np.round(bound, 3)), (f"|offset| + {BOUND_SIGMAS:g} std of the static error at a "
                                                         f"pose, {error_model.source}")


@dataclass(frozen=True)
class EffectConfig:
    """Shape constants and bounds of the library's nonlinear terms."""
    coulomb_width: float = 0.05              # rad/s, start of the fitted width w of tanh(dq / w)
    coulomb_widths: tuple = (0.002, 0.5)     # rad/s, bounds of w: from a step to the width of Gaz's sigmoids
    tilt_max: float = 0.35                   # rad (20 deg), bound of the tilt angles ax, ay
    sigmoid_p2: tuple = (0.5, 200.0)         # s/rad, bounds of Gaz p2 (fitted values 5-17, Gaz et al. 2019)
    sigmoid_p3: tuple = (-0.3, 0.3)          # rad/s, bounds of Gaz p3 (fitted |p3| < 0.05, Gaz et al. 2019)
    sigmoid_rows: int = 2000                 # samples per joint used for the sigmoid's fit (every k-th row)
    coulomb_rows: int = 1000                 # ... for the Coulomb width (each one a filter window of dq; ours)
    max_mass: float = 4.0                    # kg, payload mass bound: the Panda's rated 3 kg (datasheet) + 1 kg margin
    max_com: float = 0.3                     # m, payload CoM distance bound |r| from the ee origin: within reach of
    #                                          the hand (a tool or a held object; a CoM metres away is not a load)
    offset_max: float | tuple = PANDA_OFFSET_MAX   # Nm, |tau_0 J_j| bound per joint (one number: every joint):
    #                                          what a torque sensor's static error reaches (offset_bounds)
    offset_source: str = PANDA_OFFSET_SOURCE  # where offset_max comes from (said beside a fit held to it)
    scale_max: float = 2.0                   # upper bound of k_G, k_M: a model off by 2x is another arm
    friction_factor: float = 10.0            # friction, rotor bounds: this many times the largest value Gaz et al.
    #                                          2019 identified on a Panda (fv 0.23, fc 0.36, p1 1.28) or the
    #                                          0.05 kg m^2 rotor inertia of the realistic plant
    bias_joints: int = 0                     # joints whose sin q_k, cos q_k enter the pose_bias effect (7 on the
    #                                          Panda); 0: no pose_bias in the library (opt-in: a map of 15 n
    #                                          parameters absorbs any static error, a wrong gravity scale included)


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
        if len(cols) == 0:                                   # e.g. friction of an arm that never moves
            return Y
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
    lower, upper: physical bounds per parameter name (repeated per joint for a per-joint effect, or one per joint
    there; None = unbounded); source: where they come from.
    scale: each parameter's plausible size (a change the log must be able to see; identify.py), None = unknown.
    nl_bounds: (lower (k,), upper (k,)) of the nonlinear parameters, what their fits keep to.
    physical: a named constraint of physical.KINDS: "rigid_body" (10 parameters with a positive semidefinite
    pseudo-inertia), "tilt" (parameters = angles (ax, ay), regressor columns c(ax, ay) = R g - g, 3 of them).
    Nonlinear effects also give nonlinear=(names, units, initial (k,)) and
    fit_nonlinear(signals, rows, z, nl) -> nl (signals of the whole log, rows (T',) the training rows, z (T', n) the
    residual they should explain, nl the start), and their regressor takes (signals, nl)."""
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
    lower: tuple | None = None
    upper: tuple | None = None
    physical: str = ""
    radius: float = np.inf
    scale: tuple | None = None
    nl_bounds: tuple | None = None
    source: str = ""                       # where lower/upper come from, said beside a fit held to them

    def __post_init__(self):
        for name in ("lower", "upper", "scale"):
            v = getattr(self, name)
            if v is not None and len(v) != len(self.params):
                raise ValueError(f"{name}: expected one bound per parameter ({len(self.params)}), found {len(v)}")
        if self.physical not in KINDS:
            raise ValueError(f"physical: expected one of {KINDS}, found {self.physical!r}")

    def size(self, n: int) -> int:
        return len(self.params) * (n if self.per_joint else 1)

    def columns(self, n: int) -> int:
        """Columns of the regressor block: size(n), or 3 for a tilt (the components of dg)."""
        return 3 if self.physical == "tilt" else self.size(n)

    def coef(self, p, g) -> np.ndarray:
        """The block's coefficients for parameters p: p itself, or dg = R(ax, ay) g - g (3,) for a tilt."""
        return tilt_columns(p, g)[0] if self.physical == "tilt" else np.asarray(p, dtype=float)

    def check(self, name: str, p, n: int, nonlinear: bool = False) -> np.ndarray:
        """p as a float array (size(n),) (or (n, k) nonlinear parameters), ValueError naming `name` unless it holds
        real, finite numbers within the effect's bounds (lower/upper, or nl_bounds)."""
        a = np.asarray(p, dtype=object if isinstance(p, (list, tuple)) else None)
        flat = a.ravel().tolist() if a.dtype == object else None
        if flat is not None and not all(isinstance(v, (int, float, np.integer, np.floating)) and
                                        not isinstance(v, (bool, np.bool_)) for v in flat):
            raise ValueError(f"{name}: expected real numbers for {self.name!r}, found {p!r}")
        a = np.asarray(p)
        if a.dtype.kind not in "fiu":
            raise ValueError(f"{name}: expected real numbers for {self.name!r}, found dtype {a.dtype}")
        a = a.astype(float)
        want = (n, len(self.nonlinear[0])) if nonlinear else (self.size(n),)
        if a.shape != want:
            raise ValueError(f"{name}: expected shape {want} for {self.name!r}, found {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name}: expected finite values for {self.name!r}, found {a.ravel().tolist()}")
        lo, hi = (np.broadcast_to(np.asarray(b, float), want) for b in self.nl_bounds) if nonlinear else \
            self.bounds(n)
        bad = np.flatnonzero(((a < lo) | (a > hi)).ravel())
        if len(bad):
            i = int(bad[0])
            raise ValueError(f"{name}: expected {self.name!r} values within [{lo.ravel()[i]:g}, {hi.ravel()[i]:g}], "
                             f"found {a.ravel()[i]:g} (entry {i})")
        return a

    def column_scales(self, n: int, g) -> np.ndarray:
        """The plausible size (columns(n),) of each column's coefficient (identify.py): `scale` per parameter
        (repeated per joint), for a tilt |g| (s, s, s^2 / 2) with s its angle's scale; NaN without a scale."""
        if self.scale is None:
            return np.full(self.columns(n), np.nan)
        if self.physical == "tilt":
            a = float(self.scale[0])
            return float(np.linalg.norm(g)) * np.array([a, a, a * a / 2])
        return np.repeat(np.asarray(self.scale, float), n if self.per_joint else 1)

    def bounds(self, n: int):
        """(lower, upper) (size(n),) of the parameters, +-inf where unbounded."""
        k = n if self.per_joint else 1

        def each(values, fill):
            out = []
            for name, v in zip(self.params, values if values is not None else [fill] * len(self.params)):
                v = np.asarray(v, float)
                if v.ndim and v.shape != (k,):
                    raise ValueError(f"{self.name}: expected one bound of {name} or one per joint ({k}), found "
                                     f"{v.size}")
                out.append(np.broadcast_to(v, (k,)))
            return np.concatenate(out)
        return each(self.lower, -np.inf), each(self.upper, np.inf)

    def labels(self, n: int) -> tuple:
        """A name per parameter: 'I_a J2' for a per-joint effect, else the parameter's name."""
        if not self.per_joint:
            return tuple(self.params)
        return tuple(f"{p} J{j + 1}" for p in self.params for j in range(n))

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
        want = (T, n) if diagonal else (T, n, self.columns(n))
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
            deg = f" ({_fmt(np.degrees(vals))} deg)" if unit == "rad" else ""
            lines.append(f"{name} = {_fmt(vals)} {unit}{deg}")
        if self.nonlinear and nl is not None:
            for i, (name, unit) in enumerate(zip(self.nonlinear[0], self.nonlinear[1])):
                lines.append(f"{name} = {_fmt(np.asarray(nl)[:, i])} {unit}")
        if self.payload and p[0] > 1e-3:                # a gram or more: a load to describe
            lines.append(f"theta: m = {p[0]:.3f} kg, r = {_fmt(p[1:4] / p[0])} m (ee frame)")
        return "; ".join(lines)


def custom(name: str, explanation: str, regressor: Callable, params, units, per_joint_params: bool = False,
           signal: str = "", lower=None, upper=None) -> Effect:
    """A user-defined effect from one regressor function signals -> (T, n, k) block (or, with per_joint_params and
    one parameter name, its per-joint signal (T, n)); signals offers t, q, dq, ddq, robot, gravity, motion, ...
    lower, upper: physical bounds, one per parameter name (None = unbounded); the fit keeps to them."""
    params, units = tuple(params), tuple(units)
    if len(params) != len(units):
        raise ValueError(f"units: expected one unit per parameter ({len(params)}), found {len(units)}")
    return Effect(name, explanation, regressor, params, units, per_joint=per_joint_params, signal=signal,
                  lower=None if lower is None else tuple(lower), upper=None if upper is None else tuple(upper))


def pose_basis(q, m: int) -> np.ndarray:
    """The pose-bias basis (T, 1 + 2m) of q (T, n): 1, sin q_1..q_m, cos q_1..q_m (joints beyond n: zero columns)."""
    T, n = q.shape
    k = min(n, m)
    X = np.zeros((T, 1 + 2 * m))
    X[:, 0] = 1.0
    X[:, 1:1 + k], X[:, 1 + m:1 + m + k] = np.sin(q[:, :k]), np.cos(q[:, :k])
    return X


def pose_bias_block(q, m: int) -> np.ndarray:
    """Regressor (T, n, (1 + 2m) n) of pose_bias: joint j's torque = sum_i p[i n + j] X_i(q), X = pose_basis(q, m)
    (the per-joint parameter layout of Effect.labels: basis function i, then joint j)."""
    X = pose_basis(q, m)
    T, n = q.shape
    Y = np.zeros((T, n, X.shape[1], n))
    Y[:, np.arange(n), :, np.arange(n)] = X                 # (n, T, 1 + 2m) assigned on the diagonal j = j'
    return Y.reshape(T, n, -1)


def segments(effects, n: int, g, relax=()) -> list:
    """The physical.Segment of each effect's columns, in order (for physical.solve_physical); the effects named in
    relax get none of their constraints (a tilt then fits all of dg)."""
    out, i0 = [], 0
    for e in effects:
        k = e.columns(n)
        if e.name in relax:
            out.append(Segment(e.name, i0, i0 + k, np.full(k, -np.inf), np.full(k, np.inf)))
        else:
            lo, hi = e.bounds(n)
            out.append(Segment(e.name, i0, i0 + k, lo, hi, e.physical, np.asarray(g, float), e.labels(n), e.radius))
        i0 += k
    return out


def _fmt(v):
    v = np.atleast_1d(v)
    return f"{v[0]:.4g}" if len(v) == 1 else "[" + ", ".join(f"{x:.4g}" for x in v) + "]"


def library(config: EffectConfig = EffectConfig()) -> dict:
    """The built-in effects by name (regressors in the tau_J sign: the torque the drives add for the effect), each
    with its physical bounds: scales, masses, inertias and friction coefficients are >= 0."""
    c = config
    body = ("m", "m_cx", "m_cy", "m_cz", "Ixx", "Ixy", "Iyy", "Ixz", "Iyz", "Izz")
    inf, k = np.inf, c.friction_factor
    om = tuple(map(float, c.offset_max)) if np.ndim(c.offset_max) else float(c.offset_max)
    size = 1.0                               # Nm, an offset's plausible size (identify.py): "up to about 1 Nm"
    #                                          (panda_facts.md)
    load = dict(payload=True, smooth=False, radius=c.max_com)
    rated = 3.0                              # kg, the Panda's rated payload (datasheet): a load's plausible size
    effects = [
        Effect("gravity", "the arm's own weight, G(q) of the nominal link masses and CoMs, scaled by k_G",
               lambda s: s.gravity[:, :, None], ("k_G",), ("(1 = nominal)",), nominal=1.0, smooth=False, lower=(0.0,),
               upper=(c.scale_max,), scale=(0.1,)),
        Effect("motion", "the arm's inertial, Coriolis and centrifugal torques M(q) ddq + C(q, dq) dq, scaled by k_M",
               lambda s: s.motion[:, :, None], ("k_M",), ("(1 = nominal)",), nominal=1.0, signal="ddq", smooth=False,
               lower=(0.0,), upper=(c.scale_max,), scale=(0.1,)),
        Effect("payload", "a load at the end-effector whose weight pulls on the arm (static: Eqs. 4-5, "
               "phi = (m, m r), r in the ee frame)", lambda s: -s.payload, ("m", "m_rx", "m_ry", "m_rz"),
               ("kg", "kg m", "kg m", "kg m"), lower=(0.0, -inf, -inf, -inf), upper=(c.max_mass, inf, inf, inf),
               physical="payload", scale=(rated, rated * c.max_com, rated * c.max_com, rated * c.max_com), **load),
        Effect("rigid_payload", "a rigid load at the end-effector: its weight and its inertia under motion "
               "(Newton-Euler; inertia about the ee origin; pseudo-inertia positive semidefinite)", lambda s: -s.body,
               body, ("kg", "kg m", "kg m", "kg m") + ("kg m^2",) * 6, physical="rigid_body", **load,
               lower=(0.0,) + (-inf,) * 9, upper=(c.max_mass,) + (inf,) * 9,
               scale=(rated,) + (rated * c.max_com,) * 3 + (rated * c.max_com ** 2,) * 6),
        Effect("viscous", "friction growing in proportion to joint speed (lubricant shear in the gears), fv dq",
               lambda s: s.dq, ("fv",), ("Nm s/rad",), per_joint=True, signal="dq", smooth=False, lower=(0.0,),
               upper=(k * 0.23,), scale=(0.23,)),
        Effect("coulomb", "sliding friction of constant size opposing motion, fc sign(dq), smoothed as "
               "fc tanh(dq / w) with the width w fitted per joint", lambda s, nl: np.tanh(s.dq / nl[:, 0]),
               ("fc",), ("Nm",), per_joint=True, signal="dq", lower=(0.0,), upper=(k * 0.36,), scale=(0.36,),
               nonlinear=(("w",), ("rad/s",), (c.coulomb_width,)), nl_bounds=tuple(zip(c.coulomb_widths)),
               fit_nonlinear=lambda s, rows, z, nl: fit_coulomb(s, rows, z, nl, c.coulomb_widths, c.coulomb_rows)),
        Effect("sigmoid", "joint friction as a sigmoid of speed (Gaz et al. 2019): p1/(1+exp(-p2(dq+p3))) - "
               "p1/(1+exp(-p2 p3))", lambda s, nl: sigmoid_shape(s.dq, nl[:, 0], nl[:, 1]),
               ("p1",), ("Nm",), per_joint=True, signal="dq", lower=(0.0,), upper=(k * 1.28,), scale=(1.28,),
               nonlinear=(("p2", "p3"), ("s/rad", "rad/s"), (10.0, 0.0)), nl_bounds=tuple(zip(c.sigmoid_p2, c.sigmoid_p3)),
               fit_nonlinear=lambda s, rows, z, nl: fit_sigmoid(s, rows, z, nl, c.sigmoid_p2, c.sigmoid_p3,
                                                                c.sigmoid_rows)),
        Effect("offset", "a constant bias of each joint torque sensor (calibration drift)",
               lambda s: np.ones_like(s.q), ("tau_0",), ("Nm",), per_joint=True, signal="t", smooth=False,
               lower=(tuple(-np.asarray(om)) if np.ndim(om) else -om,), upper=(om,), scale=(size,),
               source=c.offset_source),
        Effect("rotor", "the motor rotor's inertia seen through the gearbox, I_a ddq, missing from a link-only model",
               lambda s: s.ddq, ("I_a",), ("kg m^2",), per_joint=True, signal="ddq", smooth=False, lower=(0.0,),
               upper=(k * 0.05,), scale=(0.05,)),
        Effect("tilt", "the base is not level: gravity rotated by ax about world x, then ay about world y, "
               "G(q; g') - G(q; g) = -W dg with dg = Ry(ay) Rx(ax) g - g (exact)",
               lambda s: -s.gravity_map, ("ax", "ay"), ("rad", "rad"), smooth=False, physical="tilt",
               lower=(-c.tilt_max,) * 2, upper=(c.tilt_max,) * 2, scale=(c.tilt_max,) * 2),
    ] + [
        Effect("pose_bias", "a static torque that depends on the pose only: the torque sensor's pose-dependent bias "
               "(and any static torque the nominal gravity misses), per joint a constant plus the first harmonics "
               "sin q_k, cos q_k of every joint", lambda s: pose_bias_block(s.q, c.bias_joints),
               ("b",) + tuple(f"{f} q{k + 1}" for f in ("sin", "cos") for k in range(c.bias_joints)),
               ("Nm",) * (1 + 2 * c.bias_joints), per_joint=True, signal="q", smooth=False,
               scale=(size,) * (1 + 2 * c.bias_joints)),
    ][:1 if c.bias_joints > 0 else 0]
    return {e.name: e for e in effects}


_sigmoid_shape = sigmoid_shape           # the name benchmarks import
