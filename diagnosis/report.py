"""The diagnosis as text, JSON and plots: the comparison table, the ranking and forward selection, the findings, and
what loading a log dropped and filled in."""
from __future__ import annotations

import numpy as np

from diagnosis.compare import Comparison
from diagnosis.findings import format_findings
from diagnosis.forward import DiagnoseConfig, Diagnosis


def _row(label, values, fmt="{:8.3f}", blank="       -"):
    """A table row; a NaN cell (nothing to compute there, the notes say why) prints as `blank`."""
    cell = lambda v: blank if isinstance(v, (float, np.floating)) and not np.isfinite(v) else fmt.format(v)  # noqa: E731
    return f"  {label:26s}" + "".join(cell(v) for v in values)


def _share(x) -> str:
    """A share of explained variance as a 9-wide percent; below -100 % it is no share: the effect made it worse."""
    return f"{100 * x:8.1f}%" if x >= -1 else "    worse"


def format_comparison(c: Comparison) -> str:
    """compare() as a table: joints across, error measures and regimes down."""
    n = len(c.rms)
    lines = [_row("per joint", [f"J{j + 1}" for j in range(n)], "{:>8s}"), _row("RMS error [Nm]", c.rms),
             _row("fit [%] (100 (1 - NRMSE))", c.fit, "{:8.1f}"), _row("mean error [Nm]", c.mean)]
    if c.fit_note:
        lines.append(f"    fit '-' on {', '.join(c.fit_note)}: {next(iter(c.fit_note.values()))}"
                     + (" (and alike)" if len(c.fit_note) > 1 else ""))
    lines.append("  RMS error by regime [Nm] (share of samples in brackets on the right; '-': the joint has no "
                 "sample in the regime):")
    for name, r in c.regimes.items():
        lines.append(_row(f"  {name}", r["rms"]) + f"   ({100 * np.mean(r['share']):.0f} %)")
    for name in ("dq > 0", "dq < 0"):
        lines.append(_row(f"  mean error, {name}", c.regimes[name]["mean"]))
    worst = "; ".join(f"{w['t0']:.2f}-{w['t1']:.2f} s (J{w['joint']} {w['rms']:.3f} Nm, {w['ratio']:.1f}x its RMS)"
                      for w in c.worst)
    return "\n".join(lines + [f"  worst segments: {worst}"])


def format_diagnosis(d: Diagnosis, config: DiagnoseConfig = DiagnoseConfig()) -> str:
    """diagnose() as the ranking table, the forward-selection steps and the fitted model."""
    n = len(d.rms)
    lines = [f"  held-out: 2-fold over {d.info['blocks']} interleaved blocks of {d.info['block_s']} s; significant = "
             f"(a) RMS of the summed error over all joints drops >= {100 * config.min_total_drop:.0f} % with t >= "
             f"{config.t_min} over blocks, (b) no joint's RMS rises >= {100 * config.max_rise:.0f} % with t >= "
             f"{config.t_min}, (c) RMS drop >= {100 * config.min_drop:.0f} % on a joint with t >= {config.t_min} "
             f"and >= {config.min_torque} Nm RMS explained",
             f"  {'rank':4s} {'effect':14s} {'params':>6s} {'explained':>9s}  {'joints':14s} held-out RMS after [Nm]",
             f"  {'':4s} {'':14s} {'':6s} {'total':>9s}  {'worse':14s} held-out RMS change [%] (negative = better)"]
    for i, r in enumerate(d.ranking):
        joints, worse = " ".join(map(str, r["joints"])) or "-", " ".join(map(str, r["worse"])) or "-"
        lines.append(f"  {i + 1:4d} {r['effect']:14s} {r['k']:6d} {_share(r['explained'])}  {joints:14s} "
                     + " ".join(f"{v:.3f}" for v in r["rms_after"]))
        lines.append(f"  {'':4s} {'':14s} {'':6s} {100 * r['total_change']:+8.1f}%  {worse:14s} "
                     + " ".join(f"{100 * v:+.1f}" for v in r["rms_change"]))
    lines.append(f"  forward selection, held-out RMS per joint [Nm], J1..J{n}:")
    lines.append("    start       " + " ".join(f"{v:.3f}" for v in d.rms))
    for st in d.steps:
        lines.append(f"    + {st['effect']:9s} " + " ".join(f"{v:.3f}" for v in st["rms_after"])
                     + f"   ({100 * st['explained']:.1f} % of the rest explained, joints {st['joints']})")
    lines.append(f"    stop: {d.stop}")
    if not d.steps and not any(r["significant"] for r in d.ranking):
        lines.append("  nothing missing: no candidate effect explains a significant part of the residual")
    lines += format_findings(d.findings)
    lines += ["  model after selection (fitted on the whole log):", d.model.report()]
    return "\n".join(lines)


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return [_jsonable(v) for v in x.tolist()]
    if isinstance(x, (float, np.floating)):
        return None if not np.isfinite(x) else round(float(x), 6)
    return x.item() if isinstance(x, np.generic) else x


def cleaning_summary(info: dict) -> str:
    """One sentence of what loading dropped and filled in (info of prepare): malformed, NaN and stale rows dropped,
    cycles missing from the time stamps, all filled in by interpolation onto the uniform grid."""
    lines = info.get("bad_lines") or []
    where = f" (file lines {', '.join(map(str, lines))}{' ...' if info.get('bad_rows', 0) > len(lines) else ''})" \
        if lines else ""
    text = (f"rows dropped: {info.get('bad_rows', 0)} malformed{where}, {info.get('nan_rows', 0)} with NaN/inf, "
            f"{info.get('stale_rows', 0)} stale repeats; ")
    if info.get("gaps"):
        text += (f"{info['missing_cycles']} missing cycles in {info['gaps']} gaps of the time stamps (longest "
                 f"{1e3 * info['longest_gap']:.0f} ms at t = {info['gap_at']:.3f} s)")
    else:
        text += "no gaps in the time stamps"
    filled = "the dropped rows and missing cycles" if info.get("gaps") else "the dropped rows"
    return text + (f"; {filled} filled in by linear interpolation" if info.get("resampled") else "")
