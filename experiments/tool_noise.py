"""The fit's noise std against the torque sensor's part of the residual (docs/tool_identification.md): that part and
its stale cycles through the fit in std, and the plant's sensor noise drawn alone through the fit.
python -m experiments.tool_noise --seeds 0-9 [--draws 60] [--no-stale] [--fill]"""
from __future__ import annotations

import argparse
import dataclasses

import numpy as np
from scipy.signal import savgol_coeffs, savgol_filter

import experiments.tool_izz as tz
import motion.tool_id as ti
import sim
from dynamics import Robot
import franka
from experiments.tool_bench import draw_tool
from motion.tool_forms import params_of_tool
from robot.identify import prepared, run_motion, sim_backend, torque_of

S = tz.S
FIT = dataclasses.replace(S.fit, offsets=False)
WINDOW = 77             # samples: robot.identify.LOG's 0.075 s at 1 kHz, as diagnosis.logs.prepare rounds it


def filter_correlation():
    """The rows' noise autocorrelation (lags 0-8 rows) of white noise through the log's filter, its long-run
    variance over a row's, and the same summed with the sandwich's Bartlett weights."""
    c = savgol_coeffs(WINDOW, 3)
    r = np.array([c[:len(c) - S.every * k] @ c[S.every * k:] if S.every * k < len(c) else 0.0
                  for k in range(9)]) / (c @ c)
    bartlett = 1 + 2 * sum((1 - k / (S.hac_lags + 1)) * r[k] for k in range(1, 9))
    return r, 1 + 2 * r[1:].sum(), bartlett


def fit_parts(Y, tau, Z):
    """The fit as fit_tool's referred one: values (10,), noise std (10,) and the linear response c -> (10,)."""
    pi, info, Yr, tr, Yw, tw, Zw = ti._weighted_fit(Y, tau, Z, FIT, S.drive_share)
    J = ti._jacobian(pi)
    std = np.sqrt(ti._noise_variance(J, info, Yr, tr, S))
    scale, w2 = tw / np.where(tau == 0, 1.0, tau), info.weights ** 2
    G = np.einsum("j,tji,tjk->ik", w2, Yr, Yr) + np.diag(1.0 / np.square([*FIT.prior_std, *[FIT.inertia_std] * 6]))
    respond = lambda c: J @ np.linalg.solve(G, np.einsum("j,tji,tj->i", w2, Yr, ti.partial_out(Yw, c * scale, Zw)[1]))
    return ti._parameters(pi), std, respond


def sensor_noise(rng, T, rows):
    """(rows, 7) the realistic plant's white torque noise and quantisation (sim.PlantConfig.realistic), both runs,
    through the log's filter."""
    c = sim.PlantConfig.realistic(np.random.default_rng(0))
    sd, step = np.asarray(c.tau_noise), np.asarray(c.tau_step)
    runs = [sd * rng.normal(size=(T, 7)) + step * rng.uniform(-0.5, 0.5, size=(T, 7)) for _ in range(2)]
    return savgol_filter(runs[0] + runs[1], WINDOW, 3, axis=0, mode="interp")[rows]


def drawn(d, rng, draws):
    """(draws, 10) errors / the fit's noise std of the plant's sensor noise alone on the seed's rows and columns."""
    base, T = d["Y"] @ ti._weighted_fit(d["Y"], d["tau"], d["Z_this"], FIT, S.drive_share)[0], d["samples"]
    rows = np.arange(S.edge, T - S.edge, S.every)
    out = [fit_parts(d["Y"], base + sensor_noise(rng, T, rows), d["Z_this"])[:2] for _ in range(draws)]
    v, s = np.array([o[0] for o in out]), np.array([o[1] for o in out])
    return (v - v.mean(0)) / s * np.sqrt(draws / (draws - 1))


