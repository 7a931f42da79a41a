"""Controller demo on the simulated Panda (Sec. 5.2 static hold): CPIC with and without exact payload compensation,
the best RME could do. Run through sim.py: `python sim.py hold` (the limit cycle is in scenarios.py)."""
from __future__ import annotations

import numpy as np

from cpic import CPIC, Attractor, rotation_log, run_closed_loop

THETA = np.array([0.9, 0.05, -0.03, 0.13])     # (m, rx, ry, rz), a Table 5 payload


def hold(args):
    """Static hold at the ready pose; the payload is attached at t = 1.75 s (as in Sec. 5.2); run without compensation
    and with exact compensation -robot.payload_torque(q, theta) from t = 2.05 s. Returns the error table."""
    from sim import Plant, PlantConfig, Q_READY       # here, so that sim.py may import this module
    t_attach, t_comp, seconds = 1.75, 2.05, 4.0
    runs = {}
    for name, on in (("none", False), ("exact", True)):
        rng = np.random.default_rng(args.seed)                 # the same plant for both runs
        plant = Plant(PlantConfig.realistic(rng) if args.preset == "realistic" else PlantConfig.ideal(), rng=rng)
        if args.view:
            plant.open_viewer()
        robot, first = plant.robot, plant.reset(Q_READY)
        p_star, R_star = robot.ee_pose(Q_READY)
        plant.schedule_payload(t_attach, THETA[0], THETA[1:])
        comp = (lambda t, q: -robot.payload_torque(q, THETA) if t >= t_comp else None) if on else None
        log = run_closed_loop(plant, CPIC(robot, Attractor(p_star, R_star)), first, seconds, comp)
        p, R = robot.ee_pose(log["q"])
        log["pos_mm"] = 1e3 * np.linalg.norm(p - p_star, axis=1)
        log["rot_deg"] = np.degrees([np.linalg.norm(rotation_log(Ri @ R_star.T)) for Ri in R])
        runs[name] = log
    print(f"CPIC static hold at the ready pose ({args.preset} plant, seed {args.seed}); payload m = {THETA[0]} kg, "
          f"r = {THETA[1:]} m attached at t = {t_attach} s;\nexact compensation -payload_torque(q, theta) "
          f"from t = {t_comp} s in the second run.")
    print("   t [s]   |ee error| [mm]  none / exact   rotation [deg]  none / exact")
    table = []
    for t in (1.7, 1.8, 1.9, 2.05, 2.2, 2.5, 3.0, 3.5, 4.0):
        k = int(np.searchsorted(runs["none"]["t"], t - 1e-9))
        k = min(k, len(runs["none"]["t"]) - 1)
        row = [runs[r][key][k] for key in ("pos_mm", "rot_deg") for r in ("none", "exact")]
        table.append([t] + row)
        print(f"  {t:5.2f}   {row[0]:12.2f} / {row[1]:6.2f}      {row[2]:10.2f} / {row[3]:5.2f}")
    if args.plot:
        try:
            import matplotlib
            matplotlib.use("Agg")
            import matplotlib.pyplot as plt
        except ImportError:
            print("--plot: matplotlib is not installed; no figure written")
        else:
            fig, ax = plt.subplots(figsize=(7, 3.5))
            for r in ("none", "exact"):
                ax.plot(runs[r]["t"], runs[r]["pos_mm"], label=f"compensation: {r}")
            ax.axvline(t_attach, color="k", ls=":", label="payload attached")
            ax.axvline(t_comp, color="C1", ls=":", label="exact compensation on")
            ax.set(xlabel="t [s]", ylabel="|p - p*| [mm]", title="CPIC static hold")
            ax.legend()
            fig.savefig(args.plot, dpi=120, bbox_inches="tight")
            print(f"figure written to {args.plot}")
    return np.array(table)
