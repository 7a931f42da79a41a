"""Dense strictly convex QP min 1/2 x^T H x + g^T x s.t. A x >= b by Goldfarb and Idnani's dual active-set method
(Math. Prog. 27, 1983), NumPy and scipy's BLAS/LAPACK only, warm-startable: the solver of the CPIC torque QP (Sec. 3,
Eq. 8; Appendix B, D). cpic.py re-exports solve_qp; experiments/qp_bench.py times it against quadprog."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import blas, lapack


@dataclass(frozen=True)
class QPInfo:
    """status: "optimal" | "infeasible" | "max_iterations" | "degenerate" (numerical breakdown: overflow, NaN, or
    an answer that fails the final feasibility check); iterations: active-set changes (adds + drops); active:
    indices of the active constraints (k,); multipliers: lambda (m,) >= 0, zero off the active set; residual: max
    KKT violation (abs)."""
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
    L, bad = lapack.dpotrf(H, lower=1)                # H = L L^T; bad > 0 unless H is positive definite
    if bad:
        raise ValueError(f"H: expected positive definite, found eigenvalues {np.linalg.eigvalsh(H)}")
    W = _checked_active(active, m)
    x = -lapack.dpotrs(L, g, lower=1)[0]              # the unconstrained minimiser -H^-1 g
    r = A @ x - b
    if W or m and not r[r.argmin()] >= 0.0:           # else it is the answer: H^-1 is not needed
        if max_iterations is None:
            max_iterations = 5 * (n + m) + 10
        Li = lapack.dtrtri(L, lower=1)[0]             # L^-1; H^-1 = L^-T L^-1
        x, status, it, W, mult, r = _dual(Li.T @ Li, g, A, b, W, int(max_iterations), 1e-11, x, r)
    else:
        status, it, mult = "optimal" if _all_finite(x) else "degenerate", 0, np.zeros(m)
    return x, QPInfo(status, it, np.array(W, dtype=int), mult, _residual(H, g, A, x, mult, W, r))


def _checked_problem(H, g, A, b):
    """(H, g, A, b) as float arrays of consistent shapes and finite values, H symmetric; else ValueError."""
    H, g, A, b = (np.asarray(H, dtype=float), np.asarray(g, dtype=float), np.asarray(A, dtype=float),
                  np.asarray(b, dtype=float))
    n = g.shape[0] if g.ndim == 1 else 0
    if n == 0 or H.shape != (n, n) or b.ndim != 1 or A.shape != (b.shape[0], n):
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
        return _residual(H, g, A, x, mult, list(active), A @ x - b)


def _residual(H, g, A, x, mult, W, r):
    """kkt_residual with the slacks r = A x - b (m,) already known."""
    st = H @ x + g
    if W:
        st -= mult @ A
    worst = max(st[st.argmax()], -st[st.argmin()], 0.0)
    if len(r):
        worst = max(worst, -r[r.argmin()], max((abs(mult[i] * r[i]) for i in W), default=0.0))
    worst = float(worst)
    return worst if worst == worst else np.inf        # NaN (from inf - inf) reads as inf


def dual_active_set(B, g, A, b, active, max_iterations, tol=1e-11):
    """Goldfarb and Idnani's dual method on unchecked inputs, for the 1 kHz loop: B (n, n) is any factor with
    B^T B = H^-1 (e.g. B = L^-1 for H = L L^T, or the transposed Cholesky factor of H^-1), g (n,), A (m, n), b (m,),
    active: list of ints (warm start). Returns x (n,), status, iterations (adds + drops), active indices (list),
    multipliers (m,); status "degenerate" when the numbers break down (never an exception)."""
    return _dual(B.T @ B, g, A, b, active, max_iterations, tol)[:5]


def dual_active_set_from_inverse(Hinv, g, A, b, active, max_iterations, tol=1e-11):
    """dual_active_set given H^-1 (n, n) itself, symmetric positive definite (unchecked): for a loop that has H^-1
    in closed form (cpic.CPIC) and need not factor it."""
    return _dual(Hinv, g, A, b, active, max_iterations, tol)[:5]


def _dual(Hinv, g, A, b, active, max_iterations, tol, x=None, s=None):
    """Goldfarb and Idnani's dual method from H^-1 (n, n): (x, status, iterations, W, multipliers (m,), A x - b).

    Rows are scaled to unit length in the metric of H^-1, so that slacks and multipliers mean the same for every
    row. GI's operators for the active rows N (q, n), Hop = H^-1 - H^-1 N^T (N H^-1 N^T)^-1 N H^-1 (primal step
    z = Hop a) and N* = (N H^-1 N^T)^-1 N H^-1 (dual step r = N* a) (GI 1983, Sec. 3), are kept as their products
    with every row, next to the iterate: Y = [Hop A^T, x; A Hop A^T, A x - b; -N* A^T, lambda] ((2n + m, m + 1);
    column p holds (z, A z, -r) of row p). Adding row p is one rank-one update of Y that also takes GI's full step
    (x, slacks and lambda move by t (z, A z, -r)); a drop is one rank-one downdate after a q x q solve. The
    all-row products cost m (n + m) per change but no further solve, and every step is a handful of BLAS calls.
    A warm start is first tried as the answer itself (one q x q solve); answers reached through nearly dependent
    rows or a warm start's drops are polished by the exact solve on the final active set; an "optimal" answer must
    pass a feasibility check on slacks recomputed from x (_feasible). x (n,), s (m,): the unconstrained minimiser
    and its slacks, when known.
    """
    n, m = g.shape[0], b.shape[0]
    if x is None:
        x = -(Hinv @ g)                               # the unconstrained minimiser
        s = A @ x - b                                 # (m,) slacks
    gx = float(g @ x)                                 # -|x|_H^2: finite iff x is (but for overflow)
    if not active and (not m or s[s.argmin()] >= 0.0) and abs(gx) < np.inf:
        return x, "optimal", 0, [], np.zeros(m), s    # the unconstrained minimiser is feasible
    if active and len(active) <= n:                   # the warm start is often the answer (1 kHz loop)
        out = _warm_answer(Hinv, A, b, x, s, list(dict.fromkeys(active)))
        if out is not None:
            return out
    try:
        xs, status, it, W, lam, inv_norm = _solve(Hinv, A, b, x, s, gx, active, max_iterations, tol)
    except np.linalg.LinAlgError:                     # a singular Gram matrix of active rows
        xs, status, it, W, lam, inv_norm = x, "degenerate", 0, [], np.zeros(0), None
    mult = np.zeros(m)
    lam = lam.tolist()
    for i, lam_i in zip(W, lam):
        mult[i] = lam_i * inv_norm[i] if lam_i > 0.0 else 0.0     # back to the unscaled rows of A
    r = A @ xs - b
    if status == "optimal" and not (_feasible(A, b, xs, r) and math.isfinite(math.fsum(lam))):
        status = "degenerate"
    return xs, status, it, W, mult, r


def _warm_answer(Hinv, A, b, x, s, W):
    """The minimiser on the rows W (lambda = (A_W H^-1 A_W^T)^-1 (b_W - A_W x), x + H^-1 A_W^T lambda) if it is the
    QP's answer (lambda >= 0, the other rows satisfied exactly, A_W x = b_W to rounding), else None."""
    AW = A[W]
    AHW = AW @ Hinv                                   # (q, n)
    K, lam = AHW @ AW.T, -s[W]
    _, lam, bad = lapack.dposv(K, lam)
    if bad or not lam[lam.argmin()] >= 0.0:
        return None
    xs = x + lam @ AHW
    r = A @ xs - b
    rest = r.copy()
    rest[W] = np.inf
    if not (rest[rest.argmin()] >= 0.0 and _feasible(A, b, xs, r)):
        return None
    mult = np.zeros(len(b))
    mult[W] = lam
    return xs, "optimal", 0, W, mult, r


