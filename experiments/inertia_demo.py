"""The payload's inertia from motion and its compensation (motion/): a 4 s limit cycle with the wrist turning along
it, a 1.5 kg box 0.1 m out; RME's static compensation alone against RME + the inertial compensation.
`python sim.py inertia [--seed S] [--json]`."""
from __future__ import annotations

import gc
import json
import time
from dataclasses import dataclass, replace

import numpy as np

from cpic import CPIC, Attractor, LimitCycle, rotation_log
from experiments.runner import PayloadChange, PolicySwitch, run
from experiments.scenarios import limit_cycle_policy
from motion.compensation import InertialCompensation, InertiaSettings
from motion.inertia import inertia_of, rigid_body
from rme import RME
from sim import Plant, PlantConfig

BOX = (1.5, (0.0, 0.0, 0.1), (0.3, 0.1, 0.1))   # kg, CoM (m, ee frame), box sides along the ee x, y, z (m)


def box_inertia(m, sides) -> np.ndarray:
    """A solid box's inertia (3, 3) about its centre: m/12 (b^2 + c^2), ... (a closed form)."""
    a, b, c = sides
    return m / 12.0 * np.diag([b * b + c * c, a * a + c * c, a * a + b * b])


@dataclass(frozen=True)
class WristCycle:
    """The limit cycle (cpic.LimitCycle) with the ee orientation tied to the phase phi of the cycle:
    R*(phi) = R_star Exp(amplitude (sin k phi, cos k phi, sin(k phi + 1))); f_w = w* - a_r log(R R*^T), w* the
    rotation rate of R* along the cycle. Turning the wrist is what makes a payload's rotational inertia show."""
    cycle: LimitCycle
    amplitude: float = 0.4           # rad (ours)
    harmonic: int = 3                # turns of the wrist pattern per turn of the cycle (ours)

    def phase(self, p) -> float:
        u = p[1:] - self.cycle.center[1:]
        return float(np.arctan2(u[1], u[0]))

    def orientation(self, phi) -> np.ndarray:
        k, A = self.harmonic, self.amplitude
        v = A * np.array([np.sin(k * phi), np.cos(k * phi), np.sin(k * phi + 1.0)])
        angle = np.linalg.norm(v)
        K = np.cross(np.eye(3), v / angle)                  # Rodrigues
        return self.cycle.R_star @ (np.eye(3) + np.sin(angle) * K + (1 - np.cos(angle)) * K @ K)

    def __call__(self, p, R):
        f, (V_pos, _) = self.cycle(p, R)
        phi, h = self.phase(p), 1e-5
        R_star = self.orientation(phi)
        dR = (self.orientation(phi + h) - self.orientation(phi - h)) / (2 * h) * (2 * np.pi / self.cycle.period)
        W = dR @ R_star.T                                    # [w*]x
        e = rotation_log(R @ R_star.T)
        f = f.copy()
        f[3:] = np.array([W[2, 1], W[0, 2], W[1, 0]]) - self.cycle.gain_rot * e
        return f, (V_pos, 0.5 * self.cycle.gain_rot * (e @ e))


def path_error(log, reference, window):
    """RMS distance [mm] and orientation angle [mrad] of the ee over the time window (t0, t1) to the path it followed
    over `reference` (t0, t1) (the same motion without payload): each sample against the nearest reference point."""
    from scipy.spatial import cKDTree
    ref, sel = [(log.t >= a) & (log.t < b) for a, b in (reference, window)]
    d, i = cKDTree(log.p[ref]).query(log.p[sel])
    angle = [np.linalg.norm(rotation_log(R @ Rr.T)) for R, Rr in zip(log.R[sel], log.R[ref][i])]
    return 1e3 * float(np.sqrt(np.mean(d ** 2))), 1e3 * float(np.sqrt(np.mean(np.square(angle))))


