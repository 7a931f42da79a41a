"""Izz's bias split by source (docs/tool_identification.md): the bench's runs again with the plant's true states, the
fit's linear response to each part of the residual at the true tool, and fits with the drives' columns from q, the
true states or instrumented. python -m experiments.tool_izz --seeds 0-9"""
from __future__ import annotations

import argparse
import dataclasses

import mujoco
import numpy as np
from scipy.signal import savgol_filter

import franka
import motion.tool_id as ti
from dynamics import Robot
from experiments.tool_bench import draw_tool
from motion.tool_forms import params_of_tool
from robot.identify import LOG, prepared, run_motion, sim_backend, torque_of

S = ti.ToolFitSettings()
LAGS = ((8, 16), (8, 16, 24))   # rows (10 samples each): beyond the 77-sample filter, so the instruments' noise is
#                                 independent of the row's


def traced_run(robot, seed, tool, run, center=None):
    """run_motion on the plant of `seed` and every read's true qpos, qvel, qacc, applied torque and whether the read
    repeated the last one (a stale packet: 1) (T, 29)."""
    backend, trace, last = sim_backend(seed, tool, run), [], [None]
    read = backend.read

    def read_and_trace():
        s, d = read(), backend.plant.data
        stale = last[0] is not None and np.array_equal(s.tau_J, last[0])
        last[0] = np.array(s.tau_J, dtype=float)
        trace.append(np.concatenate([d.qpos, d.qvel, d.qacc, d.ctrl, [float(stale)]]))
        return s
    backend.read = read_and_trace
    log = run_motion(backend, robot, franka.run_loop, center=center)[0]
    return prepared(log), np.array(trace), backend.plant


def smooth(x):
    win = 2 * int(round(LOG.sg_window / 1e-3 / 2)) + 1                # as diagnosis.logs.prepare at 1 kHz
    return savgol_filter(x, win, LOG.sg_order, axis=0, mode="interp")


def plant_inverse(model, q, dq, ddq):
    d, out = mujoco.MjData(model), np.empty_like(q)
    for i in range(len(q)):
        d.qpos[:], d.qvel[:], d.qacc[:] = q[i], dq[i], ddq[i]
        mujoco.mj_inverse(model, d)
        out[i] = d.qfrc_inverse
    return out


def seed_data(robot, seed):
    """Rows, Y, tau of the difference, the measured and true-state columns, and the residual's parts (paper sign)."""
    tool = draw_tool(np.random.default_rng([seed, 32]))
    ref, ref_trace, plant = traced_run(robot, seed, None, 0)
    run, run_trace, _ = traced_run(robot, seed, tool, 1, center=ref.q[0])
    T = min(len(ref.q), len(run.q))
    rows = np.arange(S.edge, T - S.edge, S.every)
    arm = plant.model
    arm.dof_armature[:] = 0.0                                          # the reference's plant: no payload
    out = {"tool": tool, "Y": robot.body_regressor(run.q[rows], run.dq[rows], run.ddq[rows]),
           "tau": (torque_of(robot, run)[:T] - torque_of(robot, ref)[:T])[rows], "parts": {}, "samples": T}
    cols = {}
    for sign, name, log, trace in ((1, "t", run, run_trace), (-1, "r", ref, ref_trace)):
        q, v = trace[:T, :7], smooth(trace[:T, 7:14])
        a = np.gradient(v, 1e-3, axis=0)
        moved = np.diff(trace[:T + 1, 7:14], axis=0) / 1e-3          # the acceleration each step integrated (its
        #   torque is the command written after this read; MuJoCo's qacc at the read is under the previous one)
        drive = -smooth(plant._friction(trace[:T, 7:14]) + np.asarray(plant.config.armature) * moved)
        q, v, a = q[rows], v[rows], a[rows]
        nominal = robot.inverse_dynamics(q, v, a)
        parts = {"drives": drive[rows], "arm error": nominal - plant_inverse(arm, q, v, a),
                 "states' noise": robot.inverse_dynamics(q, log.dq[rows], log.ddq[rows]) - nominal,
                 "torque sensor": smooth(trace[:T, 21:28])[rows] - log.tau_J[:T][rows]}
        for k, p in parts.items():
            out["parts"][k] = out["parts"].get(k, 0.0) + sign * p
        out["stale cycles"] = out.get("stale cycles", 0.0) + sign * stale_torque(trace[:T])[rows]
        cols[name] = (log.dq[rows], log.ddq[rows], v, a)
    (vt, at), (vr, ar) = (ti._from_q(log.q[:T], 1e-3, S.q_window) for log in (run, ref))
    out["Z_q"] = columns(vt[rows], at[rows], vr[rows], ar[rows])
    out["Z"] = columns(cols["t"][0], cols["t"][1], cols["r"][0], cols["r"][1])
    out["Z_this"] = out["Z"].copy()
    out["Z_this"][:, list(S.q_columns)] = out["Z_q"][:, list(S.q_columns)]
    out["Z_true"] = columns(cols["t"][2], cols["t"][3], cols["r"][2], cols["r"][3])
    out["Z_true_ddq"] = columns(cols["t"][0], cols["t"][3], cols["r"][0], cols["r"][3])
    out["Z_true_friction"] = columns(cols["t"][2], cols["t"][1], cols["r"][2], cols["r"][1])
    e = out["tau"] - out["Y"] @ params_of_tool(tool)
    out["parts"]["what is left"] = e - sum(out["parts"].values())
    out["parts"]["all"] = e
    return out