def _solve(Hinv, A, b, x, s, gx, active, max_iterations, tol):
    """Set-up, warm start, loop and polish of _dual: (x, status, iterations, W, lambda (k,) of the scaled rows,
    1 / row norms (m,))."""
    n, m = x.shape[0], s.shape[0]
    nm = n + m
    if not m or abs(gx) == np.inf:
        return x, ("optimal" if m and abs(gx) < np.inf else "degenerate"), 0, [], np.zeros(0), None
    AH = A @ Hinv                                     # (m, n) = A H^-1
    norms2 = np.einsum("ij,ij->i", AH, A)             # |a_i|^2 in the metric of H^-1
    lo, hi = norms2[norms2.argmin()], norms2[norms2.argmax()]
    if not hi < np.inf:                               # overflow or NaN
        return x, "degenerate", 0, [], np.zeros(0), None
    if lo > 1e-24 * (1.0 + hi):
        inv_norm = norms2 ** -0.5
    else:                                             # a zero row reads 0 >= b_i
        usable = norms2 > 1e-24 * (1.0 + hi)
        if (b[~usable] > 0.0).any():
            return x, "infeasible", 0, [], np.zeros(0), None
        inv_norm = np.where(usable, np.where(usable, norms2, 1.0) ** -0.5, 0.0)     # 0 >= 0: inert
    AH *= inv_norm[:, None]                           # the rows of A scaled to |a_i|_{H^-1} = 1: A H^-1
    XK = np.concatenate((AH, AH @ (A.T * inv_norm)), axis=1)   # (A H^-1, A H^-1 A^T) (m, n + m), kept for drops
    Y = np.zeros((2 * n + m, m + 1), order="F")      # column-major: a row's column is contiguous, and BLAS's
    #                                                   dger updates Y in place (f2py copies only other layouts)
    Y.T[:m, :nm] = XK
    Y[:n, m] = x
    np.multiply(s, inv_norm, out=Y[n:nm, m])
    # tolerance on a scaled slack: its rounding scale |x|_H + |b_i| / |a_i|_{H^-1}
    tols = (tol * (1.0 + math.sqrt(abs(gx))), tol, b, inv_norm)
    W = []
    skipped, az_warm = _warm_start(Y, XK, W, active, n, m) if active else (0, 1.0)
    status, steps, az_loop = _loop(Y, XK, W, n, m, max_iterations - skipped, tols)
    q = len(W)
    xs, lam = Y[:n, m].copy(), Y[nm:nm + q, m].copy()
    if status == "optimal" and q and (skipped or min(az_warm, az_loop) < 1e-3):   # polish: rounding grows
        # as 1 / a^T Hop a, and with the jumps of a warm start's drops
        XW = XK[W]                                    # (q, n + m)
        lam_p = _spd_solve(XW[:, [n + i for i in W]], -(s[W] * inv_norm[W]))  # the exact minimiser on W
        if lam_p[lam_p.argmin()] >= -1e-9 * (1.0 + np.abs(lam_p).max()):
            xs, lam = x + lam_p @ XW[:, :n], lam_p
    return xs, status, skipped + steps, W, lam, inv_norm


