"""Timings of every hot path and the component benchmarks: `python sim.py timing` (the model, the plant, RME, the
controller's QP and step, the network, VI) and `python sim.py detector-bench`, `python sim.py vi-bench`. Absolute times
on a shared 2-core machine vary 2-3x between runs: compare rows of one run as ratios. `python -m experiments.timing
worker`: franka.py's 1 kHz callback with RME's estimates in a thread, in a worker process or within the callback."""
from __future__ import annotations

import sys
import time

import numpy as np

from cpic import CPIC, Attractor, JointHold
from detector import Detector, DetectorSettings
from dynamics import Q_READY, Robot, phi_of
from diagnosis.diagnose import diagnose
from diagnosis.effect_model import Model
from diagnosis.effects import Signals, _sigmoid_shape
from diagnosis.excite import ExciteConfig, multisine
from diagnosis.logs import Log, prepare
from experiments.bench import TABLE5
from experiments.episodes import detector_episode, simulated_window
from experiments.runner import PayloadChange, Push, run
from experiments.timing_tools import median_us
from qp import dual_active_set, solve_qp
from rme import RME
from sim import GAZ_FO, GAZ_P1, GAZ_P2, GAZ_P3, Plant, PlantConfig
import vi


def timing(table: bool = True) -> dict:
    """Median microseconds of every hot path, {row: us}; printed as one labelled table if `table`."""
    robot, rng = Robot.panda(), np.random.default_rng(0)
    n = robot.n
    q, dq = Q_READY + rng.normal(0, 0.2, n), rng.normal(0, 0.5, n)
    Qw = Q_READY + rng.normal(0, 0.2, (200, n))
    phi = phi_of([0.9, 0.05, -0.03, 0.13])
    rows = {
        "model: jacobian": median_us(lambda: robot.jacobian(q)),
        "model: mass_matrix": median_us(lambda: robot.mass_matrix(q)),
        "model: bias": median_us(lambda: robot.bias(q, dq)),
        "model: payload_regressor": median_us(lambda: robot.payload_regressor(q)),
        "model: payload_regressor, 200-sample window": median_us(lambda: robot.payload_regressor(Qw), 300),
        "model: terms (J, M, C dq + G in one pass)": median_us(lambda: robot.terms(q, dq)),
        "model: one control step's model (control_terms + tau_mm)": median_us(lambda: _step_model(robot, q, dq, phi)),
    }
    for preset in ("ideal", "realistic"):
        r2 = np.random.default_rng(1)
        plant = Plant(PlantConfig.preset(preset, r2), rng=r2)
        s = plant.reset(Q_READY)
        tau, _ = JointHold(plant.robot, Q_READY).step(s.q, s.dq)      # a fixed command: the arm stays near its pose
        rows[f"plant: step ({preset})"] = median_us(lambda: plant.step(tau), 3000)
    est = RME(robot, rng=np.random.default_rng(0))
    z = np.zeros(n)
    rows["RME.update: one 1 kHz sample, no detection"] = median_us(lambda: est.update(Q_READY, z, z), 3000)
    rows["RME: one judgement of a departure (changes.ChangeModel.judge)"] = _judgement_us(robot, phi)
    windows = [simulated_window(np.array(th), np.random.default_rng(i))[1:] for i, th in enumerate(TABLE5)]
    rows["RME.estimate: network + VI, 200-sample window (Table 5)"] = float(np.median(
        [est.estimate(qw, tau, referred=True).seconds * 1e6 for tau, qw in windows * 20]))
    for k, v in cpic_benchmark().items():
        if k.endswith("_us"):
            rows[f"CPIC: {k[:-3].replace('_', ' ')}"] = v
    from experiments.training import benchmark as nn_benchmark
    for k, v in nn_benchmark(repeats=1000, held_out_episodes=0).items():
        if k.endswith("_us"):
            rows[f"network: {k[:-3].replace('_', ' ')}"] = v
    if table:
        from experiments.timing_tools import print_table
        stat = lambda k: ("99th percentile" if "p99" in k else "median of each problem's best of 7" if "best" in k
                          else "median")
        print_table("time of every hot path (this machine, this run)", ["hot path", "statistic", "time [us]"],
                    [[k.replace(" median best", "").replace(" p99", "").replace(" median", ""), stat(k), f"{v:.1f}"]
                     for k, v in rows.items()],
                    "the 1 kHz loop has 1000 us per cycle; on a shared machine absolute times vary 2-3x between "
                    "runs: compare rows of one run.")
    return rows


