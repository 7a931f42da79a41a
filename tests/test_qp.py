"""Tests of qp.py: the dual active-set QP solver against closed-form optima, an exhaustive active-set reference,
quadprog (the same method in Fortran, when installed) and scipy's linprog (feasibility verdicts), warm starts,
degenerate and overflowing problems and input checks."""
import itertools

import numpy as np
import pytest

import cpic
from experiments.qp_bench import quadprog_solve, random_problem
from qp import dual_active_set, dual_active_set_from_inverse, solve_qp


# --- QP solver -----------------------------------------------------------------------------------------------
def random_spd(rng, n=7):
    B = rng.normal(size=(n, n))
    return B @ B.T + 0.1 * np.eye(n)


def constructed_qp(rng, n=7):
    """A QP whose optimum x* is known by construction: k active constraints with multipliers > 0 (sometimes one
    weakly active: multiplier 0, slack 0), the rest strictly inactive; H x* + g = A^T lambda."""
    m = int(rng.integers(n, 29))
    k = int(rng.integers(0, n + 1))
    H, A, x_star = random_spd(rng, n), rng.normal(size=(m, n)), rng.normal(size=n)
    lam = np.zeros(m)
    lam[:k] = rng.uniform(0.1, 10.0, k)
    slack = np.where(np.arange(m) < k, 0.0, rng.uniform(0.1, 2.0, m))
    if k < n and rng.random() < 0.2:
        slack[k] = 0.0                                # weakly active: degenerate but x* unchanged
    perm = rng.permutation(m)
    A, lam, slack = A[perm], lam[perm], slack[perm]
    b = A @ x_star - slack
    g = A.T @ lam - H @ x_star
    return H, g, A, b, x_star, k


def kkt_violation(H, g, A, b, x, lam):
    s = A @ x - b
    return max(np.abs(H @ x + g - A.T @ lam).max(), max(0.0, -s.min()), max(0.0, -lam.min()),
               np.abs(lam * s).max())


def objective(H, g, x):
    return 0.5 * x @ H @ x + g @ x


def test_qp_matches_closed_form_optimum_on_200_constructed_problems():
    rng = np.random.default_rng(0)
    active_sizes = []
    for _ in range(200):
        H, g, A, b, x_star, k = constructed_qp(rng)
        x, info = solve_qp(H, g, A, b)
        assert info.status == "optimal"
        f_ref = objective(H, g, x_star)
        assert abs(objective(H, g, x) - f_ref) <= 1e-8 * max(1.0, abs(f_ref))
        assert np.abs(x - x_star).max() <= 1e-8 * max(1.0, np.abs(x_star).max())
        assert kkt_violation(H, g, A, b, x, info.multipliers) <= 1e-8
        H += 1.0; g += 10.0; A += 1.0; x += 1.0          # the caller reuses its arrays before reading residual
        assert info.residual <= 1e-8                      # which is still that of the problem solved
        active_sizes.append(k)
    assert max(active_sizes) == 7 and np.mean(np.array(active_sizes) >= 5) > 0.2   # many-active cases are in


def enumeration_reference(H, g, A, b, tol=1e-9):
    """Exhaustive search over active sets (at most n of them): the KKT point with lambda >= 0 that is feasible."""
    n, m = len(g), len(b)
    for k in range(min(n, m) + 1):
        subsets = list(itertools.combinations(range(m), k))
        S = np.array(subsets, dtype=int).reshape(len(subsets), k)
        K = np.zeros((len(S), n + k, n + k))
        K[:, :n, :n] = H
        K[:, :n, n:] = -A[S].transpose(0, 2, 1)
        K[:, n:, :n] = A[S]
        rhs = np.zeros((len(S), n + k))
        rhs[:, :n], rhs[:, n:] = -g, b[S]
        ok = np.abs(np.linalg.det(K)) > 1e-12
        sol = np.linalg.solve(K[ok], rhs[ok][..., None])[..., 0]
        x, lam = sol[:, :n], sol[:, n:]
        good = (lam.min(axis=1, initial=0.0) >= -tol) & ((x @ A.T - b).min(axis=1) >= -tol)
        if good.any():
            return x[np.argmax(good)]
    raise AssertionError("no KKT point found")


