"""RME on real robot logs of one unchanged load, beside plain least squares and the authors' range noise rule:
per 200 ms rest window, the mass and CoM, their spread over windows, the reported sigma and how often 2 sigma holds
the pooled least-squares value. `python sim.py real-logs DIR [--calibration FILE] [--json]`."""
from __future__ import annotations

import glob
import json
import os

import numpy as np

from diagnosis.calibrate import RestConfig, calibrate, pooled_payload, rest_data
from diagnosis.logs import load_log
from dynamics import theta_of
from error_model import as_error_model
from experiments.baselines import methods
from rme import RME

NAMES = ("m", "rx", "ry", "rz")


def _summary(M, S, truth, names=NAMES, mass=None):
    """Per parameter: median, spread (std over windows), median reported sigma, 2-sigma coverage of truth; and of
    a mass known otherwise (mass [kg], None: not known): for m, coverage_mass."""
    out = {}
    for i, name in enumerate(names):
        m, s = M[:, i], S[:, i]
        ok = np.isfinite(m)
        out[name] = dict(median=float(np.median(m[ok])) if ok.any() else None,
                         spread=float(np.std(m[ok])) if ok.sum() > 1 else None,
                         sigma=float(np.median(s[ok])) if np.isfinite(s[ok]).any() else None,
                         coverage=float(np.mean(np.abs(m[ok] - truth[i]) < 2 * s[ok])) if np.isfinite(s[ok]).any()
                         else None)
        if i == 0 and mass is not None:
            out[name]["coverage_mass"] = float(np.mean(np.abs(m[ok] - mass) < 2 * s[ok])) if np.isfinite(s[ok]).any() \
                else None
    return out


def leave_pose_out(data, samples, seed=0, pose_model="offset"):
    """RME on each pose's windows (absolute) calibrated (load fitted; pose_model as diagnosis.calibrate's) on the
    windows of the other poses only: what a calibration says of a pose it has not seen. Returns (mean (W, 4),
    std (W, 4)) in the windows' order."""
    labels = data.pose_labels()
    M, S = np.full((len(labels), 4), np.nan), np.full((len(labels), 4), np.nan)
    for p in range(labels.max() + 1):
        model, _ = calibrate(data.subset(labels != p), "fit", pose_model)
        est = RME(rng=np.random.default_rng(seed), calibration=model)
        for w in np.flatnonzero(labels == p):
            e = est.estimate(*samples(w))
            M[w], S[w] = e.mean, e.std
    return M, S


def real_logs(paths, calibration=None, config: RestConfig = RestConfig(), leave_out: bool = False,
              mass: float | None = None, pose_model: str = "offset") -> dict:
    """The benchmark as a dict: absolute windows (each as it is) against the pooled least-squares theta, and
    referred windows (each less the mean of the window before it in the same rest run: no change, truth m = 0).
    leave_out: also RME calibrated, for each pose, on the other poses' windows (leave_pose_out; 3 poses at least;
    pose_model "offset" or "links", as diagnosis.calibrate's).
    mass [kg]: the load's mass known otherwise (other logs, a scale): each absolute row says how often it is held."""
    if not paths:
        raise ValueError("logs: expected at least one log file, found none")
    est = RME(rng=np.random.default_rng(0))
    logs = [load_log(p) for p in paths]
    data = rest_data(logs, est.robot, config)
    if len(data.tau) < 2:
        raise ValueError(f"logs: expected at least 2 rest windows of {config.length} samples, found {len(data.tau)}")
    pooled = theta_of(pooled_payload(data))
    res = dict(logs=len(paths), windows=int(len(data.tau)), poses=data.poses(), pooled=pooled.tolist(),
               calibration=None if calibration is None else str(calibration), absolute={}, referred={},
               mass=mass, **{"referred, the window before given": {}})
    samples = lambda w: (logs[data.rows[w, 0]].q[data.rows[w, 1]:data.rows[w, 2]],
                         logs[data.rows[w, 0]].tau_ext[data.rows[w, 1]:data.rows[w, 2]])
    pairs = np.flatnonzero(data.before >= 0)
    for name, est in methods(est.robot, calibration=calibration).items():
        out = [est.estimate(*samples(w)) for w in range(len(data.tau))]
        res["absolute"][name] = _summary(np.array([e.mean for e in out]), np.array([e.std for e in out]), pooled,
                                         mass=mass)
        res["broad prior"] = res.get("broad prior", {}) | {name: float(np.mean([e.prior_source == "broad" for e in out]))}
        ref = [est.estimate(*samples(w), baseline=data.tau[data.before[w]]) for w in pairs]
        if ref:
            res["referred"][name] = _summary(np.array([e.mean for e in ref])[:, :1], np.array([e.std for e in ref])[:, :1],
                                             [0.0], names=("m",))
            ref = [est.estimate(*samples(w), baseline=samples(data.before[w])[1]) for w in pairs]   # its window
            res["referred, the window before given"][name] = _summary(
                np.array([e.mean for e in ref])[:, :1], np.array([e.std for e in ref])[:, :1], [0.0], names=("m",))
    if leave_out:
        if res["poses"] < 3:
            raise ValueError(f"--leave-pose-out: expected rest at 3 poses at least (a calibration with the load "
                             f"fitted needs 2), found {res['poses']}")
        res["absolute"]["RME, calibrated on the other poses"] = _summary(
            *leave_pose_out(data, samples, pose_model=pose_model), pooled, mass=mass)
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
                                                        res["referred"]),
                       ("referred, the window before given as samples", res["referred, the window before given"])):
        print(f"  {part}")
        for name, row in rows.items():
            txt = "  ".join(f"{k} {cell(v['median'], '{:+.3f}')} +-{cell(v['spread'], '{:.3f}')} "
                            f"sigma {cell(v['sigma'], '{:.3f}')} cov {cell(v['coverage'], '{:.0%}')}"
                            + (f" holds {res['mass']:g} kg {cell(v['coverage_mass'], '{:.0%}')}"
                               if "coverage_mass" in v else "")
                            for k, v in row.items() if isinstance(v, dict))
            print(f"    {name:<14} {txt}")


def main(args):
    if not os.path.isdir(args.dir):
        raise ValueError(f"DIR: expected a folder of logs, found no folder at {args.dir!r}")
    as_error_model(args.calibration)                     # a calibration that cannot be read: before the logs
    paths = sorted(glob.glob(os.path.join(args.dir, "*.csv")) + glob.glob(os.path.join(args.dir, "*.npz")))
    res = real_logs(paths, calibration=args.calibration, leave_out=args.leave_pose_out, mass=args.mass,
                     pose_model=args.pose_model)
    print(json.dumps(res)) if args.json else print_real_logs(res)
    return res
