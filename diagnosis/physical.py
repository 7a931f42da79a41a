"""Physically consistent least squares for the effect model (Eq. 1 plus effects): parameter bounds, a rigid payload
whose pseudo-inertia is positive semidefinite (Wensing, Kim, Slotine 2017), an exact base tilt (gravity rotated,
|g| kept). The constrained problem is solved on the K x K factor of the normal equations, never on the T rows."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares, lsq_linear

from motion.inertia import inertia_of, pseudo_inertia, params_of as body_params   # noqa: F401 (re-exported)

KINDS = ("", "tilt", "rigid_body", "payload")   # the named constraints an effect may declare beside its bounds


def solve(G, b, rcond: float = 1e-10):
    """Least squares from normal equations G p = b (K, K), (K,): Jacobi-scaled, pseudo-inverse below rcond * the
    largest eigenvalue (unidentifiable combinations get 0). Returns (p (K,), info {rank, K})."""
    K = len(b)
    if K == 0:
        return np.zeros(0), {"rank": 0, "K": 0}
    d = np.sqrt(np.maximum(np.diag(G), 0.0))
    d[d == 0] = 1.0
    lam, V = np.linalg.eigh(G / np.outer(d, d))
    keep = lam > rcond * max(lam.max(), 1e-300)
    p = V[:, keep] @ ((V[:, keep].T @ (b / d)) / lam[keep])
    return p / d, {"rank": int(keep.sum()), "K": K}


# --- exact tilt: g' = Ry(ay) Rx(ax) g, columns c = g' - g of the gravity map (G(q; g') = -W g') -------------------
def _rot(axis: int, a: float):
    c, s = np.cos(a), np.sin(a)
    R, dR = np.eye(3), np.zeros((3, 3))
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R[i, i], R[i, j], R[j, i], R[j, j] = c, -s, s, c
    dR[i, i], dR[i, j], dR[j, i], dR[j, j] = -s, -c, c, -s
    return R, dR


def tilt_columns(a, g):
    """c = Ry(ay) Rx(ax) g - g (3,) and dc/da (3, 2) for the angles a = (ax, ay) [rad], as sim.PlantConfig.gravity_tilt
    tilts the plant's gravity."""
    Rx, dRx = _rot(0, a[0])
    Ry, dRy = _rot(1, a[1])
    g = np.asarray(g, dtype=float)
    return Ry @ Rx @ g - g, np.stack([Ry @ dRx @ g, dRy @ Rx @ g], axis=1)


def tilt_angles(c, g, iterations: int = 20):
    """The angles (2,) whose tilted gravity is nearest to g + c in direction (Gauss-Newton from the linearisation)."""
    g = np.asarray(g, dtype=float)
    target = (g + c) * np.linalg.norm(g) / max(np.linalg.norm(g + c), 1e-300) - g
    a = np.zeros(2)
    for _ in range(iterations):
        f, J = tilt_columns(a, g)
        step = np.linalg.lstsq(J, target - f, rcond=None)[0]
        a = a + step
        if np.abs(step).max() < 1e-13:
            break
    return a


# --- rigid body: p = (m, m cx, m cy, m cz, Ixx, Ixy, Iyy, Ixz, Iyz, Izz), I about the frame's origin ---------------
def body_issues(p, tol: float = 1e-9) -> list:
    """What makes p non-physical, [(issue, value)]: ('m', m < 0), ('Ixx', Ixx < 0) ..., ('triangle inequality', the
    worst Ixx + Iyy - Izz and its permutations), ('min eigenvalue of the pseudo-inertia', < 0); [] if physical."""
    p = np.asarray(p, dtype=float)
    d = np.diag(inertia_of(p))
    scale = tol * max(np.abs(p).max(), 1e-12)
    out = [("m", float(p[0]))] if p[0] < -scale else []
    out += [(n, float(v)) for n, v in zip(("Ixx", "Iyy", "Izz"), d) if v < -scale]
    if not out and np.min(d.sum() - 2 * d) < -scale:
        out.append(("triangle inequality", float(np.min(d.sum() - 2 * d))))
    low = float(np.linalg.eigvalsh(pseudo_inertia(p)).min())
    return out + [("min eigenvalue of the pseudo-inertia", low)] if low < -scale else out


