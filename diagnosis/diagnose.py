"""Compare a robot model with a log, find the missing physical effect, add it, watch the error fall (the
nominal Eq. 1 model and the effects of effects.py; held-out forward selection). CLI: `python rme.py diagnose LOG
[--add EFFECT ...] [--json] [--plot FILE]`; `python sim.py hidden-effect` for the demo."""
from __future__ import annotations

import argparse
import importlib.util
import json
import sys
from dataclasses import dataclass, field

import numpy as np

from dynamics import Robot
from diagnosis.effect_model import Model
from diagnosis.effects import EffectConfig
from diagnosis.findings import collect, format_findings
from diagnosis.heldout import Selection, blocks_of, rank
from diagnosis.logs import Log, LogConfig, cleaning_summary, load_log


@dataclass(frozen=True)
class CompareConfig:
    """Regimes and segments in which compare() splits the error."""
    v_rest: float = 0.02        # rad/s, |dq| below: at rest (20x the 1e-3 rad/s velocity noise of realistic())
    v_sign: float = 0.1         # rad/s, |dq| above: a clear sign of dq (the 0.05 s filter x 2 rad/s^2 smears 0.1 rad/s)
    v_fast: float = 0.5         # rad/s, |dq| above: fast (a quarter of the Panda's 2.2-2.6 rad/s limits)
    a_acc: float = 2.0          # rad/s^2, |ddq| above: accelerating (10-25 % of the 7.5-20 rad/s^2 limits)
    segment: float = 0.5        # s, length of the time segments ranked by error
    worst: int = 3              # how many worst segments to report


@dataclass(frozen=True)
class DiagnoseConfig:
    """Held-out forward selection (see diagnose)."""
    block: float = 0.5          # s, interleaved hold-out blocks: >> the 0.05 s filter window, << the motion's periods
    min_drop: float = 0.10      # an effect must cut the held-out RMS of some joint by >= 10 % ...
    t_min: float = 3.0          # ... with t >= 3 for the per-block log error ratios (one-sided p < 0.01) ...
    min_torque: float = 0.01    # Nm, ... explaining >= 0.01 Nm RMS there: half the Panda's 0.02 Nm torque resolution
    min_total_drop: float = 0.01  # and cut the RMS of the summed held-out error by >= 1 % with t >= t_min (not 10 %:
                                  # an effect of a wrist joint is small beside the shoulders' error in the sum) ...
    max_rise: float = 0.05      # ... and raise no joint's held-out RMS by >= 5 % with t >= t_min
    max_add: int = 6            # forward-selection steps at most
    min_blocks: int = 6         # fewer hold-out blocks: the log is too short to diagnose


@dataclass
class Comparison:
    """compare() output: per joint (n,) rms [Nm], fit [%] (100 (1 - NRMSE) of tau_J; NaN where undefined, fit_note
    says why), mean [Nm]; regimes: name -> {rms, mean, share} (n,) each (NaN where a joint has no sample in the
    regime); worst: [{t0, t1, rms, joint}]; residual (T, n) = tau_J - model; t (T,)."""
    rms: np.ndarray
    fit: np.ndarray
    mean: np.ndarray
    regimes: dict
    worst: list
    residual: np.ndarray
    t: np.ndarray
    fit_note: dict = field(default_factory=dict)


def fit_percent(y, r):
    """Per joint (n,): 100 (1 - RMS(r) / std(y)), the share of the torque's variation y (T, n) the model explains
    given its residual r (T, n), and {joint: why} where it is no share: tau_J varies by less than the model's error
    (a static log), so 1 - NRMSE would be a large negative number that says nothing (NaN there)."""
    rms, spread = np.sqrt(np.mean(r ** 2, axis=0)), y.std(axis=0)
    fit, notes = np.full(len(rms), np.nan), {}
    for j in range(len(rms)):
        if spread[j] > rms[j]:
            fit[j] = 100 * (1 - rms[j] / spread[j])
        else:
            notes[f"J{j + 1}"] = (f"tau_J varies by {spread[j]:.3f} Nm RMS, less than the {rms[j]:.3f} Nm error: "
                                  "nothing for a share to explain")
    return fit, notes


