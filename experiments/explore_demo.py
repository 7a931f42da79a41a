"""The exploration's checks and demo (`python sim.py explore`): Table 5's payloads at the ready pose on the realistic
plant, the estimate at rest beside the one from both poses, the limits the motion came near, and the storage check
(Prop. 4.1) of the moving target."""
from __future__ import annotations

import dataclasses
import math

import mujoco
import numpy as np

from cpic import CPIC, Attractor, storage
from dynamics import Q_READY
from experiments.explore import ExploreSettings, Explorer, MovingAttractor
from experiments.runner import ExactCompensation, PayloadChange, run
from rme import RME
from sim import Plant, PlantConfig


def limits_touched(rec, ctrl, t0, t1):
    """Over rec's rows in [t0, t1] s: (smallest joint margin to [q_min, q_max] [rad], largest |tau| / tau_max); a
    limit is touched when the margin is <= 0 or the ratio reaches 1 (the command clipped)."""
    q, tau = (v[(rec.t >= t0) & (rec.t <= t1)] for v in (rec.q, rec.tau))
    margin = float(np.min(np.minimum(q - ctrl.q_min, ctrl.q_max - q)))
    return margin, float(np.max(np.abs(tau) / ctrl.tau_max))


def storage_check(theta, settings: ExploreSettings = ExploreSettings(), hold=0.3, seconds=None):
    """The exploration motion alone on the ideal plant holding theta (4,) with exact compensation: S = 1/2 dq^T M dq +
    lambda_1 V + P (cpic.storage, the plant's own M) over each 1 ms step with that step's target must not increase
    (Prop. 4.1, F_ext = 0, Delta F_mm = 0); the moving target adds lambda_1 [V(x, c_k+1) - V(x, c_k)].
    Returns dict(max_rise [J] of S over a step at a fixed target, target_work [J], seconds)."""
    plant = Plant()
    plant.set_payload(theta[0], theta[1:])
    robot = plant.robot
    policy = MovingAttractor(Attractor(*robot.ee_pose(Q_READY)))
    ctrl = CPIC(robot, policy)
    T, dwell = settings.profile(0.0)[1], settings.settle + settings.window / 1000.0
    seconds = seconds or hold + 2 * T + dwell + 0.3
    pivot, angles = Explorer._pivot_of(robot, Q_READY, settings.pivot, policy.base.p_star), []

    def move(k, sample):
        t = k * plant.dt - hold
        policy.move(settings.profile(t)[0] - settings.profile(t - T - dwell)[0], settings.axis, pivot)
        angles.append(policy.angle)
    rec = run(plant, ctrl, seconds, estimator=ExactCompensation(robot, theta), q0=Q_READY, before_step=move)
    d, M = mujoco.MjData(plant.model), np.zeros((robot.n, robot.n))
    q, dq = np.concatenate([rec.q, [rec.last.q]]), np.concatenate([rec.dq, [rec.last.dq]])
    p, R = robot.ee_pose(q)
    S_now, S_next, work = [], [], 0.0
    for k in range(len(rec.t)):                                   # S(x_k, c_k) and S(x_k+1, c_k)
        target = policy.at(angles[k])
        for i, out in ((k, S_now), (k + 1, S_next)):
            d.qpos[:] = q[i]
            mujoco.mj_forward(plant.model, d)
            mujoco.mj_fullM(plant.model, d, M)
            out.append(storage(dq[i], M, target(p[i], R[i])[1], ctrl.config, ctrl.posture_potential(q[i])))
        if k + 1 < len(rec.t):                                    # what moving the target to c_k+1 adds
            work += storage(np.zeros(robot.n), M, policy.at(angles[k + 1])(p[k + 1], R[k + 1])[1], ctrl.config, 0.0)
            work -= storage(np.zeros(robot.n), M, target(p[k + 1], R[k + 1])[1], ctrl.config, 0.0)
    rise = np.array(S_next) - np.array(S_now)
    return dict(max_rise=float(rise.max()), target_work=float(work), seconds=float(seconds))


def explore_trial(theta, seed, settings: ExploreSettings = ExploreSettings(), preset="realistic", pushes=(),
                  t_attach=0.75, seconds=5.0, correction=None):
    """Hold the ready pose under CPIC with RME (correction: e.g. a bias map, experiments/bias_map.py) and the
    explorer, attach theta (4,) at t_attach: (Record, CPIC)."""
    rng = np.random.default_rng(seed)
    plant = Plant(PlantConfig.preset(preset, rng), rng=rng)
    ctrl = CPIC(plant.robot, Attractor(*plant.robot.ee_pose(Q_READY)))
    rme = RME(plant.robot, rng=np.random.default_rng(seed + 1), correction=correction)
    rec = run(plant, ctrl, seconds, estimator=rme, events=[PayloadChange(t_attach, theta[0], theta[1:])] +
              list(pushes), q0=Q_READY, explorer=Explorer(settings))
    return rec, ctrl


