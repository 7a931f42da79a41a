"""Real-robot bridge: RME (Sec. 4) feeding the CPIC torque controller (Sec. 5, Eq. 8, Eq. 5's compensation) in one
1 kHz loop on a Franka Panda (pylibfranka or panda-python) or on the project's own sim.Plant (--sim). tau_ext in the
paper's sign (Eq. 1) is minus libfranka's tau_ext_hat_filtered; the command sent excludes gravity (libfranka adds G)."""
from __future__ import annotations

import json
import sys

import numpy as np

import checks
from dynamics import Robot
from error_model import as_error_model
from robot.backends import (Q_START, FrankySimBackend, PandaPyBackend, PylibfrankaBackend, SimBackend, State,
                            paper_tau_ext)
from robot.loop import (TASKS, Safety, SafetyConfig, make_controller, own_cpu, realtime_priority, run_loop, save_log,
                        summarize)
from robot.worker import WORKERS, EstimatorSpec, make_worker

__all__ = ["Q_START", "State", "paper_tau_ext", "SimBackend", "PylibfrankaBackend", "PandaPyBackend", "FrankySimBackend",
           "Safety", "SafetyConfig", "make_controller", "run_loop", "own_cpu", "realtime_priority", "summarize",
           "save_log", "main"]  # backends, the loop: robot/
LIBS = ("pylibfranka", "panda-py")
SIM_COM = (0.03, -0.02, 0.05)   # m, ee frame: the --sim payload, off the flange axis


# --- command line ------------------------------------------------------------------------------------------------
def make_backend(args, rng: np.random.Generator):
    if args.sim:
        payload = [(args.seconds / 2, args.sim_payload, SIM_COM)] if args.sim_payload > 0 else []
        if getattr(args, "sim_tool", None):            # the tool on the flange from the start (flange frame F)
            from robot.identify import sim_payload
            payload = sim_payload(args.sim_tool, payload)
        return SimBackend(rng, payload=payload, paced=args.paced)
    if args.lib == "pylibfranka":
        return PylibfrankaBackend(args.robot_ip, realtime=not args.no_realtime, control=not args.dry_run)
    return PandaPyBackend(args.robot_ip, control=not args.dry_run)


