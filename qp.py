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
    L, bad = lapack.dpotrf(H, 1)                      # H = L L^T (lower); bad > 0 unless H is positive definite
    if bad:
        raise ValueError(f"H: expected positive definite, found eigenvalues {np.linalg.eigvalsh(H)}")
    W = [] if active is None else _checked_active(active, m)
    if max_iterations is None:
        max_iterations = 5 * (n + m) + 10
    # y = L^T x turns H into I: min 1/2 |y|^2 + u^T y s.t. V y >= b with V^T = L^-1 A^T (n, m), u = L^-1 g (n,)
    VT = blas.dtrsm(1.0, L, A.T, 0, 1) if m else A.T
    y, status, it, W, mult = _unit(VT, blas.dtrsv(L, g, 1, 0, 1), b, W, int(max_iterations), 1e-11)
    x = blas.dtrsv(L, y, 1, 0, 1, 1)                  # x = L^-T y
    status, r, r_min = _checked_answer(A, b, x, status)
    return x, QPInfo(status, it, np.array(W, dtype=int), mult, _residual(H, g, A, x, mult, W, r, r_min))


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
    # a cheap screen (BLAS dot products cost a tenth of a NumPy call): a sum of squares is inf or NaN where an
    # entry is not finite (or it overflows); only a screen that fails pays for the checks that name the culprit
    h, ddot = H.ravel(), blas.ddot
    squares = ddot(g, g) + ddot(h, h) + (ddot(b, b) + ddot(A.ravel(), A.ravel()) if len(b) else 0.0)
    if squares < math.inf:
        d = H - H.T                                   # antisymmetric: its max is max |H - H^T|
        if d.item(d.argmax()) <= 1e-10:
            return H, g, A, b
    for name, v in (("g", g), ("H", H), ("b", b), ("A", A)):
        if not _all_finite(v):
            raise ValueError(f"{name}: expected finite values, found {v[~np.isfinite(v)][0]}")
    asymmetry = _max(H - H.T)
    if asymmetry > 1e-10 * max(1.0, _max(H.diagonal())):              # |H_ij| <= max H_ii if H is SPD
        raise ValueError(f"H: expected a symmetric matrix, found max |H - H^T| = {asymmetry:.3g}")
    return H, g, A, b


def _checked_active(active, m):
    """Warm-start indices as a list of ints in [0, m); else ValueError."""
    W = np.asarray(active).reshape(-1)
    if W.size and (W.dtype.kind not in "iu" or not all(0 <= i < m for i in W.tolist())):
        raise ValueError(f"active: expected integer indices in [0, {m}), found {W}")
    return W.tolist()


def kkt_residual(H, g, A, b, x, mult, active):
    """Largest absolute KKT violation at (x (n,), lambda = mult (m,), zero off the list `active`): stationarity
    |H x + g - A^T lambda|, primal max(0, b - A x), complementarity |lambda_i (A x - b)_i|; inf on overflow."""
    with np.errstate(over="ignore", invalid="ignore"):
        r = A @ x - b
        return _residual(H, g, A, x, mult, list(active), r, r[r.argmin()] if len(r) else 0.0)


def _residual(H, g, A, x, mult, W, r, r_min):
    """kkt_residual with the slacks r = A x - b (m,) and their minimum r_min already known."""
    st = blas.dgemv(1.0, H.T, x, 1.0, g, 0, 1, 0, 1, 1, 0)          # H x + g (H.T: H's memory, column-major)
    if W:
        blas.dgemv(-1.0, A.T, mult, 1.0, st, 0, 1, 0, 1, 0, 1)      # - A^T lambda, in place
    lam, r_list = mult.tolist(), r.tolist()
    worst = max(abs(st.item(blas.idamax(st))), -float(r_min), 0.0,
                max((abs(lam[i] * r_list[i]) for i in W), default=0.0))
    return worst if worst == worst and blas.dasum(st) < math.inf else np.inf    # NaN reads as inf


def _checked_answer(A, b, x, status):
    """(status, r = A x - b (m,), min r): an "optimal" answer that fails _feasible becomes "degenerate"."""
    if not len(b):
        return status, b[:], 0.0
    r = blas.dgemv(1.0, A.T, x, -1.0, b, 0, 1, 0, 1, 1, 0)           # A x - b
    r_min = r[r.argmin()]
    if status == "optimal" and not _feasible(A, b, x, r, r_min):
        status = "degenerate"
    return status, r, r_min


