"""Speed of qp.solve_qp against quadprog (PyPI quadprog 0.1.14: Turlach's Fortran implementation of the same
Goldfarb-Idnani dual method) on random strictly convex QPs of the CPIC's size: 7 variables, 4-28 inequality
constraints. `python -m experiments.qp_bench`; needs `pip install quadprog` (used only here and in tests/test_qp.py)."""
from __future__ import annotations

import time

import numpy as np

from qp import solve_qp


def random_problem(rng: np.random.Generator, n=7, m_range=(4, 28)):
    """(H (n, n) SPD, g (n,), A (m, n), b (m,)) with m uniform in m_range: strictly feasible (A x0 - b >= |N(0, 1)|)
    and g large enough that 4-7 constraints are active at most optima (seed 0: 1 % none, 77 % four or more)."""
    m = int(rng.integers(m_range[0], m_range[1] + 1))
    B = rng.normal(size=(n, n))
    H, A, x0 = B @ B.T + 0.1 * np.eye(n), rng.normal(size=(m, n)), rng.normal(size=n)
    b = A @ x0 - np.abs(rng.normal(size=m))
    return H, 5.0 * rng.normal(size=n), A, b


def quadprog_solve(H, g, A, b):
    """The same QP through quadprog: min 1/2 x^T G x - a^T x s.t. C^T x >= b -> (x (n,), active indices)."""
    import quadprog
    x, _, _, _, _, iact = quadprog.solve_qp(H, -g, A.T, b, 0)
    return x, np.sort(iact[iact > 0] - 1)


def qp_benchmark(seed=0, problems=300, repeats=20, show=True) -> dict:
    """Per problem the median of `repeats` interleaved calls of each solver [us]; over the problems their median and
    99th percentile, the median of the per-problem ratios solve_qp / quadprog, and the largest |x - x_quadprog|."""
    import importlib
    importlib.import_module("quadprog")               # fail early with ImportError when it is missing
    rng = np.random.default_rng(seed)
    ours, ref, worst = np.empty((problems, repeats)), np.empty((problems, repeats)), 0.0
    for i in range(problems):
        H, g, A, b = random_problem(rng)
        calls = ((ours, lambda: solve_qp(H, g, A, b)), (ref, lambda: quadprog_solve(H, g, A, b)))
        for k in range(repeats):
            for out, call in calls:                   # interleaved: both see the same machine load
                t0 = time.perf_counter()
                call()
                out[i, k] = 1e6 * (time.perf_counter() - t0)
        worst = max(worst, float(np.abs(solve_qp(H, g, A, b)[0] - quadprog_solve(H, g, A, b)[0]).max()))
    ours_us, ref_us = np.median(ours, axis=1), np.median(ref, axis=1)   # (problems,)
    result = {"problems": problems, "solve_qp_median_us": float(np.median(ours_us)),
              "solve_qp_p99_us": float(np.percentile(ours_us, 99)), "quadprog_median_us": float(np.median(ref_us)),
              "quadprog_p99_us": float(np.percentile(ref_us, 99)),
              "ratio_of_medians": float(np.median(ours_us) / np.median(ref_us)),
              "median_ratio": float(np.median(ours_us / ref_us)), "max_abs_x_difference": worst}
    if show:
        from experiments.timing_tools import print_table
        us = lambda v: f"{v:.1f}"
        print_table(f"solve_qp against quadprog on {problems} random QPs (7 variables, 4-28 constraints, seed {seed})",
                    ["solver", "median [us]", "p99 [us]"],
                    [["solve_qp (ours)", us(result["solve_qp_median_us"]), us(result["solve_qp_p99_us"])],
                     ["quadprog (Fortran)", us(result["quadprog_median_us"]), us(result["quadprog_p99_us"])]],
                    f"each problem's time is the median of {repeats} interleaved calls; solve_qp / quadprog: "
                    f"{result['median_ratio']:.2f} (median of the ratios); largest |x - x_quadprog| "
                    f"{result['max_abs_x_difference']:.1e} (the same optimum).")
    return result


if __name__ == "__main__":
    qp_benchmark()
