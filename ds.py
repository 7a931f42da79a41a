"""Motion policies f(x) with their Lyapunov functions V(x) (Sec. 3, Eq. 6), as CPIC (cpic.py) follows them: a
linear attractor to a pose and a limit cycle in the y-z plane, each returning f (6,) and V = (V_pos, V_rot)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

import checks


def _checked_rotation(name, R):
    """R (3, 3) with R^T R = I and det R = +1 (to 1e-6); else ValueError."""
    R = checks.array(name, R, (3, 3))
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0.0:
        raise ValueError(f"{name}: expected a rotation matrix (R^T R = I, det R = 1), found {R.tolist()}")
    return R


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
        object.__setattr__(self, "p_star", checks.array("p_star", self.p_star, (3,), "[-10, 10]", "m"))
        object.__setattr__(self, "R_star", _checked_rotation("R_star", self.R_star))
        checks.number("gain_pos", self.gain_pos, "(0, 1e3]", "1/s")
        checks.number("gain_rot", self.gain_rot, "(0, 1e3]", "1/s")

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
        object.__setattr__(self, "center", checks.array("center", self.center, (3,), "[-10, 10]", "m"))
        object.__setattr__(self, "R_star", _checked_rotation("R_star", self.R_star))
        for name, interval, unit in (("radius", "(0, 10]", "m"), ("period", "(0, 1e4]", "s"),
                                     ("gain_pos", "(0, 1e3]", "1/s"), ("gain_rot", "(0, 1e3]", "1/s")):
            checks.number(name, getattr(self, name), interval, unit)

    def __call__(self, p, R):
        e = p - self.center
        u = e[1:]                                     # (y, z) relative to the centre
        rho = np.sqrt(u @ u)
        radial = u / rho if rho > 1e-12 else np.zeros(2)
        v_yz = -self.gain_pos * (rho - self.radius) * radial + (2.0 * np.pi / self.period) * np.array([-u[1], u[0]])
        f_w, V_rot = _orientation_terms(R, self.R_star, self.gain_rot)
        V_pos = 0.5 * self.gain_pos * ((rho - self.radius) ** 2 + e[0] ** 2)
        return np.concatenate([[-self.gain_pos * e[0]], v_yz, f_w]), (V_pos, V_rot)
