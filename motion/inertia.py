"""The payload's 10 inertial parameters pi from motion: least squares on tau = Y(q, dq, ddq) pi + b from running normal
equations, RME's (m, m r) as a Gaussian prior, the pseudo-inertia held PSD (Wensing, Kim, Slotine 2017) by a log-det
barrier, in steps a 1 kHz loop can spread over its samples; Savitzky-Golay (1964) derivatives of the 1 kHz signals."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import savgol_coeffs

import checks

_I_INDEX = np.array([[4, 5, 7], [5, 6, 8], [7, 8, 9]])     # pi index of I[i, j]; pi = (m, h, Ixx, Ixy, Iyy, Ixz, Iyz, Izz)


def savgol(window: int, order: int, deriv: int, dt: float, causal: bool) -> np.ndarray:
    """Savitzky-Golay weights c (window,) in time order, oldest first: x_hat^(deriv) = c @ x[-window:] evaluated at the
    newest sample (causal) or at the centre (window odd). A local polynomial of `order` fitted by least squares."""
    if window < order + 2 or (not causal and window % 2 == 0):
        raise ValueError(f"window: expected an {'' if causal else 'odd '}length >= order + 2 = {order + 2}, "
                         f"found {window}")
    pos = window - 1 if causal else window // 2
    return savgol_coeffs(window, order, deriv=deriv, delta=dt, pos=pos, use="dot")


def rigid_body(m, c, inertia=None) -> np.ndarray:
    """pi (10,) of a body of mass m [kg], CoM c (3,) [m] and inertia (3, 3) about its CoM (None: a point mass), all in
    the ee frame; the inertia in pi is about the ee origin: I_o = I_c + m (|c|^2 E - c c^T) (Steiner)."""
    c = np.asarray(c, dtype=float)
    Ic = np.zeros((3, 3)) if inertia is None else np.asarray(inertia, dtype=float)
    Io = Ic + m * ((c @ c) * np.eye(3) - np.outer(c, c))
    return np.array([m, *(m * c), Io[0, 0], Io[0, 1], Io[1, 1], Io[0, 2], Io[1, 2], Io[2, 2]])


def inertia_of(pi) -> np.ndarray:
    """I (3, 3) about the ee origin from pi (10,)."""
    return np.asarray(pi, dtype=float)[_I_INDEX]


def pseudo_inertia(pi) -> np.ndarray:
    """P (4, 4) = [[S, h], [h^T, m]], S = tr(I)/2 E - I the second moment of the mass about the ee origin:
    P >= 0 exactly when pi is a physical rigid body (a mass distribution)."""
    pi = np.asarray(pi, dtype=float)
    I = pi[_I_INDEX]
    P = np.empty((4, 4))
    P[:3, :3] = 0.5 * np.trace(I) * np.eye(3) - I
    P[:3, 3] = P[3, :3] = pi[1:4]
    P[3, 3] = pi[0]
    return P


def params_of(P) -> np.ndarray:
    """pi (10,) of a pseudo-inertia P (4, 4), the inverse of pseudo_inertia: I = tr(S) E - S."""
    S = P[:3, :3]
    I = np.trace(S) * np.eye(3) - S
    return np.array([P[3, 3], P[0, 3], P[1, 3], P[2, 3], I[0, 0], I[0, 1], I[1, 1], I[0, 2], I[1, 2], I[2, 2]])


_BASIS = np.stack([pseudo_inertia(e) for e in np.eye(10)])   # (10, 4, 4): P(pi) = sum_k pi_k B_k (P is linear)


@dataclass(frozen=True)
class FitSettings:
    prior_std: tuple = (0.05, 0.005, 0.005, 0.01)   # kg, kg m: std of RME's (m, m rx, m ry, m rz) when its estimate
                                                     #   gives no covariance (ours; static windows leave m rz loose)
    inertia_std: float = 1.0                         # kg m^2: a weak prior at 0 on the six inertia parameters (ours:
                                                     #   keeps unexcited directions finite; a payload's are < 0.1)
    min_noise: float = 1e-3                          # Nm: floor of a joint's residual std in the weighting
    tolerance: float = 1e-9                          # relative: P's smallest eigenvalue above -tol * |P| is physical
    gap: float = 1e-6                                # the projection stops within this share of its cost (at
                                                     #   least 1) of the optimum, whitened (chi-square units)
    max_steps: int = 100                             # Newton steps of the projection at most (it takes 20-40)
    offsets: bool = True                             # each joint's unknown offset b partialled out (False: b = 0,
                                                     #   the torques already referred to a reference)

    def __post_init__(self):                         # finite bounds far beyond use (checks.py)
        checks.array("prior_std", self.prior_std, (4,), "(0, 1e3]", "kg, kg m")
        for name, interval in (("inertia_std", "(0, 1e3]"), ("min_noise", "(0, 1e3]"), ("tolerance", "[0, 1]"),
                               ("gap", "(0, 1]"), ("max_steps", "1..10000")):
            checks.number(name, getattr(self, name), interval)
        checks.flag("offsets", self.offsets)


@dataclass
class FitInfo:
    """What a fit did: status 'ok' (the least-squares optimum is physical), 'projected' (held physical by the
    constraint), 'max steps' (physical, the projection stopped early) or 'no data'; std, cov of pi from the weighted
    residual; per-joint residual rms [Nm] and weight [1/Nm]."""
    status: str
    rows: int
    std: np.ndarray
    cov: np.ndarray
    residual: np.ndarray
    unconstrained: np.ndarray        # (10,) the least-squares optimum before the constraint
    iterations: int = 0
    weights: np.ndarray = None


def normal_rows(Y, tau) -> np.ndarray:
    """S (n, 12, 12) = sum over the rows of z z^T, per joint, z = (Y_j (10), tau_j, 1) from Y (N, n, 10), tau (N, n):
    everything the fit needs, of fixed size whatever N; the S of a union of rows is the sum of theirs."""
    Z = np.concatenate([Y, tau[..., None], np.ones(tau.shape + (1,))], axis=2)     # (N, n, 12)
    return np.einsum("tji,tjk->jik", Z, Z)


def fit_inertia(Y, tau, phi0, phi_cov=None, settings: FitSettings = FitSettings()):
    """pi (10,) from rows Y (N, n, 10), tau (N, n) (the payload's torque, paper sign, each joint with its own
    unknown offset) and the prior phi0 = (m, m r) (4,) with covariance phi_cov (4, 4) (None: settings.prior_std).
    Minimises |W (tau - Y pi - b)|^2 + prior over pi and the offsets b (n,), W the joints' inverse residual std,
    subject to pseudo_inertia(pi) >= 0. Returns (pi, FitInfo)."""
    Y, tau = np.asarray(Y, float), np.asarray(tau, float)
    if Y.ndim != 3 or Y.shape[2] != 10 or tau.shape != Y.shape[:2]:
        raise ValueError(f"Y, tau: expected shapes (N, n, 10) and (N, n), found {Y.shape} and {tau.shape}")
    return fit_normal(normal_rows(Y, tau), phi0, phi_cov, settings)


def fit_normal(S, phi0, phi_cov=None, settings: FitSettings = FitSettings()):
    """fit_inertia from the rows' statistics S (n, 12, 12) (normal_rows): (pi, FitInfo)."""
    steps = fit_steps(S, phi0, phi_cov, settings)
    while True:
        try:
            next(steps)
        except StopIteration as done:
            return done.value