def fills(robot, seed) -> dict:
    """The bench's two motions of `seed`, fitted with the stale rows dropped and filled (robot.identify.prepared):
    per way (value - truth, std, observed, truth) (10,) each."""
    tool = draw_tool(np.random.default_rng([seed, 32]))
    ref = run_motion(sim_backend(seed, None, 0), robot, franka.run_loop)[0]
    run = run_motion(sim_backend(seed, tool, 1), robot, franka.run_loop, center=ref["q"][0])[0]
    truth, out = np.array([ti.truth_of(tool)[k] for k in ti.NAMES]), {}
    for name, fill in (("stale rows dropped", False), ("stale rows filled", True)):
        t, r = prepared(run, fill), prepared(ref, fill)
        f = ti.fit_tool(robot, t.q, t.dq, t.ddq, torque_of(robot, t), reference=(r.q, r.dq, r.ddq, torque_of(robot, r)))
        out[name] = tuple(np.array([x[k] for k in ti.NAMES]) for x in (f.value, f.std, f.observed)) + (truth,)
        out[name] = (out[name][0] - truth, *out[name][1:])
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", default="0-9", help="first-last (inclusive)")
    ap.add_argument("--draws", type=int, default=60, help="draws of the sensor noise per seed (0: none)")
    ap.add_argument("--no-stale", action="store_true", help="the plant without stale packets (stale_prob 0)")
    ap.add_argument("--fill", action="store_true", help="only the fits with the stale rows dropped and filled")
    a = ap.parse_args(argv)
    lo, hi = map(int, a.seeds.split("-"))
    if a.fill:
        robot, fit = Robot.panda(), {}
        for seed in range(lo, hi + 1):
            for k, v in fills(robot, seed).items():
                fit.setdefault(k, []).append(v)
        tz.print_fits(fit)
        return
    if a.no_stale:
        realistic = sim.PlantConfig.realistic
        sim.PlantConfig.realistic = staticmethod(lambda rng: dataclasses.replace(realistic(rng), stale_prob=0.0))
    r, long_run, bartlett = filter_correlation()
    print(f"rows' noise autocorrelation, lags 0-8: {np.round(r, 3).tolist()}; long-run / row variance "
          f"{long_run:.2f}, with Bartlett over {S.hac_lags} rows {bartlett:.2f}")
    robot, z, rel, draws = Robot.panda(), {}, {}, []
    for seed in range(lo, hi + 1):
        d = tz.seed_data(robot, seed)
        value, std, respond = fit_parts(d["Y"], d["tau"], d["Z_this"])
        truth = ti._parameters(params_of_tool(d["tool"]))
        parts = {"torque sensor": respond(d["parts"]["torque sensor"]), "stale cycles": respond(d["stale cycles"])}
        parts["the rest of the sensor's"] = parts["torque sensor"] - parts["stale cycles"]
        parts["the fit's error"] = value - truth
        for k, v in parts.items():
            z.setdefault(k, []).append(v / std)
            rel.setdefault(k, []).append(100 * v[4:7] / truth[4:7])
        if a.draws:
            draws.append(drawn(d, np.random.default_rng([seed, 6]), a.draws))
        print(f"seed {seed}: Izz of the torque sensor's part {rel['torque sensor'][-1][2]:+.2f} %, of its stale "
              f"cycles {rel['stale cycles'][-1][2]:+.2f} %", flush=True)
    rms = lambda x: np.round(np.sqrt(np.mean(np.square(x), axis=0)), 2).tolist()
    print("per part: / the fit's noise std, mean and rms (mass, CoM x y z, Ixx Iyy Izz, Ixy Ixz Iyz); Ixx, Iyy, Izz "
          "[%] mean (sd)")
    for k in z:
        print(f"  {k:26s} {np.round(np.mean(z[k], 0), 2).tolist()}; {rms(z[k])}; "
              f"{np.round(np.mean(rel[k], 0), 2).tolist()} ({np.round(np.std(rel[k], 0), 2).tolist()})")
    if draws:
        e = np.concatenate(draws)
        print(f"the plant's sensor noise alone, {len(e)} draws: errors / std rms {rms(e)}, beyond 2 std "
              f"{np.round(100 * (np.abs(e) > 2).mean(0), 1).tolist()} %")


if __name__ == "__main__":
    main()
