"""The paper's tables reproduced in simulation (Sec. 5.1-5.2, Tables 1, 4 and 5): `python sim.py bench [--json]`."""
from __future__ import annotations

import json
import time

import numpy as np

from cpic import CPIC, Attractor
from dynamics import Q_READY
from error_model import as_error_model
from experiments.baselines import methods
from experiments.runner import PayloadChange, run
from nn_train import DataConfig, random_pose
from rme import RME, RMESettings
from sim import Plant, PlantConfig

TABLE5 = [(0.300, 0.03, 0.00, 0.13), (0.500, 0.06, 0.00, 0.13), (0.700, 0.06, 0.00, 0.13),
          (0.900, 0.05, -0.03, 0.13), (1.100, 0.05, 0.02, 0.13), (1.290, 0.05, 0.01, 0.13)]   # paper Table 5
PAPER = {"table1": {"nn": [0.229e-3, 0.366e-3, 0.629e-3, 2.560e-3], "zero": [0.319e-3, 0.594e-3, 0.880e-3, 6.513e-3]},
         "table4": {"50": [2.480e-3, 1.607e-3, 0.574e-3, 8.935e-3], "100": [2.436e-3, 0.909e-3, 0.468e-3, 4.827e-3],
                    "200": [2.467e-3, 0.86e-3, 0.396e-3, 3.88e-3], "300": [2.081e-3, 0.979e-3, 0.477e-3, 1.25e-3]},
         "estimate_ms_median": 226.0, "attach_to_compensation_ms_median": 400.0}


def datasets(count, seed, t_change=0.6, seconds=3.0, calibration=None):
    """`count` simulated static holds under CPIC at random poses (the network's training distribution of poses and
    payloads, other seeds), a payload attached at t_change, RME streaming in the loop: the windows the pipeline
    itself uses. Each: dict(theta (4,), q, tau (L, 7) referred to the 30 samples before the change for the windows
    of L = 50, 100, 200, 300 ms starting where the pipeline's window at the detection starts (its last
    RMESettings().detection_window samples), q_rest, tau_rest for the 300 samples ending at its last full-window
    estimate (the one it keeps), at_rest (bool), detected (bool), delay [ms]). calibration: RME's error model
    (error_model.as_error_model)."""
    rng, cfg, out = np.random.default_rng(seed), DataConfig(), []
    lo, hi = np.array([cfg.m_range[0], *cfg.r_low]), np.array([cfg.m_range[1], *cfg.r_high])
    for _ in range(count):
        plant = Plant(PlantConfig.realistic(rng), rng=rng)
        robot = plant.robot
        q0, theta = random_pose(robot, rng, cfg), rng.uniform(lo, hi)
        ctrl, est = CPIC(robot, Attractor(*robot.ee_pose(q0))), RME(robot, rng=np.random.default_rng(seed),
                                                                       calibration=calibration)
        rec = run(plant, ctrl, seconds, estimator=est, events=[PayloadChange(t_change, theta[0], theta[1:])], q0=q0)
        Q = np.concatenate([rec.q[1:], [rec.last.q]])             # the samples after each step
        TAU = np.concatenate([rec.tau_ext[1:], [rec.last.tau_ext]])
        k_change = int(round(t_change / plant.dt)) - 1              # sample i is at time (i + 1) dt
        hits = [e for e in est.history if e.t > t_change]
        det = [e for e in hits if e.kind == "detection"]            # not a later estimate (monitor, at rest, a held
        k_det = int(round(det[0].t / plant.dt)) - 1 if det else k_change + 300   # change's): its window ends at e.t
        ref = TAU[k_change - 30:k_change].mean(axis=0)
        start = k_det - RMESettings().detection_window
        rest = [e for e in hits if e.kind == "at rest"]
        k_rest = int(round(rest[-1].t / plant.dt)) if rest else len(Q)   # the last: the estimate kept
        out.append(dict(theta=theta, q=Q[start:start + 300], tau=TAU[start:start + 300] - ref, detected=bool(det),
                        delay=(k_det - k_change) * plant.dt * 1e3, q_rest=Q[k_rest - 300:k_rest],
                        tau_rest=TAU[k_rest - 300:k_rest] - ref, at_rest=bool(rest)))
    return out


