"""Dense strictly convex QP min 1/2 x^T H x + g^T x s.t. A x >= b by Goldfarb and Idnani's dual active-set method
(Math. Prog. 27, 1983), NumPy and scipy's BLAS/LAPACK only, warm-startable: the solver of the CPIC torque QP (Sec. 3,
Eq. 8; Appendix B, D). cpic.py re-exports solve_qp; experiments/qp_bench.py times it against quadprog."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from scipy.linalg import blas, lapack

import checks


@dataclass(frozen=True)
class QPInfo:
    """status: "optimal" | "infeasible" | "max_iterations" | "degenerate" (numerical breakdown: overflow, NaN, or
    an answer that fails the final feasibility check); iterations: active-set changes (adds + drops); active:
    indices of the active constraints (k,); multipliers: lambda (m,) >= 0, zero off the active set; residual: max
    KKT violation (abs), worked out when first read (a tenth of a solve that seldom needs it)."""
    status: str
    iterations: int
    active: np.ndarray
    multipliers: np.ndarray
    kkt: tuple = field(default=(), repr=False, compare=False)    # what residual needs: (H, g, A, x, W, r, r_min)

    @cached_property
    def residual(self) -> float:
        H, g, A, x, W, r, r_min = self.kkt
        return _residual(H, g, A, x, self.multipliers, W, r, r_min)


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
    max_iterations = 5 * (n + m) + 10 if max_iterations is None else checks.number("max_iterations", max_iterations,
                                                                                 "1..1000000")
    # y = L^T x turns H into I: min 1/2 |y|^2 + u^T y s.t. V y >= b with V^T = L^-1 A^T (n, m), u = L^-1 g (n,)
    VT = blas.dtrsm(1.0, L, A.T, 0, 1) if m else A.T
    y, status, it, W, mult = _unit(VT, blas.dtrsv(L, g, 1, 0, 1), b, W, int(max_iterations), 1e-11)
    x = blas.dtrsv(L, y, 1, 0, 1, 1)                  # x = L^-T y
    status, r, r_min = _checked_answer(A, b, x, status)
    return x, QPInfo(status, it, np.array(W, dtype=int), mult, (H.copy(), g.copy(), A.copy(), x.copy(), W, r, r_min))


def _checked_problem(H, g, A, b):
    """(H, g, A, b) as float arrays of consistent shapes and finite values, H symmetric; else ValueError."""
    if not all(type(v) is np.ndarray and v.dtype == np.float64 for v in (H, g, A, b)):
        for name, v in (("H", H), ("g", g), ("A", A), ("b", b)):   # bool, complex, text: refused, never cast
            if checks.real_array(v) is None:
                raise ValueError(f"{name}: expected real numbers, found {checks.kind(v)}")
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
    ddot, h, a = blas.ddot, H.ravel(), A.ravel()
    if ddot(g, g) + ddot(h, h) + (ddot(b, b) + ddot(a, a) if len(b) else 0.0) < math.inf:
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
    comp = 0.0
    if W:
        blas.dgemv(-1.0, A.T, mult, 1.0, st, 0, 1, 0, 1, 0, 1)      # - A^T lambda, in place
        lam, r_list = mult.tolist(), r.tolist()
        comp = max([abs(lam[i] * r_list[i]) for i in W])
    worst = max(abs(st.item(blas.idamax(st))), -float(r_min), 0.0, comp)
    return worst if worst == worst and blas.dasum(st) < math.inf else np.inf    # NaN reads as inf


def _checked_answer(A, b, x, status):
    """(status, r = A x - b (m,), min r): an "optimal" answer that fails _feasible becomes "degenerate"."""
    if not len(b):
        return status, b[:], 0.0
    r = blas.dgemv(1.0, A.T, x, -1.0, b, 0, 1, 0, 1, 1, 0)           # A x - b
    r_min = r.item(r.argmin())
    if status == "optimal" and not (r_min >= -1e-9 or _feasible(A, b, x, r)):   # every row's tolerance >= 1e-9
        status = "degenerate"
    return status, r, r_min


def _feasible(A, b, x, r, tol=1e-9):
    """A x >= b (r = A x - b) within tol times each row's rounding scale 1 + |b_i| + |a_i| |x|; False on NaN or
    overflow. The final check that turns a broken answer into status "degenerate"."""
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
    status, iterations, W, multipliers (m,)). Tries a warm start as the answer itself first (warm=True)."""
    n, m = u.shape[0], b.shape[0]
    uu = blas.ddot(u, u)                              # |x|_H^2: finite iff u is (but for overflow)
    if not m or not uu < math.inf:
        return -u, ("optimal" if uu < math.inf else "degenerate"), 0, [], np.zeros(m)
    if warm and not active:                           # the unconstrained minimiser is often the answer (half the
        y = -u                                        # controller's problems): one product tells
        s = blas.dgemv(1.0, VT, y, -1.0, b, 0, 1, 0, 1, 1, 0)    # (m,) slacks V y - b
        if s.item(s.argmin()) >= 0.0:
            return y, "optimal", 0, [], np.zeros(m)
    elif warm and len(active) <= n:                   # the warm start is often the answer
        W, y, V = list(dict.fromkeys(active)), -u, VT.T     # V (m, n): rows v_i
        VW = V.take(W, axis=0)
        out = _warm_answer(V, b, VW, VW, y, V @ y - b, W)
        if out is not None:
            return out[0], "optimal", 0, W, out[1]
    norms2 = np.add.reduce(VT * VT)                   # |a_i|_{H^-1}^2 = |v_i|^2 (m,)
    total = blas.dasum(norms2)                        # inf or NaN on overflow or NaN
    if not total < math.inf:
        return -u, "degenerate", 0, [], np.zeros(m)
    norms = np.sqrt(norms2)
    if norms2.item(norms2.argmin()) <= 1e-24 * (1.0 + total):    # a zero row reads 0 >= b_i
        usable = norms2 > 1e-24 * (1.0 + total)
        if (b[~usable] > 0.0).any():
            return -u, "infeasible", 0, [], np.zeros(m)
        norms[~usable] = np.inf                       # scaled to 0 >= 0: inert
    # rows scaled to |v_i| = 1, so that slacks and multipliers mean the same for every row; row i counts as
    # violated when its scaled slack is below -tol (1 + |x|_H) - tol |b_i| / |v_i| (its rounding scale)
    Z, Y, Yf, bs = _tableau(VT, u, b, norms)
    W = []
    skipped, az_warm, ok = _warm_start(Y, Yf, W, active, n, m) if active else (0, 1.0, True)
    status, steps, az_loop = (_loop(Y, Yf, W, n, m, max_iterations - skipped, tol * (1.0 + math.sqrt(uu)), tol,
                                    bs.tolist()) if ok else ("degenerate", 0, 1.0))
    q, nm = len(W), n + m
    ys, lam = Yf[m:nm], Yf[nm:nm + q].tolist()       # y (a view into Y), lambda_W
    if status == "optimal" and q and (skipped or az_loop < 1e-3 or az_warm < 1e-3):   # polish: rounding grows
        VW = Z[:, 1:m + 1].T.take(W, axis=0)          # as 1 / a^T Hop a, and with the jumps of a warm start's drops
        _, lam_p, bad = lapack.dposv(VW @ VW.T, bs.take(W) - VW @ Z[:, 0])    # the exact minimiser on W
        if not bad and lam_p[lam_p.argmin()] >= -1e-9 * (1.0 + np.abs(lam_p).max()):
            ys, lam = Z[:, 0] + lam_p @ VW, lam_p.tolist()
    mult, norms = np.zeros(m), norms.tolist()
    for i, lam_i in zip(W, lam):
        if lam_i > 0.0:
            mult[i] = lam_i / norms[i]                # back to the unscaled rows
    if status == "optimal" and not math.isfinite(math.fsum(lam)):
        status = "degenerate"
    return ys, status, skipped + steps, W, mult