def test_qp_matches_active_set_enumeration_on_random_problems():
    rng = np.random.default_rng(1)
    for _ in range(60):
        m = int(rng.integers(1, 13))
        H, A, x0 = random_spd(rng), rng.normal(size=(m, 7)), rng.normal(size=7)
        b = A @ x0 - np.abs(rng.normal(size=m)) * rng.integers(0, 2, size=m)     # feasible (x0), some tight
        g = 5.0 * rng.normal(size=7)
        x, info = solve_qp(H, g, A, b)
        x_ref = enumeration_reference(H, g, A, b)
        f_ref = objective(H, g, x_ref)
        assert info.status == "optimal"
        assert abs(objective(H, g, x) - f_ref) <= 1e-8 * max(1.0, abs(f_ref))
        assert kkt_violation(H, g, A, b, x, info.multipliers) <= 1e-8


def test_qp_satisfies_kkt_on_random_28_constraint_problems():
    rng = np.random.default_rng(2)
    for _ in range(100):
        H, A, x0 = random_spd(rng), rng.normal(size=(28, 7)), rng.normal(size=7)
        b = A @ x0 - np.abs(rng.normal(size=28)) * rng.integers(0, 2, size=28)
        g = 5.0 * rng.normal(size=7)
        x, info = solve_qp(H, g, A, b)
        assert info.status == "optimal"
        assert kkt_violation(H, g, A, b, x, info.multipliers) <= 1e-8


def test_qp_handles_dependent_and_overdetermined_active_constraints():
    """Degenerate optima: an active row duplicated (scaled), active rows' combinations weakly active, or more
    than n constraints through x*; from a cold start and from a random (mostly wrong) warm start."""
    rng = np.random.default_rng(10)
    for t in range(90):
        m, k = int(rng.integers(11, 29)), int(rng.integers(1, 8))
        H, A, x_star = random_spd(rng), rng.normal(size=(m, 7)), rng.normal(size=7)
        lam = np.where(np.arange(m) < k, rng.uniform(0.1, 5.0, m), 0.0)
        slack = np.where(np.arange(m) < k, 0.0, rng.uniform(0.1, 2.0, m))
        if t % 3 == 0:
            A[k] = A[0] * rng.uniform(0.5, 2.0)
        elif t % 3 == 1:
            A[k:k + 2] = rng.normal(size=(2, k)) @ A[:k]
        slack[k:k + 1 + t % 3] = 0.0
        b, g = A @ x_star - slack, A.T @ lam - H @ x_star
        for active in (None, rng.permutation(m)[:9]):
            x, info = solve_qp(H, g, A, b, active=active)
            assert info.status == "optimal" and np.abs(x - x_star).max() <= 1e-8 * max(1.0, np.abs(x_star).max())
            assert kkt_violation(H, g, A, b, x, info.multipliers) <= 1e-8


def test_qp_warm_start_gives_same_answer_in_fewer_iterations():
    rng = np.random.default_rng(3)
    for _ in range(50):
        H, g, A, b, x_star, k = constructed_qp(rng)
        x_cold, cold = solve_qp(H, g, A, b)
        x_warm, warm = solve_qp(H, g, A, b, active=cold.active)
        assert np.abs(x_warm - x_cold).max() <= 1e-10 * max(1.0, np.abs(x_cold).max())
        assert warm.iterations == 0 and (cold.iterations >= len(cold.active))
        if len(cold.active):
            assert warm.iterations < cold.iterations
        # a wrong warm start (extra inactive constraints, shuffled) still ends at the optimum
        wrong = rng.permutation(np.concatenate([cold.active, rng.integers(0, len(b), 3)]))
        x_wrong, info = solve_qp(H, g, A, b, active=wrong)
        assert info.status == "optimal" and np.abs(x_wrong - x_star).max() <= 1e-8 * max(1.0, np.abs(x_star).max())


