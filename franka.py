"""Real-robot bridge: RME (Sec. 4) feeding the CPIC torque controller (Sec. 5, Eq. 8, Eq. 5's compensation) in one
1 kHz loop on a Franka Panda (pylibfranka or panda-python) or on the project's own sim.Plant (--sim). tau_ext in the
paper's sign (Eq. 1) is minus libfranka's tau_ext_hat_filtered; the command sent excludes gravity (libfranka adds G)."""
from __future__ import annotations

import contextlib
import gc
import json
import math
import os
import sys
import time
from dataclasses import dataclass

import numpy as np

import checks
from cpic import CPIC, Attractor, CPICConfig, LimitCycle
from dynamics import Robot
from error_model import as_error_model
from rme import RME
from rme_settings import RMESettings, faulty as faulty_sample
from robot.backends import (Q_START, FrankySimBackend, PandaPyBackend, PylibfrankaBackend, SimBackend, State,
                            paper_tau_ext)
from robot.worker import WORKERS, EstimatorSpec, make_worker

__all__ = ["Q_START", "State", "paper_tau_ext", "SimBackend", "PylibfrankaBackend", "PandaPyBackend", "FrankySimBackend",
           "Safety", "SafetyConfig", "make_controller", "run_loop", "own_cpu", "summarize", "save_log",
           "main"]  # backends: robot/
LIBS = ("pylibfranka", "panda-py")
TASKS = ("hold", "limit-cycle")
SIM_COM = (0.03, -0.02, 0.05)   # m, ee frame: the --sim payload, off the flange axis (a load on it waits: hold_axial)


# --- safety ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SafetyConfig:
    max_step: float = 1.0          # Nm per 1 ms cycle: Franka's dtau_max = 1000 Nm/s (panda_facts.md); libfranka's
                                   #   own rate limiter does not act on the read/write path, so this one does

    def __post_init__(self):       # a safety setting can only tighten the robot's own limit
        checks.number("config.max_step", self.max_step, "(0, 1]", "Nm per cycle (Franka's dtau_max x 1 ms)")


class Safety:
    """The last stage before the robot. command(tau, G) takes the controller's full torque tau (n,) (gravity
    included) and the gravity G (n,) at the measured q and returns what is sent, cmd = tau - G (libfranka adds G):
    1. tau or G not finite -> the last safe command is held (zero before the first one: the robot's own gravity
       compensation alone), counted in `held`;
    2. |cmd - last| <= max_step per joint (rate limit);
    3. |cmd + G| <= tau_max per joint (torque limit; it wins over the rate limit when both cannot hold)."""

    def __init__(self, tau_max, config: SafetyConfig = SafetyConfig()):
        self.tau_max = checks.array("tau_max", tau_max, (None,), "(0, 1e4]", "Nm")
        checks.instance("config", config, SafetyConfig)
        self.config, self.last, self.held = config, np.zeros(self.tau_max.size), 0

    def command(self, tau, G) -> np.ndarray:
        tau, G = np.asarray(tau, dtype=float), np.asarray(G, dtype=float)
        n = self.tau_max.size
        if tau.shape != (n,) or G.shape != (n,):
            raise ValueError(f"tau, G: expected shapes ({n},), found {tau.shape}, {G.shape}")
        return self._command(tau, G).copy()

    def _command(self, tau, G) -> np.ndarray:
        """command() for float arrays tau, G (n,) the caller vouches for (run_loop); returns self.last itself."""
        if not math.isfinite(tau.sum() + G.sum()) and not (np.isfinite(tau).all() and np.isfinite(G).all()):
            self.held += 1                             # (a finite sum: all finite; inf or NaN: look closer)
            return self.last
        r, last = self.config.max_step, self.last
        cmd = np.subtract(tau, G)
        np.clip(cmd, last - r, last + r, out=cmd)
        np.clip(cmd, -self.tau_max - G, self.tau_max - G, out=cmd)
        self.last = cmd
        return cmd

    def ramp_down(self) -> np.ndarray:
        """The next command on the way to zero at the rate limit (gravity-free: the robot keeps holding G)."""
        r = self.config.max_step
        self.last = np.clip(0.0 - self.last, -r, r) + self.last
        return self.last.copy()