def _feasible(A, b, x, r, r_min, tol=1e-9):
    """A x >= b (r = A x - b, r_min its minimum) within tol times each row's rounding scale 1 + |b_i| + |a_i| |x|;
    False on NaN or overflow. The final check that turns a broken answer into status "degenerate"."""
    if r_min >= -tol:                                 # enough: every row's tolerance is at least tol
        return True
    r = r + tol * (1.0 + np.abs(b) + np.abs(A) @ np.abs(x))
    return bool(r[r.argmin()] >= 0.0)


def dual_active_set(B, g, A, b, active, max_iterations, tol=1e-11):
    """Goldfarb and Idnani's dual method on unchecked inputs, for the 1 kHz loop: B (n, n) is any factor with
    B^T B = H^-1 (e.g. B = L^-1 for H = L L^T, or the transposed Cholesky factor of H^-1), g (n,), A (m, n), b (m,),
    active: list of ints (warm start). Returns x (n,), status, iterations (adds + drops), active indices (list),
    multipliers (m,); status "degenerate" when the numbers break down (never an exception)."""
    y, status, it, W, mult = _unit(B @ A.T, B @ g, b, active, max_iterations, tol)    # x = B^T y: H -> I
    x = y @ B
    return x, _checked_answer(A, b, x, status)[0], it, W, mult


def dual_active_set_from_inverse(Hinv, g, A, b, active, max_iterations, tol=1e-11):
    """dual_active_set given H^-1 (n, n) itself, symmetric positive definite (unchecked): for a loop that has H^-1
    in closed form (cpic.CPIC) and need not factor it unless the warm start fails."""
    n, m = g.shape[0], b.shape[0]
    x = -(Hinv @ g)                                   # the unconstrained minimiser
    s = A @ x - b                                     # (m,) its slacks
    if not active and (not m or s[s.argmin()] >= 0.0) and abs(float(g @ x)) < np.inf:
        return x, "optimal", 0, [], np.zeros(m)
    if active and len(active) <= n:                   # the warm start is often the answer (1 kHz loop)
        W = list(dict.fromkeys(active))
        AW = A.take(W, axis=0)
        out = _warm_answer(A, b, AW, AW @ Hinv, x, s, W)
        if out is not None and _checked_answer(A, b, out[0], "optimal")[0] == "optimal":
            return out[0], "optimal", 0, W, out[1]
    C, bad = lapack.dpotrf(Hinv, 1)                   # H^-1 = C C^T: B = C^T
    if bad:
        return x, "degenerate", 0, [], np.zeros(m)
    y, status, it, W, mult = _unit(C.T @ A.T, g @ C, b, active, max_iterations, tol, warm=False)
    x = C @ y
    return x, _checked_answer(A, b, x, status)[0], it, W, mult


def _warm_answer(A, b, AW, AHW, x, s, W):
    """The minimiser on the rows W, (x + lambda AHW, multipliers (m,)) with lambda = (AHW AW^T)^-1 (-s_W), if it is
    the QP's answer (lambda >= 0, the other rows satisfied exactly), else None. AW = A_W (q, n), AHW = A_W H^-1."""
    _, lam, bad = lapack.dposv(AHW @ AW.T, -s.take(W))
    if bad or not lam[lam.argmin()] >= 0.0:
        return None
    xs = x + lam @ AHW
    r = A @ xs - b
    r[W] = np.inf
    if not r[r.argmin()] >= 0.0:
        return None
    mult = np.zeros(len(b))
    mult[W] = lam
    return xs, mult