def mse_table(est, data, length, at_rest=True):
    """MSE per parameter of est.estimate on each dataset's window of `length` samples: the one ending where RME made
    the last of its full-window estimates, the one it keeps (at_rest), or the one starting where the pipeline's
    window at the detection starts; and the wall times."""
    err, secs = [], []
    for d in data:
        q, tau = (d["q_rest"][-length:], d["tau_rest"][-length:]) if at_rest else (d["q"][:length], d["tau"][:length])
        e = est.estimate(q, tau, referred=True)
        err.append(e.mean - d["theta"])
        secs.append(e.seconds)
    return np.mean(np.square(err), axis=0).tolist(), secs


def closed_loop_trial(theta, seed, t_attach=0.75, seconds=2.5, calibration=None):
    """Realistic plant held at the ready pose by CPIC, payload attached at t_attach, RME streaming in the loop.
    Returns (first estimate after the attach, last applied estimate, ms from the attach to the compensation being
    applied); the estimates are None when nothing was detected."""
    rng = np.random.default_rng(seed)
    plant = Plant(PlantConfig.realistic(rng), rng=rng)
    robot = plant.robot
    est = RME(robot, rng=np.random.default_rng(seed + 1), calibration=calibration)
    ctrl = CPIC(robot, Attractor(*robot.ee_pose(Q_READY)))
    rec = run(plant, ctrl, seconds, estimator=est, events=[PayloadChange(t_attach, theta[0], theta[1:])], q0=Q_READY)
    on = np.flatnonzero((rec.t > t_attach) & np.any(rec.theta_hat != 0.0, axis=1))
    applied_at = rec.t[on[0]] if len(on) else None
    after = [e for e in est.history if e.t > t_attach and e.accepted]
    latency = np.nan if applied_at is None else (applied_at - t_attach) * 1e3
    return (after[0], after[-1], latency) if after else (None, None, latency)


def tables(n_datasets=100, trials=10, seed=0, log=print, calibration=None):
    """Tables 1, 4 and 5 and the two latencies, as one dict (the JSON of `python sim.py bench --json`); every RME
    with the error model `calibration` (None: the uncalibrated Panda's)."""
    t0 = time.perf_counter()
    data = datasets(n_datasets, seed=10_000 + seed, calibration=calibration)
    detected = sum(d["detected"] for d in data)
    log(f"simulated {n_datasets} datasets in {time.perf_counter() - t0:.0f} s; {detected} detections")
    nn, zero = RME(rng=np.random.default_rng(seed), calibration=calibration), RME(
        settings=RMESettings(use_network=False), rng=np.random.default_rng(seed), calibration=calibration)
    t1_nn, secs = mse_table(nn, data, 200)
    t1_zero, _ = mse_table(zero, data, 200)
    t1_base = {k: mse_table(e, data, 200)[0] for k, e in methods(seed=seed, calibration=calibration).items()
               if k != "RME"}   # beside them
    w = RMESettings().detection_window                               # the window the pipeline estimates at detection
    t1_first = {k: mse_table(e, data, w, at_rest=False)[0] for k, e in (("nn", nn), ("zero", zero))}
    t4 = {str(L): mse_table(nn, data, L)[0] for L in (50, 100, 200, 300)}
    t4_first = {str(L): mse_table(nn, data, L, at_rest=False)[0] for L in (50, 100, 200, 300)}
    log(f"tables 1 and 4 done at {time.perf_counter() - t0:.0f} s")
    t5, latencies = [], []
    for i, theta in enumerate(TABLE5):
        first, final, seen = [], [], 0
        for k in range(trials):
            e0, e1, ms = closed_loop_trial(np.array(theta), seed=1000 * (i + 1) + k + seed,
                                              calibration=calibration)
            latencies.append(ms)
            if e0 is not None:
                first.append(e0.mean), final.append(e1.mean)
                seen += bool(e1.observed[3])         # rz observed at rest (else the prior's)
        first, final = (np.array(v) if v else np.full((1, 4), np.nan) for v in (first, final))
        t5.append({"applied": list(theta), "mean": final.mean(0).tolist(), "std": final.std(0).tolist(),
                   "first_mean": first.mean(0).tolist(), "first_std": first.std(0).tolist(),
                   "detected": int(np.isfinite(first[:, 0]).sum()), "trials": trials, "rz_observed": seen})
        log(f"table 5 payload {theta}: first {np.round(first.mean(0), 3)}, at rest {np.round(final.mean(0), 3)}")
    return {"table1": {"nn": t1_nn, "zero": t1_zero}, "table1_baselines": t1_base, "table4": t4, "table5": t5,
            "table1_first": t1_first, "table4_first": t4_first, "table1_detected": int(detected),
            "table1_at_rest": int(sum(d["at_rest"] for d in data)),
            "estimate_ms_median": float(np.median(secs) * 1e3),
            "attach_to_compensation_ms_median": float(np.nanmedian(latencies)) if np.isfinite(latencies).any() else None,
            "attach_to_compensation_ms_all": [None if np.isnan(x) else float(x) for x in latencies],   # None: missed
            "settings": {"datasets": n_datasets, "trials": trials, "seed": seed, "preset": "realistic"}}


