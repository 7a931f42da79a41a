"""Demos of the pieces on their own (run through sim.py): `python sim.py hold` (CPIC with exact compensation: the
best RME could do), `python sim.py payload` (measured tau_ext beside the payload model, Eq. 4) and
`python sim.py hidden-effect` (the diagnosis tool on a log with hidden physical effects)."""
from __future__ import annotations

import json

import numpy as np

from cpic import CPIC, Attractor, JointHold, rotation_log
from diagnosis.diagnose import _jsonable, plot, run
from diagnosis.excite import QUASI_STATIC, payload_lstsq
from diagnosis.logs import prepare
from dynamics import Q_READY, phi_of
from experiments.episodes import make_plant, measure, plant_config, record_log
from experiments.runner import ExactCompensation, PayloadChange
from experiments.runner import run as run_loop
from experiments.scenarios import save_plot
from sim import Plant, PlantConfig

THETA = np.array([0.9, 0.05, -0.03, 0.13])     # (m, rx, ry, rz), Table 5 payload 4


def hold(args):
    """Static hold at the ready pose; the payload is attached at t = 1.75 s (as in Sec. 5.2); run without compensation
    and with exact compensation -robot.payload_torque(q, theta) from t = 2.05 s. Returns the error table."""
    t_attach, t_comp, seconds = 1.75, 2.05, 4.0
    runs = {}
    for name, on in (("none", False), ("exact", True)):
        rng = np.random.default_rng(args.seed)                 # the same plant for both runs
        plant = Plant(PlantConfig.preset(args.preset, rng), rng=rng)
        if args.view:
            plant.open_viewer()
        robot = plant.robot
        p_star, R_star = robot.ee_pose(Q_READY)
        oracle = ExactCompensation(robot, THETA, start=t_comp, clock=lambda: plant.t) if on else None
        log = run_loop(plant, CPIC(robot, Attractor(p_star, R_star)), seconds, estimator=oracle,
                       events=[PayloadChange(t_attach, THETA[0], THETA[1:])], q0=Q_READY, tau_ext_to_controller=False)
        runs[name] = dict(t=log.t, pos_mm=1e3 * np.linalg.norm(log.p - p_star, axis=1),
                          rot_deg=np.degrees([np.linalg.norm(rotation_log(Ri @ R_star.T)) for Ri in log.R]))
    print(f"CPIC static hold at the ready pose ({args.preset} plant, seed {args.seed}); payload m = {THETA[0]} kg, "
          f"r = {THETA[1:]} m attached at t = {t_attach} s;\nexact compensation -payload_torque(q, theta) "
          f"from t = {t_comp} s in the second run.")
    print("   t [s]   |ee error| [mm]  none / exact   rotation [deg]  none / exact")
    table = []
    for t in (1.7, 1.8, 1.9, 2.05, 2.2, 2.5, 3.0, 3.5, 4.0):
        k = min(int(np.searchsorted(runs["none"]["t"], t - 1e-9)), len(runs["none"]["t"]) - 1)
        row = [runs[r][key][k] for key in ("pos_mm", "rot_deg") for r in ("none", "exact")]
        table.append([t] + row)
        print(f"  {t:5.2f}   {row[0]:12.2f} / {row[1]:6.2f}      {row[2]:10.2f} / {row[3]:5.2f}")
    save_plot(args.plot, "CPIC static hold", [(f"compensation: {r}", runs[r]["t"], runs[r]["pos_mm"])
                                              for r in ("none", "exact")],
              [(t_attach, "payload attached"), (t_comp, "exact compensation on")])
    return np.array(table)