def _step_model(robot, q, dq, phi):
    """What one control step with compensation needs from the model: J, M, C dq + G, G, p, R and tau_mm."""
    J, M, b, G, p, R = robot.control_terms(q, dq)
    return J, M, b, G, p, R, robot.payload_regressor_from(J, R) @ phi


def cpic_benchmark(seconds=0.6, repeats=7) -> dict:
    """The controller's own QPs, recorded in a simulated hold (a 5 cm / 0.3 rad pose step that drives wrist joints
    into their E-CBF constraints, a 0.9 kg payload at 0.2 s, a 42 N push from 0.3 s to 0.5 s). Keys ending in "_us":
    the median over all calls and passes (`repeats` passes over every recorded problem); "_best_us": the median over
    problems of each problem's fastest pass (what the code can do when the machine is quiet)."""
    plant = Plant(PlantConfig.ideal())
    robot = plant.robot
    p0, R0 = robot.ee_pose(Q_READY)
    tilt = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(0.3), -np.sin(0.3)], [0.0, np.sin(0.3), np.cos(0.3)]])
    ctrl = CPIC(robot, Attractor(p0 + np.array([0.05, -0.05, 0.05]), tilt @ R0))
    problems = []
    rec = run(plant, ctrl, seconds, q0=Q_READY, tau_ext_to_controller=False,
              events=[PayloadChange(0.2, 0.9, (0.05, -0.03, 0.13)), Push(0.3, (0.0, 30.0, -30.0), 0.2)],
              before_step=lambda k, s: problems.append(ctrl.qp(s.q, s.dq)))
    states = list(zip(rec.q, rec.dq))

    def passes(calls, before=None):
        """(repeats, calls) wall times in us: whole passes over all calls (before() runs ahead of each pass)."""
        out = np.empty((repeats, len(calls)))
        for r in range(repeats):
            if before is not None:
                before()
            for k, call in enumerate(calls):
                t0 = time.perf_counter()
                call()
                out[r, k] = 1e6 * (time.perf_counter() - t0)
        return out

    qp_us = passes([lambda P=P: solve_qp(*P) for P in problems])
    active = np.array([len(solve_qp(*P)[1].active) > 0 for P in problems])
    inverses = [np.linalg.inv(P[0]) for P in problems]             # the loop has H^-1 in closed form
    loop_us = passes([lambda P=P, Hi=Hi, W=P[4].tolist():
                      dual_active_set(np.linalg.cholesky(Hi).T, P[1], P[2], P[3], W, 100)
                      for P, Hi in zip(problems, inverses)])
    step_us = passes([lambda q=q, dq=dq: ctrl.step(q, dq) for q, dq in states], before=ctrl.reset)
    model_us = passes([lambda q=q, dq=dq: robot.control_terms(q, dq) for q, dq in states[::10]])
    med = lambda a: float(np.median(a))
    return {"problems": len(problems), "fraction_with_active_constraints": float(active.mean()),
            "solve_qp_median_us": med(qp_us), "solve_qp_none_active_median_us": med(qp_us[:, ~active]),
            "solve_qp_some_active_median_us": med(qp_us[:, active]),
            "in_loop_qp_some_active_median_us": med(loop_us[:, active]),
            "step_median_us": med(step_us), "step_p99_us": float(np.percentile(step_us, 99)),
            "model_terms_median_us": med(model_us),
            "solve_qp_median_best_us": med(qp_us.min(axis=0)), "step_median_best_us": med(step_us.min(axis=0))}


