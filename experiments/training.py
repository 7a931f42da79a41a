"""The network's training data and its retraining (Appendix F, Table 6): static holds on the realistic plant with
random payloads, three referred windows per episode; `python nn_numpy.py train` retrains weights.npz from scratch,
`python nn_numpy.py bench` times the network and scores it on fresh episodes."""
from __future__ import annotations

import os
import sys
import time
from dataclasses import asdict, replace

import numpy as np

import checks
from cpic import JointHold
from dynamics import Q_READY, Robot
from experiments.episodes import measure
from experiments.timing_tools import median_us
from nn_numpy import (WEIGHTS, MismatchNet, NetConfig, backward, feature_regressor, features, forward, init_params,
                      save_weights)
from nn_train import (DataConfig, TrainConfig, adam_step, mse_loss, random_pose, split_by_episode, train)
from sim import Plant, PlantConfig


def simulate_episode(q0, theta, delays, rng, cfg=DataConfig()):
    """Hold q0 on a realistic plant, attach theta at t_change, return the referred windows.

    Returns q (k, window, 7) and tau_ext (k, window, 7) - mean(tau_ext over t_ref before the change),
    one per delay (s after the change). Simulates only up to the end of the last window."""
    plant = Plant(PlantConfig.realistic(rng), rng=rng)
    dt, hold = plant.dt, JointHold(plant.robot, q0, cfg.hold_kp, cfg.hold_kd)     # gravity + PD hold
    i_change = int(round(cfg.t_change / dt))
    starts = i_change + np.round(np.asarray(delays) / dt).astype(int)
    n_steps = int(starts.max()) + cfg.window
    plant.schedule_payload(cfg.t_change, theta[0], theta[1:])
    log = measure(plant, hold, n_steps * dt, q0=q0)
    Q, T = log["q"], log["tau_ext"]              # sample i is at time (i + 1) dt
    i_ref = i_change - int(round(cfg.t_ref / dt))
    ref = T[i_ref - 1:i_change - 1].mean(0)      # samples at times in [t_change - t_ref, t_change)
    k = np.arange(cfg.window)
    return Q[starts[:, None] + k], T[starts[:, None] + k] - ref


def make_dataset(n_episodes, rng, cfg=DataConfig(), net=NetConfig()):
    """Simulated windows: {'x' (N, M, 6) raw pseudo-wrenches, 'theta' (N, 4), 'A' (N, M, 6, 4) the
    feature_regressor, 'episode' (N,), 'delay' (N,)}."""
    if int(n_episodes) < 1:
        raise ValueError(f"n_episodes: expected >= 1, found {n_episodes}")
    robot = Robot.panda()
    lo, hi = np.array([cfg.m_range[0], *cfg.r_low]), np.array([cfg.m_range[1], *cfg.r_high])
    xs, As, thetas, eps, delays = [], [], [], [], []
    for e in range(int(n_episodes)):
        q0 = random_pose(robot, rng, cfg)
        theta = rng.uniform(lo, hi)
        d = rng.uniform(0.0, cfg.delay_max, cfg.windows_per_episode)
        Qw, Tw = simulate_episode(q0, theta, d, rng, cfg)
        for j in range(len(d)):
            xs.append(features(robot, Qw[j], Tw[j], net)), As.append(feature_regressor(robot, Qw[j], net))
            thetas.append(theta), eps.append(e), delays.append(d[j])
    return {"x": np.array(xs), "theta": np.array(thetas), "A": np.array(As), "episode": np.array(eps),
            "delay": np.array(delays)}



def train_from_scratch(episodes=350, seed=0, out=WEIGHTS, cfg=TrainConfig(), data_cfg=DataConfig(),
                       net=NetConfig(), log=print):
    """Simulate the data, split 80/20 by episode, train, write the weights file; returns its metadata."""
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    data = make_dataset(episodes, rng, data_cfg, net)
    t_data = time.perf_counter() - t0
    tr, va = split_by_episode(data, rng, cfg.val_fraction)
    log(f"data: {episodes} episodes -> {len(tr['x'])} train / {len(va['x'])} val windows in {t_data:.1f} s")
    cfg = replace(cfg, episodes=episodes)
    params, stats, info = train(tr, va, rng, cfg, net, log=log)
    meta = {"net": asdict(net), "data": asdict(data_cfg), "train": asdict(cfg), "episodes": episodes,
            "seed": seed, "n_train": len(tr["x"]), "n_val": len(va["x"]), "data_seconds": t_data,
            "wrench_frame": "ee", "tau_ext": "referred: minus its mean over t_ref before the load change",
            "target_scaling": "(theta - theta_mean) / theta_std per output, training-set stats",
            "numpy": np.__version__, **info}
    save_weights(out, params, stats, meta)
    log(f"wrote {out}: val MSE m {info['val_mse'][0]:.3e} kg^2, rx {info['val_mse'][1]:.3e}, "
        f"ry {info['val_mse'][2]:.3e}, rz {info['val_mse'][3]:.3e} m^2 ({info['seconds']:.0f} s training)")
    return meta