def _tableau(VT, u, b, norms):
    """GI's operators for the active rows N (q, n) (GI 1983, Sec. 3; here H = I), Hop = I - N^T (N N^T)^-1 N (primal
    step z = Hop a) and N* = (N N^T)^-1 N (dual step r = N* a), kept as their products with the iterate, every
    scaled row v_i d_i and every unit vector e_k, in one tableau (R = m + 2n, C = 1 + m + n):

        Y = [V y - b, V Hop V^T, V Hop;  y, Hop V^T, Hop;  lambda, -N* V^T, -N*]      (rows scaled: V = D V, b = D b)

    Column 1 + p holds (V z, z, -r) for row p, and Y[:m + n, 1:] = [V; I] Hop [V^T, I] is symmetric, so row p is
    (s_p, column 1 + p above row m + n). At the start (no active rows) Y = [V; I; 0] [y, V^T, I], one product.
    An add is one rank-one update of Y that also takes GI's full step (_add); a drop is one rank-one downdate read
    off the dropped row of -N* (_drop; N* N*^T = (N N^T)^-1), so no step solves a system. Column-major, so that the
    iterate and every row's column are contiguous for the BLAS calls of the loop.
    Returns (Z = [y, V^T, I, 0] (n, 1 + R), Y (R, C) column-major, Yf its memory: Y[i, j] = Yf[i + j R], D b (m,))
    for V^T (n, m), u (n,), b (m,), D = 1 / norms (m,)."""
    n, m = VT.shape
    C = 1 + m + n
    Z = np.zeros((n, 1 + m + 2 * n), order="F")
    Zf = Z.T.ravel()                                  # Z[i, j] = Zf[i + j n]
    np.negative(u, out=Zf[:n])                        # y = -u: the unconstrained minimiser
    np.divide(VT, norms, out=Z[:, 1:m + 1])
    Zf[C * n - n * n:C * n:n + 1] = 1.0
    Y = blas.dgemm(1.0, Z[:, 1:], Z[:, :C], 0.0, None, 1)
    Yf, bs = Y.T.ravel(), b / norms
    blas.daxpy(bs, Yf, m, -1.0)                       # the slacks: V y - b
    return Z, Y, Yf, bs


