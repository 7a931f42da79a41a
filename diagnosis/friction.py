"""The nonlinear shapes of joint friction for the effect library (the Sec. 6 friction limitation): Coulomb friction
fc tanh(dq / w) with a fitted width w, and the Gaz et al. (2019) sigmoid; their per-joint shape fits (scipy)."""
from __future__ import annotations

import numpy as np
from scipy.optimize import least_squares
from scipy.signal import savgol_coeffs
from scipy.special import expit


def sigmoid_shape(dq, p2, p3):
    """(T, n) shape functions of the Gaz friction for p2, p3 (n,): tau_f = p1 * shape, shape(0) = 0."""
    return expit(p2 * (dq + p3)) - expit(p2 * p3)


def _fit_rows(s, rows, cap: int, filtered: bool):
    """Rows to fit a shape on: pick (R,) positions into rows (every k-th, at most cap, kept half a filter window from
    the log's ends), idx (R, w) the log rows whose filtered sum gives row pick's value, coef (w,) the filter (the
    Savitzky-Golay smoother of the log, as Signals.smooth applies it away from the ends; (1,) unfiltered)."""
    rows = np.asarray(rows)
    if filtered and s.smoothing is not None and len(s) > s.smoothing[0]:
        coef = savgol_coeffs(*s.smoothing)
    else:
        coef = np.ones(1)
    h = len(coef) // 2
    ok = np.flatnonzero((rows >= h) & (rows < len(s) - h))
    pick = ok[::max(1, len(ok) // cap)]
    return pick, rows[pick][:, None] + np.arange(-h, h + 1), coef


def fit_coulomb(s, rows, z, nl, widths=(0.002, 0.5), cap: int = 1000) -> np.ndarray:
    """Widths w (n, 1) of fc tanh(dq / w) fitting z (T', n), the residual on the training rows `rows` of the log s.
    The step is sharper than the log's torque filter, so the shape goes through the same filter before it is compared
    (Signals.smooth); per joint z_j ~ fc F[tanh(dq_j / w)] + c_j (c_j a nuisance constant, as for the sigmoid),
    scipy.optimize.least_squares (TRF, analytic Jacobian) over (fc, log w, c) with log w bounded, from the best of a
    grid of widths (or the previous value)."""
    pick, idx, coef = _fit_rows(s, rows, cap, filtered=True)
    z = z[pick]
    lo, hi = np.log(widths[0]), np.log(widths[1])
    out = np.empty((s.n, 1))
    for j in range(s.n):
        V, zj = s.dq[idx, j], z[:, j]                                   # (R, w), (R,)
        far, sign, memo = np.abs(V).min(axis=1), np.sign(V[:, len(coef) // 2]), {}

        def shape(lw):
            """F[tanh(V / w)] and its derivative by log w (R,); windows with |dq| > 10 w throughout are +-1, 0. The
            last value is kept: least_squares asks for the Jacobian where it just evaluated the residual."""
            if memo.get("lw") != lw:
                near = far < 10 * np.exp(lw)
                f, df = sign.copy(), np.zeros(len(sign))
                x = V[near] / np.exp(lw)
                th = np.tanh(x)
                f[near], df[near] = th @ coef, (-x * (1 - th ** 2)) @ coef
                memo.update(lw=lw, out=(f, df))
            return memo["out"]

        def residual(x):
            return zj - x[0] * shape(x[1])[0] - x[2]

        def jacobian(x):
            f, df = shape(x[1])
            return -np.stack([f, x[0] * df, np.ones_like(f)], axis=1)

        best = None
        for lw in list(np.log([0.003, 0.01, 0.03, 0.1, 0.3])) + [np.log(np.clip(nl[j, 0], *widths))]:
            A = np.stack([shape(lw)[0], np.ones_like(zj)], axis=1)
            (fc, c), err = np.linalg.lstsq(A, zj, rcond=None)[:2]
            err = err[0] if len(err) else np.inf
            if best is None or err < best[0]:
                best = (err, np.array([fc, np.clip(lw, lo + 1e-9, hi - 1e-9), c]))
        x = best[1]
        if best[0] < 0.99 * np.sum((zj - zj.mean()) ** 2):           # a shape that explains nothing has no optimum
            x = least_squares(residual, x, jac=jacobian, bounds=([-np.inf, lo, -np.inf], [np.inf, hi, np.inf]),
                              method="trf", xtol=1e-6, ftol=1e-6, max_nfev=50).x
        out[j, 0] = np.exp(np.clip(x[1], lo, hi))
    return out


def fit_sigmoid(s, rows, z, nl, p2_bounds=(0.5, 200.0), p3_bounds=(-0.3, 0.3), cap: int = 2000) -> np.ndarray:
    """(p2, p3) per joint (n, 2) fitting z (T', n), the residual on the training rows `rows` of the log s, by
    z_j ~ p1 shape(dq_j; p2, p3) + c_j. The nuisance constant c_j keeps a sensor offset from bending the shape (an
    offset is its own effect). Per joint, scipy.optimize.least_squares (Levenberg-Marquardt, analytic Jacobian) over
    x = (p1, log p2, atanh(p3 / b), c), so p3 stays inside +-b, from the best p2 of a coarse grid (or the previous
    value). Unfiltered: its widths 2 / p2 (0.1-0.4 rad/s for Gaz's values) are slow beside the log's filter."""
    pick, idx, _ = _fit_rows(s, rows, cap, filtered=False)
    dq, z = s.dq[idx[:, 0]], z[pick]
    n, b = dq.shape[1], max(abs(p3_bounds[0]), abs(p3_bounds[1]))
    out = np.empty((n, 2))
    for j in range(n):
        v, zj = dq[:, j], z[:, j]

        def residual(x):
            return zj - x[0] * sigmoid_shape(v, np.exp(min(x[1], 30.0)), b * np.tanh(x[2])) - x[3]

        def jacobian(x):
            p2, p3 = np.exp(min(x[1], 30.0)), b * np.tanh(x[2])
            sg, s0 = expit(p2 * (v + p3)), expit(p2 * p3)
            d, d0 = sg * (1 - sg), s0 * (1 - s0)
            dp3 = x[0] * p2 * (d - d0) * b * (1 - np.tanh(x[2]) ** 2)
            return -np.stack([sg - s0, x[0] * p2 * (d * (v + p3) - d0 * p3), dp3, np.ones_like(v)], axis=1)

        starts = [(p2, 0.0) for p2 in (2.0, 5.0, 10.0, 20.0, 50.0)] + [(nl[j, 0], np.clip(nl[j, 1], -0.9 * b, 0.9 * b))]
        best = None
        for p2, p3 in starts:                # p1, c in closed form for each start
            A = np.stack([sigmoid_shape(v, p2, p3), np.ones_like(v)], axis=1)
            (p1, c), err = np.linalg.lstsq(A, zj, rcond=None)[:2]
            err = err[0] if len(err) else np.inf
            if best is None or err < best[0]:
                best = (err, np.array([p1, np.log(p2), np.arctanh(p3 / b), c]))
        x = best[1]
        if best[0] < 0.99 * np.sum((zj - zj.mean()) ** 2):     # a shape that explains nothing has no optimum
            x = least_squares(residual, x, jac=jacobian, method="lm", xtol=1e-6, ftol=1e-6, max_nfev=50).x
        out[j] = np.clip(np.exp(x[1]), *p2_bounds), b * np.tanh(x[2])
    return out