def explore_table(seed=0, settings: ExploreSettings = ExploreSettings(), preset="realistic"):
    """Table 5's six payloads, one seeded trial each: the estimate at rest (before) and from both poses (after)."""
    from experiments.bench import TABLE5
    rows = []
    for i, theta in enumerate(TABLE5):
        theta = np.array(theta)
        rec, ctrl = explore_trial(theta, seed=1000 * (i + 1) + seed, settings=settings, preset=preset)
        row = dict(truth=theta.tolist(), before=None, after=None, status="no estimate at rest", seconds=None)
        if rec.exploration:
            x = rec.exploration[0]
            end = x.end if np.isfinite(x.end) else rec.t[-1]
            margin, ratio = limits_touched(rec, ctrl, x.start, end)
            row.update(before=x.before.mean.tolist(), before_std=x.before.std.tolist(), status=x.status,
                       after=None if x.after is None else x.after.mean.tolist(),
                       after_std=None if x.after is None else x.after.std.tolist(), seconds=float(end - x.start),
                       joint_margin=margin, torque_ratio=ratio, touched=bool(margin <= 0 or ratio >= 1),
                       deviation=x.deviation)
        row["storage"] = storage_check(theta, settings)
        rows.append(row)
    err = lambda key, j: [abs(r[key][j] - r["truth"][j]) for r in rows if r[key] is not None]
    summary = {f"{key}_mean_abs_error": [float(np.mean(err(key, j))) if err(key, j) else None for j in range(4)]
               for key in ("before", "after")}
    return dict(rows=rows, **summary, settings=dataclasses.asdict(settings), preset=preset, seed=seed)


def add_reference_column(res: dict, settings: ExploreSettings, t_attach=4.0, seconds=8.5) -> dict:
    """explore_table's result res, each trial run again with settings.reference_tilt: the explorer first tilts
    load-free (from 0.25 s on, once the arm is still), and the payload is attached at t_attach, once the arm is back
    and still. Adds rows[i]["ref"] {before, after, status, seconds, reference: (start, end) of the reference tilt}
    and ref_{before,after}_mean_abs_error."""
    referring = dataclasses.replace(settings, reference_tilt=True)
    for i, row in enumerate(res["rows"]):
        s, theta = 1000 * (i + 1) + res["seed"], np.array(row["truth"])
        rec, _ = explore_trial(theta, s, settings=referring, preset=res["preset"], t_attach=t_attach, seconds=seconds)
        ref = [x for x in rec.exploration if x.reference and x.status == "recorded"]
        x = next((x for x in rec.exploration if not x.reference), None)
        row["ref"] = dict(status="no estimate at rest" if x is None else x.status,
                          before=None if x is None else x.before.mean.tolist(),
                          after=None if x is None or x.after is None or not x.referred else x.after.mean.tolist(),
                          seconds=None if x is None else float(x.end - x.start),
                          reference=[float(ref[0].start), float(ref[0].end)] if ref else None)
    for key in ("before", "after"):
        err = [[abs(a - b) for a, b in zip(r["ref"][key], r["truth"])] for r in res["rows"] if r["ref"][key]]
        res[f"ref_{key}_mean_abs_error"] = np.mean(err, axis=0).tolist() if err else [None] * 4
    return res


def explore(args):
    """`python sim.py explore [--seed S] [--json]`: the exploration on Table 5's payloads at the ready pose, without
    and with a bias map calibrated on a load-free hold log of each plant (experiments/bias_map.py), and with the
    explorer's own load-free reference tilt instead of a map."""
    import json
    from experiments.bias_map import add_map_column
    res = add_map_column(explore_table(seed=args.seed), explore_trial, ExploreSettings())
    res = add_reference_column(res, ExploreSettings())
    if args.json:
        return print(json.dumps(res)) or res
    s = ExploreSettings()
    print(f"Active exploration for the CoM along gravity: realistic plant, ready pose, seed {args.seed}; tilt "
          f"{math.degrees(s.tilt):.0f} deg about world {tuple(s.axis)} through the {s.pivot}, peak {s.speed} rad/s.\n"
          "truth (m, rx, ry, rz) | before: at rest | after: both poses | map: both poses, RME(correction=bias map) "
          "| ref: both poses, no map, a load-free reference tilt first\n     |abs error| m [g], r [mm]   time [s]  "
          "limit touched  S rise [J]")
    f = lambda v: " ".join(f"{x:6.3f}" for x in v)
    for r in res["rows"]:
        if r["before"] is None:
            print(f"  {f(r['truth'])}  {r['status']}")
            continue
        e = lambda v: "    -" if v is None else " ".join(f"{1e3 * abs(a - b):4.0f}" for a, b in zip(v, r["truth"]))
        print(f"  {f(r['truth'])}\n     before {f(r['before'])}   {e(r['before'])}\n     after  "
              f"{f(r['after']) if r['after'] else r['status']:27s}   {e(r['after'])}   {r['seconds']:5.2f}   "
              f"{'yes' if r['touched'] else 'no':3s} (margin {r['joint_margin']:.2f} rad, |tau|/max "
              f"{r['torque_ratio']:.2f})  {r['storage']['max_rise']:.1e}\n     map    "
              f"{f(r['map']['after']) if r['map']['after'] else r['map']['status']:27s}   {e(r['map']['after'])}"
              f"\n     ref    {f(r['ref']['after']) if r['ref']['after'] else r['ref']['status']:27s}   "
              f"{e(r['ref']['after'])}")
    print("mean |error|      m [g]  rx [mm]  ry [mm]  rz [mm]")
    for key in ("before", "after", "map_before", "map_after", "ref_before", "ref_after"):
        print(f"  {key:10s}     " + "  ".join(f"{1e3 * (x or np.nan):6.1f}" for x in res[f"{key}_mean_abs_error"]))
    return res
