"""RME on real robot logs of one unchanged load, beside plain least squares and the authors' range noise rule:
per 200 ms rest window, the mass and CoM, their spread over windows, the reported sigma and how often 2 sigma holds
the pooled least-squares value. `python sim.py real-logs DIR [--calibration FILE] [--json]`."""
from __future__ import annotations

import glob
import json
import os

import numpy as np

import vi
from diagnosis.calibrate import RestConfig, pooled_payload, rest_data
from diagnosis.logs import load_log
from dynamics import theta_of
from rme import RME, RMESettings

NAMES = ("m", "rx", "ry", "rz")


def least_squares(Y, tau, ridge=RestConfig.ridge):
    """Plain least squares on one window's means: tau (n,) = Y (n, 4) phi, a tiny ridge. Returns theta (4,)."""
    G = Y.T @ Y
    return theta_of(np.linalg.solve(G + ridge * np.trace(G) * np.eye(4), Y.T @ tau))


def methods(robot, rng_seed=0, calibration=None):
    """{name: estimate(q, tau, baseline) -> (mean (4,), std (4,))}: plain least squares (no std), the authors' range
    rule (VISettings(noise_rule="range")), RME as shipped (or with the calibration given)."""
    make = lambda **kw: RME(robot, rng=np.random.default_rng(rng_seed), **kw)
    rme, rng_rule = make(calibration=calibration), make(settings=RMESettings(vi=vi.VISettings(noise_rule="range")))
    ls = lambda q, tau, base: (least_squares(robot.payload_regressor(q).mean(axis=0),
                                             tau.mean(axis=0) - (0 if base is None else base)), np.full(4, np.nan))
    run = lambda est: (lambda q, tau, base: (lambda e: (e.mean, e.std, e.prior_source))(est.estimate(q, tau, base)))
    return {"least squares": ls, "range rule": run(rng_rule), "RME": run(rme)}


def _summary(M, S, truth, names=NAMES):
    """Per parameter: median, spread (std over windows), median reported sigma, 2-sigma coverage of truth."""
    out = {}
    for i, name in enumerate(names):
        m, s = M[:, i], S[:, i]
        ok = np.isfinite(m)
        out[name] = dict(median=float(np.median(m[ok])) if ok.any() else None,
                         spread=float(np.std(m[ok])) if ok.sum() > 1 else None,
                         sigma=float(np.median(s[ok])) if np.isfinite(s[ok]).any() else None,
                         coverage=float(np.mean(np.abs(m[ok] - truth[i]) < 2 * s[ok])) if np.isfinite(s[ok]).any()
                         else None)
    return out


def real_logs(paths, calibration=None, config: RestConfig = RestConfig()) -> dict:
    """The benchmark as a dict: absolute windows (each as it is) against the pooled least-squares theta, and
    referred windows (each less the mean of the window before it in the same rest run: no change, truth m = 0)."""
    if not paths:
        raise ValueError("logs: expected at least one log file, found none")
    est = RME(rng=np.random.default_rng(0))
    logs = [load_log(p) for p in paths]
    data = rest_data(logs, est.robot, config)
    if len(data.tau) < 2:
        raise ValueError(f"logs: expected at least 2 rest windows of {config.length} samples, found {len(data.tau)}")
    pooled = theta_of(pooled_payload(data))
    res = dict(logs=len(paths), windows=int(len(data.tau)), poses=data.poses(), pooled=pooled.tolist(),
               calibration=None if calibration is None else str(calibration), absolute={}, referred={})
    samples = lambda w: (logs[data.rows[w, 0]].q[data.rows[w, 1]:data.rows[w, 2]],
                         logs[data.rows[w, 0]].tau_ext[data.rows[w, 1]:data.rows[w, 2]])
    pairs = np.flatnonzero(data.before >= 0)
    for name, fn in methods(est.robot, calibration=calibration).items():
        out = [fn(*samples(w), None) for w in range(len(data.tau))]
        M, S = np.array([o[0] for o in out]), np.array([o[1] for o in out])
        res["absolute"][name] = _summary(M, S, pooled)
        if len(out[0]) > 2:
            res["absolute"][name]["broad prior"] = float(np.mean([o[2] == "broad" for o in out]))
        ref = [fn(*samples(w), data.tau[data.before[w]]) for w in pairs]
        if ref:
            res["referred"][name] = _summary(np.array([o[0] for o in ref])[:, :1], np.array([o[1] for o in ref])[:, :1],
                                             [0.0], names=("m",))
    return res


def print_real_logs(res):
    p = res["pooled"]
    print(f"{res['logs']} logs, {res['windows']} rest windows of 200 ms at {res['poses']} poses; pooled least squares: "
          f"m = {p[0]:.3f} kg, r = ({p[1]:+.3f}, {p[2]:+.3f}, {p[3]:+.3f}) m"
          + (f"; RME calibrated with {res['calibration']}" if res["calibration"] else "; RME uncalibrated"))
    print("Each window alone (absolute): median, spread (std over windows), median reported sigma, share of windows "
          "whose 2-sigma interval holds the pooled value (rz is not seen at a level pose).")
    cell = lambda x, f: "-" if x is None else f.format(x)
    for part, rows in (("absolute", res["absolute"]), ("referred to the window before (no change, m = 0)",
                                                        res["referred"])):
        print(f"  {part}")
        for name, row in rows.items():
            txt = "  ".join(f"{k} {cell(v['median'], '{:+.3f}')} +-{cell(v['spread'], '{:.3f}')} "
                            f"sigma {cell(v['sigma'], '{:.3f}')} cov {cell(v['coverage'], '{:.0%}')}"
                            for k, v in row.items() if isinstance(v, dict))
            print(f"    {name:<14} {txt}")


def main(args):
    if not os.path.isdir(args.dir):
        raise SystemExit(f"sim.py real-logs: no folder {args.dir!r}")
    paths = sorted(glob.glob(os.path.join(args.dir, "*.csv")) + glob.glob(os.path.join(args.dir, "*.npz")))
    res = real_logs(paths, calibration=args.calibration)
    print(json.dumps(res)) if args.json else print_real_logs(res)
    return res