_TRIL = np.tril_indices(4)


def _factor_forms():
    """Q (10, 10, 10) with body_params(L L^T)_i = x^T Q_i x for L lower triangular with entries x (10,)."""
    E = np.zeros((10, 4, 4))
    E[np.arange(10), _TRIL[0], _TRIL[1]] = 1.0
    Q = np.empty((10, 10, 10))
    for k in range(10):
        for m in range(10):
            Q[:, k, m] = body_params(E[k] @ E[m].T)
    return 0.5 * (Q + Q.transpose(0, 2, 1))


_Q = _factor_forms()


def _body_from_factor(x):
    """p (10,) = body_params(L L^T) and dp/dx (10, 10) for L lower triangular with entries x (10,)."""
    Qx = _Q @ x                                                          # (10, 10)
    return Qx @ x, 2 * Qx


def _factor_of(p):
    """x (10,) with L L^T the nearest PSD pseudo-inertia to p's (eigenvalues clipped, kept just above zero)."""
    w, Q = np.linalg.eigh(pseudo_inertia(p))
    floor = 1e-6 * max(np.abs(w).max(), 1e-9)
    L = np.linalg.cholesky((Q * np.maximum(w, floor)) @ Q.T)
    return L[_TRIL]


# --- the constrained solve ----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Segment:
    """The columns [i0, i1) of one effect; lo, hi (k,) bounds of its physical parameters (k = i1 - i0, or 2 for a
    tilt whose 3 columns are c(ax, ay)); kind one of KINDS; g (3,) for a tilt; labels (k,) of the parameters;
    radius [m]: for a payload or rigid body (m, m c, ...), the CoM's distance bound |c| <= radius, i.e. the
    second-order cone |m c| <= radius m."""
    name: str
    i0: int
    i1: int
    lo: np.ndarray
    hi: np.ndarray
    kind: str = ""
    g: np.ndarray | None = None
    labels: tuple = ()
    radius: float = np.inf


def violations(seg: Segment, c) -> list:
    """What the column values c (i1 - i0,) break: [(label, value)] outside the bounds; for a rigid body its
    body_issues; for a tilt [("|g + dg| / |g| - 1", value)] if |g| changes by more than 0.1 %."""
    if seg.kind == "tilt":
        ratio = np.linalg.norm(seg.g + c) / np.linalg.norm(seg.g) - 1
        return [("|g + dg| / |g| - 1", float(ratio))] if abs(ratio) > 1e-3 else []
    out = body_issues(c) if seg.kind == "rigid_body" else []
    tol = 1e-6 * (1 + np.abs(np.where(np.isfinite(seg.lo), seg.lo, 0)) + np.abs(np.where(np.isfinite(seg.hi), seg.hi, 0)))
    bad = np.flatnonzero((c < seg.lo - tol) | (c > seg.hi + tol))
    out += [(seg.labels[i] if seg.labels else str(i), float(c[i])) for i in bad if not out or i > 0]
    if seg.kind in ("payload", "rigid_body") and np.isfinite(seg.radius):
        h = float(np.linalg.norm(c[1:4]))
        if h > seg.radius * max(c[0], 0.0) * (1 + 1e-6) + 1e-6:          # 1e-6 kg m: nothing held there
            out.append(("|r| [m]", h / c[0] if c[0] > 0 else np.inf))
    return out


