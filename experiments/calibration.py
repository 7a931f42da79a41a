"""Calibration of RME's uncertainty on the realistic preset: coverage of the 2-sigma intervals and sharpness
(mean sigma / RMS error) per parameter, at poses where rz is and is not observed, and the spread of estimates
over rest windows of one unchanged load: `python sim.py calibration [--windows N] [--seed S] [--json]`."""
from __future__ import annotations

import json

import numpy as np

from cpic import JointHold
from dynamics import Q_READY
from error_model import as_error_model
from experiments.baselines import methods
from experiments.episodes import measure, simulated_window
from nn_train import DataConfig, random_pose
from rme import RME
from sim import Plant, PlantConfig

NAMES = ("m", "rx", "ry", "rz")


def calibration_windows(count, rng, cfg=DataConfig()):
    """`count` realistic windows (simulated_window), payloads uniform over the network's training box; even ones at
    the ready pose (rz not observable), odd ones at random poses (random_pose: the ee tilted up to 60 deg), the window
    starting 0.1-0.4 s after the attachment (the arm still settling to at rest). Each: dict(theta, q, tau, ready)."""
    lo, hi = np.array([cfg.m_range[0], *cfg.r_low]), np.array([cfg.m_range[1], *cfg.r_high])
    out = []
    for i in range(count):
        q0 = Q_READY if i % 2 == 0 else random_pose(Plant().robot, rng, cfg)
        theta = rng.uniform(lo, hi)
        _, tau, q = simulated_window(theta, rng, q0, delay=rng.uniform(0.1, 0.4))
        out.append(dict(theta=theta, q=q, tau=tau, ready=i % 2 == 0))
    return out


def coverage(estimates, thetas):
    """Per parameter (4,): share of |mean - theta| < 2 std, mean std / RMS error, RMS error, count."""
    err = np.array([e.mean - th for e, th in zip(estimates, thetas)]).reshape(-1, 4)
    std = np.array([e.std for e in estimates]).reshape(-1, 4)
    rms = np.sqrt(np.mean(err**2, axis=0)) if len(err) else np.full(4, np.nan)
    none = np.isnan(std).all(axis=0) if len(err) else np.ones(4, bool)         # a method that reports no sigma
    return dict(coverage=np.where(none, np.nan, np.mean(np.abs(err) < 2 * std, axis=0)).tolist() if len(err) else
                [np.nan] * 4,
                sharpness=(std.mean(axis=0) / rms).tolist() if len(err) else [np.nan] * 4,
                rmse=rms.tolist(), count=len(err))


def calibration_table(windows, est):
    """The estimates of est on windows, grouped: all, ready pose, random poses; and rz where observed / not."""
    E = [est.estimate(w["q"], w["tau"], referred=True) for w in windows]
    th = [w["theta"] for w in windows]
    pick = lambda keep: ([e for e, k in zip(E, keep) if k], [t for t, k in zip(th, keep) if k])
    ready = [w["ready"] for w in windows]
    seen = [bool(e.observed[3]) for e in E]
    return {"all": coverage(E, th), "ready pose": coverage(*pick(ready)),
            "random poses": coverage(*pick([not r for r in ready])),
            "rz observed": coverage(*pick(seen)), "rz not observed": coverage(*pick([not s for s in seen]))}


def rest_spread(rng, windows=20, theta=(0.8, 0.03, -0.02, 0.12), length=200, calibration=None):
    """One load held still at the ready pose (realistic plant, JointHold), `windows` consecutive rest windows of
    `length` samples from 1 s after the attachment, each referred to the same 100 ms before it: the spread (std)
    of the estimates across the windows against the mean reported std, per parameter."""
    plant = Plant(PlantConfig.realistic(rng), rng=rng)
    first = plant.reset(Q_READY)
    plant.schedule_payload(0.5, theta[0], theta[1:])
    log = measure(plant, JointHold(plant.robot, Q_READY), 1.5 + windows * length * plant.dt, first)
    t, est = log["t"], RME(plant.robot, rng=np.random.default_rng(0), calibration=calibration)
    ref = log["tau_ext"][(t > 0.4) & (t <= 0.5)].mean(axis=0)
    k0 = int(np.searchsorted(t, 1.5))
    E = [est.estimate(log["q"][k:k + length], log["tau_ext"][k:k + length], baseline=ref)
         for k in range(k0, k0 + windows * length, length)]
    spread, sigma = np.std([e.mean for e in E], axis=0, ddof=1), np.mean([e.std for e in E], axis=0)
    return dict(spread=spread.tolist(), mean_std=sigma.tolist(), windows=windows, theta=list(theta),
                rmse=np.sqrt(np.mean([(e.mean - theta) ** 2 for e in E], axis=0)).tolist())


def calibration_benchmark(windows=200, seed=0, calibration=None):
    """The whole benchmark as one dict (the JSON of `python sim.py calibration --json`): RME's table, and the
    baselines' (least squares: RMS error only; the range rule) on the same windows; RME with the error model
    `calibration` (None: the uncalibrated Panda's)."""
    rng = np.random.default_rng(seed)
    wins = calibration_windows(windows, rng)
    table = calibration_table(wins, RME(rng=np.random.default_rng(seed), calibration=calibration))
    base = {name: calibration_table(wins, est)["all"] for name, est in methods(seed=seed).items() if name != "RME"}
    return dict(table=table, baselines=base, rest=rest_spread(rng, calibration=calibration),
                settings=dict(windows=windows, seed=seed, preset="realistic",
                              calibration=None if calibration is None else str(calibration)))


def print_benchmark(res):
    print("2-sigma coverage [%] | sharpness = mean sigma / RMS error | RMS error (kg, m), realistic preset")
    print(f"{'group':<16}{'n':>5}  " + "".join(f"{n:>22}" for n in NAMES))
    for group, row in res["table"].items():
        cells = [f"{100 * c:5.1f} | {s:4.2f} | {r:.4f}" for c, s, r in zip(row["coverage"], row["sharpness"], row["rmse"])]
        print(f"{group:<16}{row['count']:>5}  " + "".join(f"{c:>22}" for c in cells))
    for name, row in res["baselines"].items():
        cells = [f"{'-' if np.isnan(c) else f'{100 * c:5.1f}'} | {'-' if np.isnan(sh) else f'{sh:4.2f}'} | {r:.4f}"
                 for c, sh, r in zip(row["coverage"], row["sharpness"], row["rmse"])]
        print(f"{name + ' (all)':<16}{row['count']:>5}  " + "".join(f"{c:>22}" for c in cells))
    rest = res["rest"]
    print(f"rest windows of one load {rest['theta']} ({rest['windows']} x 200 ms): spread across windows vs mean sigma")
    for n, sp, sd in zip(NAMES, rest["spread"], rest["mean_std"]):
        print(f"  {n:<3} spread {sp:.4f}  sigma {sd:.4f}  sigma/spread {sd / sp:5.2f}")


def main(args):
    as_error_model(args.calibration)                     # a calibration that cannot be read: before the work
    res = calibration_benchmark(windows=args.windows, seed=args.seed, calibration=args.calibration)
    print(json.dumps(res)) if args.json else print_benchmark(res)
    return res