def stale_torque(trace):
    """(T, 7) the applied torque less its interpolation over the reads that were not stale, filtered like tau_J: the
    torque of the cycles that acted on a repeated state, which the log (its stale rows dropped, tau_J interpolated)
    never sees; part of "the torque sensor"."""
    ctrl, keep, t = trace[:, 21:28], trace[:, 28] == 0, np.arange(len(trace))
    return smooth(ctrl - np.stack([np.interp(t, t[keep], ctrl[keep, j]) for j in range(ctrl.shape[1])], axis=1))


def columns(dq_t, ddq_t, dq_r, ddq_r):
    Z = ti.nuisance(dq_t, ddq_t, S.friction_widths) - ti.nuisance(dq_r, ddq_r, S.friction_widths)
    Z[:, :, 0] = 1.0
    return Z


def instrumented(Y, Z, lags, joints=range(7)):
    """Z with the joints' columns but the offset replaced by their least-squares projection on [1, Y_j, the same
    columns `lags` rows before and after] (two-stage least squares' first stage; rows 80 ms and more away lie beyond
    the 77-sample filter, so their noise is not the row's)."""
    Zh = Z.copy()
    for j in joints:
        c = Z[:, j, 1:]
        before = [np.concatenate([np.repeat(c[:1], L, 0), c[:-L]]) for L in lags]
        after = [np.concatenate([c[L:], np.repeat(c[-1:], L, 0)]) for L in lags]
        W = np.concatenate([np.ones((len(c), 1)), Y[:, j], *before, *after], axis=1)
        Zh[:, j, 1:] = W @ np.linalg.lstsq(W, c, rcond=None)[0]
    return Zh


def response(d, Z):
    """Each part's linear effect on (Ixx, Iyy, Izz) [% of each], the fit's joint weights from the residual."""
    pi = params_of_tool(d["tool"])
    Yr, er = ti.partial_out(d["Y"], d["parts"]["all"], Z)
    w2 = 1.0 / np.mean(er ** 2, axis=0)
    G = np.einsum("j,tji,tjk->ik", w2, Yr, Yr)
    J, truth = ti._jacobian(pi), ti._parameters(pi)
    return {k: 100 * (J @ np.linalg.solve(G, np.einsum("j,tji,tj->i", w2, Yr, ti.partial_out(d["Y"], c, Z)[1])))[4:7]
            / truth[4:7] for k, c in d["parts"].items()}


def fit_with(d, Z, tau=None, moved=None):
    """fit_tool's referred fit on the given columns: (value (10,), std (10,), observed (10,)) per NAMES; `moved`
    (Z (T, n, k) -> columns): the move of the fit on those columns added to the drives' spread in quadrature."""
    settings = dataclasses.replace(S.fit, offsets=False)
    tau = d["tau"] if tau is None else tau
    pi, info, Yr, tr, Yw, tw, Zw = ti._weighted_fit(d["Y"], tau, Z, settings, S.drive_share)
    value, J = ti._parameters(pi), ti._jacobian(pi)
    noise = ti._noise_variance(J, info, Yr, tr, S)
    spread = ti._drive_model_spread(Yw, tw, Zw, value, settings)
    if moved is not None:
        spread = np.hypot(spread, ti._parameters(ti._fit(Yw, tw, moved(Zw), settings)[0]) - value)
    std = np.sqrt(np.maximum(noise, 0.0) + spread ** 2)
    return value, std, np.array(ti._observed(value, std, S.resolution))


def fits(d) -> dict:
    """Per treatment of the columns: (value - truth, std, observed) (10,) each, fit_tool's fit on those columns."""
    Zs = {"joint 7's from q (this code)": d["Z_this"], "logged": d["Z"], "from q": d["Z_q"],
          "true states": d["Z_true"], "true ddq only": d["Z_true_ddq"],
          "true friction only": d["Z_true_friction"],
          **{f"instrumented {lags}": instrumented(d["Y"], d["Z"], lags) for lags in LAGS},
          "ddq column instrumented (8, 16)": ddq_only(d["Y"], d["Z"], LAGS[0]),
          f"joint 7's instrumented {LAGS[1]}": instrumented(d["Y"], d["Z"], LAGS[1], (6,))}
    tau = {k: d["tau"] for k in Zs}
    Zs["none, the plant's drives subtracted"], tau["none, the plant's drives subtracted"] = \
        d["Z"][:, :, :1], d["tau"] - d["parts"]["drives"]
    truth = ti._parameters(params_of_tool(d["tool"]))
    out = {}
    for k, Z in Zs.items():
        value, std, observed = fit_with(d, Z, tau[k])
        out[k] = (value - truth, std, observed, truth)
    value, std, observed = fit_with(d, d["Z"], moved=lambda Z: instrumented(d["Y"], Z, LAGS[1]))
    out[f"logged, spread with instrumented {LAGS[1]}"] = (value - truth, std, observed, truth)
    return out