def _unit(VT, u, b, active, max_iterations, tol, warm=True):
    """GI's dual method for min 1/2 |y|^2 + u^T y s.t. V y >= b (H = I; V^T (n, m), u (n,), b (m,)): (y (n,),
    status, iterations, W, multipliers (m,)). Tries a warm start as the answer itself first (warm=True).
    u is overwritten (it becomes y)."""
    n, m = u.shape[0], b.shape[0]
    uu = blas.ddot(u, u)                              # |x|_H^2: finite iff u is (but for overflow)
    y = blas.dscal(-1.0, u)                           # the unconstrained minimiser, in place
    if not m or not uu < math.inf:
        return y, ("optimal" if uu < math.inf else "degenerate"), 0, [], np.zeros(m)
    s = blas.dgemv(1.0, VT, y, -1.0, b, 0, 1, 0, 1, 1, 0)    # (m,) slacks V y - b
    if not active and s[s.argmin()] >= 0.0:
        return y, "optimal", 0, [], np.zeros(m)
    if warm and active and len(active) <= n:          # the warm start is often the answer
        W = list(dict.fromkeys(active))
        VW = VT.T.take(W, axis=0)
        out = _warm_answer(VT.T, b, VW, VW, y, s, W)
        if out is not None:
            return out[0], "optimal", 0, W, out[1]
    norms2 = np.einsum("ij,ij->j", VT, VT)            # |a_i|_{H^-1}^2 = |v_i|^2
    total = blas.dasum(norms2)                        # inf or NaN on overflow or NaN
    if not total < math.inf:
        return y, "degenerate", 0, [], np.zeros(m)
    if norms2.item(norms2.argmin()) > 1e-24 * (1.0 + total):
        inv_norm = norms2 ** -0.5
    else:                                             # a zero row reads 0 >= b_i
        usable = norms2 > 1e-24 * (1.0 + total)
        if (b[~usable] > 0.0).any():
            return y, "infeasible", 0, [], np.zeros(m)
        inv_norm = np.where(usable, np.where(usable, norms2, 1.0) ** -0.5, 0.0)     # 0 >= 0: inert
    # rows scaled to |v_i| = 1, so that slacks and multipliers mean the same for every row; row i counts as
    # violated when its scaled slack is below -tol (1 + |x|_H) - tol |b_i| / |v_i| (its rounding scale)
    tols = (tol * (1.0 + math.sqrt(uu)), tol, (b * inv_norm).tolist())
    ys, status, it, W, lam = _solve(VT * inv_norm, y, s * inv_norm, active, max_iterations, tols)
    mult, inv_norm = np.zeros(m), inv_norm.tolist()
    for i, lam_i in zip(W, lam):
        if lam_i > 0.0:
            mult[i] = lam_i * inv_norm[i]             # back to the unscaled rows
    if status == "optimal" and not math.isfinite(math.fsum(lam)):
        status = "degenerate"
    return ys, status, it, W, mult


def _solve(VT, y, s, active, max_iterations, tols):
    """Set-up, warm start, loop and polish of GI on unit rows V (m, n) from y (n,) with slacks s (m,): (y, status,
    iterations, W, lambda (list)).

    GI's operators for the active rows N (q, n) (GI 1983, Sec. 3; here H = I), Hop = I - N^T (N N^T)^-1 N (primal
    step z = Hop a) and N* = (N N^T)^-1 N (dual step r = N* a), are kept as their products with every row and
    every unit vector, next to the iterate: Y = [Hop V^T, Hop, y; V Hop V^T, V Hop, V y - b; -N* V^T, -N*, lambda]
    ((2n + m, m + n + 1); column p holds (z, V z, -r) of row p). An add is one rank-one update of Y that also
    takes GI's full step; a drop is one rank-one downdate read off the dropped row of -N* (N* N*^T =
    (N N^T)^-1), so no step solves a system. Every step is a few BLAS calls on Y's memory (level 1 with offsets
    and strides where it suffices: they cost a tenth of a NumPy call). Answers reached through nearly dependent
    rows or a warm start's drops are polished by the exact solve on the final active set.
    """
    n, m = y.shape[0], s.shape[0]
    nm, R, C = n + m, 2 * n + m, n + m + 1
    Y = np.zeros((R, C), order="F")                  # column-major: BLAS updates it in place
    Yf = Y.T.ravel()                                  # flat view: Y[i, j] = Yf[i + j R]
    Y[:n, :m] = VT
    Yf[m * R:nm * R:R + 1] = 1.0                      # Hop = I on the unit vectors
    Yf[nm * R:nm * R + n] = y                         # the iterate column: y, V y - b, lambda
    Y[n:nm] = blas.dgemm(1.0, VT, Y[:n], 0.0, None, 1)      # V times the top rows: V V^T, V, V y
    Yf[nm * R + n:nm * R + nm] = s
    W = []
    skipped, az_warm, ok = _warm_start(Y, W, active, n, m) if active else (0, 1.0, True)
    status, steps, az_loop = _loop(Y, W, n, m, max_iterations - skipped, tols) if ok else ("degenerate", 0, 1.0)
    q = len(W)
    ys, lam = Yf[nm * R:nm * R + n].copy(), Yf[nm * R + nm:nm * R + nm + q].tolist()
    if status == "optimal" and q and (skipped or az_loop < 1e-3 or az_warm < 1e-3):   # polish: rounding grows
        VW = VT.T.take(W, axis=0)                     # as 1 / a^T Hop a, and with the jumps of a warm start's drops
        _, lam_p, bad = lapack.dposv(VW @ VW.T, -s.take(W))     # the exact minimiser on W
        if not bad and lam_p[lam_p.argmin()] >= -1e-9 * (1.0 + np.abs(lam_p).max()):
            ys, lam = y + lam_p @ VW, lam_p.tolist()
    return ys, status, skipped + steps, W, lam