def _warm_start(Y, Yf, W, active, n, m):
    """Make the distinct, independent rows of `active` active by full steps (the equality-constrained minimiser),
    then drop the most negative multiplier until all are >= 0 (a dual-feasible start). Returns (the changes that
    were not adds: skipped and dropped rows, the smallest a^T Hop a of an add, False on a breakdown)."""
    nm, R, skipped, az_min = n + m, m + 2 * n, 0, 1.0
    xw = np.empty(R + 1)
    for p in dict.fromkeys(active):
        az = Yf.item(p + (1 + p) * R)
        if len(W) == n or not az > 1e-12:            # dependent on the rows already active, or a zero row
            skipped += 1
            continue
        _add(Y, Yf, W, p, az, xw)
        az_min = min(az_min, az)
    while W:
        q = len(W)
        lam = Yf[nm:nm + q].tolist()
        j = min(range(q), key=lam.__getitem__)
        if lam[j] >= 0.0:
            break
        p = W[j]
        if not _drop(Y, Yf, W, j, n, m):
            return skipped, az_min, False
        # x' = x - lambda_j Hop' a_j, lambda' = lambda + lambda_j r': the iterate column minus lambda_j column 1 + p
        blas.daxpy(Yf, Yf, R, -lam[j], (1 + p) * R, 1, 0, 1)
        skipped += 1
    return skipped, az_min, True