def _judgement_us(robot, phi) -> float:
    """Median microseconds of one judgement of what changed: a reference at rest at the ready pose, the level stepped
    by the torque of the payload phi (4,), two earlier payloads to return to."""
    est, z = RME(robot, rng=np.random.default_rng(0)), np.zeros(robot.n)
    for _ in range(2 * est.settings.changes.short + 5):
        est.update(Q_READY, z, z)                                      # the first level: the reference
    _, R, J = robot.kinematics(Q_READY)
    Y = robot.payload_regressor_from(J, R)
    for _ in range(est.settings.changes.short):
        est.model.push(Y @ phi, z)
    for earlier in ([0.5, 0.0, 0.0, 0.02], [1.5, 0.01, 0.0, 0.1]):
        est.payloads.remember(phi_of(earlier), 1e-4 * np.eye(4))
    return median_us(lambda: est.model.judge(Y, J, np.zeros(4), Q_READY, est.payloads), 500)


def detector_benchmark(episodes=8, seed=0) -> dict:
    """Algorithm 1 as printed (detector.py) on the realistic plant: detection latency (random payloads 0.2-1.5 kg
    added at 1.0 s and removed at 2.5 s, random poses near the ready pose, stiff and compliant holds), false
    detections (lateral pushes, free motion, rest; totals over 3 plants), and the time per update."""
    rng = np.random.default_rng(seed)
    latencies, missed, extra = [], 0, 0
    for i in range(episodes):
        m, r = rng.uniform(0.2, 1.5), (*rng.uniform(-0.08, 0.08, 2), rng.uniform(0.0, 0.15))
        events = [(1.0, m, r), (2.5, 0.0, (0.0, 0.0, 0.0))]
        fired = np.array(detector_episode(3.3, rng, Q_READY + rng.uniform(-0.3, 0.3, 7), events, soft=bool(i % 2)))
        hits = 0
        for t, *_ in events:
            hit = fired[(fired > t) & (fired < t + 0.5)]
            if len(hit):
                latencies.append(1e3 * (hit[0] - t))
                hits += 1
            else:
                missed += 1
        extra += len(fired) - hits                 # detections that answer no change of this episode
    pushes = [((15.0, 0, 0), 0.8, 1.0), ((0, 20.0, 0), 2.5, 0.6), ((8.0, -6.0, 0), 3.5, 1.5), ((30.0, 0, 0), 5.5, 0.2)]
    motion = lambda t: 0.3 * np.sin(np.pi * t) * np.array([1.0, 0.5, 0.0, 0.5, 0.0, 0.5, 0.0])
    plants = [np.random.default_rng(seed + i) for i in range(3)]
    false = dict(pushes_7s=sum(len(detector_episode(7.0, p, pushes=pushes)) for p in plants),
                 motion_5s=sum(len(detector_episode(5.0, p, motion=motion)) for p in plants),
                 rest_5s=sum(len(detector_episode(5.0, p)) for p in plants))
    pct = (lambda p: float(np.percentile(latencies, p))) if latencies else (lambda p: float("nan"))
    out = dict(events=2 * episodes, detected=len(latencies), missed=missed, extra_detections=extra,
               latency_ms_median=pct(50), latency_ms_p90=pct(90), latency_ms_max=pct(100),
               false_detections=false,
               update_us_median={f"window {w}, {'J' if j else 'force'} given": round(_update_us(w, j, rng), 1)
                                 for w in (500, 50_000) for j in (False, True)})
    return out


def _update_us(window, with_jacobian, rng, samples=3000):
    """Median microseconds per update with the paper's windows anchored at the end of a `window`-sample buffer."""
    w = lambda a, b: (a + window - 500, b + window - 500)
    det = Detector(DetectorSettings(window=window, check_windows=(w(431, 450), w(351, 370), w(271, 290)),
                                    end_window=w(491, 500), force_window=w(451, 500)))
    tau, F, J = rng.standard_normal((window + samples, 7)), rng.standard_normal((window + samples, 3)), \
        rng.standard_normal((6, 7))
    times = []
    for k in range(window + samples):
        t0 = time.perf_counter()
        det.update(tau[k], J=J) if with_jacobian else det.update(tau[k], force=F[k])
        times.append(time.perf_counter() - t0)
    return 1e6 * float(np.median(times[window:]))


