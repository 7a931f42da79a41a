"""Identifying the tool on the flange end to end: the excitation motion on a backend (franka.py --identify), the fit
from a run or a log (python rme.py identify LOG), the report in the forms users type in and tool.json."""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys

import numpy as np

from diagnosis.logs import LogConfig, _interp, _stale_rows, missing_cycles, prepare, read_log
from dynamics import Robot
from motion.inertia import rigid_body
from motion.tool_forms import EE_IN_F, forms, make_tool, params_of_tool, save_tool, tool_of_params
from motion.tool_id import NAMES, ToolFit, fit_tool, truth_of
from motion.tool_motion import ExcitationController, MotionSettings
from motion.tool_storage import storage_check

NOISE_STREAM = 1000     # the --sim plant's sensor noise of run k is drawn from seed + NOISE_STREAM + k
LOG = LogConfig(sg_window=0.075)   # s: the widest Savitzky-Golay window (order 3) that passes the motion's content,
#   up to 3 Hz (twice the fastest oscillation, 1.5 Hz: products of two), within 0.1 % (0.999 at 3 Hz; 0.1 s: 0.997).
#   dq's noise differentiated into ddq falls with the window: on the realistic plant the 51-sample default leaves
#   0.04-0.07 rad/s^2 rms on the wrist, above the 0.02-0.10 rad/s^2 by which the tool and the reference run's ddq
#   differ, whose drive torques the fit partials out (docs/tool_identification.md)


def sim_payload(values, later=()) -> list:
    """SimBackend's payload events for --sim-tool M CX CY CZ IXX IYY IZZ (flange frame F, inertia about the CoM),
    checked (ValueError naming --sim-tool), in the ee frame: the tool from t = 0, then each later (t, m, r_ee) load
    as one body with the tool (the plant holds one body on the flange; pi adds about the same origin)."""
    tool = make_tool(values[0], values[1:4], np.diag(values[4:7]), "--sim-tool")
    events = [(0.0, tool)]
    for t, m, r in later:
        events.append((t, tool_of_params(params_of_tool(tool) + rigid_body(m, r))))
    R = EE_IN_F
    return [(t, b.mass, R.T @ b.com, R.T @ b.inertia @ R) for t, b in events]


def sim_backend(seed: int, tool=None, run: int = 0, preset: str = "realistic"):
    """robot.backends.SimBackend: the same simulated robot for every run of a seed (its link errors and sensor bias
    map drawn from default_rng(seed)), fresh sensor noise per run, with the Tool `tool` (flange frame) fixed."""
    from robot.backends import SimBackend
    R = EE_IN_F
    payload = [] if tool is None else [(0.0, tool.mass, R.T @ tool.com, R.T @ tool.inertia @ R)]
    backend = SimBackend(np.random.default_rng(seed), payload=payload, preset=preset)
    backend.plant.rng = np.random.default_rng(seed + NOISE_STREAM + run)
    return backend


def run_motion(backend, robot: Robot, run_loop, settings: MotionSettings = MotionSettings(), seconds=None,
               center=None):
    """The excitation from backend.initial.q about `center` (default: there; the tool run: the reference run's
    start, so both runs are the same motion) through robot.loop.run_loop (for `seconds`, default: all of it; a push
    ends it settings.stop_after after the push): (log arrays, summary, controller)."""
    controller = ExcitationController(robot, backend.initial.q, settings, center)
    seconds = controller.duration if seconds is None else seconds
    summary, log = run_loop(backend, robot, controller, None, seconds, print_every=np.inf)
    summary["abandoned_at_s"] = controller.abandoned
    summary["pushed_joint"] = controller.pushed_joint
    summary["push_watch_peak_Nm"] = controller.watch.peak.round(3).tolist()   # the largest |r| per joint seen
    summary["max_abs_dq"] = np.abs(log["dq"]).max(axis=0).round(4).tolist() if len(log["dq"]) else []
    lo, hi = robot.model.jnt_range.T
    room = np.minimum(log["q"] - lo, hi - log["q"])
    summary["min_limit_distance_rad"] = float(room.min()) if len(room) else None
    return log, summary, controller