# --- the loop, written once for every backend ------------------------------------------------------------------
def make_controller(robot: Robot, q0, task: str = "hold", stiffness_scale: float = 1.0) -> CPIC:
    """CPIC holding the ee pose at q0 (hold) or circling 5 cm around it (limit-cycle, Sec. 5.3), with the DS gains
    and the posture spring scaled by stiffness_scale (1: the project's defaults, cpic.py)."""
    if task not in TASKS:
        raise ValueError(f"task: expected one of {TASKS}, found {task!r}")
    checks.number("stiffness_scale", stiffness_scale, "(0, 1]")
    p0, R0 = robot.ee_pose(np.asarray(q0, dtype=float))
    S = float(stiffness_scale)
    if task == "hold":
        policy = Attractor(p0, R0, gain_pos=3.0 * S, gain_rot=8.0 * S)
    else:                                              # the start pose is the top of the circle
        policy = LimitCycle(p0 - np.array([0.0, 0.0, 0.05]), R0, radius=0.05, gain_pos=3.0 * S, gain_rot=8.0 * S)
    return CPIC(robot, policy, CPICConfig(null_stiffness=CPICConfig.null_stiffness * S))


def run_loop(backend, robot: Robot, controller, estimator=None, seconds: float = 5.0, dry_run: bool = False,
             print_every: float = 0.5, out=None) -> tuple[dict, dict]:
    """Each cycle: state = backend.read(); tau_ext = -tau_ext_hat_filtered (paper sign); comp = estimator.update;
    tau, _ = controller.step(q, dq, comp, tau_ext); cmd = safety.command(tau, G(q)); backend.write(cmd); then, while
    the robot has yet to send the next state: the log, the estimate's poll and any garbage collection (callback_s is
    the time from the state to its command). G comes from the controller's own step when it is a CPIC on `robot`.
    A tau_ext that is not finite or beyond RME's max_abs_torque (a faulty sample: RME drops it) reaches the controller
    as the last good one and is logged as read (the summary's faulty_tau_ext counts them). A dry run writes zeros
    (the robot backends then command nothing) and prints what it would command every print_every s. Ends after
    `seconds`, on Ctrl-C or on any exception with the command ramped to zero at the rate limit and backend.stop();
    an exception is raised again after that. Returns (summary, log arrays)."""
    checks.number("seconds", seconds, "(0, 600]", "s (the log keeps every cycle: 10 min is about 250 MB)")
    n, steps = robot.n, int(round(seconds * 1000))
    safety, limit = Safety(robot.torque_limits()), robot.torque_limits()
    rec = {k: np.full((steps, n), np.nan) for k in ("q", "dq", "tau_J", "tau_ext", "tau", "tau_cmd")}
    rec["t"], rec["theta_hat"], rec["callback_s"] = np.full(steps, np.nan), np.full((steps, 4), np.nan), np.zeros(steps)
    rec["in_flight"] = np.zeros(steps, dtype=bool)     # an estimate was running beside the loop at the cycle's end
    rec["read_s"], rec["after_s"] = np.zeros(steps), np.zeros(steps)   # waiting for the state; the work after the write
    executor = getattr(estimator, "executor", None)
    busy = getattr(executor, "busy", lambda: False)    # after each write: sends queued jobs, receives results
    in_done = getattr(executor, "collect_in_done", None)
    if in_done is not None:
        executor.collect_in_done = False               # so the estimator's own poll (in update) only reads them
    shares_G = isinstance(controller, CPIC) and controller.robot is robot
    no_theta, zeros = np.zeros(4), np.zeros(n)
    _warm_up(robot, controller, estimator)
    k, t, missed, stopped, last_print, faulty, good = 0, 0.0, 0, "end", -np.inf, 0, zeros
    limit_ext = getattr(getattr(estimator, "settings", None), "max_abs_torque", RMESettings.max_abs_torque)
    collect = gc.isenabled()
    gc.collect()
    gc.freeze()                  # what exists now is never scanned again: a collection in the loop stays short
    gc.disable()                 # and it runs after the write (_collect_garbage), off the state-to-command path
    try:
        for k in range(steps):
            t_read = time.perf_counter()
            s = backend.read()
            t0 = time.perf_counter()
            rec["read_s"][k] = t0 - t_read
            tau_ext = paper_tau_ext(s.tau_ext_hat_filtered)
            comp = estimator.update(s.q, s.dq, tau_ext) if estimator is not None else None
            if faulty_sample(tau_ext, limit_ext):      # as RME drops it
                faulty += 1
            else:
                good = tau_ext
            tau, _ = controller.step(s.q, s.dq, comp, good)
            G = controller.G if shares_G else robot.gravity(s.q)
            cmd = safety._command(tau, G)              # (n,) float arrays: checks are for callers outside the loop
            rec["callback_s"][k] = time.perf_counter() - t0
            backend.write(zeros if dry_run else cmd)
            t_written = time.perf_counter()
            t += s.duration_s if k else 0.0
            missed += max(int(round(s.duration_s * 1000)) - 1, 0) if k else 0
            for key, v in (("q", s.q), ("dq", s.dq), ("tau_J", s.tau_J), ("tau_ext", tau_ext), ("tau", tau),
                           ("tau_cmd", cmd)):
                rec[key][k] = v
            rec["t"][k], rec["in_flight"][k] = t, busy()
            rec["theta_hat"][k] = getattr(estimator, "theta", no_theta)
            if dry_run and t - last_print >= print_every:
                print(f"t {t:7.3f} s  would command (gravity-free) {np.array2string(cmd, precision=2)} Nm",
                      file=out or sys.stdout)
                last_print = t
            if collect:
                _collect_garbage()
            rec["after_s"][k] = time.perf_counter() - t_written
        k = steps
    except KeyboardInterrupt:
        stopped = "interrupted (Ctrl-C)"
    except BaseException as err:
        stopped = f"error: {type(err).__name__}: {err}"
        _stop(backend, safety, dry_run)
        raise
    finally:
        if collect:
            gc.enable()
        gc.unfreeze()
        if in_done is not None:
            executor.collect_in_done = in_done
    _stop(backend, safety, dry_run)
    log = {key: v[:k] for key, v in rec.items()}
    return summarize(log, estimator, robot, limit, missed, safety.held, stopped, seconds, faulty), log


