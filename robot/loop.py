"""The 1 kHz loop of the real-robot bridge, written once for every backend: RME (Sec. 4) feeding CPIC (Sec. 5, Eq. 8,
Eq. 5's compensation), the safety stage before the robot, the loop thread's scheduling and the run's summary and log.
tau_ext in the paper's sign (Eq. 1) is minus libfranka's tau_ext_hat_filtered; the command excludes gravity."""
from __future__ import annotations

import contextlib
import gc
import math
import os
import sys
import time
from dataclasses import dataclass

import numpy as np

import checks
from cpic import CPIC, Attractor, CPICConfig, LimitCycle
from dynamics import Robot
from rme import RME
from rme_settings import RMESettings, faulty as faulty_sample
from robot.backends import Q_START, paper_tau_ext

TASKS = ("hold", "limit-cycle")


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
    the time from the state to its command); a controller whose `finished` is set (a reason) ends the run there,
    `stopped` saying why. G comes from the controller's own step when it is a CPIC on `robot`.
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
            if getattr(controller, "finished", None):  # the controller ends the run (a push abandons a motion)
                stopped, k = controller.finished, k + 1
                break
        else:
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