GAP_MARGIN = 0.005   # s: rows this close to a missed cycle are not fitted (on franky-sim a tool run with 76 missed
#                      cycles read the mass 8.0 g light with them, 0.1 g with 5 ms left out, 0.6 g with 30 ms)


def near_gaps(log, margin: float = GAP_MARGIN) -> np.ndarray:
    """(T,) bool: the rows of a prepared Log within `margin` [s] of a cycle the run missed (a step of its recorded
    stamps over 1.5 periods: filled in by interpolation, and the robot held a command the log does not show)."""
    t, near = log.t, np.zeros(len(log.t), dtype=bool)
    for lo, hi in log.info.get("gap_intervals", ()):
        near |= (t > lo - margin) & (t < hi + margin)
    return near


def prepared(log: dict, fill_stale: bool = False, source: str = "run", notes: dict | None = None):
    """A run's arrays (franka.py's, or a log file's: load_run) as a diagnosis Log (filtered as LOG says, ddq), one
    row per cycle the controller ran: the motion's phase is the row, not the robot's clock, which runs on through a
    missed cycle. So the rows keep their order at one period each (two runs of the motion pair row k with row k) and
    info marks where the robot's stamps skipped (gap_intervals, cycles_missed: near_gaps). Stale rows (q, dq, tau_J
    the last row's again) dropped, or with fill_stale and the run's tau_cmd filled by _stale_filled (not the fit's
    default: on the benchmark's seeds 0-9 its intervals covered less, docs/tool_identification.md)."""
    raw = {k: np.asarray(log[k], dtype=float) for k in ("t", "q", "dq", "tau_J", "tau_ext") if k in log}
    notes = dict(notes or {})
    if "t" in raw and len(raw["t"]) > 2:
        t = raw["t"]
        step = np.diff(t)
        if not np.all(step > 0):
            i = int(np.flatnonzero(~(step > 0))[0]) + 1
            raise ValueError(f"t: expected strictly increasing time stamps, one row per control cycle, found "
                             f"t[{i}] = {t[i]!r} after t[{i - 1}] = {t[i - 1]!r}")
        dt = float(np.median(step))
        gaps = np.flatnonzero(step > 1.5 * dt)
        raw["t"] = t[0] + dt * np.arange(len(t))
        notes.update(gap_intervals=[(float(raw["t"][i]), float(raw["t"][i + 1])) for i in gaps],
                     cycles_missed=missing_cycles(t, dt)["missing_cycles"])
    if fill_stale and "tau_cmd" in log and "tau_J" in raw and len(raw["t"]) > 2:
        raw, notes["stale_rows_filled"] = _stale_filled(raw, np.asarray(log["tau_cmd"], dtype=float))
    return prepare(raw, LOG, source=source, notes=notes)


def load_run(path):
    """A log file of the motion (a franka.py --log .npz, a libfranka CSV: one row per control cycle) read as the run
    it records (prepared), so a file and the run it was written from pair their rows alike."""
    raw, notes = read_log(path, LOG)
    return prepared(raw, source=os.fspath(path), notes=notes)


def _stale_filled(raw: dict, tau_cmd):
    """(raw, rows filled): at a row that repeats the last one the robot still applied the command sent the cycle
    before, which tau_J then measures (a state read at cycle k follows the command of cycle k - 1); interpolating
    tau_J over such a row misses the step the controller took on the repeated state (the next command). tau_J there
    is the previous command plus tau_J - previous command interpolated over the rows kept (gravity, offsets: smooth),
    q and dq interpolated, as diagnosis.logs.prepare would."""
    stale = _stale_rows(raw)
    if not stale.any():
        return raw, 0
    before = np.concatenate([tau_cmd[:1], tau_cmd[:-1]])
    i, keep = np.arange(len(stale)), ~stale
    interp = lambda v: _interp(i, i[keep], v[keep])
    out = dict(raw)
    out["q"], out["dq"] = interp(raw["q"]), interp(raw["dq"])
    out["tau_J"] = np.where(stale[:, None], before + interp(raw["tau_J"] - before), raw["tau_J"])
    if "tau_ext" in raw:
        out["tau_ext"] = interp(raw["tau_ext"])
    return out, int(stale.sum())


