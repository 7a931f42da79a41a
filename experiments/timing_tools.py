"""Wall-time measurement shared by the benchmarks: medians (and percentiles where a deadline matters)."""
from __future__ import annotations

import time

import numpy as np


def times_us(fn, repeats=2000, warmup=20) -> np.ndarray:
    """Wall time of each of `repeats` calls of fn() in microseconds, after `warmup` calls."""
    for _ in range(warmup):
        fn()
    ts = np.empty(repeats)
    for i in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts[i] = time.perf_counter() - t0
    return ts * 1e6


def median_us(fn, repeats=2000):
    """Median wall time of fn() in microseconds over `repeats` calls (after 20 warm-up calls)."""
    return float(np.median(times_us(fn, repeats)))