def _feasible(A, b, x, r, tol=1e-9):
    """A x >= b (r = A x - b) within tol times each row's rounding scale 1 + |b_i| + |a_i| |x|; False on NaN or
    overflow. The final check that turns a broken answer into status "degenerate"."""
    if not len(r) or r[r.argmin()] >= -tol:           # enough: every row's tolerance is at least tol
        return True
    r = r + tol * (1.0 + np.abs(b) + np.abs(A) @ np.abs(x))
    return bool(r[r.argmin()] >= 0.0)


def _warm_start(Y, XK, W, active, n, m):
    """Make the distinct, independent rows of `active` active by full steps (the equality-constrained minimiser),
    then drop the most negative multiplier until all are >= 0 (a dual-feasible start). Returns (the changes that
    were not adds: skipped and dropped rows, the smallest a^T Hop a of an add)."""
    nm, skipped, az_min = n + m, 0, 1.0
    for p in dict.fromkeys(active):
        az = Y[n + p, p]
        if len(W) == n or not az > 1e-12:            # dependent on the rows already active, or a zero row
            skipped += 1
            continue
        _add(Y, W, p, az, n, m)
        az_min = min(az_min, az)
    while W:
        q = len(W)
        lam = Y[nm:nm + q, m].tolist()
        j = min(range(q), key=lam.__getitem__)
        if lam[j] >= 0.0:
            break
        p = W[j]
        _drop(Y, XK, W, j, n, m)                      # x' = x - lambda_j Hop' a_j, lambda' = lambda + lambda_j r'
        Y[:, m] = blas.daxpy(Y[:, p], Y[:, m], a=-lam[j])     # in place (a contiguous column); the copy is a no-op
        skipped += 1
    return skipped, az_min