def test_qp_reports_infeasible_without_raising():
    H, g = np.eye(2), np.zeros(2)
    cases = [(np.array([[1.0, 0.0], [-1.0, 0.0]]), np.array([1.0, 0.0])),       # x1 >= 1 and x1 <= 0
             (np.array([[0.0, 0.0]]), np.array([1.0])),                          # 0 >= 1
             (np.array([[1.0, 1.0], [-1.0, 0.0], [0.0, -1.0]]), np.array([3.0, -1.0, -1.0]))]
    for A, b in cases:
        x, info = solve_qp(H, g, A, b)
        assert info.status == "infeasible" and np.isfinite(x).all()


def test_qp_infeasibility_verdict_matches_scipy_linprog():
    from scipy.optimize import linprog
    rng = np.random.default_rng(12)
    verdicts = []
    for _ in range(200):
        n, m = int(rng.integers(1, 8)), int(rng.integers(1, 29))
        H, g = random_spd(rng, n), rng.normal(size=n)
        A = rng.normal(size=(m, n)) * 10.0 ** rng.uniform(-2, 2, (m, 1))
        if m > 2 and rng.random() < 0.3:
            A[1] = -A[0] * rng.uniform(0.5, 2.0)               # opposite half-spaces
        b = rng.normal(size=m) * 10.0 ** rng.uniform(-1, 1)
        x, info = solve_qp(H, g, A, b, active=rng.integers(0, m, size=int(rng.integers(0, m + 1))))
        feasible = linprog(np.zeros(n), A_ub=-A, b_ub=-b, bounds=[(None, None)] * n, method="highs").status == 0
        assert info.status == ("optimal" if feasible else "infeasible") and np.isfinite(x).all()
        verdicts.append(feasible)
    assert 0.2 < np.mean(verdicts) < 0.8                                  # both verdicts are exercised


def test_qp_rejects_bad_input_with_named_value_error():
    H, g, A, b = np.eye(3), np.zeros(3), np.ones((2, 3)), np.zeros(2)
    bad = [((np.eye(2), g, A, b), "H"), ((H, g, np.ones((2, 4)), b), "A"), ((H, g, A, np.zeros((2, 1))), "b"),
           ((H, np.array([0.0, np.nan, 0.0]), A, b), "g"), ((np.diag([1.0, -1.0, 1.0]), g, A, b), "H"),
           ((H + np.triu(np.ones((3, 3)), 1), g, A, b), "H"), ((np.zeros((3, 3)), g, A, b), "H")]
    for args, name in bad:
        with pytest.raises(ValueError, match=f"^{name}:"):
            solve_qp(*args)
    with pytest.raises(ValueError, match="^active:"):
        solve_qp(H, g, A, b, active=[5])


def test_qp_rejects_non_finite_entries_of_each_argument():
    H, g, A, b = np.eye(3), np.zeros(3), np.ones((2, 3)), np.zeros(2)
    for bad in (np.nan, np.inf, -np.inf):
        for name, i in (("H", 0), ("g", 1), ("A", 2), ("b", 3)):
            args = [H.copy(), g.copy(), A.copy(), b.copy()]
            args[i].flat[1] = bad                     # off the diagonal of H: its mirror entry stays finite
            with pytest.raises(ValueError, match=f"^{name}: expected finite values"):
                solve_qp(*args)
        Hd = H.copy()
        Hd[2, 2] = bad
        with pytest.raises(ValueError, match="^H: expected finite values"):
            solve_qp(Hd, g, A, b)


def test_qp_without_constraints_returns_the_unconstrained_minimiser():
    rng = np.random.default_rng(13)
    for _ in range(20):
        H, g = random_spd(rng), rng.normal(size=7)
        x, info = solve_qp(H, g, np.zeros((0, 7)), np.zeros(0))
        assert info.status == "optimal" and len(info.active) == 0
        assert np.allclose(x, -np.linalg.solve(H, g), atol=1e-10) and info.residual <= 1e-10


def test_cpic_reexports_the_solver_under_its_public_name():
    """An outside check calls cpic.solve_qp(H, g, A, b, active=None) -> (x, info)."""
    rng = np.random.default_rng(14)
    H, g, A, b, x_star, _ = constructed_qp(rng)
    x, info = cpic.solve_qp(H, g, A, b, active=None)
    assert cpic.solve_qp is solve_qp and info.status == "optimal" and np.allclose(x, x_star, atol=1e-8)