def compare(model: Model, log, config: CompareConfig = CompareConfig()) -> Comparison:
    """Where the model fails on the log: per-joint RMS and fit, the worst time segments, the error by regime."""
    s = model.signals(log)
    y = s.measured()
    r = y - model.predict(s)
    rms = np.sqrt(np.mean(r ** 2, axis=0))
    fit, notes = fit_percent(y, r)
    adq, addq = np.abs(s.dq), np.abs(s.ddq)
    masks = {"at rest": adq < config.v_rest, "moving": adq >= config.v_rest, "fast": adq >= config.v_fast,
             "accelerating": addq >= config.a_acc, "dq > 0": s.dq >= config.v_sign, "dq < 0": s.dq <= -config.v_sign}
    regimes = {}
    for name, m in masks.items():
        cnt = m.sum(axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            regimes[name] = {"rms": np.sqrt((r ** 2 * m).sum(axis=0) / cnt), "mean": (r * m).sum(axis=0) / cnt,
                             "share": cnt / len(r)}
    seg = blocks_of(s.t, config.segment)
    seg_rms = np.sqrt(np.stack([np.mean(r[seg == b] ** 2, axis=0) for b in range(seg.max() + 1)]))   # (S, n)
    score = (seg_rms / np.maximum(rms, 1e-12)).mean(axis=1)          # each joint relative to its own RMS
    worst = []
    for b in np.argsort(-score)[:config.worst]:
        rows = np.flatnonzero(seg == b)
        j = int(np.argmax(seg_rms[b] / np.maximum(rms, 1e-12)))
        worst.append({"t0": float(s.t[rows[0]]), "t1": float(s.t[rows[-1]]), "joint": j + 1,
                      "rms": float(seg_rms[b, j]), "ratio": float(score[b])})
    return Comparison(rms, fit, r.mean(axis=0), regimes, worst, r, s.t, notes)


@dataclass
class Diagnosis:
    """diagnose() output. rms (n,): held-out RMS of the input model; ranking: the first round's candidates, best first,
    each {effect, k, explained, explained_joints, joints (improved), worse (joints made worse), significant, rms_after,
    rms_change (n,) = rms_after / rms_before - 1, total_change, total_t, drop, t, params}; steps: the forward
    selection, each {effect, rms_before, rms_after, rms_change, explained, joints, params}; selected: effect names;
    model: the input model plus the selected effects, fitted on the whole log; stop: why selection ended; findings:
    what the data asked of an effect beyond its physical constraints, [{effect, text, joints, violations}]."""
    rms: np.ndarray
    ranking: list
    steps: list
    selected: list
    model: Model
    stop: str
    samples: int = 0
    info: dict = field(default_factory=dict)
    findings: list = field(default_factory=list)


def diagnose(model: Model, log, candidates=None, config: DiagnoseConfig = DiagnoseConfig()) -> Diagnosis:
    """Rank the candidate effects (default: the library's effects not in the model) by how much of the model's
    residual each explains on held-out data, then add the best and repeat while the gain is significant.

    Hold-out: the log is cut into interleaved blocks of config.block seconds; each effect set is fitted on the even
    blocks and scored on the odd ones, and vice versa (2-fold), so both halves see the same motions and an effect
    cannot win by fitting noise. Significant (heldout.verdict), all three of: (a) the held-out error falls overall: the
    RMS of the summed SSE over all joints drops by >= min_total_drop with t >= t_min for the per-block log ratios of the
    totals; (b) no joint gets worse: no joint's held-out RMS rises by >= max_rise with t >= t_min for its per-block
    log ratios log(sse_after / sse_before); (c) on at least one joint the held-out RMS drops by >= min_drop AND the
    per-block log error ratios log(sse_before / sse_after) have t >= t_min AND the torque explained there is
    >= min_torque RMS. So the selection cannot trade one joint's error for another's. Parsimony: a significant
    candidate with fewer parameters is preferred unless the better-scoring one is significantly better than it on some
    joint by rule (c) (e.g. coulomb over sigmoid, payload over rigid_payload on a quasi-static log). Every fit keeps
    to the effects' physical constraints; where the unconstrained fit of a candidate breaks them and scores
    significantly better for it, that is a finding (findings.py). Candidates: Effect objects or library names."""
    s = model.signals(log)
    y = s.measured() - model.torque(s, [e for e in model.effects if e.name in model.fixed])
    block = blocks_of(s.t, config.block)
    if block.max() + 1 < config.min_blocks:
        raise ValueError(f"log: too short to diagnose: {block.max() + 1} hold-out blocks of {config.block} s, "
                         f"expected at least {config.min_blocks} ({config.min_blocks * config.block} s)")
    cands = [model.effect(c) for c in candidates] if candidates is not None else \
        [e for e in model.library.values() if e.name not in model.names]
    clash = [c.name for c in cands if c.name in model.names]
    if clash:
        raise ValueError(f"candidates: expected effects not yet in the model, found {clash} (in {model.names})")
    sel = Selection(s, y, block, config)
    for e in model.free:
        sel.extend(e)
    rms0 = np.sqrt(sel.sse.sum(axis=0) / len(s))
    ranking, steps, stop, asked = _forward_selection(sel, cands, config)
    final = model.copy()
    for st in steps:
        final.add(st["obj"])
    if final.free:
        final.fit(s)
    selected = [st["effect"] for st in steps]
    return Diagnosis(rms0, ranking, steps, selected, final, stop, len(s),
                     {"blocks": int(block.max() + 1), "block_s": config.block}, collect(asked, selected))


def _forward_selection(sel: Selection, cands: list, config: DiagnoseConfig):
    """Add the top-ranked significant candidate while there is one: (first round's ranking, steps, stop reason, what
    the data asked of each effect beyond its constraints when it was last tried {effect: asked})."""
    N, ranking, steps, asked = len(sel.s), None, [], {}
    for _ in range(config.max_add):
        if not cands:
            return ranking or [], steps, "no candidate effects left", asked
        order = rank([sel.try_effect(c) for c in cands], config, N)
        for r in order:
            asked.pop(r["effect"], None)
            if r["asked"]:
                asked[r["effect"]] = r["asked"]
        ranking = order if ranking is None else ranking
        top = order[0]
        if not top["significant"]:
            j = int(np.argmax(top["drop"]))
            stop = (f"no remaining effect is significant (best: {top['effect']}, held-out RMS drop "
                    f"{100 * top['drop'][j]:.1f} % on J{j + 1}, t = {top['t'][j]:.1f}; total "
                    f"{100 * top['total_change']:+.1f} %, t = {top['total_t']:.1f}; "
                    f"worse on joints {top['worse'] or '-'})")
            return ranking, steps, stop, asked
        steps.append(dict(effect=top["effect"], obj=top["obj"], rms_before=np.sqrt(sel.sse.sum(axis=0) / N),
                          rms_after=top["rms_after"], rms_change=top["rms_change"], explained=top["explained"],
                          joints=top["joints"], params=top["params"]))
        sel.accept(top)
        cands = [c for c in cands if c.name != top["effect"]]
    return ranking, steps, f"stopped after max_add = {config.max_add} steps", asked


def heldout_rms(model: Model, log, config: DiagnoseConfig = DiagnoseConfig()) -> np.ndarray:
    """Per-joint RMS (n,) of the model's residual on held-out blocks (its free effects refitted per fold)."""
    s = model.signals(log)
    y = s.measured() - model.torque(s, [e for e in model.effects if e.name in model.fixed])
    sel = Selection(s, y, blocks_of(s.t, config.block), config)
    for e in model.free:
        sel.extend(e)
    return np.sqrt(sel.sse.sum(axis=0) / len(s))


# --- text --------------------------------------------------------------------------------------------
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
    if not d.steps:
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


# --- CLI ---------------------------------------------------------------------------------------------
def main(argv=None, prog: str = "rme.py diagnose") -> int:
    """`diagnose LOG [--add EFFECT ...] [--json] [--plot FILE]`: compare -> diagnose -> (add -> compare). Returns the
    exit status (0 ok, 2 bad input); prog names the command in --help (e.g. "rme.py diagnose")."""
    names = sorted(Model(Robot.panda()).library)
    p = argparse.ArgumentParser(prog=prog, description="Compare the nominal model with a robot log, rank the "
                                "missing physical effects on held-out data, add them and watch the error fall.")
    p.add_argument("log", nargs="?", help=".npz (t, q, dq, [ddq], tau_J and/or tau_ext) or libfranka-style .csv")
    p.add_argument("--add", nargs="+", default=[], metavar="EFFECT", choices=names + ["pose_bias", "auto"],
                   help=f"effects to add and fit ('auto': the ones diagnose selects); one of {', '.join(names)}")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of tables")
    p.add_argument("--plot", metavar="FILE", help="save residual-over-time and residual-vs-signal plots (matplotlib)")
    p.add_argument("--model", default="nominal", choices=("nominal", "static"),
                   help="starting model: nominal = gravity + motion (Eq. 1); static = gravity only (RME's)")
    p.add_argument("--drop-nan", action="store_true", help="drop rows with NaN/inf (their count is reported)")
    p.add_argument("--xml", metavar="ARM.xml", help="the arm's MJCF (default: the project's Panda)")
    p.add_argument("--ee", default="ee", metavar="SITE", help="the end-effector site in --xml (default: ee)")
    p.add_argument("--bias-map", action="store_true", help="offer pose_bias, the per-joint map of the load-free "
                   "torque over the pose (opt-in: it absorbs any static error); fit it on a log of still holds")
    p.add_argument("--save", metavar="MODEL.json", help="save the model after --add (Model.load reads it; "
                   "RME(correction=Model.load(path)) uses it)")
    args = p.parse_args(argv)
    if args.log is None:
        p.error("a LOG file is needed")
    if args.plot and importlib.util.find_spec("matplotlib") is None:
        print("error: --plot needs matplotlib, which is not installed (pip install matplotlib)", file=sys.stderr)
        return 2
    if args.save and not args.add:
        p.error("--save needs --add (the effects to fit and save)")
    try:
        robot = Robot.from_xml(args.xml, ee=args.ee) if args.xml else Robot.panda()
        log = load_log(args.log, LogConfig(drop_nan=args.drop_nan))
        if log.n != robot.n:
            raise ValueError(f"log: {log.n} joints, expected {robot.n} like the arm ({args.xml or 'the Panda'})")
        bias_map = args.bias_map or "pose_bias" in args.add
        out = run(log, args.add, args.model, robot, EffectConfig(bias_joints=robot.n) if bias_map else EffectConfig())
        if args.save:
            out["added"].save(args.save)
    except ValueError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    if args.plot:
        plot(args.plot, out)
    if args.json:
        print(json.dumps(_jsonable(out["json"])))
    else:
        print(out["text"])
    return 0


def run(log: Log, add=(), start: str = "nominal", robot: Robot | None = None, config=EffectConfig()) -> dict:
    """compare -> diagnose -> add -> compare on a loaded log; the text report, the JSON object and the pieces."""
    robot = robot or Robot.panda()
    model = Model.nominal(robot, config) if start == "nominal" else Model.static(robot, config)
    s = model.signals(log)                         # the log's rigid-body terms, computed once
    before = compare(model, s)
    d = diagnose(model, s)
    i = log.info
    text = [f"log {i.get('source')}: {len(log)} samples, {log.t[-1] - log.t[0]:.2f} s at dt = {i.get('dt', 0):.4g} s; "
            f"{cleaning_summary(i)}; filter: {i.get('filter')}",
            f"compare: {start} model ({' + '.join(model.names)}), residual = tau_J - model = -tau_ext (paper sign)",
            format_comparison(before), "diagnose:", format_diagnosis(d)]
    js = {"log": i.get("source"), "samples": len(log), "stale_rows": i.get("stale_rows"), "nan_rows": i.get("nan_rows"),
          "bad_rows": i.get("bad_rows", 0), "gaps": i.get("gaps", 0), "missing_cycles": i.get("missing_cycles", 0),
          "longest_gap_s": i.get("longest_gap", 0.0),
          "model": model.names, "rms": before.rms, "fit_percent": before.fit, "fit_undefined": before.fit_note,
          "rms_heldout": d.rms,
          "ranking": [{"effect": r["effect"], "explained": r["explained"], "joints": r["joints"],
                       "significant": r["significant"], "rms_after": r["rms_after"], "worse_joints": r["worse"],
                       "rms_change_percent": 100 * r["rms_change"], "total_change_percent": 100 * r["total_change"]}
                      for r in d.ranking],
          "selected": d.selected, "stop": d.stop, "findings": d.findings}
    out = {"model": model, "before": before, "diagnosis": d, "log": log}
    if add:
        added = model.copy()
        for name in (d.selected if "auto" in add else add):
            added.add(name)
        added.fit(s)
        after, held = compare(added, s), heldout_rms(added, s)
        text += [f"after adding {', '.join(added.names[len(model.names):]) or 'nothing'} (fitted on the whole log):"]
        text += [] if "auto" in add else [added.report()]
        text += [format_comparison(after),
                 "  held-out RMS [Nm]  " + " ".join(f"{v:.3f}" for v in held)]
        js["after"] = {"effects": added.names, "rms": after.rms, "fit_percent": after.fit,
                       "fit_undefined": after.fit_note, "rms_heldout": held,
                       "params": {e.name: added.params[e.name] for e in added.free},
                       "nonlinear": {e.name: added.nl[e.name] for e in added.free if e.name in added.nl},
                       "held_to_constraints": {k: [[lbl, v] for lbl, v in vs] for k, vs in added.violations.items()}}
        out.update(added=added, after=after)
    out.update(text="\n".join(text), json=js)
    return out


def plot(path, out: dict):
    """Residual of the starting model over time per joint (left), and on the right the residual left for the top
    effect (every other selected effect removed) against the signal that effect depends on, with its fitted torque."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    log, r = out["log"], out["before"].residual
    n = r.shape[1]
    fig, ax = plt.subplots(n, 2, figsize=(11, 1.6 * n), squeeze=False)
    top = _top_effect(out)
    step = max(1, len(r) // 4000)
    for j in range(n):
        ax[j, 0].plot(log.t, r[:, j], lw=0.6)
        ax[j, 0].set_ylabel(f"J{j + 1} [Nm]")
        if top is not None:
            x = top["x"][::step, j]
            ax[j, 1].plot(x, top["residual"][::step, j], ".", ms=1, label="residual")
            ax[j, 1].plot(x, top["fitted"][::step, j], ".", ms=1, label=f"fitted {top['name']}")
    ax[0, 0].set_title("residual tau_J - model over time")
    ax[-1, 0].set_xlabel("t [s]")
    if top is not None:
        ax[0, 1].set_title(f"residual left for '{top['name']}' vs what it depends on")
        ax[-1, 1].set_xlabel(top["xlabel"])
        ax[0, 1].legend(loc="upper right", markerscale=8, fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _top_effect(out: dict):
    """The first selected (else best-ranked) effect: its fitted torque, the residual without it, its signal."""
    d, log = out["diagnosis"], out["log"]
    name = d.selected[0] if d.selected else (d.ranking[0]["effect"] if d.ranking else None)
    if name is None:
        return None
    if name in d.model.names:
        m = d.model
    else:
        m = out["model"].copy().add(d.ranking[0]["obj"])
        m.fit(log)
    e = next(e for e in m.effects if e.name == name)
    s = m.signals(log)
    fitted = m.torque(s, [e])
    signals = {"q": (log.q, "q [rad]"), "dq": (log.dq, "dq [rad/s]"), "ddq": (log.ddq, "ddq [rad/s^2]"),
               "t": (np.broadcast_to(log.t[:, None], fitted.shape), "t [s]")}
    x, xlabel = signals.get(e.signal, (fitted, "its torque [Nm]"))
    return {"name": name, "fitted": fitted, "residual": m.residual(s) + fitted, "x": x, "xlabel": xlabel}


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