def simulate(seed=0, inertial=True, preset="realistic", cycles=(2, 3), box=BOX, settings=None, period=4.0):
    """One run: hold 1 s, the wrist cycle unloaded for cycles[0] periods (the arm's own residual), hold, the box is
    attached 1 s into the hold, RME estimates it at rest, then the cycle with the box for cycles[1] periods.
    Returns (Record, estimator, times dict)."""
    rng = np.random.default_rng(seed)
    plant = Plant(PlantConfig.preset(preset, rng), rng=rng)
    robot = plant.robot
    base = limit_cycle_policy()
    policy = WristCycle(LimitCycle(base.center, base.R_star, radius=base.radius, period=period))
    start = base.center + np.array([0.0, base.radius, 0.0])
    hold = Attractor(start, policy.orientation(0.0))
    T = period
    t = dict(cycle=1.0, hold=1.0 + cycles[0] * T, attach=2.0 + cycles[0] * T, move=4.5 + cycles[0] * T)
    t["end"] = t["move"] + cycles[1] * T
    q0 = _start_pose(robot, hold)
    rme = RME(robot, rng=np.random.default_rng(seed + 1))
    if settings is None:
        gain = plant.config.observer_gain if plant.config.observer == "momentum" else None
        settings = InertiaSettings(observer_gain=gain)
    est = InertialCompensation(rme, settings) if inertial else rme
    m, c, sides = box
    events = [PayloadChange(t["attach"], m, c, box_inertia(m, sides)),
              PolicySwitch(t["cycle"], policy), PolicySwitch(t["hold"], hold), PolicySwitch(t["move"], policy)]
    log = run(plant, CPIC(robot, hold), t["end"], estimator=est, events=events, q0=q0)
    return log, est, t, policy


def _start_pose(robot, hold, iterations=200):
    """A joint pose whose ee is at the hold's pose (damped least squares from the ready pose)."""
    from dynamics import Q_READY
    q = Q_READY.copy()
    for _ in range(iterations):
        p, R, J = robot.kinematics(q)
        e = np.concatenate([hold.p_star - p, rotation_log(hold.R_star @ R.T)])
        q = q + J.T @ np.linalg.solve(J @ J.T + 1e-4 * np.eye(6), e)
        if np.abs(e).max() < 1e-9:
            break
    return q


class _Replay:
    """A stand-in for RME that replays a run's compensated estimate theta_hat (T, 4) and history and returns no
    torque: the wrapper's own work is what is timed."""

    def __init__(self, robot, theta_hat, history):
        self.robot, self._theta, self.history, self.k = robot, theta_hat, history, 0
        self.theta, self._zero = theta_hat[0], np.zeros(robot.n)

    def update(self, q, dq, tau_ext):
        self.theta, self.k = self._theta[self.k], self.k + 1
        return self._zero


def replay(log, settings, timed=True):
    """The run's samples through a fresh InertialCompensation (a stand-in RME): (estimator, per-sample wall and
    CPU time [s] (T,) each, refit in flight (T,) bool). The collector is paused while timing."""
    est = InertialCompensation(_Replay(log.robot, log.theta_hat, log.history), settings)
    T = len(log.t)
    wall, cpu, busy = np.zeros(T), np.zeros(T), np.zeros(T, dtype=bool)
    gc.collect()
    gc.disable()
    try:
        for k in range(T):
            t0, c0 = time.perf_counter(), time.thread_time()
            est.update(log.q[k], log.dq[k], log.tau_ext[k])
            wall[k], cpu[k], busy[k] = time.perf_counter() - t0, time.thread_time() - c0, est.busy
    finally:
        gc.enable()
    return est, wall, cpu, busy


def plain_loop(log):
    """The same number of samples of a fixed piece of work (the ee kinematics): the machine's own noise."""
    wall, cpu = np.zeros(len(log.t)), np.zeros(len(log.t))
    gc.collect()
    gc.disable()
    try:
        for k, q in enumerate(log.q):
            t0, c0 = time.perf_counter(), time.thread_time()
            log.robot.kinematics(q)
            wall[k], cpu[k] = time.perf_counter() - t0, time.thread_time() - c0
    finally:
        gc.enable()
    return wall, cpu


def cost_per_sample(log, settings, repeats=3):
    """Per-sample cost [us] of the wrapper on the run's samples beside a plain loop: median, p99, max of wall and
    CPU time; the samples with a refit in flight alone; and the max over samples of the min over `repeats`
    replays (one heavy sample shows in every replay, the machine's spikes do not)."""
    stats = lambda x: [float(np.median(x)) * 1e6, float(np.percentile(x, 99)) * 1e6, float(x.max()) * 1e6]
    runs = [replay(log, settings) for _ in range(repeats)]
    est, wall, cpu, busy = runs[0]
    pw, pc = plain_loop(log)
    return est, dict(samples=len(wall), wrapper_wall=stats(wall), wrapper_cpu=stats(cpu), plain_wall=stats(pw),
                     plain_cpu=stats(pc), refit_samples=int(busy.sum()), refit_cpu=stats(cpu[busy]),
                     min_of_repeats_cpu_max=float(np.min([r[2] for r in runs], axis=0).max()) * 1e6)


