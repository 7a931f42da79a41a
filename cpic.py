"""Constrained passive interaction control (CPIC, Sec. 3, Eqs. 7-8; Appendix B, D) of the DS policies of ds.py: the
passive impedance law F_c = G_x - D(x)(xdot - f(x)), the exponential-CBF torque QP (solved by qp.py's dual active-set
KKT solver) and the RME compensation hook; and JointHold, a plain joint PD hold for recording data."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import lapack

import checks
from dynamics import Robot, as_states
from ds import Attractor, LimitCycle, rotation_log   # noqa: F401  (re-exported: the policies CPIC follows)
from qp import QPInfo, dual_active_set_from_inverse, solve_qp

__all__ = ["Attractor", "LimitCycle", "CPIC", "CPICConfig", "StepInfo", "JointHold", "damping_matrix",
           "impedance_wrench", "rotation_log", "storage", "solve_qp", "QPInfo"]   # solve_qp, QPInfo: from qp.py


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
    if damping_pos[1] != damping_pos[2] or damping_rot[1] != damping_rot[2]:
        return G_x - np.concatenate([damping_matrix(f[:3], damping_pos) @ e[:3],
                                     damping_matrix(f[3:], damping_rot) @ e[3:]])
    fl, el = f.tolist(), e.tolist()                   # six numbers: plain floats beat array calls here
    return G_x - np.array(_damp(fl[:3], damping_pos, el[:3]) + _damp(fl[3:], damping_rot, el[3:]))


def _damp(f, eigenvalues, e):
    """D(f) e (list of 3) for lambda_2 = lambda_3: Q Lambda Q^T = lambda_2 I + (lambda_1 - lambda_2) e1 e1^T exactly
    (f = 0: e1 = the world x axis, as in damping_matrix)."""
    l1, l2, ff = eigenvalues[0], eigenvalues[1], f[0] * f[0] + f[1] * f[1] + f[2] * f[2]
    k, f = ((l1 - l2) * (f[0] * e[0] + f[1] * e[1] + f[2] * e[2]) / ff, f) if ff > 1e-24 else (l1 - l2, (e[0], 0, 0))
    return [l2 * e[0] + k * f[0], l2 * e[1] + k * f[1], l2 * e[2] + k * f[2]]


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
    payload_mass: float = 3.0         # kg: a compensation stands for a payload of at most this (the Panda's rated
    payload_com: float = 0.3          #   payload, RMESettings.max_mass) with |rx|, |ry|, |rz| at most this m (max_com)

    def __post_init__(self):
        """Every field checked (checks.py); upper bounds far beyond any use keep the QP's terms finite (gains 1e4,
        joint limits within 100 rad, torques 1e4 Nm; CPIC also keeps tau_max within the robot's own limits)."""
        for name, shape, interval in (("damping_pos", (3,), "(0, 1e4]"), ("damping_rot", (3,), "(0, 1e3]"),
                                      ("tau_max", (None,), "(0, 1e4]"), ("fallback_damping", (None,), "[0, 1e3]"),
                                      ("q_min", (None,), "[-100, 100]"), ("q_max", (None,), "[-100, 100]"),
                                      ("q_rest", (None,), "[-100, 100]")):
            None if getattr(self, name) is None else checks.array(name, getattr(self, name), shape, interval)
        for name, interval in (("k1", "(0, 1e4]"), ("k2", "(0, 1e4]"), ("null_weight", "(0, 1e6]"),
                               ("null_damping", "[0, 1e3]"), ("null_stiffness", "[0, 1e4]"),
                               ("max_iterations", "1..10000"), ("payload_mass", "[0, 50]"), ("payload_com", "[0, 1]")):
            checks.number(name, getattr(self, name), interval)


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
    task equilibrium x = x* stays. (N(q) k_p (q_rest - q) is no gradient and feeds energy in: tests/test_cpic.py; on
    null-space projections and passivity see Dietrich, Ott and Albu-Schaeffer, IJRR 2015.) Rest pose: config.q_rest
    if given, else the q of the first step after construction, reset() or a policy change (setting ctrl.policy, as the
    runner's PolicySwitch does, resets); re-taking it sets P to 0, which only removes stored energy.

    The compensation (e.g. -robot.payload_torque(q, theta_hat)) is added after the QP (Appendix B). q, dq must be
    finite (ValueError otherwise). For any finite state the output is finite and within tau_max: when the policy's
    output, the model terms or the QP break down (infeasible, singular J, overflow of an absurd dq, ...) the safe
    torque clip(G + comp - K dq) is used and StepInfo says why.
    """

    def __init__(self, robot, policy, config: CPICConfig | None = None):
        checks.has_methods("robot", robot, "control_terms", "torque_limits", "jacobian")   # what step calls
        self.robot, self.config = robot, CPICConfig() if config is None else config
        c, n, lim = checks.instance("config", self.config, CPICConfig), robot.n, robot.model.jnt_range
        self.q_min = checks.array("config.q_min", lim[:, 0] if c.q_min is None else c.q_min, (n,), unit="(robot.n)")
        self.q_max = checks.array("config.q_max", lim[:, 1] if c.q_max is None else c.q_max, (n,), unit="(robot.n)")
        checks.array("config.fallback_damping", c.fallback_damping, (n,), unit="(robot.n)")
        None if c.q_rest is None else checks.array("config.q_rest", c.q_rest, (n,), unit="(robot.n)")
        self.tau_max = checks.array("config.tau_max", c.tau_max, (n,), unit="(robot.n)")
        if np.any(self.q_min >= self.q_max):
            raise ValueError(f"config.q_min: expected q_min < q_max, found {self.q_min.tolist()}, "
                             f"{self.q_max.tolist()}")
        if np.any(self.tau_max > robot.torque_limits()):     # a setting can only tighten the drives' own limits
            raise ValueError(f"config.tau_max: expected limits within the robot's own, robot.torque_limits() = "
                             f"{robot.torque_limits().tolist()} Nm, found {self.tau_max.tolist()}")
        self._I, self._zeros, self._tau_min, self._X = np.eye(n), np.zeros(n), -self.tau_max, np.zeros((3, n))
        m, r = c.payload_mass, 3 ** 0.5 * c.payload_com     # _payload_like's bound a d_j + b
        a = m * (float(np.linalg.norm(robot.g)) + 13.0 + 25.0 * r)
        self._payload_bound = (a, a * r + 25.0 * m * r * r)
        self._A = np.vstack([np.zeros((2 * n, n)), self._I, -self._I])   # constraint rows; the torque rows: fixed
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
        self._active, q_rest = [], self.config.q_rest
        self._rest = None if q_rest is None else (np.asarray(q_rest, dtype=float), _null_projector(self.robot, q_rest))

    def posture_potential(self, q):
        """P = k_p/2 (q - q_rest)^T N_rest (q - q_rest) [J] at q (n,); 0 while no rest pose is taken."""
        e = None if self._rest is None else np.asarray(q, dtype=float) - self._rest[0]
        return 0.0 if e is None else 0.5 * self.config.null_stiffness * float(e @ self._rest[1] @ e)

    def step(self, q, dq, compensation=None, tau_ext=None):
        """q, dq (n,) measured; compensation (n,) added after the QP (None = 0). Returns (tau (n,), StepInfo).

        tau_ext (n,), optional: the measured external torque (paper sign). None (default) = the nominal
        dynamics of Appendix B, ddq = M^-1 (tau - C dq - G), assuming the compensation cancels the mismatch.
        Given, the E-CBF predicts ddq = M^-1 (tau + comp - C dq - G + tau_ext) as in Eq. 8's equality, so a
        push is resisted at the limit (without it a push d [rad/s^2] can overshoot a limit by about d / k1).
        """
        G, dq, comp, f, V, F_c, tau_free, terms, why = self._terms(q, dq, compensation, tau_ext)
        self.G = G                                    # G(q) (n,) at this step's q: the caller need not recompute it
        if why:
            return self._fallback(G, dq, comp, f, V, F_c, f"fallback: {why}")
        if not self._active and self._satisfies(tau_free, comp, *terms[4:]):   # QP optimum = unconstrained one
            tau_qp, status, it, active = tau_free, "optimal", 0, []
        else:
            Hinv, g = self._objective(*terms[:4])    # NaN or inf: the QP's status is "degenerate"
            tau_qp, status, it, active, _ = dual_active_set_from_inverse(
                Hinv, g, self._A, self._constraint_bounds(comp, *terms[4:]), self._active, self.config.max_iterations)
        if status != "optimal" or not math.isfinite(tau_qp @ tau_qp):
            self._active = []
            return self._fallback(G, dq, comp, f, V, F_c, f"fallback: QP {status}")
        self._active, tau = active, np.minimum(np.maximum(tau_qp + comp, self._tau_min), self.tau_max)
        return tau, StepInfo(status, it, np.array(active, dtype=int), False, f, V, F_c, tau_qp)

    def qp(self, q, dq, compensation=None, tau_ext=None):
        """The QP that step() solves at this state, for inspection: (H (n, n), g (n,), A (4n, n), b (4n,),
        warm-start active set), ready for solve_qp(H, g, A, b, active)."""
        _, _, comp, _, _, _, _, terms, why = self._terms(q, dq, compensation, tau_ext)
        if why:
            raise ValueError(f"q, dq: no QP at this state ({why})")
        (Hinv, g), b, active = self._objective(*terms[:4]), self._constraint_bounds(comp, *terms[4:]), self._active
        return 0.5 * (np.linalg.inv(Hinv) + np.linalg.inv(Hinv).T), g, self._A.copy(), b, np.array(active, dtype=int)

    def _terms(self, q, dq, compensation, tau_ext):
        """Model terms, policy, F_c, tau_free = J^T F_t + N tau_0 (N v = v - J^T (J^+T v): N is never formed), the QP's
        terms (J, J^+T, F_t, N tau_0; q, k2 dq, M^-1, M^-1 bias) and why = "" or the reason for the safe torque."""
        robot, c, n = self.robot, self.config, self.robot.n
        J, M, bias, G, p, R = robot.control_terms(q, dq)          # one kinematics pass; validates q and dq
        q, dq = np.asarray(q, dtype=float), np.asarray(dq, dtype=float)
        comp = self._zeros if compensation is None else self._payload_like(compensation, J)
        if tau_ext is not None:
            bias = bias - checks.floats("tau_ext", tau_ext, (n,)) - comp
        f, V = _policy_output(self.policy(p, R))
        nothing = (G, dq, comp, f, V, np.full(6, np.nan), None, None)
        if not math.isfinite(float(f @ f) + V[0] + V[1]):
            return nothing + ("policy output not finite (or beyond 1e154)",)
        (_, Jp, bad), (_, Minv, bad_M) = lapack.dposv(np.dot(J, J.T), J), lapack.dposv(M, self._I)  # Cholesky solves:
        if bad or bad_M:                              # J^+T = (J J^T)^-1 J (6, n), M^-1 (n, n)
            return nothing + ("singular J or M",)
        if self._rest is None:                        # the first step after a reset: rest at this q
            Nproj = self._I - np.dot(J.T, Jp)
            self._rest = (q.copy(), 0.5 * (Nproj + Nproj.T))
        X = self._X                                   # (3, n): G, tau_p, tau_0 = G - k_n dq + tau_p
        X[0], X[1] = G, -c.null_stiffness * np.dot(self._rest[1], q - self._rest[0])   # posture spring -dP/dq
        X[2] = X[0] + X[1] - c.null_damping * dq
        JpX = np.dot(X, Jp.T)                         # (3, 6): J^+T G, J^+T tau_p, J^+T tau_0
        F_c = impedance_wrench(JpX[0], np.dot(J, dq), f, c.damping_pos, c.damping_rot)
        F_t = F_c + JpX[1]                            # the posture spring's task part joins F_c, its null part tau_0
        null = X[2] - np.dot(JpX[2], J)               # N tau_0
        tau_free = np.dot(F_t, J) + null
        a0 = np.dot(Minv, bias)                       # ddq = M^-1 tau - a0
        if not math.isfinite(float(tau_free @ tau_free) + float(a0 @ a0)):
            return nothing[:5] + (F_c, None, None, "model terms not finite (or beyond 1e154)")
        return G, dq, comp, f, V, F_c, tau_free, (J, Jp, F_t, null, q, c.k2 * dq, Minv, a0), ""

    def _payload_like(self, comp, J):
        """comp (n,) if a payload of at most payload_mass m with its CoM within r = sqrt(3) payload_com of the ee can
        need it, else ValueError (garbage is not clipped to full torque). Accelerated within Franka's Cartesian limits
        a = 13 m/s^2, alpha = 25 rad/s^2 (libfranka's specifications), it loads joint j with at most
        m (|g| + a + alpha r) (d_j + r) + m r^2 alpha, d_j = |J_v[:, j]|: the ee origin's distance from joint j's
        axis."""
        comp, (a, b) = checks.floats("compensation", comp, (self.robot.n,)), self._payload_bound
        if comp.max() <= b and -comp.min() <= b:      # within b, the bound at d_j = 0: nothing more to check
            return comp
        bound = a * np.sqrt(np.einsum("ij,ij->j", J[:3], J[:3])) + b
        if not np.all(np.abs(comp) <= bound):
            c = self.config
            raise ValueError(f"compensation: expected what a payload up to {c.payload_mass:g} kg, CoM within "
                             f"{c.payload_com:g} m of the ee per axis, can need at this q (CPICConfig.payload_mass, "
                             f"payload_com): |comp| <= {np.round(bound, 2).tolist()} Nm, found "
                             f"{np.round(comp, 3).tolist()}")
        return comp

    def _objective(self, J, Jp, F_t, null):
        """H^-1 (n, n), g (n,): H = J^+ J^+T + w N has the closed-form inverse H^-1 = J^T J + N / w = I / w + J^T (J -
        J^+T / w) (J^+T J^T = I, J N = 0); g = -H tau_free = -(J^+ F_t + w N tau_0)."""
        w = self.config.null_weight
        Hinv = np.dot(J.T, J - Jp / w)
        Hinv += Hinv.T                                # symmetric to rounding: the QP reads every entry
        Hinv.flat[::self.robot.n + 1] += 2.0 / w
        return 0.5 * Hinv, -(np.dot(F_t, Jp) + w * null)

    def _satisfies(self, tau, comp, q, k_dq, Minv, a0):
        """Whether tau (n,) meets every row of the QP to 1e-9: both E-CBF rows (_constraint_bounds) and the limits."""
        x, k1, room = Minv @ tau - a0 + k_dq, self.config.k1, self.tau_max - np.abs(tau + comp)    # x = ddq + k2 dq
        lo, hi = x + k1 * (q - self.q_min), k1 * (self.q_max - q) - x
        return min(lo[lo.argmin()], hi[hi.argmin()], room[room.argmin()]) >= -1e-9

    def _constraint_bounds(self, comp, q, k_dq, Minv, a0):
        """b (4n,) for A tau >= b, A's rows +-M^-1 (E-CBF on h = q - q_min, q_max - q: ddq + k2 dq + k1 h >= 0 with
        ddq = M^-1 tau - a0; set here), then +-I (torque limits)."""
        c, n, A, b = self.config, self.robot.n, self._A, np.empty(4 * self.robot.n)
        A[:n] = Minv
        np.negative(Minv, out=A[n:2 * n])
        b[:n] = a0 - c.k1 * (q - self.q_min) - k_dq
        b[n:2 * n] = k_dq - c.k1 * (self.q_max - q) - a0
        b[2 * n:3 * n] = -self.tau_max - comp
        b[3 * n:] = comp - self.tau_max
        return b

    def _fallback(self, G, dq, comp, f, V, F_c, status):
        """Safe torque when the QP has no answer: gravity compensation + compensation + joint damping, clipped."""
        tau = np.clip(G + comp - np.asarray(self.config.fallback_damping) * dq, -self.tau_max, self.tau_max)
        tau[np.isnan(tau)] = 0.0                      # (+-inf clip to the limits; NaN only from inf - inf)
        return tau, StepInfo(status, 0, np.zeros(0, dtype=int), True, f, V, F_c, tau - comp)


def _policy_output(out):
    """(f (6,), (V_pos, V_rot)) of a policy's output; a wrong type or shape is a ValueError (NaN, inf are not: step
    falls back to the safe torque and says why)."""
    f, V = out if type(out) is tuple and len(out) == 2 else (None, None)
    if type(f) is np.ndarray and f.dtype == np.float64 and f.shape == (6,) and type(V) is tuple and len(V) == 2 and \
            type(V[0]) in (float, np.float64) and type(V[1]) in (float, np.float64):
        return f, V                                   # what Attractor and LimitCycle return: the 1 kHz loop's case
    f, V = checks.real_array(f), checks.real_array(V)
    if f is None or V is None or f.shape != (6,) or V.shape != (2,):
        raise ValueError(f"policy: expected (f, (V_pos, V_rot)) with f of 6 real numbers, found {out!r:.80}")
    return f.astype(float), (float(V[0]), float(V[1]))


def _null_projector(robot, q):
    """N = I - J^+ J (n, n) at q: the projector onto the null space of J (pseudo-inverse: any rank)."""
    N = np.eye(robot.n) - np.linalg.pinv(J := robot.jacobian(q)) @ J
    return 0.5 * (N + N.T)


def storage(dq, M, V, config: CPICConfig, P):
    """S = 1/2 dq^T M dq + lambda_1 V + P (Prop. 4.1; P = ctrl.posture_potential(q), the posture spring's),
    lambda_1 V = lambda_1,pos V_pos + lambda_1,rot V_rot; dq^T M dq = xdot^T M_x xdot + the null-space motion's."""
    return 0.5 * dq @ M @ dq + config.damping_pos[0] * V[0] + config.damping_rot[0] * V[1] + P


class JointHold:
    """A stiff joint-space hold, tau = G(q) + Kp (q0 - q) - Kd dq (+ compensation) on the nominal model: the simple
    controller used for recording data (CPIC above is the paper's controller). Gains: ours, stiff enough that a
    3 kg load moves the arm by a few mrad."""

    def __init__(self, robot: Robot, q0, kp=(600.0,) * 4 + (50.0,) * 3, kd=(40.0,) * 4 + (4.0,) * 3):
        self.robot, self.q0 = robot, as_states("q0", q0, robot.n, allow_window=False)[0][0]
        self.kp, self.kd = (checks.array(k, v, (robot.n,), "[0, 1e5]") for k, v in (("kp", kp), ("kd", kd)))

    def step(self, q, dq, compensation=None, tau_ext=None):
        """(tau (n,), None): the hold's torque for the state q, dq (n,), plus the compensation if given."""
        n = self.robot.n
        tau = self.robot.gravity(q) + self.kp * (self.q0 - q) - self.kd * checks.floats("dq", dq, (n,))
        return (tau if compensation is None else tau + checks.floats("compensation", compensation, (n,))), None