def fit_steps(S, phi0, phi_cov=None, settings: FitSettings = FitSettings()):
    """fit_normal as a generator of steps of O(n 10^2) operations each (no step touches rows): a loop runs one
    per sample with next(); the last raises StopIteration whose value is (pi, FitInfo)."""
    S, phi0 = np.asarray(S, float), np.asarray(phi0, float)
    if S.ndim != 3 or S.shape[1:] != (12, 12):
        raise ValueError(f"S: expected the statistics (n, 12, 12) of normal_rows, found shape {S.shape}")
    if phi0.shape != (4,) or not np.all(np.isfinite(phi0)):
        raise ValueError(f"phi0: expected a finite (m, m rx, m ry, m rz) (4,), found {phi0.tolist()}")
    prior_cov = np.diag(np.square(settings.prior_std)) if phi_cov is None else np.asarray(phi_cov, float)
    mean, Pinv, n, N = np.concatenate([phi0, np.zeros(6)]), np.zeros((10, 10)), len(S), S[0, 11, 11]
    Pinv[:4, :4] = np.linalg.inv(prior_cov + 1e-12 * np.eye(4))
    Pinv[4:, 4:] = np.eye(6) / settings.inertia_std ** 2
    if N < 2:
        cov = np.linalg.inv(Pinv)
        return mean, FitInfo("no data", int(N), np.sqrt(np.diag(cov)), cov, np.full(n, np.nan), mean, 0, np.ones(n))
    mu = S[:, :11, 11] / N if settings.offsets else np.zeros((n, 11))   # (n, 11) the means of (Y_j, tau_j)
    C = S[:, :11, :11] - N * mu[:, :, None] * mu[:, None, :]   # (n, 11, 11) centred: the offsets b partialled out
    w = np.ones(n)
    yield                                                      # (the solves from the next sample on)
    for _ in range(2):                                         # weights from the residual of the pass before
        x, G = _weighted_solve(C, w, Pinv, mean)
        w = 1.0 / np.maximum(np.sqrt(_rss(C, x) / N), settings.min_noise)
        yield
    x, G = _weighted_solve(C, w, Pinv, mean)
    dof = max(N * n - n * settings.offsets - 10, 1)
    s2 = max(np.sum(w ** 2 * _rss(C, x)) / dof, 1e-12)        # whitened residual variance (about 1)
    cov = s2 * np.linalg.inv(G)
    yield
    pi, status, iterations = yield from _physical_steps(x, G, settings)
    return pi, FitInfo(status, int(N), np.sqrt(np.diag(cov)), cov, np.sqrt(_rss(C, pi) / N), x, iterations, w)


