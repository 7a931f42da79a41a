"""Compare a robot model with a log, find the missing physical effect, add it, watch the error fall (the
nominal Eq. 1 model and the effects of effects.py; held-out forward selection). CLI: `python rme.py diagnose LOG
[--add EFFECT ...] [--json] [--plot FILE] [--save F]`; `python sim.py hidden-effect` for the demo."""
from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import json
import os
import sys


import numpy as np

from dynamics import Robot
from diagnosis.anomalies import AnomalyConfig, oscillation, steps
from diagnosis.compare import CompareConfig, Comparison, compare, fit_percent  # noqa: F401 (the package's API)
from diagnosis.effect_model import Model
from diagnosis.effects import EffectConfig, offset_bounds
from error_model import as_error_model
from diagnosis.forward import DiagnoseConfig, Diagnosis, diagnose, heldout_rms  # noqa: F401
from diagnosis.logs import Log, LogConfig, load_log
from diagnosis.figure import plot  # noqa: F401  (diagnose's figure; demos import it from here)
from diagnosis.report import _jsonable, cleaning_summary, format_comparison, format_diagnosis  # noqa: F401


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
    p.add_argument("--plot", metavar="FILE",
                   help="save the residual before and after each added effect and the per-joint RMS (matplotlib)")
    p.add_argument("--model", default="nominal", choices=("nominal", "static"),
                   help="starting model: nominal = gravity + motion (Eq. 1); static = gravity only (RME's)")
    p.add_argument("--drop-nan", action="store_true", help="drop rows with NaN/inf (their count is reported)")
    p.add_argument("--xml", metavar="ARM.xml", help="the arm's MJCF (default: the project's Panda)")
    p.add_argument("--ee", default="ee", metavar="SITE", help="the end-effector site in --xml (default: ee)")
    p.add_argument("--bias-map", action="store_true", help="offer pose_bias, the per-joint map of the load-free "
                   "torque over the pose (opt-in: it absorbs any static error); fit it on a log of still holds")
    p.add_argument("--save", metavar="MODEL.json", help="save the model after --add (Model.load reads it; "
                   "RME(correction=Model.load(path)) uses it); refused if a parameter is held at a bound")
    p.add_argument("--force", action="store_true", help="--save even a model with parameters held at their bounds")
    p.add_argument("--calibration", metavar="ROBOT.json", help="the robot's error model (`rme.py calibrate --save`): "
                   "each joint's offset bound from its static error at the log's poses (default: a real Panda's)")
    args = p.parse_args(argv)
    if args.log is None:
        p.error("a LOG file is needed")
    for flag, path in (("--save", args.save), ("--plot", args.plot)):
        folder = os.path.dirname(os.path.abspath(path)) if path else None
        if folder and not (os.path.isdir(folder) and os.access(folder, os.W_OK)):
            print(f"error: {flag}: expected a writable folder for {path!r}, found no such folder" if not
                  os.path.isdir(folder) else f"error: {flag}: the folder of {path!r} is not writable", file=sys.stderr)
            return 2
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
        config = EffectConfig(bias_joints=robot.n) if bias_map else EffectConfig()
        if args.calibration:
            config = calibrated_config(config, as_error_model(args.calibration, robot.n), robot, log)
        out = run(log, args.add, args.model, robot, config)
        if args.save:
            _save(out["added"], args.save, args.force)
        if args.plot:
            plot(args.plot, out)
    except (ValueError, OSError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(_jsonable(out["json"])))
    else:
        print(out["text"])
    return 0


def calibrated_config(config: EffectConfig, error_model, robot: Robot, log: Log, every: int = 50) -> EffectConfig:
    """config with each joint's offset bound from the robot's error model at the log's poses (effects.offset_bounds;
    the gravity torque of every `every`-th sample)."""
    if len(error_model.offset) != robot.n:
        raise ValueError(f"--calibration: expected an error model of {robot.n} joints like the arm, found "
                         f"{len(error_model.offset)} ({error_model.source})")
    gravity = np.array([robot.gravity(q) for q in log.q[::every]])
    links = None if error_model.links is None else \
        [robot.link_gravity_regressor(q, error_model.links) for q in log.q[::every]]
    bound, source = offset_bounds(error_model, gravity, links)
    return dataclasses.replace(config, offset_max=bound, offset_source=source)


def _save(model: Model, path: str, force: bool):
    """model.save(path), refused (ValueError) while a parameter is held at a bound of the fit (the unconstrained fit
    asked for more, or it sits at a bound), unless force."""
    held = {e: [lbl for lbl, _ in v] for e, v in model.violations.items() if v}
    for e, v in model.at_bounds.items():
        held.setdefault(e, []).extend(lbl for lbl, _ in v if lbl not in held.get(e, []))
    if held and not force:
        what = "; ".join(f"{e}: {', '.join(v)}" for e, v in held.items())
        raise ValueError(f"--save: the fit holds parameters at their physical bounds ({what}); the data asked for "
                         "more than a physical model gives (see the findings). Not saved; --force saves it anyway")
    model.save(path)


