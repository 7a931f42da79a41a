"""Constrained passive interaction control (CPIC, Sec. 3, Eqs. 6-8; Appendix B, D): DS motion policies, the passive
impedance law F_c = G_x - D(x)(xdot - f(x)), the exponential-CBF torque QP (solved by qp.py's dual active-set KKT
solver) and the RME compensation hook; and JointHold, a plain joint PD hold for recording data."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from dynamics import Robot, as_states
from qp import QPInfo, dual_active_set, solve_qp   # noqa: F401  (re-exported: cpic.solve_qp)


def _checked(name, v, shape=None, low=None, strict=True):
    """v as a float (shape None) or a float array of that shape, finite and > low (>= low if not strict); else
    ValueError naming it, with what was found and what was expected."""
    what = "a finite number" if shape is None else f"finite values of shape {shape}"
    what += "" if low is None else f" {'>' if strict else '>='} {low:g}"
    try:
        a = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected {what}, found {v!r}") from None
    if a.shape != (() if shape is None else shape):
        raise ValueError(f"{name}: expected {what}, found shape {a.shape}")
    if not np.all(np.isfinite(a)) or low is not None and not np.all(a > low if strict else a >= low):
        raise ValueError(f"{name}: expected {what}, found {a.tolist()}")
    return a if shape is not None else float(a)


def _checked_rotation(name, R):
    """R (3, 3) with R^T R = I and det R = +1 (to 1e-6); else ValueError."""
    R = _checked(name, R, (3, 3))
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0.0:
        raise ValueError(f"{name}: expected a rotation matrix (R^T R = I, det R = 1), found {R.tolist()}")
    return R


# --- motion policies f(x) with their Lyapunov functions V(x) (Sec. 3, Eq. 6) ---------------------------------
def rotation_log(R):
    """log map of R (3, 3) -> rotation vector (3,) = angle * axis, angle in [0, pi]."""
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])      # 2 sin(angle) axis
    angle = math.acos(min(1.0, max(-1.0, 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0))))
    if angle < 1e-6:
        return 0.5 * w                                # first order: log R = vee(R - R^T) / 2
    if angle < math.pi - 1e-4:
        return (angle / (2.0 * math.sin(angle))) * w
    B = 0.5 * (R + np.eye(3))                         # near pi: B = axis axis^T (+ O(pi - angle))
    k = int(np.argmax(np.diag(B)))
    axis = B[:, k] / math.sqrt(B[k, k])
    return angle * (axis if axis @ w >= 0.0 else -axis)


def _orientation_terms(R, R_star, gain):
    """f_w = -a log(R R*^T) (world angular velocity, (3,)) and V_rot = a/2 |log(R R*^T)|^2: f_w = -grad V_rot."""
    e = rotation_log(R @ R_star.T)
    return -gain * e, 0.5 * gain * (e @ e)


@dataclass(frozen=True)
class Attractor:
    """Linear DS to the pose (p_star (3,), R_star (3, 3)): f = (-a_p (p - p*), -a_r log(R R*^T)) (6,),
    V = a_p/2 |p - p*|^2 + a_r/2 |log(R R*^T)|^2, conservative (f = -grad V) as Appendix D assumes."""
    p_star: np.ndarray
    R_star: np.ndarray = field(default_factory=lambda: np.eye(3))
    gain_pos: float = 3.0        # 1/s; our choice: stiffness lambda_1 a_p = 450 N/m with lambda_1 = 150
    gain_rot: float = 8.0        # 1/s; our choice: stiffness lambda_1 a_r = 40 N m/rad with lambda_1 = 5

    def __post_init__(self):
        object.__setattr__(self, "p_star", _checked("p_star", self.p_star, (3,)))
        object.__setattr__(self, "R_star", _checked_rotation("R_star", self.R_star))
        _checked("gain_pos", self.gain_pos, low=0.0)
        _checked("gain_rot", self.gain_rot, low=0.0)

    def __call__(self, p, R):
        """-> f (6,), V = (V_pos, V_rot)."""
        e = p - self.p_star
        f_w, V_rot = _orientation_terms(R, self.R_star, self.gain_rot)
        return np.concatenate([-self.gain_pos * e, f_w]), (0.5 * self.gain_pos * (e @ e), V_rot)


@dataclass(frozen=True)
class LimitCycle:
    """Stable limit cycle in the world y-z plane around `center` (3,) (Sec. 5.3): in polar coordinates
    (rho, phi) of (y, z): drho/dt = -a (rho - radius), dphi/dt = 2 pi / period, dx/dt = -a (x - x_c);
    V_pos = a/2 ((rho - radius)^2 + (x - x_c)^2) decreases along f; orientation held at R_star."""
    center: np.ndarray
    R_star: np.ndarray = field(default_factory=lambda: np.eye(3))
    radius: float = 0.1          # m; our choice (the paper gives no size)
    period: float = 4.0          # s; our choice: 0.16 m/s along the cycle
    gain_pos: float = 3.0        # 1/s, radial and out-of-plane convergence
    gain_rot: float = 8.0        # 1/s

    def __post_init__(self):
        object.__setattr__(self, "center", _checked("center", self.center, (3,)))
        object.__setattr__(self, "R_star", _checked_rotation("R_star", self.R_star))
        for name in ("radius", "period", "gain_pos", "gain_rot"):
            _checked(name, getattr(self, name), low=0.0)

    def __call__(self, p, R):
        e = p - self.center
        u = e[1:]                                     # (y, z) relative to the centre
        rho = np.sqrt(u @ u)
        radial = u / rho if rho > 1e-12 else np.zeros(2)
        omega = 2.0 * np.pi / self.period
        v_yz = -self.gain_pos * (rho - self.radius) * radial + omega * np.array([-u[1], u[0]])
        f_w, V_rot = _orientation_terms(R, self.R_star, self.gain_rot)
        V_pos = 0.5 * self.gain_pos * ((rho - self.radius) ** 2 + e[0] ** 2)
        return np.concatenate([[-self.gain_pos * e[0]], v_yz, f_w]), (V_pos, V_rot)


# --- passive impedance law (Eq. 7; Kronander and Billard 2016) ----------------------------------------------
def damping_matrix(f, eigenvalues):
    """D = Q Lambda Q^T (3, 3), Q = [e1 e2 e3] orthonormal with e1 = f / |f| (the world x axis when f = 0,
    where any basis keeps D f = lambda_1 f); eigenvalues (3,) = (lambda_1, lambda_2, lambda_3)."""
    x, y, z = (float(v) for v in f)
    nf = np.sqrt(x * x + y * y + z * z)
    x, y, z = (x / nf, y / nf, z / nf) if nf > 1e-12 else (1.0, 0.0, 0.0)
    k = min(range(3), key=lambda i: abs((x, y, z)[i]))        # the world axis least aligned with e1
    u = (0.0, -z, y) if k == 0 else ((z, 0.0, -x) if k == 1 else (-y, x, 0.0))   # e1 x axis_k
    nu = np.sqrt(u[0] ** 2 + u[1] ** 2 + u[2] ** 2)
    u = (u[0] / nu, u[1] / nu, u[2] / nu)
    w = (y * u[2] - z * u[1], z * u[0] - x * u[2], x * u[1] - y * u[0])          # e1 x e2
    Q = np.array([[x, u[0], w[0]], [y, u[1], w[1]], [z, u[2], w[2]]])
    return (Q * eigenvalues) @ Q.T


def impedance_wrench(G_x, xdot, f, damping_pos, damping_rot):
    """F_c = G_x - D(x)(xdot - f(x)) (6,), D = blockdiag(D_pos(f_v), D_rot(f_w)); G_x, xdot, f (6,)."""
    e = xdot - f
    return G_x - np.concatenate([_damp(f[:3], damping_pos, e[:3]), _damp(f[3:], damping_rot, e[3:])])


def _damp(f, eigenvalues, e):
    """D(f) e (3,); with lambda_2 = lambda_3, Q Lambda Q^T = lambda_2 I + (lambda_1 - lambda_2) e1 e1^T exactly."""
    l1, l2, l3 = eigenvalues
    if l2 != l3:
        return damping_matrix(f, eigenvalues) @ e
    ff = float(f @ f)
    if ff <= 1e-24:                                   # f = 0: e1 = world x axis, as in damping_matrix
        return l2 * e + np.array([(l1 - l2) * e[0], 0.0, 0.0])
    return l2 * e + ((l1 - l2) * float(f @ e) / ff) * f


# --- the CPIC torque QP (Eq. 8, Appendix D) with the RME compensation hook (Eq. 5, Appendix B) -----------------
@dataclass(frozen=True)
class CPICConfig:
    damping_pos: tuple = (150.0, 150.0, 150.0)  # N s/m, D eigenvalues (along f first); the lab's Franka passive-DS
    #                                             value (franka_interactive_controllers: "150 for franka")
    damping_rot: tuple = (5.0, 5.0, 5.0)        # N m s/rad; the lab's Franka value (paper_notes.md "Controller").
    #   Measured on the delay-free plant: the velocity loop dq+ = (I - dt M^-1 K_v) dq (K_v = J^T D J + k_n N, torque
    #   held over the step) is stable for dt lambda_max(M^-1 K_v) < 2; it is 0.89-1.09 on the ideal plant (no rotor
    #   inertia, wrist task inertia >= 0.0047 kg m^2), 0.21 on the realistic one; linearised hold: most negative
    #   eigenvalue -0.09, no chatter (10 would give -1.15). A 1-step command delay would make 5 unstable (|z| 1.05).
    k1: float = 30.0                  # 1/s^2, E-CBF gain on h (lab range k1 = 30..1000, paper_notes.md)
    k2: float = 50.0                  # 1/s, E-CBF gain on dh/dt (lab range k2 = 50..1000)
    tau_max: tuple = (87.0,) * 4 + (12.0,) * 3  # N m, Panda torque limits (panda_facts.md)
    q_min: tuple | None = None        # rad; None: the model's joint ranges (panda.xml = Franka documentation)
    q_max: tuple | None = None
    null_weight: float = 1.0          # w in + w |N (tau - tau_0)|^2 (our choice: H = J^+ J^+T alone is singular
    #                                   for a 7-DoF arm; w does not change the unconstrained optimum)
    null_damping: float = 1.0         # N m s/rad, k_n in tau_0 = G - k_n dq + tau_p (ours; dissipative)
    null_stiffness: float = 10.0      # N m/rad, k_p of the posture spring (ours, as in Franka's Cartesian impedance
    #                                   example): without it a payload's torque has a null-space part nothing resists,
    #                                   and the arm drifts along its redundancy to a joint limit
    q_rest: tuple | None = None       # rad, its rest pose; None: the q of the first step after a reset (CPIC)
    fallback_damping: tuple = (20.0,) * 4 + (3.0,) * 3   # N m s/rad, safe torque G + comp - K dq (our choice)
    max_iterations: int = 100         # active-set changes per QP

    def __post_init__(self):
        for name in ("damping_pos", "damping_rot"):
            _checked(name, getattr(self, name), (3,), low=0.0)
        for name in ("k1", "k2", "null_weight"):
            _checked(name, getattr(self, name), low=0.0)
        for name in ("null_damping", "null_stiffness"):
            _checked(name, getattr(self, name), low=0.0, strict=False)
        for name, low, strict in (("tau_max", 0.0, True), ("fallback_damping", 0.0, False), ("q_min", None, True),
                                  ("q_max", None, True), ("q_rest", None, True)):
            v = getattr(self, name)
            if v is not None:
                _checked(name, v, (np.size(v),), low=low, strict=strict)
        if not (isinstance(self.max_iterations, (int, np.integer)) and self.max_iterations >= 1):
            raise ValueError(f"max_iterations: expected an integer >= 1, found {self.max_iterations!r}")


@dataclass(frozen=True)
class StepInfo:
    """status: QP status or "fallback: <reason>"; f (6,), V = (V_pos, V_rot), F_c (6,), tau_qp (n,) before
    compensation; active: active constraint indices (rows: CBF lower 0..n-1, upper n..2n-1, tau >= -max
    2n..3n-1, tau <= max 3n..4n-1)."""
    status: str
    iterations: int
    active: np.ndarray
    fallback: bool
    f: np.ndarray
    V: tuple
    F_c: np.ndarray
    tau_qp: np.ndarray


class CPIC:
    """ctrl = CPIC(robot, policy, config); tau, info = ctrl.step(q, dq, compensation) at 1 kHz.

    QP over tau (n,):  min |J^+T tau - F_t|^2 + w |N (tau - tau_0)|^2,  J^+T = (J J^T)^-1 J (6, n),
    N = I - J^T J^+T (null space of J), F_t = F_c + J^+T tau_p, tau_0 = G - k_n dq + tau_p, subject to, with
    ddq = M^-1 (tau - C dq - G) (nominal model; tau_ext = 0 unless given), the E-CBF h'' >= -k1 h - k2 h' for
    h = q - q_min, q_max - q, and |tau + comp| <= tau_max. With nothing active
    tau = J^T F_c + N (G - k_n dq) + tau_p = G - J^T D (xdot - f) - k_n N dq + tau_p (Appendix D, unconstrained case,
    plus the null-space damping and posture spring a redundant arm needs).

    Posture spring (ours): tau_p = -k_p N_rest (q - q_rest) = -dP/dq, P = k_p/2 (q - q_rest)^T N_rest (q - q_rest) with
    N_rest = N(q_rest) fixed: a gradient, so S = 1/2 dq^T M dq + lambda_1 V + P never increases (storage()); at q_rest
    it acts in the null space only, and P = 0 on a hyperplane through q_rest that the self-motion crosses, so the
    task equilibrium x = x* stays. (N(q) k_p (q_rest - q) is no gradient and feeds energy in: test_cpic.py; on null-
    space projections and passivity see Dietrich, Ott and Albu-Schaeffer, IJRR 2015.) Rest pose: config.q_rest if
    given, else the q of the first step after construction, reset() or a policy change (setting ctrl.policy, as the
    runner's PolicySwitch does, resets); re-taking it sets P to 0, which only removes stored energy.

    The compensation (e.g. -robot.payload_torque(q, theta_hat)) is added after the QP (Appendix B). q, dq must be
    finite (ValueError otherwise). For any finite state the output is finite and within tau_max: when the policy's
    output, the model terms or the QP break down (infeasible, singular J, overflow of an absurd dq, ...) the safe
    torque clip(G + comp - K dq) is used and StepInfo says why.
    """

    def __init__(self, robot, policy, config: CPICConfig | None = None):
        self.robot = robot
        self.config = c = CPICConfig() if config is None else config
        n = robot.n
        rng = robot.model.jnt_range
        self.q_min = np.asarray(rng[:, 0] if c.q_min is None else c.q_min, dtype=float)
        self.q_max = np.asarray(rng[:, 1] if c.q_max is None else c.q_max, dtype=float)
        self.tau_max = np.asarray(c.tau_max, dtype=float)
        for name, v in (("q_min", self.q_min), ("q_max", self.q_max), ("tau_max", self.tau_max),
                        ("fallback_damping", np.asarray(c.fallback_damping)),
                        ("q_rest", np.zeros(n) if c.q_rest is None else np.asarray(c.q_rest))):
            if v.shape != (n,) or not np.all(np.isfinite(v)):
                raise ValueError(f"config.{name}: expected {n} finite values (robot.n), found {v.tolist()}")
        if np.any(self.q_min >= self.q_max) or np.any(self.tau_max <= 0):
            raise ValueError(f"config: expected q_min < q_max and tau_max > 0, found {self.q_min}, "
                             f"{self.q_max}, {self.tau_max}")
        self._I = np.eye(n)
        self._A = np.zeros((4 * n, n))                # constraint rows; the torque rows never change
        self._A[2 * n:3 * n], self._A[3 * n:] = self._I, -self._I
        self.policy = policy                          # checks it and resets

    @property
    def policy(self):
        """The DS f(p, R) -> (f (6,), (V_pos, V_rot)); setting it resets the controller (see reset)."""
        return self._policy

    @policy.setter
    def policy(self, policy):
        if not callable(policy):
            raise ValueError(f"policy: expected a callable f(p, R) -> (f (6,), V), found {type(policy).__name__}")
        self._policy = policy
        self.reset()

    @property
    def q_rest(self):
        """The posture spring's rest pose (n,), or None until the first step after a reset takes it."""
        return None if self._rest is None else self._rest[0].copy()

    def reset(self):
        """Start a new motion from the next step: forget the warm start (previous active set) and re-take the
        posture spring's rest pose (config.q_rest if given, else the q of the next step)."""
        self._active = []
        q_rest = self.config.q_rest
        self._rest = None if q_rest is None else (np.asarray(q_rest, dtype=float), _null_projector(self.robot, q_rest))

    def posture_potential(self, q):
        """P = k_p/2 (q - q_rest)^T N_rest (q - q_rest) [J] at q (n,); 0 while no rest pose is taken."""
        if self._rest is None:
            return 0.0
        e = np.asarray(q, dtype=float) - self._rest[0]
        return 0.5 * self.config.null_stiffness * float(e @ self._rest[1] @ e)

    def step(self, q, dq, compensation=None, tau_ext=None):
        """q, dq (n,) measured; compensation (n,) added after the QP (None = 0). Returns (tau (n,), StepInfo).

        tau_ext (n,), optional: the measured external torque (paper sign). None (default) = the nominal
        dynamics of Appendix B, ddq = M^-1 (tau - C dq - G), assuming the compensation cancels the mismatch.
        Given, the E-CBF predicts ddq = M^-1 (tau + comp - C dq - G + tau_ext) as in Eq. 8's equality, so a
        push is resisted at the limit (without it a push d [rad/s^2] can overshoot a limit by about d / k1).
        """
        G, dq, comp, f, V, F_c, tau_free, Hinv, g, b, why = self._terms(q, dq, compensation, tau_ext)
        if why:
            return self._fallback(G, dq, comp, f, V, F_c, f"fallback: {why}")
        if not self._active and (self._A @ tau_free - b).min() >= -1e-9:   # QP optimum = unconstrained one
            tau_qp, status, it, active = tau_free, "optimal", 0, []
        else:
            try:
                B = np.linalg.cholesky(Hinv).T        # B^T B = H^-1
            except np.linalg.LinAlgError:
                return self._fallback(G, dq, comp, f, V, F_c, "fallback: H not positive definite")
            tau_qp, status, it, active, _ = dual_active_set(B, g, self._A, b, self._active,
                                                            self.config.max_iterations)
        if status != "optimal" or not np.isfinite(tau_qp).all():
            self._active = []
            return self._fallback(G, dq, comp, f, V, F_c, f"fallback: QP {status}")
        self._active = active
        tau = np.minimum(np.maximum(tau_qp + comp, -self.tau_max), self.tau_max)
        return tau, StepInfo(status, it, np.array(active, dtype=int), False, f, V, F_c, tau_qp)

    def qp(self, q, dq, compensation=None, tau_ext=None):
        """The QP that step() solves at this state, for inspection: (H (n, n), g (n,), A (4n, n), b (4n,),
        warm-start active set), ready for solve_qp(H, g, A, b, active)."""
        out = self._terms(q, dq, compensation, tau_ext)
        if out[-1]:
            raise ValueError(f"q, dq: no QP at this state ({out[-1]})")
        H = np.linalg.inv(out[-4])
        return 0.5 * (H + H.T), out[-3], self._A.copy(), out[-2], np.array(self._active, dtype=int)

    def _terms(self, q, dq, compensation, tau_ext):
        """Model terms, policy, F_c, the unconstrained optimum tau_free = J^T F_t + N tau_0 and the QP data
        (H^-1, g, b), and why = "" or the reason for the safe torque (then the QP data are None)."""
        robot, c, n = self.robot, self.config, self.robot.n
        J, M, bias, G, p, R = robot.control_terms(q, dq)          # one kinematics pass; validates q and dq
        q, dq = np.asarray(q, dtype=float), np.asarray(dq, dtype=float)
        comp = np.zeros(n) if compensation is None else _checked("compensation", compensation, (n,))
        if tau_ext is not None:
            bias = bias - _checked("tau_ext", tau_ext, (n,)) - comp
        f, V = self.policy(p, R)
        f = np.asarray(f, dtype=float)
        if f.shape != (6,) or np.shape(V) != (2,):
            raise ValueError(f"policy: expected f of shape (6,) and V = (V_pos, V_rot), found {f.shape}, {V}")
        nothing = (G, dq, comp, f, V, np.full(6, np.nan), None, None, None, None)
        if not math.isfinite(float(f @ f) + V[0] + V[1]):
            return nothing + ("policy output not finite (or beyond 1e154)",)
        try:
            Jp = np.linalg.solve(J @ J.T, J)          # J^+T (6, n)
            F_c = impedance_wrench(Jp @ G, J @ dq, f, c.damping_pos, c.damping_rot)
            Nproj = self._I - J.T @ Jp                # (n, n), projector onto the null space of J
            # H = J^+ J^+T + w N has the closed-form inverse H^-1 = J^T J + N / w (J^+T J^T = I, J N = 0)
            Hinv = J.T @ J + Nproj / c.null_weight
            Hinv = 0.5 * (Hinv + Hinv.T)
            if self._rest is None:                    # the first step after a reset: rest at this q
                self._rest = (q.copy(), 0.5 * (Nproj + Nproj.T))
            q_rest, N_rest = self._rest
            tau_p = -c.null_stiffness * (N_rest @ (q - q_rest))   # posture spring, -dP/dq
            F_t = F_c + Jp @ tau_p                    # its task part joins F_c, its null part tau_0
            null = Nproj @ (G - c.null_damping * dq + tau_p)      # N tau_0
            g = -(Jp.T @ F_t + c.null_weight * null)  # g = -H tau_free
            b = self._constraint_bounds(q, dq, np.linalg.inv(M), bias, comp)
        except np.linalg.LinAlgError:
            return nothing + ("singular J or M",)
        if not math.isfinite(float(g @ g) + float(b @ b)):
            return nothing[:5] + (F_c, None, None, None, None, "model terms not finite (or beyond 1e154)")
        return G, dq, comp, f, V, F_c, J.T @ F_t + null, Hinv, g, b, ""

    def _constraint_bounds(self, q, dq, Minv, bias, comp):
        """b (4n,) for A tau >= b: rows +-M^-1 (E-CBF on q - q_min, q_max - q), then +-I (torque limits).
        h = q - q_min: ddq + k2 dq + k1 (q - q_min) >= 0 with ddq = M^-1 (tau - bias)."""
        c, n, A = self.config, self.robot.n, self._A
        A[:n] = Minv
        np.negative(Minv, out=A[n:2 * n])
        a0 = Minv @ bias                              # ddq = M^-1 tau - a0
        k_dq = c.k2 * dq
        b = np.empty(4 * n)
        b[:n] = a0 - c.k1 * (q - self.q_min) - k_dq
        b[n:2 * n] = k_dq - c.k1 * (self.q_max - q) - a0
        b[2 * n:3 * n] = -self.tau_max - comp
        b[3 * n:] = comp - self.tau_max
        return b

    def _fallback(self, G, dq, comp, f, V, F_c, status):
        """Safe torque when the QP has no answer: gravity compensation + compensation + joint damping, clipped."""
        tau = np.clip(G + comp - np.asarray(self.config.fallback_damping) * dq, -self.tau_max, self.tau_max)
        tau = np.where(np.isnan(tau), 0.0, tau)       # (+-inf clip to the limits; NaN only from inf - inf)
        return tau, StepInfo(status, 0, np.zeros(0, dtype=int), True, f, V, F_c, tau - comp)


def _null_projector(robot, q):
    """N = I - J^+ J (n, n) at q: the projector onto the null space of J (pseudo-inverse: any rank)."""
    J = robot.jacobian(q)
    N = np.eye(robot.n) - np.linalg.pinv(J) @ J
    return 0.5 * (N + N.T)


def storage(dq, M, V, config: CPICConfig, P):
    """S = 1/2 dq^T M dq + lambda_1 V + P (Prop. 4.1 with the posture spring's potential P =
    ctrl.posture_potential(q)), lambda_1 V = lambda_1,pos V_pos + lambda_1,rot V_rot. Joint-space kinetic energy:
    1/2 xdot^T M_x xdot plus the null-space motion's kinetic energy."""
    return 0.5 * dq @ M @ dq + config.damping_pos[0] * V[0] + config.damping_rot[0] * V[1] + P


class JointHold:
    """A stiff joint-space hold, tau = G(q) + Kp (q0 - q) - Kd dq (+ compensation) on the nominal model: the simple
    controller used for recording data (CPIC above is the paper's controller). Gains: ours, stiff enough that a
    3 kg load moves the arm by a few mrad."""

    def __init__(self, robot: Robot, q0, kp=(600.0,) * 4 + (50.0,) * 3, kd=(40.0,) * 4 + (4.0,) * 3):
        self.robot, self.q0 = robot, as_states("q0", q0, robot.n, allow_window=False)[0][0]
        self.kp, self.kd = np.asarray(kp, dtype=float), np.asarray(kd, dtype=float)

    def step(self, q, dq, compensation=None, tau_ext=None):
        """(tau (n,), None): the hold's torque for the state q, dq (n,), plus the compensation if given."""
        tau = self.robot.gravity(q) + self.kp * (self.q0 - q) - self.kd * dq
        return (tau if compensation is None else tau + compensation), None