def inertia_demo(args):
    """RME static only vs RME + inertial compensation on the wrist cycle, realistic preset."""
    seed, m, c, sides = args.seed, *BOX
    truth = rigid_body(m, c, box_inertia(m, sides))
    out, logs = {}, {}
    for name, inertial in (("static", False), ("inertial", True)):
        wall = time.perf_counter()
        logs[name] = log, est, t, policy = simulate(seed, inertial)
        T = policy.cycle.period
        out[name] = dict(tracking_mm_mrad=[path_error(log, (t["hold"] - T, t["hold"]), (t["end"] - T, t["end"]))],
                         seconds=time.perf_counter() - wall)
    log, est, t, policy = logs["inertial"]
    replayed, cost = cost_per_sample(log, est.settings)
    unscreened = replay(log, replace(est.settings, settle=0.0))[0].pi
    fits = [dict(t=ft, diag=np.diag(inertia_of(p)).tolist(), std=info.std[[4, 6, 9]].tolist(), status=info.status,
                 rows=info.rows) for ft, p, info in est.fits]
    final = est.pi
    rel = (np.diag(inertia_of(final)) - np.diag(inertia_of(truth))) / np.diag(inertia_of(truth))
    result = dict(seed=seed, preset="realistic", payload=dict(m=m, c=list(c), box=list(sides)),
                  truth_diag=np.diag(inertia_of(truth)).tolist(), estimate_diag=np.diag(inertia_of(final)).tolist(),
                  relative_error=rel.tolist(), within_20_percent=bool(np.all(np.abs(rel) < 0.2)),
                  rme_theta=est.theta.tolist(), fits=fits,
                  tracking={k: v["tracking_mm_mrad"][0] for k, v in out.items()}, cost_us=cost,
                  replay_matches=bool(len(replayed.fits) == len(est.fits) and np.allclose(replayed.pi, final)),
                  unscreened_relative_error=((np.diag(inertia_of(unscreened)) - np.diag(inertia_of(truth)))
                                             / np.diag(inertia_of(truth))).tolist(),
                  wall_seconds={k: v["seconds"] for k, v in out.items()}, times=t)
    if args.json:
        print(json.dumps(result))
        return result
    _report(result)
    return result


def _report(r):
    print(f"Wrist-turning limit cycle, realistic plant (seed {r['seed']}); payload {r['payload']['m']} kg box "
          f"{r['payload']['box']} m, CoM {r['payload']['c']} m (ee frame).")
    t = r["times"]
    print(f"  unloaded cycle {t['cycle']:.1f}-{t['hold']:.1f} s (the arm's own residual), box attached at "
          f"{t['attach']:.1f} s (at rest), cycle with the box {t['move']:.1f}-{t['end']:.1f} s")
    th = r["rme_theta"]
    print(f"  RME static estimate: m = {th[0]:.3f} kg, r = ({th[1]:+.3f}, {th[2]:+.3f}, {th[3]:+.3f}) m")
    print("\n  fit at t [s]   rows   status      Ixx, Iyy, Izz about the ee origin [kg m^2] (+- 1 std)")
    for f in r["fits"]:
        print(f"  {f['t']:10.2f}   {f['rows']:5d}   {f['status']:9s}   " +
              "  ".join(f"{d:.4f} +- {s:.4f}" for d, s in zip(f["diag"], f["std"])))
    print(f"  {'truth':>10s}                       " + "  ".join(f"{d:.4f}" for d in r["truth_diag"]))
    print(f"  relative error of the last fit: {np.round(100 * np.array(r['relative_error']), 1).tolist()} % "
          f"(within 20 %: {r['within_20_percent']})")
    print("\n  last cycle with the box, rms distance to the unloaded path:   position [mm]   orientation [mrad]")
    for k, label in (("static", "RME static only"), ("inertial", "RME + inertial")):
        pos, rot = r["tracking"][k]
        print(f"  {label:24s} {pos:38.2f} {rot:18.2f}")
    c = r["cost_us"]
    print(f"\n  cost per 1 kHz sample [us] over {c['samples']} samples (replayed, stand-in RME):  median   p99    max")
    for k, label in (("wrapper_wall", "wrapper, wall"), ("wrapper_cpu", "wrapper, CPU (thread_time)"),
                     ("plain_wall", "plain loop (ee kinematics), wall"), ("plain_cpu", "plain loop, CPU"),
                     ("refit_cpu", f"samples with a refit step ({c['refit_samples']}), CPU")):
        print(f"  {label:44s} {c[k][0]:7.0f} {c[k][1]:6.0f} {c[k][2]:6.0f}")
    print(f"  max over samples of the min over 3 replays, CPU: {c['min_of_repeats_cpu_max']:.0f} us; "
          f"the replay reproduces the run's fits: {r['replay_matches']}")
    print(f"  without the jolt screening (settle = 0) the last fit's error: "
          f"{np.round(100 * np.array(r['unscreened_relative_error']), 1).tolist()} %")
