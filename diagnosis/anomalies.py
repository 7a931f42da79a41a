"""What a log holds that is no effect of the model (Eq. 1 plus effects.py): a vibration in the residual at rest (a
flexible load: frequency, damping) and a step of the static torque the pose does not explain (a load changed)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import uniform_filter1d
from scipy.optimize import least_squares


@dataclass(frozen=True)
class AnomalyConfig:
    """Thresholds of the vibration and step findings."""
    v_rest: float = 0.02        # rad/s, every |dq| below: at rest (CompareConfig.v_rest)
    min_rest: float = 2.0       # s, shortest rest stretch searched for a vibration (5 periods at 2.5 Hz)
    band: tuple = (0.5, 20.0)   # Hz, vibration band: above a hold's drift, inside the log filter's pass band
    trend: float = 1.0          # s, moving mean removed first (a drift or a settling arm)
    min_peak: float = 10.0      # the peak's power over the band's median power, summed over joints (white noise:
    #                             about 5 for the largest of 200 bins)
    min_amplitude: float = 0.02  # Nm, the Panda's torque resolution (datasheet, panda_facts.md)
    window: float = 1.0         # s, means compared before and after a step (>= 2 periods of a load's vibration
    #                             above 2 Hz, which then cancels to within a third of its amplitude)
    guard: float = 0.15         # s, left out on each side of a step (the log filter and a load's placing)
    min_step: float = 0.7       # Nm, norm of the static torque change: the paper detector's lowest activation
    #                             threshold (App. A: 0.7-1.1 Nm)
    pose_share: float = 0.5     # a step counts if the pose explains less than this share of it (see steps())
    max_span: float = 5.0       # s, the longest stretch two compared windows may span (a settling arm, not a drift)


def rest_stretches(dq, dt: float, config: AnomalyConfig = AnomalyConfig()) -> list:
    """[(first, last + 1)] rows of the stretches at rest at least config.min_rest long. dq (T, n)."""
    still = np.all(np.abs(dq) < config.v_rest, axis=1).astype(int)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], still, [0]])))
    return [(a, b) for a, b in zip(edges[::2], edges[1::2]) if (b - a) * dt >= config.min_rest]


def oscillation(t, r, dq, config: AnomalyConfig = AnomalyConfig()):
    """The strongest vibration of the residual r (T, n) in the longest rest stretch, or None: {frequency [Hz],
    damping (ratio), decay [1/s], amplitude [Nm], joint (1-based), joints (where it stands out), t0 [s], peak}.
    Hypotheses: broadband error (no peak) against a resonance (a narrow peak, a decaying sinusoid); the periodogram
    of the trend-free residual finds the peak, a damped sinusoid fitted from the largest envelope gives frequency and
    damping (exp(-decay t) cos(2 pi f t): damping ratio decay / sqrt(decay^2 + (2 pi f)^2))."""
    dt = float(np.median(np.diff(t)))
    stretches = rest_stretches(dq, dt, config)
    if not stretches:
        return None
    a, b = max(stretches, key=lambda s: s[1] - s[0])
    x = r[a:b] - uniform_filter1d(r[a:b], max(3, int(config.trend / dt)), axis=0, mode="nearest")
    f = np.fft.rfftfreq(len(x), dt)
    P = np.abs(np.fft.rfft(x * np.hanning(len(x))[:, None], axis=0)) ** 2          # (F, n)
    band = (f >= config.band[0]) & (f <= config.band[1])
    if band.sum() < 10:
        return None
    norm = P[band] / np.maximum(np.median(P[band], axis=0), 1e-300)                # (B, n)
    total = norm.sum(axis=1) / norm.shape[1]
    k = int(np.argmax(total))
    if total[k] < config.min_peak:
        return None
    j = int(np.argmax(norm[k]))
    fit = _damped_sine(t[a:b] - t[a], x[:, j], float(f[band][k]))
    if fit is None or fit["amplitude"] < config.min_amplitude:
        return None
    joints = [int(i) + 1 for i in np.flatnonzero(norm[k] >= config.min_peak)]
    return dict(fit, joint=j + 1, joints=joints or [j + 1], t0=float(t[a] + fit.pop("start")), peak=float(total[k]))


def _damped_sine(t, x, f0: float):
    """{frequency, decay, damping, amplitude, start} of A exp(-s (t - t0)) cos(w (t - t0) + phi) fitted to x (T,)
    from t0, the largest envelope (a moving RMS over one period); None if the fit fails."""
    period = max(3, int(round(1 / (f0 * (t[1] - t[0])))))
    env = np.sqrt(uniform_filter1d(x ** 2, period, mode="nearest"))
    i0 = int(np.argmax(env[: max(1, len(x) - 4 * period)]))
    tt, xx = t[i0:] - t[i0], x[i0:]
    w0, A0 = 2 * np.pi * f0, np.sqrt(2) * env[i0]

    def model(p):
        return p[0] * np.exp(-p[1] * tt) * np.cos(p[2] * tt + p[3])
    best = None
    for phi in (0.0, np.pi / 2, np.pi, 3 * np.pi / 2):
        res = least_squares(lambda p: model(p) - xx, [A0, 0.5, w0, phi], x_scale=[A0, 1.0, w0, 1.0],
                            bounds=([0, 0, 0.8 * w0, -10], [np.inf, 50, 1.2 * w0, 10]))
        if res.success and (best is None or res.cost < best.cost):
            best = res
    if best is None:
        return None
    A, s, w = best.x[:3]
    return {"frequency": float(w / (2 * np.pi)), "decay": float(s), "damping": float(s / np.hypot(s, w)),
            "amplitude": float(A), "start": float(t[i0])}


def steps(t, r, q, dq, pose_torque, config: AnomalyConfig = AnomalyConfig()) -> list:
    """Where the static torque changes by a step the pose does not explain (a load put down or picked up), [{t [s],
    size [Nm] (norm over joints), change (n,) [Nm], explained (share the pose change can explain), moved (the arm
    moved between the two windows)}].

    Hypotheses for a change d = mean(r after) - mean(r before) of the residual r (T, n), means over `window` seconds
    of rest samples on each side (the nearest ones, guard seconds left out, at most max_span apart: a load is often put
    in the hand while the arm gives way): the pose changed and an effect the model misses depends on it (the change
    is at most what a plausible load and model error make between the two poses, pose_torque(q_a, q_b) [Nm]), or the
    load changed (any change, at one pose as well). A step is a local maximum of |d| on a 10 ms grid with
    |d| >= min_step that the pose explains less than pose_share of; its time, the centre of the change, is refined
    to 1 ms: where the means right before and after it differ most (window seconds at rest, 0.1 s across motion)."""
    dt = float(np.median(np.diff(t)))
    W, g = int(config.window / dt), int(config.guard / dt)
    still = np.all(np.abs(dq) < config.v_rest, axis=1).astype(float)
    cs = lambda x: np.concatenate([np.zeros((1,) + x.shape[1:]), np.cumsum(x, axis=0)])      # noqa: E731
    S_r, S_q, S_n = cs(r * still[:, None]), cs(q * still[:, None]), cs(still)
    grid = np.arange(g, len(t) - g, max(1, int(0.01 / dt)))
    a, b = grid - g, grid + g                                      # the windows end at a and start at b
    i0 = np.searchsorted(S_n, S_n[a] - W)                          # rows [i0, a) hold W rest samples
    i1 = np.minimum(np.searchsorted(S_n, S_n[b] + W), len(t))      # rows [b, i1) hold W rest samples
    ok = (S_n[a] >= W) & (S_n[-1] - S_n[b] >= W) & ((i1 - i0) * dt <= config.max_span)
    d = ((S_r[i1] - S_r[b]) - (S_r[a] - S_r[i0])) / W              # (G, n)
    size = np.where(ok, np.linalg.norm(d, axis=1), 0.0)
    found, taken = [], np.zeros(len(grid), bool)
    for i in np.argsort(-size):
        if size[i] < config.min_step:
            break
        if taken[i]:
            continue
        taken[(grid >= i0[i] - W - g) & (grid < i1[i] + W + g)] = True  # every window that reaches this change
        qa, qb = (S_q[a[i]] - S_q[i0[i]]) / W, (S_q[i1[i]] - S_q[b[i]]) / W
        explained = min(1.0, pose_torque(qa, qb) / size[i])
        if explained >= config.pose_share:
            continue
        lo = i0[i] + int(np.searchsorted(S_n[i0[i]:], S_n[a[i]], side="left"))   # the last rest row before: a
        hi = b[i] + int(np.searchsorted(S_n[b[i]:], S_n[b[i]] + 1, side="left"))  # the first rest row after b
        moved = bool((hi - lo) * dt > 2 * config.guard + 0.05)
        h = int(0.1 / dt) if moved else W
        found.append(dict(t=float(t[_centre(r, min(lo, a[i]), max(hi, b[i]), h)]), size=float(size[i]),
                          change=d[i], explained=float(explained), moved=moved))
    return sorted(found, key=lambda s: s["t"])


def _centre(r, lo, hi, h):
    """The row in [lo, hi) where the means of h rows before and after it differ most: the middle of the change (a
    vibration cancels in h rows as it does in the detection)."""
    lo, hi = max(h, lo), min(len(r) - h, hi)
    cs = np.concatenate([np.zeros((1, r.shape[1])), np.cumsum(r, axis=0)])
    rows = np.arange(lo, max(hi, lo + 1))
    diff = (cs[rows + h] - cs[rows]) - (cs[rows] - cs[rows - h])
    return int(rows[np.argmax(np.linalg.norm(diff, axis=1))])