def ddq_only(Y, Z, lags):
    Zh = instrumented(Y, Z, lags)
    Zh[:, :, 1:-1] = Z[:, :, 1:-1]
    return Zh


def print_fits(fit: dict):
    """Per treatment over the seeds: mass and CoM (worst, rms), the moments' mean error (sd) [%], their errors
    beyond 2 std, the errors / std rms of mass, CoM and the moments, the moments called observed."""
    print("fits: mass worst, rms [g]; CoM worst, rms [mm]; Ixx, Iyy, Izz mean (sd) [%]; beyond 2 std (of the seven); "
          "error / std rms mass, CoM, Ixx, Iyy, Izz; moments, masses called observed")
    for k, rows in fit.items():
        e, s, o, t = (np.array(x) for x in zip(*rows))
        rel, z = 100 * e[:, 4:7] / t[:, 4:7], e[:, :7] / s[:, :7]
        rms = lambda x: float(np.sqrt(np.mean(np.square(x))))
        print(f"  {k:46s} {1e3 * np.abs(e[:, 0]).max():.1f}, {1e3 * rms(e[:, 0]):.2f} g; "
              f"{1e3 * np.abs(e[:, 1:4]).max():.2f}, {1e3 * rms(e[:, 1:4]):.3f} mm; "
              f"{np.round(rel.mean(0), 2).tolist()} ({np.round(rel.std(0), 1).tolist()}); "
              f"{int((np.abs(z) > 2).sum())} of {z.size}; {rms(z[:, 0]):.2f}, {rms(z[:, 1:4]):.2f}, "
              f"{[round(rms(z[:, i]), 2) for i in (4, 5, 6)]}; {int(o[:, 4:7].sum())}, {int(o[:, 0].sum())}")


def coefficient(d, Z, joint=6):
    """Joint 7's rotor-inertia coefficient on the residual at the true tool, and R^2 of the drives' torque by Z."""
    e = d["parts"]["all"][:, joint]
    b = np.linalg.lstsq(Z[:, joint], e, rcond=None)[0]
    D = d["parts"]["drives"][:, joint]
    left = D - Z[:, joint] @ np.linalg.lstsq(Z[:, joint], D, rcond=None)[0]
    return b[-1], 1.0 - left.var() / D.var()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", default="0-9", help="first-last (inclusive)")
    lo, hi = map(int, ap.parse_args(argv).seeds.split("-"))
    robot, resp, fit = Robot.panda(), {}, {}
    for seed in range(lo, hi + 1):
        d = seed_data(robot, seed)
        for k, v in response(d, d["Z"]).items():
            resp.setdefault(k, []).append(v)
        resp.setdefault("drives, columns from the true states", []).append(response(d, d["Z_true"])["drives"])
        for k, v in response(d, d["Z_this"]).items():
            resp.setdefault(f"{k}, joint 7's from q (this code)", []).append(v)
        resp.setdefault(f"drives, joint 7's instrumented {LAGS[1]}", []).append(
            response(d, instrumented(d["Y"], d["Z"], LAGS[1], (6,)))["drives"])
        for k, v in fits(d).items():
            fit.setdefault(k, []).append(v)
        noise, signal = (d["Z"] - d["Z_true"])[:, 6], d["Z_true"][:, 6]
        print(f"seed {seed}: joint 7's dq, ddq difference rms signal {signal[:, 1].std():.5f}, "
              f"{signal[:, -1].std():.4f}, noise {noise[:, 1].std():.5f}, {noise[:, -1].std():.4f}", flush=True)
        print(f"seed {seed}: joint 7 rotor inertia, R^2 of the drives' torque: measured columns "
              f"{np.round(coefficient(d, d['Z']), 3).tolist()}, true-state columns "
              f"{np.round(coefficient(d, d['Z_true']), 3).tolist()}, from q "
              f"{np.round(coefficient(d, d['Z_q']), 3).tolist()}, instrumented {LAGS[1]} "
              f"{np.round(coefficient(d, instrumented(d['Y'], d['Z'], LAGS[1])), 3).tolist()}; what is "
              f"left on Izz {resp['what is left'][-1][2]:+.2f} %", flush=True)
    print("the fit's linear response to each part (the logged columns unless said), Ixx, Iyy, Izz [%] mean (sd):")
    for k, v in resp.items():
        print(f"  {k:50s} {np.round(np.mean(v, 0), 2).tolist()} ({np.round(np.std(v, 0), 2).tolist()})")
    print_fits(fit)


if __name__ == "__main__":
    main()