def solve_physical(G, b, segs, rcond: float = 1e-10):
    """min ||A c - y||^2 given G = A^T A, b = A^T y (K,) with each segment's constraints. The unconstrained solution
    is kept when it satisfies them all (never for a tilt: |g| must stay); else, on the Jacobi-scaled eigen-factor
    R^T R = G (rank x K): bounds alone go to scipy's lsq_linear (BVLS), bounds and rigid bodies to a barrier method,
    a tilt's angles (with the rest: bounds, a body as its Cholesky factor J = L L^T) to scipy's least_squares (TRF).
    Returns (c (K,), info {rank, K, constrained, params (per
    segment: physical values; angles for a tilt), unconstrained (K,), violations {name: [(label, value)]}, status})."""
    c_u, info = solve(G, b, rcond)
    viol = {s.name: v for s in segs for v in [violations(s, c_u[s.i0:s.i1])] if v}
    info.update(unconstrained=c_u, violations=viol, status="unconstrained")
    if not viol and not any(s.kind == "tilt" for s in segs):
        info.update(constrained=False, params=[c_u[s.i0:s.i1] for s in segs])
        return c_u, info
    K = len(b)
    d = np.sqrt(np.maximum(np.diag(G), 0.0))
    d[d == 0] = 1.0
    lam, V = np.linalg.eigh(G / np.outer(d, d))
    keep = lam > rcond * max(lam.max(), 1e-300)
    R = np.sqrt(lam[keep])[:, None] * V[:, keep].T                     # (k, K), acting on u = d c
    e = (V[:, keep].T @ (b / d)) / np.sqrt(lam[keep])                   # ||A c - y||^2 = ||R u - e||^2 + const
    lo, hi = np.full(K, -np.inf), np.full(K, np.inf)
    for s in segs:
        if s.kind != "tilt":
            lo[s.i0:s.i1], hi[s.i0:s.i1] = s.lo * d[s.i0:s.i1], s.hi * d[s.i0:s.i1]
    if all(s.kind == "" for s in segs):
        res = lsq_linear(R, e, bounds=(lo, hi), method="bvls" if keep.sum() == K else "trf", tol=1e-12)
        c = res.x / d
        info.update(constrained=True, params=[c[s.i0:s.i1] for s in segs], status=f"lsq_linear: {res.status}")
        return c, info
    if not any(s.kind == "tilt" for s in segs):
        c, status = _solve_barrier(R.T @ R, R.T @ e, d, lo, hi, segs, c_u)
        info.update(constrained=True, params=[c[s.i0:s.i1] for s in segs], status=status)
        return c, info
    return _solve_mapped(R, e, d, lo, hi, segs, c_u, info)


_A = np.stack([pseudo_inertia(e) for e in np.eye(10)])                 # (10, 4, 4): J(p) = sum_i p_i A_i