def vi_benchmark(n_random=14, repeats=5, seed=0) -> dict:
    """Median fit time and iterations on realistic simulated windows (Table 5's payloads at the ready pose and
    n_random random payloads at random poses near it), with the zero prior mean and a calibrated prior
    (truth + sigma_prior * N(0, 1)); the paper's Adam start (q = prior) for comparison."""
    rng = np.random.default_rng(seed)
    cases = [(np.array(th), Q_READY) for th in TABLE5]
    cases += [(np.array([rng.uniform(0.2, 1.5), *rng.uniform(-0.08, 0.08, 2), rng.uniform(0.0, 0.15)]),
               Q_READY + rng.uniform(-0.3, 0.3, 7)) for _ in range(n_random)]
    windows = [(simulated_window(th, rng, q0)[:2], th) for th, q0 in cases]
    sp = np.asarray(vi.VISettings().sigma_prior)
    priors = {"zero": [np.zeros(4)] * len(cases), "calibrated": [th + sp * rng.standard_normal(4) for th, _ in cases]}
    out = {}
    for name, settings in (("warm start (default)", vi.VISettings()),
                           ("q starts at prior", vi.VISettings(warm_start=False))):
        for prior, mu_priors in priors.items():
            ms, its, conv, err, z_mf, z_lap = [], [], [], [], [], []
            for ((Y, tau), th), mu_prior in zip(windows, mu_priors):
                for _ in range(repeats):
                    p = vi.fit(Y, tau, mu_prior, settings, rng)
                    ms.append(1e3 * p.seconds), its.append(p.iterations), conv.append(p.converged)
                err.append(p.mean - th), z_mf.append(np.abs(p.mean - th) / p.std)
                z_lap.append(np.abs(p.mean - th) / p.marginal_std)
            out[f"{name}, {prior} prior mean"] = dict(
                ms_median=round(float(np.median(ms)), 3), ms_p90=round(float(np.percentile(ms, 90)), 3),
                iterations_median=float(np.median(its)), iterations_max=int(np.max(its)),
                converged=float(np.mean(conv)), rmse=np.sqrt(np.mean(np.square(err), 0)).round(4).tolist(),
                cover2_std=(np.array(z_mf) < 2).mean(0).round(2).tolist(),
                cover2_marginal=(np.array(z_lap) < 2).mean(0).round(2).tolist())
    return out


def print_dict(title: str, d: dict, indent: str = "  "):
    """A benchmark's result as labelled lines, nested dicts indented."""
    print(title)
    for k, v in d.items():
        if isinstance(v, dict):
            print_dict(f"{indent}{k}:", v, indent + "  ")
        else:
            print(f"{indent}{k}: {round(v, 3) if isinstance(v, float) else v}")


def diagnose_benchmark(seconds: float = 20.0, repeats: int = 5) -> dict:
    """Median wall time of diagnose on a 20,000-sample, 7-joint log: a multi-sine with Gaz friction and offsets added
    to the nominal torque and white sensor noise (synthetic: no plant needed to time the diagnosis)."""
    rng = np.random.default_rng(0)
    robot = Robot.panda()
    t = 1e-3 * np.arange(int(seconds * 1000))
    q, dq, ddq = multisine(t, ExciteConfig(), rng)
    s = Signals(Log(t, q, dq, ddq, None, np.zeros_like(q)), robot)
    tau_J = s.inverse_dynamics + np.asarray(GAZ_P1) * _sigmoid_shape(dq, np.asarray(GAZ_P2), np.asarray(GAZ_P3))
    tau_J += np.asarray(GAZ_FO) + 0.02 * rng.normal(size=q.shape)
    t0 = time.perf_counter()
    log = prepare({"t": t, "q": q, "dq": dq, "tau_J": tau_J})
    t_load = time.perf_counter() - t0
    times, d = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        d = diagnose(Model.nominal(robot), log)
        times.append(time.perf_counter() - t0)
    res = {"samples": len(log), "joints": log.n, "median_s": float(np.median(times)), "runs": repeats,
           "prepare_s": t_load, "selected": d.selected}
    return res