def test_qp_matches_quadprog_in_x_and_active_set_on_random_problems():
    """300 random 7-variable problems with 4-28 constraints (the benchmark's): x and the active set agree with
    quadprog's; active = multiplier > 1e-9 on both sides (weakly active rows may differ between the methods)."""
    pytest.importorskip("quadprog")
    rng = np.random.default_rng(17)
    sizes = []
    for _ in range(300):
        H, g, A, b = random_problem(rng)
        x, info = solve_qp(H, g, A, b)
        x_ref, active_ref = quadprog_solve(H, g, A, b)
        assert info.status == "optimal" and np.abs(x - x_ref).max() <= 1e-9 * max(1.0, np.abs(x_ref).max())
        lam_ref = np.linalg.lstsq(A[active_ref].T, H @ x_ref + g, rcond=None)[0]   # H x + g = A_W^T lambda
        strong_ref = set(active_ref[lam_ref > 1e-9].tolist())
        assert set(np.flatnonzero(info.multipliers > 1e-9).tolist()) == strong_ref
        sizes.append(len(strong_ref))
    assert np.mean(np.array(sizes) >= 4) > 0.5                         # most optima have several active rows


def test_dual_active_set_takes_any_factor_of_the_inverse_hessian():
    """The loop's entry point: B = L^-1 (H = L L^T) and B = chol(H^-1)^T (what CPIC passes) give solve_qp's answer,
    cold and warm started."""
    rng = np.random.default_rng(18)
    for _ in range(50):
        H, g, A, b, x_star, _ = constructed_qp(rng)
        x_ref, info = solve_qp(H, g, A, b)
        for B in (np.linalg.inv(np.linalg.cholesky(H)), np.linalg.cholesky(np.linalg.inv(H)).T):
            for warm in ([], info.active.tolist()):
                x, status, it, active, mult = dual_active_set(B, g, A, b, warm, 100)
                assert status == "optimal" and np.abs(x - x_ref).max() <= 1e-9 * max(1.0, np.abs(x_ref).max())
                assert sorted(active) == sorted(info.active.tolist()) and np.allclose(mult, info.multipliers)


def test_dual_active_set_reports_broken_numbers_without_raising():
    """Unchecked inputs with NaN or inf (the 1 kHz loop's, e.g. from an absurd velocity): a status other than
    "optimal", never an exception."""
    rng = np.random.default_rng(19)
    for i in range(60):
        H, g, A, b, _, _ = constructed_qp(rng)
        B = np.linalg.inv(np.linalg.cholesky(H))
        args = [B, g, A, b]
        which = i % 4
        args[which] = args[which].copy()
        args[which].flat[int(rng.integers(args[which].size))] = (np.nan, np.inf, -np.inf)[i % 3]
        with np.errstate(all="ignore"):
            x, status, it, active, mult = dual_active_set(*args, active=list(range(i % 3)), max_iterations=100)
        if which != 3 or i % 3 == 0:                                  # b_i = -inf is a harmless row; +inf is not
            assert status != "optimal", (which, i % 3)


def test_qp_never_reports_optimal_for_an_answer_that_violates_a_constraint():
    """Entries of +-1e300 in A, g or b overflow the arithmetic: every "optimal" answer must be finite and satisfy
    A x >= b up to rounding (1e-9 (1 + |b_i| + |a_i| |x|), evaluated without overflow). The first two optima,
    x = (1, 1e300), have multipliers near 1e600, beyond double precision: they must not be reported optimal."""
    H, big = np.eye(2), 1e300
    cases = [(np.array([[1.0, 0.0], [-big, 1.0]]), np.array([1.0, 0.0]), np.array([-big, 0.0])),
             (np.array([[1.0, 0.0], [-big, 1.0]]), np.array([1.0, 0.0]), np.array([big, big])),
             (np.array([[-big, 1.0]]), np.array([1.0]), np.array([-big, 0.0])),
             (np.array([[1.0, 1.0]]), np.array([1.0]), np.array([big, big])),
             (np.array([[1.0, 0.0], [0.0, 1.0]]), np.array([1.0, big]), np.zeros(2)),
             (np.array([[1.0, 0.0], [-big, 1.0]]), np.array([1.0, 0.0]), np.zeros(2))]
    verdicts = []
    for A, b, g in cases:
        with np.errstate(all="ignore"):
            x, info = solve_qp(H, g, A, b)
            scale = 1.0 + np.abs(b) + np.abs(A) @ np.abs(x)
            s = A @ x - b
        if info.status == "optimal":
            assert np.isfinite(x).all() and np.isfinite(scale).all() and np.isfinite(s).all()
            assert (s >= -1e-9 * scale).all(), (A, b, g, x)
        verdicts.append(info.status)
    assert "optimal" not in verdicts[:2] and "optimal" in verdicts    # the check is not vacuous


