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


def print_table(title: str, header, rows, note: str = ""):
    """A labelled table: the title, a header (columns' names with units), one line per row (the first column left-
    aligned, the others right-aligned, values already rounded to strings), and a sentence on how to read it."""
    rows = [[str(v) for v in r] for r in rows]
    widths = [max(len(str(h)), *(len(r[i]) for r in rows)) for i, h in enumerate(header)]
    line = lambda cells: "  " + "  ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in
                                           enumerate(zip(cells, widths)))
    print(title)
    print(line([str(h) for h in header]))
    for r in rows:
        print(line(r))
    if note:
        print(f"  {note}")