def _solve_barrier(H, f, d, lo, hi, segs, c_u, gap: float = 1e-13, newton: int = 50):
    """min 1/2 u^T H u - f^T u (u = d c) with every rigid body's J(c) > 0 and lo < u < hi: the barrier method (Boyd
    and Vandenberghe, Convex Optimization, Sec. 11.3; -log det J for each body, -log for each finite bound), from
    the nearest strictly feasible point to c_u, until the duality gap m / t <= gap * |1/2 f^T u_unconstrained|."""
    K = len(f)
    bodies = [np.arange(s.i0, s.i1) for s in segs if s.kind == "rigid_body"]
    cones = [(np.arange(s.i0, s.i0 + 4), s.radius) for s in segs
             if s.kind in ("payload", "rigid_body") and np.isfinite(s.radius)]
    has_lo, has_hi = np.isfinite(lo), np.isfinite(hi)
    u = d * c_u
    for ix in bodies:                                              # eigenvalues raised to a margin above zero
        w, Q = np.linalg.eigh(pseudo_inertia(c_u[ix]))
        u[ix] = d[ix] * body_params((Q * np.maximum(w, 1e-3 * max(w.max(), 1e-9))) @ Q.T)
    margin = np.minimum(1e-3 * (np.abs(u) + 1e-6 * (1 + np.abs(u).max())), 0.25 * (hi - lo))   # inside a narrow box
    u = np.where(has_lo, np.maximum(u, lo + margin), u)
    u = np.where(has_hi, np.minimum(u, hi - margin), u)
    for ix, rho in cones:                                          # m c shrunk inside the cone (keeps J > 0)
        c = u[ix] / d[ix]
        c[0] = max(c[0], 1e-3 * (hi[ix[0]] / d[ix[0]] if np.isfinite(hi[ix[0]]) else 1.0))
        h = np.linalg.norm(c[1:])
        c[1:] *= min(1.0, 0.9 * rho * c[0] / max(h, 1e-300))
        u[ix] = d[ix] * c
    m = 4 * len(bodies) + 2 * len(cones) + has_lo.sum() + has_hi.sum()
    ridge = 1e-12 * max(np.trace(H) / K, 1e-300) * np.eye(K)

    def barrier(u, need=2):
        """phi(u), its gradient and Hessian (or phi alone for need=0; inf outside the domain)."""
        if np.any(u[has_lo] <= lo[has_lo]) or np.any(u[has_hi] >= hi[has_hi]):
            return np.inf, None, None
        phi, g, Hb = 0.0, np.zeros(K), np.zeros((K, K))
        for ix in bodies:
            J = np.einsum("i,ijk->jk", u[ix] / d[ix], _A)
            try:
                Lc = np.linalg.cholesky(J)
            except np.linalg.LinAlgError:
                return np.inf, None, None
            phi -= 2 * np.log(np.diag(Lc)).sum()
            if need:
                B = np.linalg.solve(J, _A.transpose(1, 0, 2).reshape(4, -1)).reshape(4, 10, 4).transpose(1, 0, 2)
                g[ix] -= np.trace(B, axis1=1, axis2=2) / d[ix]         # -tr(J^-1 A_i) / d_i
                Hb[np.ix_(ix, ix)] += np.einsum("ijk,lkj->il", B, B) / np.outer(d[ix], d[ix])
        for ix, rho in cones:                  # -log(rho^2 m^2 - |h|^2), the cone's barrier (Boyd and Vandenberghe 11.6)
            c = u[ix] / d[ix]
            w = np.array([rho ** 2, -1.0, -1.0, -1.0])
            sc = float(w @ c ** 2)
            if sc <= 0 or c[0] <= 0:
                return np.inf, None, None
            phi -= np.log(sc)
            if need:
                ds = 2 * w * c / d[ix]
                g[ix] -= ds / sc
                Hb[np.ix_(ix, ix)] += np.outer(ds, ds) / sc ** 2 - np.diag(2 * w / d[ix] ** 2) / sc
        a, b = u - lo, hi - u
        phi -= np.log(a[has_lo]).sum() + np.log(b[has_hi]).sum()
        g += np.where(has_lo, -1 / np.where(has_lo, a, 1), 0) + np.where(has_hi, 1 / np.where(has_hi, b, 1), 0)
        Hb[np.diag_indices(K)] += np.where(has_lo, 1 / np.where(has_lo, a, 1) ** 2, 0) + \
            np.where(has_hi, 1 / np.where(has_hi, b, 1) ** 2, 0)
        return phi, g, Hb

    if not np.isfinite(barrier(u, need=0)[0]):          # clamped into a box, a body lost its positive definiteness
        u = _interior(u, d, lo, hi, bodies, cones)
    obj = lambda u: 0.5 * u @ H @ u - f @ u                                # noqa: E731
    f_u = obj(d * c_u)
    t = m / max(obj(u) - f_u, 1e-300)
    steps, singular = 0, False
    for _ in range(40):                                                 # t grows by 10 per round: 1e40 at most
        for _ in range(newton):                                         # centering: Newton on t obj + phi
            phi, g, Hb = barrier(u)
            grad = t * (H @ u - f) + g
            try:
                du = -np.linalg.solve(t * H + Hb + t * ridge, grad)
            except np.linalg.LinAlgError:
                singular = True                 # the Newton system singular in rounding (t large): no step left,
                break                           # the point reached is inside and as close as this t gets
            dec = -grad @ du
            steps += 1
            if dec / 2 <= 1e-12 * max(1.0, abs(t * obj(u))):
                break
            alpha, now = 1.0, t * obj(u) + phi
            while alpha > 1e-12:
                cand = u + alpha * du
                val = barrier(cand, need=0)[0]
                if np.isfinite(val) and t * obj(cand) + val <= now - 0.25 * alpha * dec:
                    break
                alpha *= 0.5
            if alpha <= 1e-12:
                break                           # no feasible descent left at this t (rounding): stay inside
            u = u + alpha * du
        if singular or m / t <= gap * max(abs(f_u), 1e-300):
            break
        t *= 10.0
    return u / d, f"barrier: {steps} Newton steps, duality gap <= {m / t:.2g}" + (
        ", stopped where the Newton system became singular in rounding" if singular else "")