def held_out_mse(model, n_episodes=40, seed=2024):
    """MSE per parameter (4,) of the model and of the training-set mean on fresh simulated windows."""
    d = make_dataset(n_episodes, np.random.default_rng(seed), net=model.net)
    err = model.predict(d["x"]) - d["theta"]
    return (err ** 2).mean(0), ((model.stats["theta_mean"] - d["theta"]) ** 2).mean(0)


def benchmark(path=WEIGHTS, repeats=2000, held_out_episodes=40):
    """Timings (keys ending in "_us": medians in microseconds) of one window's forward pass (`repeats` calls), of
    `features` for a 200-sample window (repeats / 4) and of one training step, batch 32 (repeats / 10), then the
    training figures stored in the weights file and the MSE on `held_out_episodes` fresh simulated episodes."""
    if int(repeats) < 10:
        raise ValueError(f"repeats: expected an integer >= 10, found {repeats}")
    model, rng, robot = MismatchNet.load(path), np.random.default_rng(0), Robot.panda()
    x1 = rng.standard_normal((1, 20, 6)) * model.stats["x_std"] + model.stats["x_mean"]
    q = Q_READY + 0.01 * rng.standard_normal((200, 7))                    # a 200 ms window at 1 kHz (T, 7)
    tau = 0.1 * rng.standard_normal((200, 7))
    xb, tb = rng.standard_normal((32, 20, 6)), rng.standard_normal((32, 4))
    params, state = init_params(rng), {}

    def step():
        y, cache = forward(xb, params, rng=rng)
        adam_step(params, backward(mse_loss(y, tb)[1], cache)[1], state, 1e-4)
    out = {"forward_median_us": median_us(lambda: model.predict(x1), int(repeats)),
           "features_median_us": median_us(lambda: features(robot, q, tau), int(repeats) // 4),
           "train_step_median_us": median_us(step, int(repeats) // 10)}
    out["train_samples_per_s"] = 32 / (1e-6 * out["train_step_median_us"])
    m = model.meta
    out.update(training_seconds=m.get("seconds"), data_seconds=m.get("data_seconds"), iterations=m.get("iterations"),
               epochs=m.get("epochs"), val_mse=m.get("val_mse"))
    if held_out_episodes > 0:
        nn_mse, mean_mse = held_out_mse(model, held_out_episodes)
        out.update(held_out_mse=nn_mse.tolist(), held_out_mean_mse=mean_mse.tolist())
    return out


def main(argv=None):
    ap = checks.Parser(prog="nn_numpy.py", description=__doc__)
    ap.add_argument("command", choices=["train", "bench"])
    ap.add_argument("--episodes", type=checks.argument("1..100000"), default=TrainConfig.episodes,
                    help="train: simulated episodes, 1..100000")
    ap.add_argument("--seed", type=checks.argument("0..4294967295"), default=0, help="train: the seed of the data's "
                    "and the training's np.random.Generator, 0..4294967295")
    ap.add_argument("--out", default=WEIGHTS, help="train: the weights file to write (its folder must exist); "
                    "bench: the weights file to time")
    a = ap.parse_args(argv)
    if a.command == "train" and not os.path.isdir(os.path.dirname(os.path.abspath(a.out))):
        ap.error(f"--out: expected a file in an existing folder, found {a.out!r}")
    if a.command == "bench" and not os.path.isfile(a.out):
        ap.error(f"--out: expected a weights file to read, found no file at {a.out!r}")
    try:
        if a.command == "train":
            train_from_scratch(a.episodes, a.seed, a.out, log=lambda s: print(s, flush=True))
        else:
            print_benchmark(benchmark(a.out), a.out)
    except (ValueError, OSError) as err:            # a failure is one line on stderr, no traceback
        print(f"nn_numpy.py {a.command}: {type(err).__name__}: {err}", file=sys.stderr)
        return 1
    return 0


def print_benchmark(r: dict, path: str):
    """benchmark's result as labelled tables: what this run measured, and what the weights file records of the run
    that trained it."""
    from experiments.timing_tools import print_table
    print_table("the network's time, measured in this run", ["call", "median [us]"],
                [["forward, one window", f"{r['forward_median_us']:.1f}"],
                 ["features of a 200-sample window", f"{r['features_median_us']:.1f}"],
                 ["training step, batch 32", f"{r['train_step_median_us']:.0f}"]],
                f"training throughput: {r['train_samples_per_s']:.0f} samples/s.")
    rec = lambda v, fmt: "-" if v is None else " ".join(format(x, fmt) for x in np.atleast_1d(v))
    print_table(f"\nrecorded in {path} by the run that trained it (not measured now)", ["training [s]",
                "data generation [s]", "iterations", "epochs", "validation MSE m, rx, ry, rz [kg^2, m^2]"],
                [[rec(r["training_seconds"], ".0f"), rec(r["data_seconds"], ".0f"), rec(r["iterations"], "d"),
                  rec(r["epochs"], "d"), rec(r["val_mse"], ".2e")]], "")
    if "held_out_mse" in r:
        print_table("\nMSE on fresh simulated episodes (measured now)", ["predictor", "m [kg^2]", "rx [m^2]",
                    "ry [m^2]", "rz [m^2]"], [[name, *(f"{v:.2e}" for v in r[key])] for name, key in
                                              (("network", "held_out_mse"), ("training-set mean", "held_out_mean_mse"))],
                    "lower is better; the training-set mean is what a network that learned nothing would score.")