def run(log: Log, add=(), start: str = "nominal", robot: Robot | None = None, config=EffectConfig()) -> dict:
    """compare -> diagnose -> add -> compare on a loaded log, and what the log holds that is no effect (a vibration,
    a step: each segment between steps diagnosed too); the text report, the JSON object and the pieces."""
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
    off = model.library.get("offset")
    bounds = {} if off is None else {"offset": {"bound": off.bounds(robot.n)[1].tolist(), "source": off.source}}
    if off is not None:
        text.insert(2, "offset bounds [Nm]          " + " ".join(f"{x:.3f}" for x in bounds["offset"]["bound"])
                    + f"   ({off.source})")
    js = {"log": i.get("source"), "samples": len(log), "stale_rows": i.get("stale_rows"), "nan_rows": i.get("nan_rows"),
          "bad_rows": i.get("bad_rows", 0), "gaps": i.get("gaps", 0), "missing_cycles": i.get("missing_cycles", 0),
          "longest_gap_s": i.get("longest_gap", 0.0),
          "model": model.names, "rms": before.rms, "fit_percent": before.fit, "fit_undefined": before.fit_note,
          "rms_heldout": d.rms, "excitation": d.info.get("excitation"),
          "ranking": [{"effect": r["effect"], "explained": r["explained"], "joints": r["joints"],
                       "significant": r["significant"], "rms_after": r["rms_after"], "worse_joints": r["worse"],
                       "rms_change_percent": 100 * r["rms_change"], "total_change_percent": 100 * r["total_change"]}
                      for r in d.ranking],
          "selected": d.selected, "stop": d.stop, "findings": d.findings, "bounds": bounds}
    extra = log_findings(log, s, model, before, d)
    text += extra["text"]
    js.update(vibration=extra["vibration"], steps=extra["steps"], segments=extra["segments"])
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
                       "held_to_constraints": {k: [[lbl, v] for lbl, v in vs] for k, vs in added.violations.items()},
                       "at_bounds": {k: [[lbl, v] for lbl, v in vs] for k, vs in added.at_bounds.items()},
                       "not_identified": added.held}
        out.update(added=added, after=after)
    out.update(text="\n".join(text), json=js)
    return out


def log_findings(log: Log, s, model: Model, before, d, config: AnomalyConfig = AnomalyConfig()) -> dict:
    """The vibration of the residual left after selection, the steps of the starting model's residual the pose does
    not explain, and a diagnosis of each segment between steps: {vibration, steps, segments, text (lines)}."""
    robot, c = model.robot, model.config
    r = d.model.residual(s) if d.model.free else before.residual
    vib = oscillation(log.t, r, log.dq, config)
    reach = float(np.hypot(c.max_mass, c.max_mass * c.max_com))            # |phi| of the largest plausible load

    def pose_torque(qa, qb):
        dY = robot.payload_regressor(qb) - robot.payload_regressor(qa)
        return np.linalg.norm(dY, 2) * reach + c.scale_max / 20 * np.linalg.norm(robot.gravity(qb) - robot.gravity(qa))
    found = steps(log.t, before.residual, log.q, log.dq, pose_torque, config)
    text, segs = [], []
    if vib:
        text.append(f"  vibration: {vib['frequency']:.2f} Hz, damping ratio {vib['damping']:.3f} (decay "
                    f"{vib['decay']:.2f} 1/s), {vib['amplitude']:.3f} Nm on J{vib['joint']} from t = {vib['t0']:.2f} s "
                    f"(joints {vib['joints']}): a flexible or loosely held load vibrating at rest; no effect of the "
                    "model is a vibration, so it stays in the residual (hold still longer, or stiffen the grasp)")
    bounds = [log.t[0]] + [x["t"] for x in found] + [log.t[-1]]
    for x in found:
        text.append(f"  step: the static torque changes by {x['size']:.2f} Nm at t = {x['t']:.3f} s (the pose "
                    f"explains {100 * x['explained']:.0f} % of it{'; the arm moved meanwhile' if x['moved'] else ''}): "
                    "a load changed during the log; each segment is diagnosed on its own below")
    for t0, t1 in zip(bounds[:-1], bounds[1:]) if found else ():
        rows = (log.t >= t0 + config.guard) & (log.t <= t1 - config.guard)
        seg = {"t0": float(t0), "t1": float(t1)}
        try:
            part = diagnose(model, log.rows(rows))
            seg.update(selected=part.selected, stop=part.stop, model=part.model.report(),
                       findings=[f["text"] for f in part.findings])
            text.append(f"  segment {t0:.2f}-{t1:.2f} s: selected {part.selected or 'nothing'}; {part.stop}")
            text += [f"      {line.strip()}" for line in part.model.report().splitlines()[len(model.names):]]
        except ValueError as err:
            seg.update(error=str(err))
            text.append(f"  segment {t0:.2f}-{t1:.2f} s: not diagnosed: {err}")
        segs.append(seg)
    return {"vibration": vib, "steps": found, "segments": segs,
            "text": (["findings on the log (not effects of the model):"] + text) if text else []}


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