def _interior(u, d, lo, hi, bodies, cones):
    """u with every rigid body and payload cone moved to a strictly feasible point of its bounds: the mass inside its
    bounds, the CoM at the origin and, for a body, an inertia of a sphere of 0.1 m radius about it (0.01 m kg^2/kg,
    isotropic: pseudo-inertia positive definite)."""
    u = u.copy()
    for ix in [ix for ix in bodies] + [ix for ix, _ in cones]:
        i0 = ix[0]
        m_lo = lo[i0] / d[i0] if np.isfinite(lo[i0]) else 0.0
        m_hi = hi[i0] / d[i0] if np.isfinite(hi[i0]) else max(u[i0] / d[i0], 1.0)
        m = float(np.clip(u[i0] / d[i0], m_lo + 0.25 * (m_hi - m_lo), m_lo + 0.75 * (m_hi - m_lo)))
        c = np.zeros(len(ix))
        c[0] = m
        if len(ix) == 10:
            c[[4, 6, 9]] = 0.01 * m                                   # Ixx, Iyy, Izz (pinocchio's order)
        u[ix] = d[ix] * c
    return u


def _solve_mapped(R, e, d, lo, hi, segs, c_u, info):
    """solve_physical with tilt / rigid-body segments: x = (u of the plain columns, tilt angles, body factors)."""
    K = len(d)
    plain = np.ones(K, dtype=bool)
    x0, xlo, xhi, parts = [], [], [], []                # parts: (segment, slice of x)
    for s in segs:
        if s.kind in ("tilt", "rigid_body"):        # a payload's cone is not kept beside a tilt: bounds only
            plain[s.i0:s.i1] = False
    ip = np.flatnonzero(plain)
    x0.append(np.clip(d[ip] * c_u[ip], lo[ip], hi[ip]))
    xlo.append(lo[ip])
    xhi.append(hi[ip])
    n0 = len(ip)
    for s in segs:
        if s.kind == "tilt":
            start, a_lo, a_hi = tilt_angles(c_u[s.i0:s.i1], s.g), s.lo, s.hi
        elif s.kind == "rigid_body":
            start, a_lo, a_hi = _factor_of(c_u[s.i0:s.i1]), np.full(10, -np.inf), np.full(10, np.inf)
        else:
            continue
        parts.append((s, slice(n0, n0 + len(start))))
        n0 += len(start)
        x0.append(np.clip(start, a_lo + 1e-12, a_hi - 1e-12))
        xlo.append(a_lo)
        xhi.append(a_hi)
    x0, xlo, xhi = np.concatenate(x0), np.concatenate(xlo), np.concatenate(xhi)

    def unpack(x):
        u, D = np.zeros(K), np.zeros((K, len(x)))
        u[ip], D[ip, np.arange(len(ip))] = x[:len(ip)], 1.0
        for s, sl in parts:
            f, J = tilt_columns(x[sl], s.g) if s.kind == "tilt" else _body_from_factor(x[sl])
            u[s.i0:s.i1], D[s.i0:s.i1, sl] = d[s.i0:s.i1] * f, d[s.i0:s.i1, None] * J
        return u, D

    res = least_squares(lambda x: R @ unpack(x)[0] - e, x0, jac=lambda x: R @ unpack(x)[1], bounds=(xlo, xhi),
                        method="trf", x_scale="jac", xtol=1e-12, ftol=1e-12, gtol=1e-12, max_nfev=500)
    c = unpack(res.x)[0] / d
    angles = {s.name: res.x[sl] for s, sl in parts if s.kind == "tilt"}
    params = [angles.get(s.name, c[s.i0:s.i1]) for s in segs]
    info.update(constrained=True, params=params, status=f"least_squares: {res.status}, {res.nfev} evaluations")
    return c, info