def test_qp_drop_steps_reach_the_enumerated_optimum():
    """Problems whose cold solve drops rows (partial steps: iterations > adds), the path whose rank-one downdate
    is read off the stored rows of -N*: the optimum equals the exhaustive active-set search's, KKT holds."""
    rng = np.random.default_rng(21)
    dropped = 0
    while dropped < 25:
        H, g, A, b = random_problem(rng, m_range=(6, 12))
        x, info = solve_qp(H, g, A, b)
        if info.iterations == len(info.active):
            continue
        dropped += 1
        x_ref = enumeration_reference(H, g, A, b)
        f_ref = objective(H, g, x_ref)
        assert info.status == "optimal" and abs(objective(H, g, x) - f_ref) <= 1e-9 * max(1.0, abs(f_ref))
        assert np.abs(x - x_ref).max() <= 1e-8 * max(1.0, np.abs(x_ref).max())
        assert kkt_violation(H, g, A, b, x, info.multipliers) <= 1e-8


def test_dual_active_set_from_inverse_matches_solve_qp_from_any_warm_start():
    """CPIC's entry point: H^-1 given; a right warm start is answered by one solve, a wrong or empty one falls
    back to the full method (on a Cholesky factor of H^-1); all give solve_qp's x and multipliers."""
    rng = np.random.default_rng(22)
    for _ in range(60):
        H, g, A, b = random_problem(rng)
        x_ref, info = solve_qp(H, g, A, b)
        Hinv = np.linalg.inv(H)
        for warm in ([], info.active.tolist(), rng.permutation(len(b))[:5].tolist()):
            x, status, it, active, mult = dual_active_set_from_inverse(0.5 * (Hinv + Hinv.T), g, A, b, warm, 200)
            assert status == "optimal" and np.abs(x - x_ref).max() <= 1e-9 * max(1.0, np.abs(x_ref).max())
            assert np.allclose(mult, info.multipliers, rtol=1e-7, atol=1e-9)
            assert kkt_violation(H, g, A, b, x, mult) <= 1e-8


def test_qp_matches_quadprog_with_zero_duplicate_and_rescaled_rows():
    """Rows of zero (0 >= b_i, b_i <= 0: inert), duplicated and rescaled (by 1e-3 .. 1e3) rows leave the optimum of
    the benchmark's problems unchanged: x equals quadprog's on the plain problem, cold and from a wrong warm start,
    and a zero row never carries a multiplier."""
    pytest.importorskip("quadprog")
    rng = np.random.default_rng(23)
    for _ in range(100):
        H, g, A, b = random_problem(rng)
        x_ref, _ = quadprog_solve(H, g, A, b)
        m = len(b)
        k = int(rng.integers(0, m))
        scale = 10.0 ** rng.uniform(-3, 3, m + 1)
        A2 = np.vstack([A, np.zeros((2, 7)), A[k]]) * np.concatenate([scale[:m], [1.0, 1.0], scale[m:]])[:, None]
        b2 = np.concatenate([b, [0.0, -1.0], [b[k]]]) * np.concatenate([scale[:m], [1.0, 1.0], scale[m:]])
        for active in (None, rng.permutation(m + 3)[:5]):
            x, info = solve_qp(H, g, A2, b2, active=active)
            assert info.status == "optimal" and np.abs(x - x_ref).max() <= 1e-9 * max(1.0, np.abs(x_ref).max())
            assert info.multipliers[m] == 0.0 and info.multipliers[m + 1] == 0.0
            assert kkt_violation(H, g, A2, b2, x, info.multipliers) <= 1e-7 * max(1.0, np.abs(info.multipliers).max())