def torque_of(robot: Robot, log) -> np.ndarray:
    """tau_ext (T, n), paper sign, for the fit: the model's M ddq + C dq + G less tau_J when the log has tau_J (the
    same filter on both, no observer lag), else the log's own tau_ext."""
    if log.tau_J is not None:
        return robot.inverse_dynamics(log.q, log.dq, log.ddq) - log.tau_J
    if log.tau_ext is None:
        raise ValueError("log: expected tau_J or tau_ext columns, found neither")
    return log.tau_ext


def fit_logs(robot: Robot, log, reference=None) -> ToolFit:
    """fit_tool on a prepared Log, referred to the prepared Log `reference` (the flange empty) when given; rows near a
    cycle either run missed (near_gaps) are not fitted."""
    ref = None if reference is None else (reference.q, reference.dq, reference.ddq, torque_of(robot, reference))
    keep = ~near_gaps(log)
    if reference is not None:                             # (the two runs are cut to the shorter, row k beside row k)
        T = min(len(log.t), len(reference.t))
        keep = keep[:T] & ~near_gaps(reference)[:T]
    return fit_tool(robot, log.q, log.dq, log.ddq, torque_of(robot, log), reference=ref, dt=log.info["dt"], keep=keep)


def rows_of(log) -> dict:
    """What reading a run or log file did to its rows (a prepared Log): counted for the report."""
    i = log.info
    return {"rows": len(log.t), "cycles_missed": i.get("cycles_missed", 0), "skips": len(i.get("gap_intervals", ())),
            "rows_near_skips_not_fitted": int(near_gaps(log).sum()), "stale_rows_interpolated": i.get("stale_rows", 0),
            "malformed_rows_dropped": i.get("bad_rows", 0), "nan_rows_dropped": i.get("nan_rows", 0)}


def report(fit: ToolFit, truth=None, motion: dict | None = None, runs: dict | None = None) -> dict:
    """What --json prints: mass, com, inertia (F) and the three forms, the fit per parameter, the motion's figures,
    the rows of each run (runs: name -> prepared Log, rows_of) and beside a known tool its error per parameter."""
    out = {**forms(fit.tool), "fit": fit.report()}
    if motion is not None:
        out["motion"] = motion
    if runs:
        out["rows"] = {name: rows_of(log) for name, log in runs.items() if log is not None}
    if truth is not None:
        t = truth_of(truth)
        out["truth"] = t
        out["error"] = {k: fit.value[k] - t[k] for k in NAMES}
    return out