def _warm_start(Y, W, active, n, m):
    """Make the distinct, independent rows of `active` active by full steps (the equality-constrained minimiser),
    then drop the most negative multiplier until all are >= 0 (a dual-feasible start). Returns (the changes that
    were not adds: skipped and dropped rows, the smallest a^T Hop a of an add, False on a breakdown)."""
    nm, R, skipped, az_min = n + m, 2 * n + m, 0, 1.0
    Yf = Y.T.ravel()
    x, w = np.empty(R), np.empty(nm + 1)
    for p in dict.fromkeys(active):
        az = Yf.item(n + p + p * R)
        if len(W) == n or not az > 1e-12:            # dependent on the rows already active, or a zero row
            skipped += 1
            continue
        _add(Y, Yf, W, p, az, x, w)
        az_min = min(az_min, az)
    while W:
        q = len(W)
        lam = Yf[nm * R + nm:nm * R + nm + q].tolist()
        j = min(range(q), key=lam.__getitem__)
        if lam[j] >= 0.0:
            break
        p = W[j]
        if not _drop(Y, Yf, W, j, n, m):
            return skipped, az_min, False
        # x' = x - lambda_j Hop' a_j, lambda' = lambda + lambda_j r': the iterate column minus lambda_j column p
        blas.daxpy(Yf, Yf, R, -lam[j], p * R, 1, nm * R, 1)
        skipped += 1
    return skipped, az_min, True


def _loop(Y, W, n, m, budget, tols):
    """GI's main loop: add the most violated row p; partial steps drop the active row whose multiplier reaches 0.
    tols = (tol (1 + |x|_H), tol, b_i / |v_i| (list)): row i counts as violated below -tols[0] - tol |b_i| / |v_i|.
    Returns (status, iterations, the smallest a^T Hop a of an add). The add is _add inlined: this is the hot path,
    where every Python-level call counts."""
    nm, R, it, az_min, inf = n + m, 2 * n + m, 0, 1.0, math.inf
    tol0, tol, bs = tols
    Yf, ones, x, w = Y.T.ravel(), np.ones(n), np.empty(2 * n + m), np.empty(n + m + 1)
    dasum, ddot, dcopy, dger, item = blas.dasum, blas.ddot, blas.dcopy, blas.dger, Y.T.ravel().item
    lam0 = nm * R + nm                                # Yf index of lambda_0
    s = Yf[nm * R + n:lam0]                           # scaled slacks (view)
    q = len(W)
    while True:
        p = int(s.argmin())
        sp = s.item(p)
        if not sp < -tol0 - tol * abs(bs[p]):
            return "optimal", it, az_min              # every row satisfied within its tolerance
        lam_p = 0.0
        while True:
            if it >= budget:
                return "max_iterations", it, az_min
            pR = p * R
            az = item(n + p + pR)                     # a_p^T Hop a_p, in [0, 1]
            t2 = -sp / az if az > 1e-12 and q < n else inf     # full step: row p becomes active
            t1, j = inf, -1
            # partial step: lambda_i = 0 first, at t = lambda_i / r_i, for the entries -r_i < 0 of column p
            # (sum |-r| - sum -r = twice their mass: two BLAS calls rule the common case out)
            if q and dasum(Yf, q, nm + pR, 1) - ddot(Yf, ones, q, nm + pR, 1, 0, 1) > 2e-12:
                c3, lam = Yf[nm + pR:nm + pR + q].tolist(), Yf[lam0:lam0 + q].tolist()     # -r, lambda
                for i in range(q):
                    if c3[i] < -1e-12 and -lam[i] / c3[i] < t1:
                        t1, j = -lam[i] / c3[i], i
            if t2 <= t1 and t2 < inf:
                it += 1
                if az < az_min:
                    az_min = az
                dcopy(Yf, x, R, pR, 1, 0, 1)          # _add: column p, (z, V z, -r)
                x[nm + q] = 1.0
                dcopy(Yf, w, nm + 1, n + p, R, 0, 1)  # row n + p
                dger(-1.0 / az, x, w, 1, 1, Y, 1, 1, 1)
                W.append(p)
                if lam_p:
                    Yf[lam0 + q] += lam_p             # the multiplier gained in the partial steps before
                q += 1
                break
            if j < 0:                                 # no step is bounded: the dual is unbounded (or NaN)
                return ("infeasible" if t2 == inf else "degenerate"), it, az_min
            it += 1
            blas.daxpy(Yf, Yf, R, t1, pR, 1, nm * R, 1)    # y, slacks, lambda move by t1 (z, V z, -r)
            lam_p += t1
            if not _drop(Y, Yf, W, j, n, m):
                return "degenerate", it, az_min
            q -= 1
            sp = s.item(p)


