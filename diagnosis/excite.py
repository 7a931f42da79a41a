"""Exciting trajectories for model diagnosis: a smooth multi-sine joint reference tracked by computed torque on the
nominal model (Eq. 1) + PD, and the least-squares payload of a log (Eqs. 4-5). Simulated logs: experiments/episodes.py."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

import vi
from dynamics import Robot

# Gaz et al. 2019, supplementary: linear friction model tau_f = fv dq + fc sign(dq) + fo (panda_facts.md)
GAZ_FV = (0.0665, 0.1987, 0.0399, 0.2257, 0.1023, -0.0132, 0.0638)    # Nm s/rad
GAZ_FC = (0.2450, 0.1523, 0.1827, 0.3591, 0.2669, 0.1658, 0.2109)     # Nm


@dataclass(frozen=True)
class ExciteConfig:
    """The multi-sine reference q_d(t) = center + sum_i (v / (K w_ij)) sin(w_ij t + phase_ij) and its tracking gains."""
    center: tuple = (0.0, -0.2, 0.0, -1.9, 0.0, 1.9, 0.8)   # rad, >= 1.1 rad from every limit (panda_facts.md)
    freqs: tuple = (0.13, 0.29, 0.47, 0.71)   # Hz, components (x (1 + 0.07 j) on joint j so joints decorrelate)
    speed: float = 1.0                         # rad/s, peak joint speed (about half the Panda's 2.2 rad/s limits)
    freq_scale: float = 1.0                    # > 1: faster oscillations, larger accelerations
    kp: float = 400.0                          # 1/s^2, computed-torque stiffness (20 rad/s closed-loop bandwidth)
    kd: float = 40.0                           # 1/s, critical damping for kp
    settle: float = 0.5                        # s, dropped from the start (5 time constants of the tracking loop)


# slow sweeps: the payload's own motion torques stay below ~0.005 Nm, so a static payload model (Eqs. 4-5) fits them
QUASI_STATIC = ExciteConfig(speed=0.1, freq_scale=0.05)


def multisine(t, config: ExciteConfig, rng: np.random.Generator):
    """q_d, dq_d, ddq_d (T, n) at times t (T,); phases drawn from rng."""
    t = np.asarray(t, dtype=float)[:, None, None]
    n, K = len(config.center), len(config.freqs)
    w = 2 * np.pi * config.freq_scale * np.outer(1 + 0.07 * np.arange(n), config.freqs)      # (n, K)
    phase = rng.uniform(0, 2 * np.pi, size=(n, K))
    amp = config.speed / K / w                                                              # (n, K)
    arg = w * t + phase                                                                     # (T, n, K)
    q = np.asarray(config.center) + (amp * np.sin(arg)).sum(-1)
    return q, (amp * w * np.cos(arg)).sum(-1), -(amp * w ** 2 * np.sin(arg)).sum(-1)


class Tracker:
    """Computed torque on the nominal model: tau = M(q) (ddq_d + kp e + kd de) + C dq + G, on the sensed sample."""

    def __init__(self, robot: Robot, t, q_d, dq_d, ddq_d, config: ExciteConfig):
        self.robot, self.ref, self.config = robot, (q_d, dq_d, ddq_d), config
        self._k = 0                                    # control steps taken: the reference row t[k]

    def step(self, q, dq, compensation=None, tau_ext=None):
        """(tau (n,), None) for the state q, dq at the next reference time (one call per control step)."""
        k, self._k = min(self._k, len(self.ref[0]) - 1), self._k + 1
        q_d, dq_d, ddq_d = (r[k] for r in self.ref)
        _, M, b = self.robot.terms(q, dq)
        tau = M @ (ddq_d + self.config.kp * (q_d - q) + self.config.kd * (dq_d - dq)) + b
        return (tau if compensation is None else tau + compensation), None


def payload_lstsq(robot: Robot, q, tau_ext) -> np.ndarray:
    """theta = (m, r) (4,) from the least-squares phi of tau_ext (T, n) ~ payload_regressor(q) phi (paper Eqs. 4-5)."""
    Y = robot.payload_regressor(q).reshape(-1, 4)
    phi = np.linalg.lstsq(Y, np.asarray(tau_ext).reshape(-1), rcond=None)[0]
    return vi.theta_of(phi)


@dataclass(frozen=True)
class HoldsConfig:
    """A load-free calibration of the pose-dependent torque (effects "pose_bias"): holds at poses drawn uniformly in
    a box center +- spans, joined by cosine moves; only the still end of each hold is fitted (no friction there)."""
    spans: tuple = (0.05, 0.05, 0.05, 0.05, 0.1, 0.6, 0.1)   # rad, half-widths per joint (ours: a tilt of the ee
    #                              turns joint 6; a load shifts the others by < 0.04 rad under CPIC)
    poses: int = 60                # holds (the basis has 15 functions per joint; 60 poses over-determine them 4x)
    hold: float = 0.5              # s at each pose
    settle: float = 0.25           # s of each hold left out of the fit (the tracking loop settles at 20 rad/s)
    margin: float = 0.05           # s before each move left out too (the log's torque filter spans +-0.025 s)
    speed: float = 0.8             # rad/s, peak joint speed of a move (cosine profile; ours)
    min_move: float = 0.2          # s, shortest move


def hold_poses(center, config: HoldsConfig, rng: np.random.Generator) -> np.ndarray:
    """The centre and config.poses - 1 poses (P, n) drawn uniformly in center +- spans, in nearest-neighbour order
    (short moves)."""
    center, spans = np.asarray(center, dtype=float), np.asarray(config.spans, dtype=float)
    if center.shape != spans.shape:
        raise ValueError(f"center: expected {spans.shape[0]} joint angles like config.spans, found {center.shape}")
    todo = list(center + spans * rng.uniform(-1.0, 1.0, size=(config.poses - 1, len(center))))
    out = [center]
    while todo:
        k = int(np.argmin([np.abs(p - out[-1]).max() for p in todo]))
        out.append(todo.pop(k))
    return np.array(out)


def hold_reference(poses, config: HoldsConfig, dt: float = 1e-3):
    """A reference through poses (P, n): hold each, then move to the next on a cosine profile whose peak joint speed is
    config.speed. Returns t (T,), q_d, dq_d, ddq_d (T, n) and still (T,): the samples to fit (settled, not near a
    move)."""
    segs = []
    for a, b in zip(poses, list(poses[1:]) + [None]):
        steps = int(round(config.hold / dt))
        hold = np.repeat(a[None], steps, axis=0)
        still = (np.arange(steps) * dt >= config.settle) & (np.arange(steps) * dt < config.hold - config.margin)
        segs.append((hold, np.zeros_like(hold), np.zeros_like(hold), still))
        if b is None:
            break
        T = max(config.min_move, np.pi * np.abs(b - a).max() / (2.0 * config.speed))
        s = np.arange(int(round(T / dt)))[:, None] * dt / T                  # (K, 1) in [0, 1)
        w = np.pi / T
        segs.append((a + 0.5 * (b - a) * (1 - np.cos(np.pi * s)), 0.5 * (b - a) * w * np.sin(np.pi * s),
                     0.5 * (b - a) * w ** 2 * np.cos(np.pi * s), np.zeros(len(s), dtype=bool)))
    q, dq, ddq, still = (np.concatenate(parts) for parts in zip(*segs))
    return dt * np.arange(len(q)), q, dq, ddq, still
