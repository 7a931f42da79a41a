"""Controller demos on the simulated Panda (Sec. 5.2 static hold, Sec. 5.3 limit cycle): CPIC with and without
exact payload compensation. Run through sim.py: `python sim.py hold`, `python sim.py limit-cycle`."""
from __future__ import annotations

import numpy as np

from cpic import CPIC, Attractor, LimitCycle, rotation_log, run_closed_loop

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


def limit_cycle(args):
    """Limit cycle in the y-z plane (radius 0.1 m, period 4 s) through the ready pose; the payload is attached at
    t = 4 s; without and with exact compensation from t = 4.3 s. Prints radial / out-of-plane errors and phase rate."""
    from sim import Plant, PlantConfig, Q_READY
    t_attach, t_comp, seconds = 4.0, 4.3, 10.0
    runs, out = {}, {}
    for name, on in (("none", False), ("exact", True)):
        rng = np.random.default_rng(args.seed)
        plant = Plant(PlantConfig.realistic(rng) if args.preset == "realistic" else PlantConfig.ideal(), rng=rng)
        if args.view:
            plant.open_viewer()
        robot, first = plant.robot, plant.reset(Q_READY)
        p0, R0 = robot.ee_pose(Q_READY)
        policy = LimitCycle(p0 - np.array([0.0, 0.1, 0.0]), R0)
        plant.schedule_payload(t_attach, THETA[0], THETA[1:])
        comp = (lambda t, q: -robot.payload_torque(q, THETA) if t >= t_comp else None) if on else None
        log = run_closed_loop(plant, CPIC(robot, policy), first, seconds, comp)
        p = robot.ee_pose(log["q"])[0]
        log["y"], log["z"] = p[:, 1], p[:, 2]
        e = p - policy.center
        log["radial_mm"] = 1e3 * (np.hypot(e[:, 1], e[:, 2]) - policy.radius)
        log["normal_mm"] = 1e3 * e[:, 0]
        log["phase"] = np.unwrap(np.arctan2(e[:, 2], e[:, 1]))
        runs[name] = (log, policy)
    print(f"CPIC limit cycle in the y-z plane ({args.preset} plant, seed {args.seed}): radius 0.1 m, period 4 s; "
          f"payload m = {THETA[0]} kg attached at t = {t_attach} s; exact compensation from t = {t_comp} s.")
    print("  window [s]   compensation   mean |rho - r| [mm]   max [mm]   mean |x - x_c| [mm]   turns/s (target 0.25)")
    for lo, hi in ((2.0, 4.0), (4.0, 6.0), (6.0, 10.0)):
        for name in ("none", "exact"):
            log, policy = runs[name]
            w = (log["t"] > lo) & (log["t"] <= hi)
            rate = (log["phase"][w][-1] - log["phase"][w][0]) / (2 * np.pi * (log["t"][w][-1] - log["t"][w][0]))
            out[(lo, hi, name)] = (np.abs(log["radial_mm"][w]).mean(), np.abs(log["radial_mm"][w]).max(),
                                   np.abs(log["normal_mm"][w]).mean(), rate)
            print(f"  {lo:4.1f}-{hi:4.1f}   {name:>12}   {out[(lo, hi, name)][0]:19.2f}   {out[(lo, hi, name)][1]:8.2f}"
                  f"   {out[(lo, hi, name)][2]:19.2f}   {rate:10.3f}")
    if args.plot:
        try:
            import matplotlib
            matplotlib.use("Agg")
            import matplotlib.pyplot as plt
        except ImportError:
            print("--plot: matplotlib is not installed; no figure written")
        else:
            fig, ax = plt.subplots(figsize=(5, 5))
            for name in ("none", "exact"):
                log, policy = runs[name]
                late = log["t"] > t_attach + 1.0
                ax.plot(1e3 * log["y"][late], 1e3 * log["z"][late], label=f"after the payload, compensation: {name}")
            phi = np.linspace(0.0, 2 * np.pi, 200)
            ax.plot(1e3 * (policy.center[1] + policy.radius * np.cos(phi)),
                    1e3 * (policy.center[2] + policy.radius * np.sin(phi)), "k:", label="limit cycle")
            ax.set(xlabel="y [mm]", ylabel="z [mm]", title="CPIC limit cycle", aspect="equal")
            ax.legend(fontsize=8)
            fig.savefig(args.plot, dpi=120, bbox_inches="tight")
            print(f"figure written to {args.plot}")
    return out