def _weighted_solve(C, w, Pinv, mean):
    """x (10,) minimising sum_j w_j^2 |tau_j - Y_j x|^2 (centred) + |x - mean|^2_Pinv, and its normal matrix G."""
    w2 = w ** 2
    G = np.einsum("j,jik->ik", w2, C[:, :10, :10]) + Pinv
    return np.linalg.solve(G, np.einsum("j,ji->i", w2, C[:, :10, 10]) + Pinv @ mean), G


def _rss(C, x):
    """Per-joint residual sum of squares (n,) of the centred rows at pi = x: v^T C_j v, v = (-x, 1)."""
    v = np.append(-x, 1.0)
    return np.maximum(np.einsum("i,jik,k->j", v, C, v), 0.0)


def _physical_steps(x, G, settings):
    """The pi nearest to x in the metric G (10, 10) with pseudo_inertia(pi) >= 0, a convex problem: the log-det
    barrier t |pi - x|^2_G / 2 - log det P(pi) minimised by damped Newton steps for t rising 20-fold until the
    gap 4 / t is below settings.gap of the cost (Boyd and Vandenberghe 2004, Sec. 11.3), from x's clipped
    projection. One Newton step or one trial of its line search per next(); returns (pi, status, iterations)."""
    P = pseudo_inertia(x)
    w, V = np.linalg.eigh(P)
    if w.min() >= -settings.tolerance * max(np.abs(P).max(), 1e-12):
        return x, "ok", 0
    pi = params_of((V * np.maximum(w, 1e-6 * max(np.abs(w).max(), 1e-12))) @ V.T)   # strictly feasible
    yield
    f = lambda p: 0.5 * (p - x) @ G @ (p - x)
    t, steps = 4.0 / max(f(pi), settings.gap), 0
    F, _ = _barrier(pi, t, f)
    yield                                                      # (the Newton steps from the next sample on)
    while steps < settings.max_steps:
        Pinv = np.linalg.inv(pseudo_inertia(pi))
        B = Pinv @ _BASIS                                      # (10, 4, 4): P^-1 B_k
        g = t * G @ (pi - x) - np.trace(B, axis1=1, axis2=2)
        d = -np.linalg.solve(t * G + np.einsum("kij,lji->kl", B, B), g)
        if -g @ d < 1e-6:                                      # Newton decrement^2: centred for this t
            if 4.0 / t < settings.gap * max(f(pi), 1.0):
                yield                                          # (the result's residual on the next sample)
                return pi, "projected", steps
            t *= 20.0
            F, _ = _barrier(pi, t, f)
            yield                                              # (the next t's first Newton step: the next sample)
            continue
        s = 1.0
        for _ in range(50):                                    # backtracking: stay inside, decrease enough
            F_new, ok = _barrier(pi + s * d, t, f)
            if ok and F_new <= F + 0.25 * s * (g @ d):
                break
            s *= 0.5
            yield                                              # (the next trial on the next sample)
        else:
            return pi, "max steps", steps                      # no step inside: pi is physical as it is
        pi, F, steps = pi + s * d, F_new, steps + 1
        yield
    return pi, "max steps", steps


def _barrier(pi, t, f):
    """(t f(pi) - log det P(pi), P(pi) > 0): the barrier objective, inf outside."""
    try:
        L = np.linalg.cholesky(pseudo_inertia(pi))
    except np.linalg.LinAlgError:
        return np.inf, False
    return t * f(pi) - 2.0 * np.sum(np.log(np.diag(L))), True