def print_tables(res):
    fmt = lambda v: "  ".join(f"{x * 1e3:7.3f}" for x in v)
    print("MSE x 1e-3        m [kg^2]  rx [m^2]  ry [m^2]  rz [m^2]      paper")
    for k in ("nn", "zero"):
        print(f"Table 1 {k:>5}:   {fmt(res['table1'][k])}     {fmt(PAPER['table1'][k])}")
    for k, v in res["table1_baselines"].items():
        print(f"  {k:>13}:   {fmt(v)}     (baseline, the same windows)")
    for k in ("nn", "zero"):
        print(f"  first {k:>5}:    {fmt(res['table1_first'][k])}   (windows at the detection)")
    for k, v in res["table4"].items():
        print(f"Table 4 {k:>3} ms:  {fmt(v)}     {fmt(PAPER['table4'][k])}")
    for k, v in res["table4_first"].items():
        print(f"  first {k:>3} ms:  {fmt(v)}")
    print(f"({res['table1_detected']} of {res['settings']['datasets']} changes estimated at their detection, "
          f"{res['table1_at_rest']} estimated at rest; the others' windows are taken at fixed times)")
    print("Table 5: applied (m, rx, ry, rz) -> mean +- std over the trials: first estimate | estimate at rest")
    for row in res["table5"]:
        first = "  ".join(f"{m:6.3f}+-{s:5.3f}" for m, s in zip(row["first_mean"], row["first_std"]))
        rest = "  ".join(f"{m:6.3f}+-{s:5.3f}" for m, s in zip(row["mean"], row["std"]))
        print(f"  {row['applied']}\n     first:   {first}\n     at rest: {rest}   ({row['detected']}/{row['trials']} detected)")
        if row.get("rz_observed", row["detected"]) < row["detected"]:
            print(f"              rz: prior, not observed at this pose ({row['detected'] - row['rz_observed']} of "
                  f"{row['detected']} trials)")
    print(f"estimate (network + VI) median: {res['estimate_ms_median']:.2f} ms (paper: 226 ms)")
    print(f"load change -> compensation applied, median: {res['attach_to_compensation_ms_median']:.0f} ms "
          f"(paper: about 400 ms)")


def bench(args):
    as_error_model(args.calibration)                     # a calibration that cannot be read: before the work
    res = tables(seed=args.seed, log=(lambda *a: None) if args.json else print, calibration=args.calibration)
    print(json.dumps(res) if args.json else "", end="\n" if args.json else "")
    if not args.json:
        print_tables(res)
    return res