def format_text(rep: dict) -> str:
    """The report for a person: each parameter with its interval and whether the motion saw it, then the forms."""
    lines = ["tool on the flange (flange frame F; inertia about the CoM)"]
    for k, p in rep["fit"]["parameters"].items():
        unit = "kg" if k == "mass" else "m" if k.startswith("com") else "kg m^2"
        seen = "" if p["observed"] else "   NOT OBSERVED by this motion"
        lines.append(f"  {k:6s} {p['value']:+.5f} {unit:6s} 2 std {2 * p['std']:.5f}{seen}")
    lines += [f"  note: {n}" for n in rep["fit"]["notes"]]
    d, s = rep["desk"], rep["libfranka_set_load"]
    lines += ["this is everything on the flange (the model's arm has no hand): enter it in Desk as the end effector,",
              "or set Desk's end effector to none and send it by setLoad / SetLoad (not both):",
              "Desk (Settings > End effector), flange frame:",
              f"  mass {d['mass']} kg, center of mass {d['center_of_mass']} m, inertia {d['inertia']} kg m^2",
              "libfranka (added to Desk's end effector; refused while a controller runs):", f"  {s['call']}",
              "franka_ros2:", f"  {rep['franka_ros2_set_load']['command']}"]
    for name, r in rep.get("rows", {}).items():
        lines.append(f"{name} run: {r['rows']} rows; the robot's stamps skip {r['skips']} times ({r['cycles_missed']} "
                     f"cycles missed), {r['rows_near_skips_not_fitted']} rows near them not fitted; "
                     f"{r['stale_rows_interpolated']} stale rows interpolated, {r['malformed_rows_dropped']} malformed "
                     f"and {r['nan_rows_dropped']} NaN rows dropped")
    if "motion" in rep:
        m = rep["motion"]
        lines.append(f"motion: {m.get('seconds', 0.0):.2f} s, max |dq| {max(m.get('max_abs_dq') or [0]):.3f} rad/s, "
                     f"closest limit {m.get('min_limit_distance_rad') or 0.0:.3f} rad")
        if "storage" in m:
            st = m["storage"]
            lines.append(f"storage check (this motion with this tool on the ideal plant, its weight compensated): the "
                         f"largest rise of S beyond the set point's work in a step {st['max_rise']:.1e} J, "
                         f"{'passive' if st['passive'] else 'NOT PASSIVE'} (tolerance {st['tolerance']:.0e} J)")
    return "\n".join(lines)


def _emit(rep, args, fit):
    if args.save:
        save_tool(args.save, fit.tool, rep["fit"])
    print(json.dumps(rep, indent=1) if args.json else format_text(rep))
    return 0


def _emit_abandoned(summary: dict, args, which: str) -> int:
    """A push ended the motion: what stopped it and when, no fit (the motion is not the one the fit and the reference
    assume; rerun it). Exit status 3."""
    rep = {"abandoned_at_s": summary["abandoned_at_s"], "run": which, "stopped": summary["stopped"],
           "seconds": summary["seconds"], "motion": summary, "fit": None,
           "note": f"a push abandoned the {which} motion at {summary['abandoned_at_s']:.3f} s: no tool is identified "
                   f"(nothing saved{'' if not args.save else ' to ' + args.save}); rerun it untouched"}
    print(json.dumps(rep, indent=1) if args.json else "\n".join(
        [f"ABANDONED: {rep['note']}", f"  {summary['stopped']}; the run lasted {summary['seconds']:.3f} s"]))
    return 3


def abandoned_in(path) -> float | None:
    """The time [s] a push abandoned the motion logged in `path` (a franka.py --identify --log .npz), else None."""
    if not str(path).lower().endswith(".npz"):
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            t = float(z["abandoned_at_s"]) if "abandoned_at_s" in z else np.nan
    except (OSError, ValueError):
        return None                                    # load_run reports a file it cannot read
    return None if np.isnan(t) else t


def _refuse_abandoned(path, name: str):
    t = abandoned_in(path)
    if t is not None:
        raise ValueError(f"{name}: expected a log of the whole motion, found one a push abandoned at {t:.3f} s "
                         f"({path!r}): rerun it untouched")


def _start_of(reference, q, settings: MotionSettings = MotionSettings()) -> np.ndarray:
    """The reference's start pose (n,), the tool run's centre; ValueError naming --reference and the joint when it
    lies further than settings.max_shift from the arm's pose q (n,) (refused before any control starts)."""
    center = reference.q[0]
    shift = np.abs(center - q)
    if shift.max() > settings.max_shift:
        j = int(np.argmax(shift))
        raise ValueError(f"--reference: expected its start pose within {settings.max_shift} rad of the arm's on every "
                         f"joint, found joint {j + 1} {shift[j]:.3f} rad away: move the arm to the reference's start "
                         f"pose or record the reference again here")
    return center