def _loop(Y, Yf, W, n, m, budget, tol0, tol, bs):
    """GI's main loop: add the most violated row p; partial steps drop the active row whose multiplier reaches 0.
    Row i counts as violated when its scaled slack is below -tol0 - tol |bs_i| (bs: b_i / |v_i|, a list).
    Returns (status, iterations, the smallest a^T Hop a of an add). The add is _add inlined: this is the hot path,
    where every Python-level call counts (a memoryview reads and writes single entries at a third of the cost)."""
    nm, C, R, it, az_min, inf = n + m, n + m + 1, m + 2 * n, 0, 1.0, math.inf
    xw = np.empty(R + 1)
    Ym, xm, w, x = memoryview(Yf), memoryview(xw), xw[:C], xw[1:]    # row p, column 1 + p: see _add
    dcopy, dger = blas.dcopy, blas.dger
    s = Yf[:m]                                        # scaled slacks (view)
    q = len(W)
    while True:
        p = int(s.argmin())
        sp = Ym[p]
        if not sp < -tol0 - tol * abs(bs[p]):
            return "optimal", it, az_min              # every row satisfied within its tolerance
        lam_p = 0.0
        while True:
            if it >= budget:
                return "max_iterations", it, az_min
            col = (1 + p) * R                         # Yf index of column 1 + p: (V z, z, -r)
            az = Ym[col + p]                          # a_p^T Hop a_p, in [0, 1]
            t2 = -sp / az if az > 1e-12 and q < n else inf     # full step: row p becomes active
            t1, j = inf, -1
            if q:                                     # partial step: lambda_i = 0 first, at t = lambda_i / r_i,
                c3 = Ym[col + nm:col + nm + q].tolist()    # for the entries -r_i < 0
                if min(c3) < -1e-12:
                    lam = Ym[nm:nm + q].tolist()
                    for i in range(q):
                        if c3[i] < -1e-12 and -lam[i] / c3[i] < t1:
                            t1, j = -lam[i] / c3[i], i
            if t2 <= t1 and t2 < inf:
                it += 1
                if az < az_min:
                    az_min = az
                dcopy(Yf, xw, R, col, 1, 1, 1)        # _add, inlined
                xm[0] = sp
                xm[C + q] = 1.0
                dger(-1.0 / az, x, w, 1, 1, Y, 1, 1, 1)
                W.append(p)
                if lam_p:
                    Ym[nm + q] += lam_p               # the multiplier gained in the partial steps before
                q += 1
                break
            if j < 0:                                 # no step is bounded: the dual is unbounded (or NaN)
                return ("infeasible" if t2 == inf else "degenerate"), it, az_min
            it += 1
            blas.daxpy(Yf, Yf, R, t1, col, 1, 0, 1)   # slacks, y, lambda move by t1 (V z, z, -r)
            lam_p += t1
            if not _drop(Y, Yf, W, j, n, m):
                return "degenerate", it, az_min
            q -= 1
            sp = Ym[p]


def _add(Y, Yf, W, p, az, xw):
    """Row p joins the active set with GI's full step: Hop' = Hop - z z^T / a^T z, N*' = [N* - r z^T / a^T z;
    z^T / a^T z], applied to every column of Y; on the iterate column it moves (slacks, y, lambda) by t (V z, z, -r)
    with t = -s_p / a^T z, and the new multiplier is t. That is Y -= x w^T / a^T z with x = column 1 + p (and 1 in
    the new row of -N*) and w = row p = (s_p, x[:m + n]) (the symmetric block): one copy fills both, as
    xw = (s_p, x) (R + 1,), x = xw[1:], w = xw[:C]."""
    R, C = Y.shape
    blas.dcopy(Yf, xw, R, (1 + p) * R, 1, 1, 1)       # xw[1:] = column 1 + p
    xw[0] = Yf.item(p)
    xw[C + len(W)] = 1.0                              # the new row of -N* is -z^T (column) / a^T z
    blas.dger(-1.0 / az, xw[1:], xw[:C], 1, 1, Y, 1, 1, 1)     # Y -= x w^T / a^T z, in place
    W.append(p)


def _drop(Y, Yf, W, j, n, m):
    """Active row j leaves (GI 1983, in the metric of H = I): with k = N*_j^T (n,) and c = N* k = (N N^T)^-1 e_j
    (q,), Hop' = Hop + k k^T / c_j and N*_i' = N*_i - (c_i / c_j) k^T. Row m + n + j of Y, -k^T times each column,
    gives (V k, k) (the symmetric block) and c = N* k in one product. The iterate column is left alone.
    False if c_j is not positive (a breakdown)."""
    nm, q, R = n + m, len(W), m + 2 * n
    r, v = blas.dcopy(Yf, np.empty(nm + 1), nm + 1, nm + j, R), np.zeros(R)    # r = (lambda_j, -(V k)^T, -k^T)
    blas.dgemv(-1.0, Y[nm:nm + q, 1 + m:], r, 0.0, v, 1 + m, 1, nm, 1, 0, 1)     # v[nm:] = -N* k = -c (q,)
    cj = -v.item(nm + j)
    if not cj > 0.0:
        return False
    blas.dcopy(r, v, nm, 1)                           # v = -(V k, k, c)
    r[0] = 0.0
    blas.dger(1.0 / cj, v, r, 1, 1, Y, 1, 1, 1)       # Y += (V k, k, c) (k^T Y) / c_j, in place
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