def _warm_up(robot, controller, estimator):
    """Run the cycle's code once at the ready pose before the first state, keeping nothing (a CPIC forgets the step
    by reset(); a spare RME of the same settings and a spare Safety stand in for the others): in cold caches the
    first cycle took 0.5 ms on the project's plant and 1.3 ms against franky-sim; a robot's next state does not wait."""
    if robot.n != len(Q_START):
        return
    zeros = np.zeros(robot.n)
    if isinstance(controller, CPIC) and controller.robot is robot:
        Safety(robot.torque_limits())._command(controller.step(Q_START, zeros, zeros, zeros)[0], controller.G)
        controller.reset()
    if isinstance(estimator, RME):
        spare = RME(robot, weights=None, settings=estimator.settings)
        for _ in range(3):
            spare.update(Q_START, zeros, zeros)


@contextlib.contextmanager
def realtime_priority(priority: int = 80):
    """Run the block with the calling thread at Linux SCHED_FIFO `priority` (as libfranka's RealtimeConfig.kEnforce
    does on a robot), restoring its policy after; yields True if it could (CAP_SYS_NICE), else False and runs as is.
    For a loop that blocks on each state (a robot, franky-sim); never around a loop that spins."""
    try:                                     # threads and processes started in the block do not inherit it
        before = os.sched_getscheduler(0), os.sched_getparam(0)
        os.sched_setscheduler(0, os.SCHED_FIFO | os.SCHED_RESET_ON_FORK, os.sched_param(priority))
    except (AttributeError, OSError):
        before = None
    if before is None:
        yield False
        return
    try:
        yield True
    finally:
        os.sched_setscheduler(0, before[0], before[1])


@contextlib.contextmanager
def own_cpu(pids=()):
    """Run the block with the calling thread on a CPU of its own (the last one it may use) and the processes `pids`
    (the estimate's worker, a simulator) kept off it, restoring every affinity after; yields that CPU, or None when
    only one CPU is allowed or Linux refuses. A worker that ran on the loop's CPU while the loop waited for its
    state left the loop's next cycle in cold caches (franky-sim: in-flight p99 0.23-0.35 ms, pinned 0.23-0.25 ms)."""
    def restore():
        for p, a in theirs + [(0, mine)]:
            with contextlib.suppress(OSError):
                os.sched_setaffinity(p, a)
    try:
        mine, theirs = os.sched_getaffinity(0), [(p, os.sched_getaffinity(p)) for p in pids]
        cpu = max(mine) if len(mine) > 1 else None
    except (AttributeError, OSError):
        cpu = None
    try:
        if cpu is not None:
            os.sched_setaffinity(0, {cpu})
            for p, a in theirs:
                os.sched_setaffinity(p, (a - {cpu}) or a)
    except OSError:                                    # half pinned: put everything back
        restore()
        cpu = None
    try:
        yield cpu
    finally:
        if cpu is not None:
            restore()


def _collect_garbage():
    """What the collector would do at this point, by its own thresholds: the youngest generation whose count is
    over its threshold, and the ones below it (the loop calls this after its write; automatic collection is off)."""
    counts, limits = gc.get_count(), gc.get_threshold()
    if counts[0] > limits[0]:
        gc.collect(2 if counts[2] > limits[2] and counts[1] > limits[1] else 1 if counts[1] > limits[1] else 0)