def worker_benchmark(seconds: float = 8.0, seed: int = 0, workers=("thread", "process", "callback")) -> dict:
    """franka.py's loop (CPIC hold + RME) on the paced realistic plant (one state per ms of wall time, as the robot
    gives them), a load of 1.0 / 0.5 kg added and removed every second, a worker process kept off the loop's CPU
    (franka.own_cpu, as franka.py does). Per worker ("callback": the estimates within
    RME.update): the callback time [ms] over all cycles and over the cycles with an estimate in flight (median, p99,
    max), missed cycles (none on the plant: it waits), the estimates made and the mass compensated at the end."""
    import franka
    from robot.worker import EstimatorSpec, make_worker
    loads = [(t, 1.0 if t % 4 == 1 else 0.5 if t % 4 == 3 else 0.0, (0.03, -0.02, 0.05)) for t in range(1, int(seconds))]
    out = {}
    for kind in workers:
        spec = EstimatorSpec(seed=seed + 1)
        worker = None if kind == "callback" else make_worker(kind, spec)
        backend = franka.SimBackend(np.random.default_rng(seed), payload=loads, paced=True)
        robot = backend.plant.robot
        est, switch = spec.build(executor=worker), sys.getswitchinterval()
        sys.setswitchinterval(1e-4)                # as franka.py
        try:
            with franka.own_cpu([worker.pid] if hasattr(worker, "pid") else []):   # as franka.py
                summary, _ = franka.run_loop(backend, robot, franka.make_controller(robot, backend.initial.q), est,
                                             seconds)
        finally:
            sys.setswitchinterval(switch)
            if worker is not None:
                worker.shutdown()
        out[kind] = {"callback_ms": summary["callback_ms"],
                     "callback_ms_estimate_in_flight": summary["callback_ms_estimate_in_flight"],
                     "missed_cycles": summary["missed_cycles"], "estimates": len(summary["estimates"]),
                     "mass_at_end": summary["theta_hat"][0]}
    return out


def franky_benchmark(seconds: float = 10.0) -> dict:
    """franka.py's loop through pylibfranka against franky-sim on 127.0.0.1 (robot.franky_load.run_client: CPIC
    hold, RME with its estimates in a worker process, 1 kg added to the simulated hand at half time; the loop's
    thread at SCHED_FIFO where permitted, as libfranka runs it on a robot): robot ticks,
    missed packets (libfranka's durations), the states that came late and how many of them followed a cycle of the
    loop (state to command plus the work after the write) that did not fit in 0.9 ms (the others: franky-sim's own
    clock jumping while the loop waited), the callback times [ms], the estimates and the mass at the end."""
    from robot.franky_load import run_client
    summary, log, est = run_client(seconds=seconds, at=int(seconds * 500), realtime=True)
    late = np.flatnonzero(np.diff(log["t"]) > 1.5e-3) + 1          # ticks whose state came late
    busy = 1e3 * (log["callback_s"][late - 1] + log["after_s"][late - 1])   # the loop's cycle before each [ms]
    return {"robot_ticks": summary["cycles"], "loop_at_sched_fifo": summary["realtime"],
            "missed_cycles": summary["missed_cycles"],
            "late_states": len(late), "late_after_a_cycle_over_0.9_ms": int((busy >= 0.9).sum()),
            "callback_ms": summary["callback_ms"],
            "callback_ms_estimate_in_flight": summary["callback_ms_estimate_in_flight"],
            "estimates": [(round(e.t, 3), e.kind, e.accepted, round(float(e.mean[0]), 3)) for e in est.history],
            "mass_at_end": float(est.theta[0])}


if __name__ == "__main__":          # python -m experiments.timing worker | franky
    if sys.argv[1:] not in (["worker"], ["franky"]):
        print("usage: python -m experiments.timing worker | franky  (the other timings: python sim.py timing)")
        sys.exit(2)
    if sys.argv[1] == "franky":     # needs requirements-robot.txt
        print_dict("franka.py loop against franky-sim, 10 s, 1 kg added at 5 s:", franky_benchmark())
    else:
        print_dict("franka.py loop, callback times [ms] by where the estimates run:", worker_benchmark())