def payload(args):
    """The arm holds its pose, a payload is attached at 0.5 s, and the measured tau_ext (referred to the torque seen
    just before) is printed beside robot.payload_torque for the true theta."""
    rng = np.random.default_rng(args.seed)
    plant = Plant(PlantConfig.preset(args.preset, rng), rng=rng)
    if args.view:
        plant.open_viewer()
    plant.schedule_payload(0.5, THETA[0], THETA[1:])
    first = plant.reset(Q_READY)
    log = measure(plant, JointHold(plant.robot, Q_READY), 1.5, first)
    before = log["tau_ext"][(log["t"] > 0.4) & (log["t"] <= 0.5)].mean(axis=0)
    after_mask = log["t"] > 1.3
    after = log["tau_ext"][after_mask].mean(axis=0)
    model = plant.robot.payload_torque(log["q"][after_mask], THETA).mean(axis=0)
    print(f"Panda at the ready pose, {args.preset} plant; payload m = {THETA[0]} kg, "
          f"r = {THETA[1:]} m (ee frame) attached at t = 0.5 s")
    print("joint   tau_ext before   tau_ext after   after - before   payload_torque(q, theta)   [Nm]")
    for j in range(plant.robot.n):
        print(f"  {j + 1}   {before[j]:14.3f}  {after[j]:14.3f}  {after[j] - before[j]:15.3f}  {model[j]:24.3f}")
    err = np.abs(after - before - model)
    print(f"largest |measured change - model| = {err.max():.3f} Nm "
          f"(sensor noise, quantisation and the plant's differences from the nominal model)")
    return err


def hidden_effect(args):
    """A plant hiding Gaz friction and joint torque offsets (panda_facts.md) records a 12 s multi-sine;
    compare -> diagnose -> add -> compare; then a 0.9 kg payload (Table 5) in a slow sweep is estimated by least
    squares from tau_ext with and without model.correction.
    args: seed, preset ("realistic": realistic torque sensing; "ideal": perfect sensors), plot, json, view."""
    rng = np.random.default_rng(args.seed)
    hidden = ("sigmoid", "offset")
    config, _ = plant_config(hidden, realistic_sensing=args.preset == "realistic")
    plant = make_plant(config, rng, args.view)
    log = prepare(record_log(config, 12.0, rng, plant=plant), source="simulated")
    out = run(log, add=["auto"], robot=plant.robot)
    sweep = prepare(record_log(config, 5.0, rng, QUASI_STATIC, payload=(THETA[0], THETA[1:], None), plant=plant))
    fix = out["added"].correction(sweep.q, sweep.dq, sweep.ddq)
    before = payload_lstsq(plant.robot, sweep.q, sweep.tau_ext)
    after = payload_lstsq(plant.robot, sweep.q, sweep.tau_ext - fix)
    if args.plot:
        plot(args.plot, out)
        print(f"figure written to {args.plot}")
    if args.json:
        js = dict(out["json"], hidden=list(hidden), preset=args.preset,
                  payload={"true": THETA, "uncorrected": before, "corrected": after})
        print(json.dumps(_jsonable(js)))
        return js
    before_rms, after_rms = out["before"].rms, out["after"].rms
    print(f"hidden-effect demo ({args.preset} sensing, seed {args.seed}): the plant hides Gaz sigmoid friction and "
          "joint torque offsets (Gaz et al. 2019 values, panda_facts.md) that the nominal model lacks\n")
    print(out["text"])
    print("\nthe error fell (RMS per joint [Nm], nominal -> with the selected effects):")
    for j in range(len(before_rms)):
        ratio = before_rms[j] / max(after_rms[j], 1e-9)
        print(f"  J{j + 1}  {before_rms[j]:.3f} -> {after_rms[j]:.3f}  ({ratio:.0f}x)")
    print(f"\nbetter estimates from the better model: payload theta = (m, rx, ry, rz) = {THETA} held in a 5 s slow "
          "sweep, least squares on tau_ext ~ payload_regressor(q) phi")
    Y = plant.robot.payload_regressor(sweep.q)
    for name, est in (("tau_ext", before), ("tau_ext - model.correction", after)):
        err = est - THETA
        torque = np.sqrt(np.mean((Y @ (phi_of(est) - phi_of(THETA))) ** 2))
        print(f"  {name:27s} m = {est[0]:.3f} kg, r = ({est[1]:.3f}, {est[2]:.3f}, {est[3]:.3f}) m;  error: "
              f"{abs(err[0]):.3f} kg, {1000 * np.linalg.norm(err[1:]):.1f} mm, payload torque {torque:.4f} Nm RMS")
    return out