def main(argv=None) -> int:
    ap = checks.Parser(prog="franka.py", description=__doc__)
    ap.add_argument("--robot-ip", help="the robot's FCI address (not needed with --sim)")
    ap.add_argument("--lib", choices=LIBS, default="pylibfranka")
    ap.add_argument("--task", choices=TASKS, default="hold")
    ap.add_argument("--seconds", type=checks.argument("(0, 600]", "s"), default=10.0,
                    help="run time in (0, 600] s (the log keeps every cycle: 10 min is about 250 MB)")
    ap.add_argument("--log", type=checks.writable, help="write the run to this .npz (diagnosis.logs.load_log reads it)")
    ap.add_argument("--json", action="store_true", help="print the summary as JSON")
    ap.add_argument("--plot", metavar="FILE", help="save a figure of the run: the estimate over time (needs matplotlib)")
    ap.add_argument("--dry-run", action="store_true", help="read states, print what would be commanded, command nothing")
    ap.add_argument("--sim", action="store_true", help="the project's MuJoCo plant instead of a robot")
    ap.add_argument("--sim-payload", type=checks.argument("[0, 3]", "kg"), default=0.0,
                    help=f"with --sim: kg in [0, 3] added at half time, its CoM at {SIM_COM} m in the ee frame "
                         "(off the flange's axis)")
    ap.add_argument("--stiffness-scale", type=checks.argument("(0, 1]"), default=1.0,
                    help="DS gains and posture spring x S, (0, 1]")
    ap.add_argument("--no-realtime", action="store_true", help="pylibfranka RealtimeConfig.kIgnore (no RT kernel)")
    ap.add_argument("--seed", type=checks.argument("0..4294967294"), default=0,
                    help="the --sim plant's noise, 0..4294967294")
    ap.add_argument("--paced", action="store_true", help="with --sim: one state per ms of wall time, as a robot")
    ap.add_argument("--worker", choices=WORKERS, default="process", help="where RME's estimates run beside the loop")
    ap.add_argument("--sync-estimate", action="store_true", help="RME's estimates within the callback, no worker")
    ap.add_argument("--calibration", metavar="FILE", default=None,
                    help="RME's error model of this robot (python rme.py calibrate LOG --save FILE)")
    ap.add_argument("--identify", action="store_true", help="identify the tool on the flange (a <= 20 s slow motion)")
    ap.add_argument("--sim-tool", type=float, nargs=7, metavar=("M", "CX", "CY", "CZ", "IXX", "IYY", "IZZ"),
                    help="with --sim: the tool on the flange, kg, m and kg m^2 about its CoM, flange frame F")
    ap.add_argument("--reference", help="with --identify: a log of the motion with the flange empty")
    ap.add_argument("--save", metavar="FILE", help="with --identify: write tool.json")
    ap.add_argument("--tool", metavar="FILE", help="tool.json: the tool taken as known, RME estimates what is added")
    args = ap.parse_args(argv)
    if not args.sim and not args.robot_ip:
        ap.error("--robot-ip: expected the robot's address (or --sim), found none")
    if args.identify:                                  # robot/identify.py: the motion, the fit, the forms
        from robot.identify import franka_identify
        return franka_identify(args, run_loop, make_backend)
    robot = Robot.panda()
    try:                                               # the estimator, rebuilt as it is in a worker process; a
        spec = EstimatorSpec(seed=args.seed + 1, calibration=args.calibration, tool=args.tool)   # calibration
        as_error_model(args.calibration)                                         # file that cannot be read stops us
    except ValueError as err:
        print(f"franka.py: not started: {err}", file=sys.stderr)
        return 2
    try:
        backend = make_backend(args, np.random.default_rng(args.seed))
    except RuntimeError as err:
        print(f"franka.py: not started: {err}", file=sys.stderr)
        return 2
    controller = make_controller(robot, backend.initial.q, args.task, args.stiffness_scale)
    try:
        worker = None if args.sync_estimate else make_worker(args.worker, spec)   # the estimates (1.5-4 ms)
    except (RuntimeError, ValueError):
        backend.stop()
        raise
    estimator, switch = spec.build(executor=worker), sys.getswitchinterval()
    sys.setswitchinterval(1e-4)                # the loop gets the GIL back from an estimate's thread within 0.1 ms
    try:
        with own_cpu([worker.pid] if hasattr(worker, "pid") else []):
            summary, log = run_loop(backend, robot, controller, estimator, args.seconds, dry_run=args.dry_run)
    finally:
        sys.setswitchinterval(switch)
        if worker is not None:
            worker.shutdown()
    summary["estimate_in"] = "callback" if args.sync_estimate else args.worker
    if args.sim and args.sim_payload > 0:              # what the estimates are to be compared with
        summary["sim_payload"] = p = {"t": args.seconds / 2, "mass": args.sim_payload, "com": list(SIM_COM)}
        log["theta"] = np.where((log["t"] >= p["t"] - 1e-9)[:, None], [p["mass"], *SIM_COM], 0.0)
    if args.log:
        save_log(args.log, log, estimator)
    if args.plot:
        from experiments.figures import plot_run
        plot_run(args.plot, log, estimator.history, robot, "franka.py run" + " (--sim)" * args.sim, args.json)
    if args.json:
        print(json.dumps(summary, indent=1))
    else:
        cb = summary["callback_ms"]
        print(f"{summary['cycles']} cycles, {summary['seconds']:.3f} s, stopped: {summary['stopped']}; callback "
              f"median/p99/max {'/'.join(f'{cb[k]:.2f}' for k in ('median', 'p99', 'max'))} ms")
        for e in summary["estimates"]:
            state = (f"applied at {e['applied']:.3f} s" if e["accepted"] else "refused") + (
                f" ({e['reason']})" if e["reason"] else "")
            blind = "" if e["rz_observed"] or e["kind"] == "back" else " (rz: prior, not observed at this pose)"
            print(f"  {e['t']:7.3f} s  {e['kind']}: m = {e['mass']:.3f} kg, r = {e['com']} m{blind}, {state}")
        if "sim_payload" in summary:
            print("  simulated payload: m = {mass} kg, r = {com} m from {t:.3f} s".format(**summary["sim_payload"]))
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except (ValueError, RuntimeError, OSError) as err:     # a failure is one line on stderr (exit status 1)
        sys.exit(f"franka.py: {type(err).__name__}: {err}")