def franka_identify(args, run_loop, make_backend) -> int:
    """franka.py --identify: with --sim, a reference motion with the flange empty and then the motion with the tool
    of --sim-tool on the same simulated robot; on a robot, the motion with --reference FILE (an earlier --identify
    --log FILE with the flange empty) if given. Prints the report (--json) with the storage check of this motion with
    the tool found (motion.tool_storage, about 15 s), writes --save and --log. run_loop and
    make_backend: franka.py's. Exit status 0; 3 when a push abandoned a motion: the run ends settings.stop_after
    after the push, the report says when and which joint, and nothing is fitted or saved (the log, if asked for,
    is written and marked, so it is refused as a --reference or by rme.py identify)."""
    if args.dry_run or (args.sim_tool is not None and not args.sim):
        raise ValueError(f"--identify: expected a motion (no --dry-run) and --sim-tool only with --sim, found "
                         f"--dry-run {args.dry_run}, --sim {args.sim}, --sim-tool {args.sim_tool}")
    robot = Robot.panda()
    truth = None if args.sim_tool is None else make_tool(args.sim_tool[0], args.sim_tool[1:4],
                                                         np.diag(args.sim_tool[4:7]), "--sim-tool")
    if args.reference is not None:
        _refuse_abandoned(args.reference, "--reference")
    reference = None if args.reference is None else load_run(args.reference)
    if args.sim:
        if reference is None:
            ref_log, ref_summary, _ = run_motion(sim_backend(args.seed, None, 0), robot, run_loop)
            if ref_summary["abandoned_at_s"] is not None:
                return _emit_abandoned(ref_summary, args, "reference (flange empty)")
            reference = prepared(ref_log)
        backend = sim_backend(args.seed, truth, 1)
    else:                                              # the robot's backend, as franka.py builds it
        try:
            backend = make_backend(args, np.random.default_rng(args.seed))
        except RuntimeError as err:
            print(f"franka.py: not started: {err}", file=sys.stderr)
            return 2
    center = None if reference is None else _start_of(reference, backend.initial.q)   # the same motion
    log, summary, _ = run_motion(backend, robot, run_loop, center=center)
    abandoned = summary["abandoned_at_s"]
    if args.log:                                       # an abandoned motion's log says so (refused as a reference)
        np.savez(args.log, **log, tau_ext_sign="paper", abandoned_at_s=np.nan if abandoned is None else abandoned)
    if abandoned is not None:
        return _emit_abandoned(summary, args, "tool" if args.sim else "identification")
    run = prepared(log)
    fit = fit_logs(robot, run, reference)
    start = backend.initial.q if center is None else center
    summary["storage"] = dataclasses.asdict(storage_check(fit.tool, start))   # this motion, this tool
    return _emit(report(fit, truth, summary, {"tool": run, "reference": reference}), args, fit)


def log_main(argv=None, prog: str = "rme.py identify") -> int:
    """python rme.py identify LOG [--reference REF] [--json] [--save tool.json]."""
    ap = argparse.ArgumentParser(prog=prog, description="the tool's mass, CoM and inertia from a log of a motion")
    ap.add_argument("log", help="a franka.py --log .npz or a libfranka CSV of a motion with the tool")
    ap.add_argument("--reference", help="a log of the same motion with the flange empty (removes the arm's own error)")
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--save", metavar="FILE", help="write tool.json")
    args = ap.parse_args(argv)
    robot = Robot.panda()
    try:
        _refuse_abandoned(args.log, "log")
        if args.reference is not None:
            _refuse_abandoned(args.reference, "--reference")
        log = load_run(args.log)
        reference = None if args.reference is None else load_run(args.reference)
        fit = fit_logs(robot, log, reference)
    except ValueError as err:
        print(f"{prog}: {err}", file=sys.stderr)
        return 2
    return _emit(report(fit, runs={"tool": log, "reference": reference}), args, fit)