def _stop(backend, safety: Safety, dry_run: bool, max_cycles: int = 100):
    """Ramp the command to zero at the rate limit (87 Nm takes 87 cycles), then stop the backend."""
    try:
        for _ in range(max_cycles if not dry_run else 0):
            if not np.any(safety.last):
                break
            backend.read()
            backend.write(safety.ramp_down())
    finally:
        backend.stop()


def summarize(log, estimator, robot, limit, missed, held, stopped, seconds, faulty=0) -> dict:
    """What --json prints: run length, estimates (time, mass, CoM), torque and rate peaks, timing."""
    cmd, q = log["tau_cmd"], log["q"]
    G = robot.gravity(q) if len(q) else np.zeros((0, robot.n))
    sent = cmd + G                                     # the torque the drives deliver (command + robot's gravity)
    dtau = np.abs(np.diff(np.vstack([np.zeros((1, robot.n)), cmd]), axis=0))
    cb, flight = log["callback_s"] * 1e3, log["in_flight"]
    peak = lambda a: np.abs(a).max(axis=0).round(4).tolist() if len(a) else [0.0] * robot.n
    stats = lambda a: {"median": float(np.median(a)) if len(a) else 0.0,
                       "p99": float(np.percentile(a, 99)) if len(a) else 0.0,
                       "max": float(a.max()) if len(a) else 0.0, "cycles": int(len(a))}
    return {"seconds": float(log["t"][-1]) if len(log["t"]) else 0.0, "requested_seconds": seconds,
            "cycles": int(len(log["t"])), "stopped": stopped, "missed_cycles": int(missed), "nan_held": int(held),
            "faulty_tau_ext": int(faulty),
            "estimates": [{"t": round(float(e.t), 4), "mass": round(float(e.mean[0]), 4),
                           "applied": round(float(e.applied), 4) if np.isfinite(e.applied) else None,
                           "com": np.round(e.mean[1:], 4).tolist(), "kind": e.kind, "accepted": bool(e.accepted),
                           "seconds": round(float(e.seconds), 4), "rz_observed": bool(e.observed[3]), "reason": e.reason}
                          for e in getattr(estimator, "history", [])],
            "theta_hat": np.round(getattr(estimator, "theta", np.zeros(4)), 4).tolist(),
            "max_abs_tau": peak(sent), "tau_limit": limit.tolist(), "max_abs_dtau": peak(dtau),
            "dtau_limit": SafetyConfig.max_step,     # Nm per 1 ms cycle, the rate limit Safety enforces
            "callback_ms": stats(cb), "callback_ms_estimate_in_flight": stats(cb[flight | np.roll(flight, 1)])}


def save_log(path, log, estimator=None):
    """An .npz diagnosis.logs.load_log reads: t, q, dq, tau_J, tau_ext (paper sign, tau_ext_sign='paper'), plus
    tau (the controller's torque, gravity included), tau_cmd (sent, gravity-free), theta_hat (T, 4), callback_s, and
    the estimates: est_t, est_applied (K,), est_theta, est_std (K, 4), est_observed (K, 4) bool, est_kind,
    est_accepted, est_reason, est_seconds (K,). `python rme.py plot` draws it."""
    np.savez(path, **log, tau_ext_sign="paper", **_estimates(estimator))


def _estimates(estimator) -> dict:
    """The estimator's history as save_log's est_* arrays."""
    hist = list(getattr(estimator, "history", []))
    return dict(est_t=np.array([e.t for e in hist], float), est_applied=np.array([e.applied for e in hist], float),
                est_theta=np.array([e.mean for e in hist], float).reshape(-1, 4),
                est_std=np.array([e.std for e in hist], float).reshape(-1, 4),
                est_observed=np.array([e.observed for e in hist], bool).reshape(-1, 4),
                est_kind=np.array([e.kind for e in hist], dtype=str),
                est_accepted=np.array([e.accepted for e in hist], bool),
                est_reason=np.array([e.reason for e in hist], dtype=str),
                est_seconds=np.array([e.seconds for e in hist], float))


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
            blind = "" if e["rz_observed"] or e["kind"] == "withdrawn" else " (rz: prior, not observed at this pose)"
            print(f"  {e['t']:7.3f} s  {e['kind']}: m = {e['mass']:.3f} kg, r = {e['com']} m{blind}, {state}")
        if "sim_payload" in summary:
            print("  simulated payload: m = {mass} kg, r = {com} m from {t:.3f} s".format(**summary["sim_payload"]))
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except (ValueError, RuntimeError, OSError) as err:     # a failure is one line on stderr (exit status 1)
        sys.exit(f"franka.py: {type(err).__name__}: {err}")