def _add(Y, Yf, W, p, az, x, w):
    """Row p joins the active set with GI's full step: Hop' = Hop - z z^T / a^T z, N*' = [N* - r z^T / a^T z;
    z^T / a^T z], applied to every column of Y; on the iterate column it moves (y, slacks, lambda) by t (z, V z, -r)
    with t = -s_p / a^T z, and the new multiplier is t. Row n + p of Y is z^T times each column. x (2n + m,),
    w (m + n + 1,): scratch."""
    R, C = Y.shape
    n = (R - C + 1)
    blas.dcopy(Yf, x, R, p * R, 1, 0, 1)              # column p: (z, V z, -r)
    x[R - n + len(W)] = 1.0                           # the new row of -N* is -z^T (column) / a^T z
    blas.dcopy(Yf, w, C, n + p, R, 0, 1)              # row n + p: z^T (column)
    blas.dger(-1.0 / az, x, w, 1, 1, Y, 1, 1, 1)     # Y -= x w^T / a^T z, in place
    W.append(p)


def _drop(Y, Yf, W, j, n, m):
    """Active row j leaves (GI 1983, in the metric of H = I): with k = N*_j^T (n,) and c = N* k = (N N^T)^-1 e_j
    (q,), Hop' = Hop + k k^T / c_j and N*_i' = N*_i - (c_i / c_j) k^T. Row j of -N* in Y gives k (unit-vector
    columns), V k (row columns) and k^T times every column, so the downdate needs q dot products. The iterate
    column is left alone. False if c_j is not positive (a breakdown)."""
    nm, R, q = n + m, 2 * n + m, len(W)
    r = blas.dcopy(Yf, np.empty(nm + 1), nm + 1, nm + j, R, 0, 1)     # -(k^T V^T, k^T, lambda_j)
    c = [blas.ddot(Yf, r, n, nm + i + m * R, R, m, 1) for i in range(q)]    # N* k  (q,)
    cj = c[j]
    if not cj > 0.0:
        return False
    v = np.zeros(R)                                   # -(k, V k, -c)
    blas.dcopy(r, v, n, m, 1, 0, 1)
    blas.dcopy(r, v, m, 0, 1, n, 1)
    for i in range(q):
        v[nm + i] = -c[i]
    r[nm] = 0.0
    blas.dger(1.0 / cj, v, r, 1, 1, Y, 1, 1, 1)      # Y += (k, V k, -c) (k^T Y) / c_j, in place
    Y[nm + j:nm + q - 1] = Y[nm + j + 1:nm + q]
    Y[nm + q - 1] = 0.0
    del W[j]
    return True


# ndarray.max / .min / .all cost about 1 us each on these tiny arrays, nearly all of it call overhead; argmax /
# argmin cost a quarter of that and give the same values, a NaN included (both pick it); _max needs a non-empty v.
def _max(v):
    return v.ravel()[v.argmax()]


def _all_finite(v):
    ok = np.isfinite(v).ravel()
    return not ok.size or bool(ok[ok.argmin()])       # argmin finds a False if there is one