def _loop(Y, XK, W, n, m, budget, tols):
    """GI's main loop: add the most violated row p; partial steps drop the active row whose multiplier reaches 0.
    tols = (tol (1 + |x|_H), tol, b, 1 / row norms): row i counts as violated below -tols[0] - tol |b_i| / |a_i|.
    Returns (status, iterations, the smallest a^T Hop a of an add)."""
    nm, it, az_min, inf = n + m, 0, 1.0, math.inf
    tol0, tol, b, inv_norm = tols
    s = Y[n:nm, m]                                    # scaled slacks (view)
    while True:
        p = int(s.argmin())
        sp = float(s[p])
        if not (sp < -tol0 and sp < -tol0 - tol * abs(float(b[p]) * float(inv_norm[p]))):
            return "optimal", it, az_min              # every row satisfied within its tolerance
        lam_p = 0.0
        while True:
            if it >= budget:
                return "max_iterations", it, az_min
            q = len(W)
            az = float(Y[n + p, p])                   # a_p^T Hop a_p, in [0, 1]
            t2 = -float(s[p]) / az if az > 1e-12 and q < n else inf     # full step: row p becomes active
            t1, j = inf, -1
            if q:
                c3, lam = Y[nm:nm + q, p].tolist(), Y[nm:nm + q, m].tolist()     # -r, lambda
                for i in range(q):                    # partial step: lambda_i = 0 first, at t = lambda_i / r_i
                    if c3[i] < -1e-12 and -lam[i] / c3[i] < t1:
                        t1, j = -lam[i] / c3[i], i
            if t2 <= t1 and t2 < inf:
                it += 1
                az_min = min(az_min, az)
                _add(Y, W, p, az, n, m)
                if lam_p:
                    Y[nm + q, m] += lam_p             # the multiplier gained in the partial steps before
                break
            if j < 0:                                 # no step is bounded: the dual is unbounded (or NaN)
                return ("infeasible" if t2 == inf else "degenerate"), it, az_min
            it += 1
            Y[:, m] = blas.daxpy(Y[:, p], Y[:, m], a=t1)   # x, slacks, lambda move by t1 (z, A z, -r)
            lam_p += t1
            _drop(Y, XK, W, j, n, m)


def _add(Y, W, p, az, n, m):
    """Row p joins the active set with GI's full step: Hop' = Hop - z z^T / a^T z, N*' = [N* - r z^T / a^T z;
    z^T / a^T z], applied to every column of Y; on the iterate column it moves (x, slacks, lambda) by t (z, A z, -r)
    with t = -s_p / a^T z, and the new multiplier is t."""
    w = Y[n + p] * (-1.0 / az)                        # -((A z)^T, s_p) / a^T z  (m + 1,)
    blas.dger(1.0, Y[:, p].copy(), w, a=Y, overwrite_a=1)   # Y += (z, A z, -r) w^T, in place
    Y[n + m + len(W)] = w
    W.append(p)


def _drop(Y, XK, W, j, n, m):
    """Active row j leaves (GI 1983, in the metric of H): with c = (N H^-1 N^T)^-1 e_j (q,) and k = N*_j^T =
    H^-1 N^T c, k^T H k = c_j and N* H k = c, so Hop' = Hop + k k^T / c_j and N*_i' = N*_i - (c_i / c_j) k^T.
    XK (m, n + m): (A H^-1, A H^-1 A^T) of the scaled rows. The iterate column is left alone."""
    nm, q = n + m, len(W)
    XW = XK[W]                                        # (q, n + m)
    e = np.zeros(q)
    e[j] = 1.0
    c = _spd_solve(XW[:, [n + i for i in W]], e)
    v, w = np.zeros(2 * n + m), np.zeros(m + 1)
    np.matmul(c, XW, out=v[:nm])                      # (k, A k)
    v[nm:nm + q] = c
    np.multiply(v[n:nm], 1.0 / c[j], out=w[:m])
    blas.dger(1.0, v, w, a=Y, overwrite_a=1)          # Y[:, :m] += (k, A k, N* H k) (A k)^T / c_j, in place
    Y[nm + j:nm + q - 1] = Y[nm + j + 1:nm + q]
    Y[nm + q - 1] = 0.0
    del W[j]


def _spd_solve(K, rhs):
    """K^-1 rhs for a symmetric positive definite K (q, q) (LAPACK dposv); LinAlgError if K is not."""
    x, bad = lapack.dposv(K, rhs)[1:]
    if bad:
        raise np.linalg.LinAlgError("the Gram matrix of the active rows is singular")
    return x


# ndarray.max / .min / .all cost about 1 us each on these tiny arrays, nearly all of it call overhead; argmax /
# argmin cost a quarter of that and give the same values, a NaN included (both pick it); _max needs a non-empty v.
def _max(v):
    return v.ravel()[v.argmax()]


def _all_finite(v):
    ok = np.isfinite(v).ravel()
    return not ok.size or bool(ok[ok.argmin()])       # argmin finds a False if there is one
