"""Dense strictly convex QP min 1/2 x^T H x + g^T x s.t. A x >= b by Goldfarb and Idnani's dual active-set method
on the KKT system (NumPy only, warm-startable): the solver of the CPIC torque QP (Sec. 3, Eq. 8; Appendix B, D).
cpic.py re-exports solve_qp; `python cpic.py` times it on the controller's own problems."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class QPInfo:
    """status: "optimal" | "infeasible" | "max_iterations" | "degenerate" (numerical breakdown);
    iterations: active-set changes (adds + drops); active: indices of the active constraints (k,);
    multipliers: lambda (m,) >= 0, zero off the active set; residual: max KKT violation (abs)."""
    status: str
    iterations: int
    active: np.ndarray
    multipliers: np.ndarray
    residual: float


def solve_qp(H, g, A, b, active=None, max_iterations=None):
    """Strictly convex QP min 1/2 x^T H x + g^T x s.t. A x >= b; H (n, n) SPD, g (n,), A (m, n), b (m,).

    active: indices believed active (warm start, e.g. the previous info.active); inconsistent ones (linearly
    dependent, negative multiplier) are dropped. Returns (x (n,), QPInfo); never raises after validation.
    """
    H, g, A, b = _checked_problem(H, g, A, b)
    n, m = g.shape[0], b.shape[0]
    try:
        L = np.linalg.cholesky(H)                     # H = L L^T; fails unless H is positive definite
    except np.linalg.LinAlgError:
        raise ValueError(f"H: expected positive definite, found eigenvalues {np.linalg.eigvalsh(H)}") from None
    W = _checked_active(active, m)
    if max_iterations is None:
        max_iterations = 5 * (n + m) + 10
    x, status, it, W, mult = dual_active_set(np.linalg.inv(L), g, A, b, W, int(max_iterations))
    return x, QPInfo(status, it, np.array(W, dtype=int), mult, kkt_residual(H, g, A, b, x, mult, W))


def _checked_problem(H, g, A, b):
    """(H, g, A, b) as float arrays of consistent shapes and finite values, H symmetric; else ValueError."""
    H, g, A, b = (np.asarray(v, dtype=float) for v in (H, g, A, b))
    n = g.shape[0] if g.ndim == 1 and g.shape[0] > 0 else 0
    m = b.shape[0] if b.ndim == 1 else -1
    for name, v, shape, what in (("g", g, (n,), "(n,), n >= 1"), ("H", H, (n, n), "(n, n)"),
                                 ("b", b, (m,), "(m,)"), ("A", A, (m, n), "(m, n) = (len(b), len(g))")):
        if v.shape != shape or n == 0:
            raise ValueError(f"{name}: expected shape {what}, found {v.shape}")
    if not _all_finite(np.concatenate((g, H.ravel(), b, A.ravel()))):  # one pass; the culprit only on failure
        for name, v in (("g", g), ("H", H), ("b", b), ("A", A)):
            if not _all_finite(v):
                raise ValueError(f"{name}: expected finite values, found {v[~np.isfinite(v)][0]}")
    asymmetry = _max(H - H.T)                         # = max |H - H^T| (antisymmetric)
    if asymmetry > 1e-10 * max(1.0, _max(H.diagonal())):              # |H_ij| <= max H_ii if H is SPD
        raise ValueError(f"H: expected a symmetric matrix, found max |H - H^T| = {asymmetry:.3g}")
    return H, g, A, b


def _checked_active(active, m):
    """Warm-start indices as a list of ints in [0, m); else ValueError."""
    if active is None:
        return []
    W = np.asarray(active).reshape(-1)
    if W.size and (W.dtype.kind not in "iu" or not all(0 <= i < m for i in W.tolist())):
        raise ValueError(f"active: expected integer indices in [0, {m}), found {W}")
    return W.tolist()


def kkt_residual(H, g, A, b, x, mult, active):
    """Largest absolute KKT violation at (x (n,), lambda = mult (m,), zero off the list `active`): stationarity
    |H x + g - A^T lambda|, primal max(0, b - A x), complementarity |lambda_i (A x - b)_i|; inf on overflow."""
    with np.errstate(over="ignore", invalid="ignore"):
        r = H @ x + g
        if len(active):
            r -= mult @ A
        worst = _max(np.abs(r))
        if len(b):
            s = A @ x - b                             # (m,) slacks
            worst = max(worst, -_min(s), _max(np.abs(mult * s)) if len(active) else 0.0)
        return float(max(worst, 0.0))


def dual_active_set(B, g, A, b, active, max_iterations, tol=1e-11):
    """Goldfarb and Idnani's dual method (Math. Prog. 27, 1983); unchecked inputs, for the loop. B (n, n) is any
    factor with B^T B = H^-1 (B = L^-1 for H = L L^T), so that H itself is never needed.

    In x = B^T y the QP is min 1/2 |y + c|^2 s.t. N y >= d (c = B g, rows of N = A B^T scaled to unit
    length), so every KKT solve is a k x k normal-equation solve with k <= n active constraints. Starting from
    any dual-feasible active set (the warm start after dropping negative multipliers), each iteration adds
    the most violated constraint, taking partial steps that drop active ones whose multiplier reaches zero.
    active: list of ints. Returns x (n,), status, iterations (adds + drops), active indices (list), multipliers (m,).
    """
    n, m = B.shape[0], b.shape[0]
    c = B @ g                                         # (n,)
    if not len(active):                               # fast path: the unconstrained minimiser -H^-1 g is feasible
        x = -(c @ B)
        if not m:
            return x, "optimal", 0, [], np.zeros(m)
        worst = _min(A @ x - b)                       # the scaled tolerance only when it matters
        if worst >= 0.0 or worst >= -tol * (1.0 + _max(np.abs(b)) + _max(np.abs(A)) * _max(np.abs(x))):
            return x, "optimal", 0, [], np.zeros(m)
    N, d, norms, usable = _unit_rows(A @ B.T, b)      # usable is None when no row of N is zero
    if usable is not None and (b[~usable] > 0.0).any():             # a zero row reads 0 >= b_i
        return -(c @ B), "infeasible", 0, [], np.zeros(m)
    tol = tol * (1.0 + _max(np.abs(c)) + _max(np.abs(d)))
    W, it, status = [], 0, "optimal"
    if len(active):                                   # distinct, usable, independent indices
        W = list(dict.fromkeys(active)) if usable is None else [i for i in dict.fromkeys(active) if usable[i]]
        W, it = _independent(N, W, n)
    try:
        W, lam, y, drops = _dual_feasible_start(N, d, c, W)
        it += drops
        while True:
            s = N @ y - d
            s[W] = np.inf
            p = int(s.argmin())
            if s[p] >= -tol:
                break
            status, W, lam, y, steps = _add_constraint(N, d, y, W, lam, p, max_iterations - it)
            it += steps
            if status != "optimal":
                break
        if status == "optimal" and it and W:           # polish: the exact minimiser on the final active set
            lam_p, y_p = _eqp(N, d, c, W)
            if _min(lam_p) >= -tol and _min(N @ y_p - d) >= -tol:
                lam, y = lam_p, y_p
    except np.linalg.LinAlgError:
        status, y, W, lam = "degenerate", -c, [], np.zeros(0)
    if not (_all_finite(y) and _all_finite(lam)):
        status, y, W, lam = "degenerate", -c, [], np.zeros(0)
    mult = np.zeros(m)
    if W:
        mult[W] = np.maximum(lam, 0.0) / norms[W]     # back to the unscaled rows of A
    return y @ B, status, it, W, mult


def _unit_rows(N, b):
    """N y >= b with the rows of N (m, n) scaled to unit length, in place: (N, d (m,), norms (m,), usable), usable
    = None when every row is usable, else a (m,) mask; zero rows (|N_i| ~ 0) become 0 >= -1 (never active)."""
    norms = np.sqrt((N * N) @ np.ones(N.shape[1]))
    floor = 1e-12 * (1.0 + _max(norms))
    if _min(norms) > floor:                           # the usual case: no zero row
        N /= norms[:, None]
        return N, b / norms, norms, None
    usable = norms > floor
    norms = np.where(usable, norms, 1.0)
    N /= norms[:, None]
    return N, np.where(usable, b / norms, -1.0), norms, usable


def _independent(N, W, n):
    """Greedy Gram-Schmidt: keep the indices whose rows are independent of the ones kept before (k <= n)."""
    if len(W) <= 1:
        return W, 0                                   # rows are unit length
    basis, keep = [], []
    for i in W:
        v = N[i] - (np.array(basis).T @ (np.array(basis) @ N[i]) if basis else 0.0)
        nv = np.sqrt(v @ v)
        if nv > 1e-8 and len(keep) < n:
            basis.append(v / nv)
            keep.append(i)
    return keep, len(W) - len(keep)


def _eqp(N, d, c, W):
    """Minimiser of 1/2 |y + c|^2 on N_W y = d_W: y = -c + N_W^T lam, (N_W N_W^T) lam = d_W + N_W c."""
    if len(W) == 1:                                   # unit row: N_W N_W^T = 1
        nw = N[W[0]]
        lam = d[W[0]] + nw @ c
        return np.array([lam]), lam * nw - c
    NW = N[W]
    lam = np.linalg.solve(NW @ NW.T, d[W] + NW @ c)
    return lam, NW.T @ lam - c


def _dual_feasible_start(N, d, c, W):
    """Drop the most negative multiplier until the warm-start set is dual feasible (lambda >= 0)."""
    drops = 0
    while W:
        lam, y = _eqp(N, d, c, W)
        j = int(lam.argmin())
        if lam[j] >= 0.0:
            return W, lam, y, drops
        W, drops = W[:j] + W[j + 1:], drops + 1
    return [], np.zeros(0), -c, drops


def _add_constraint(N, d, y, W, lam, p, budget):
    """Add violated constraint p (Goldfarb-Idnani step 2): primal step along z, dual step -r, partial steps
    drop the blocking active constraint. Returns (status, W, lam, y, iterations)."""
    n_p, lam_p, steps = N[p], 0.0, 0
    while steps < budget:
        if W:
            NW = N[W]                                 # (k, n)
            r = np.linalg.solve(NW @ NW.T, NW @ n_p)   # n_p = N_W^T r + z, z _|_ rows of N_W
            z = n_p - NW.T @ r
        else:
            r, z = np.zeros(0), n_p
        zz = z @ z
        t2 = (d[p] - n_p @ y) / zz if zz > 1e-14 else np.inf      # full step: constraint p becomes active
        pos = r > 1e-12
        t1, j = np.inf, -1
        if pos.any():
            ratios = np.where(pos, lam / np.where(pos, r, 1.0), np.inf)
            j = int(ratios.argmin())
            t1 = ratios[j]                            # partial step: multiplier j reaches zero first
        if t1 == np.inf and t2 == np.inf:
            return "infeasible", W, lam, y, steps
        t = min(t1, t2)
        if zz > 1e-14:
            y = y + t * z
        lam, lam_p, steps = lam - t * r, lam_p + t, steps + 1
        if t2 <= t1:
            return "optimal", W + [p], np.append(lam, lam_p), y, steps
        W, lam = W[:j] + W[j + 1:], np.delete(lam, j)
    return "max_iterations", W, lam, y, steps


# ndarray.max / .min / .all cost about 1 us each on these tiny arrays, nearly all of it call overhead; at 17 per
# call they were the largest library item in the profile of solve_qp. argmax / argmin cost a quarter of that and
# give the same values, a NaN included (both pick it); _max and _min need a non-empty v.
def _max(v):
    return v.ravel()[v.argmax()]


def _min(v):
    return v.ravel()[v.argmin()]


def _all_finite(v):
    ok = np.isfinite(v).ravel()
    return not ok.size or bool(ok[ok.argmin()])       # argmin finds a False if there is one
