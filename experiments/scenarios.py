"""RME in closed loop on the simulated Panda (Sec. 5.2-5.3, App. C): static hold, sequential basket loading with
human pushes, limit cycle, pick-and-place; each run with and without RME. Run through sim.py:
`python sim.py`, `python sim.py basket`, `python sim.py limit-cycle`, `python sim.py pick-place`."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from cpic import CPIC, Attractor, LimitCycle
from dynamics import Q_READY, Robot
from experiments.runner import PayloadChange, PolicySwitch, Push, Record
from experiments.runner import run as run_loop
from diagnosis.effect_model import Model
from diagnosis.logs import prepare
from experiments.episodes import record_log
from experiments.figures import Mark, cycle_panel, demo_figure, save
from rme import RME
from sim import Plant, PlantConfig


def combine(*parts):
    """One rigid payload from point masses (m, rx, ry, rz): total mass and CoM (4,) and inertia about the CoM."""
    parts = [np.asarray(p, dtype=float) for p in parts if p[0] > 0]
    if not parts:
        return np.zeros(4), np.zeros((3, 3))
    m = sum(p[0] for p in parts)
    c = sum(p[0] * p[1:] for p in parts) / m
    I = sum(p[0] * ((p[1:] - c) @ (p[1:] - c) * np.eye(3) - np.outer(p[1:] - c, p[1:] - c)) for p in parts)
    return np.array([m, *c]), I


def make_plant(args, rng):
    """The plant of a demo: args.preset ('ideal' or 'realistic', drawn from rng); MuJoCo's viewer if args.view."""
    plant = Plant(PlantConfig.preset(args.preset, rng), rng=rng)
    if getattr(args, "view", False):
        plant.open_viewer()
    return plant


def run(args, seconds, loads, pushes=(), policies=(), use_rme=True, q0=Q_READY, correction=None, expect=()) -> Record:
    """One closed-loop run: CPIC (+ RME compensation when use_rme) on a plant made from args (preset, seed).
    loads: [(t, (m, rx, ry, rz) total payload, inertia or None)], pushes: [(t, duration, force (3,))],
    policies: [(t, policy)] (the first one, at t = 0, is the initial DS; default: hold the pose at q0);
    expect: times [s] at which the task tells RME a load change is coming (RME.expect_change: a grasp, a release)."""
    rng = np.random.default_rng(args.seed)                # the same plant and sensor noise with and without RME
    plant = make_plant(args, rng)
    robot = plant.robot
    policies = list(policies) or [(0.0, Attractor(*robot.ee_pose(q0)))]
    ctrl = CPIC(robot, policies[0][1])
    est = RME(robot, rng=np.random.default_rng(args.seed + 1), correction=correction) if use_rme else None
    events = [PayloadChange(t, theta[0], theta[1:], inertia) for t, theta, inertia in loads]
    events += [Push(t, force, duration) for t, duration, force in pushes]
    events += [PolicySwitch(t, policy) for t, policy in policies[1:]]
    told = {int(round(t / plant.dt)) for t in expect}
    step = (lambda k, sample: k in told and est.expect_change()) if est is not None and told else None
    return run_loop(plant, ctrl, seconds, estimator=est, events=events, q0=q0, before_step=step)


def print_estimates(log, label="RME"):
    """The timeline of estimates: when, which kind, the estimate +- 2 std (rz marked where the pose did not observe
    it: the prior), the truth at that time, when it was applied, and why it was refused or applied late."""
    t, theta = log["t"], log["theta"]
    if not log["history"]:
        print(f"  {label} detected no change")
    for e in log["history"]:
        k = min(np.searchsorted(t, e.t), len(t) - 1)
        when = (f"applied at {e.applied:.3f} s" if e.accepted else f"refused: {e.reason} (not a load)")
        if e.accepted and e.reason:
            when += f" ({e.reason})"
        what = {"detection": "finds a new payload", "at rest": "estimates again on the full window",
                "back": "returns to an earlier payload", "correction": "corrects the payload held"}
        what = what.get(e.kind, "estimates")
        blind = " (rz: prior, not observed at this pose)" if e.kind != "back" and not e.observed[3] else ""
        print(f"  {e.t:6.3f} s  {label} {what} [{e.kind}]; estimate m = {e.mean[0]:.3f} +- {2 * e.std[0]:.3f} kg, "
              f"r = ({', '.join(f'{v:+.3f}' for v in e.mean[1:])}) m{blind}"
              f"  [truth m = {theta[k, 0]:.3f}, r = ({', '.join(f'{v:+.3f}' for v in theta[k, 1:])})]  "
              f"{e.seconds * 1e3:.1f} ms, {when}")


def error_mm(log, reference=None):
    """|p - p_target| [mm] (T,), the target being the attractor's p* (or `reference` (3,))."""
    ref = log["target"] if reference is None else reference
    return 1e3 * np.linalg.norm(log["p"] - ref, axis=1)


def at(log: Record, t):
    return log.at(t)


def save_plot(path, title, curves, events=(), ylabel="|p - p*| [mm]"):
    """curves: [(label, t, y)], events: [(t, label)]. Needs matplotlib; says so when it is missing."""
    if not path:
        return
    from experiments.figures import pyplot
    plt = pyplot()
    if plt is None:
        return
    fig, ax = plt.subplots(figsize=(8, 3.6))
    for label, t, y in curves:
        ax.plot(t, y, label=label)
    for t, label in events:
        ax.axvline(t, color="0.5", ls=":", lw=1)
        ax.text(t, ax.get_ylim()[1], label, rotation=90, va="top", ha="right", fontsize=7)
    ax.set(xlabel="t [s]", ylabel=ylabel, title=title)
    ax.legend(loc="best", fontsize=8)
    save(fig, path)


def figure(path, runs, title, marks, **kw):
    """A demo's figure (experiments.figures.demo_figure) written to path, if a path is given and matplotlib is there."""
    if path:
        fig = demo_figure(runs, title, marks, **kw)
        if fig is not None:
            save(fig, path)


# --- the demos -----------------------------------------------------------------------------------------------
def static_hold(args):
    """The main demo (Sec. 5.2, Fig. 5): hold the ready pose under CPIC, an unknown payload arrives at 1.75 s."""
    theta, t_attach, seconds = np.array([0.9, 0.05, -0.03, 0.13]), 1.75, 4.0
    runs = {name: run(args, seconds, [(t_attach, theta, None)], use_rme=on) for name, on in (("without", False),
                                                                                             ("with", True))}
    print(f"Panda holding its ready pose under CPIC ({args.preset} plant, seed {args.seed}).")
    print(f"  {t_attach:6.3f} s  an unknown payload is attached: m = {theta[0]} kg, r = {tuple(theta[1:].tolist())} m (ee frame)")
    print_estimates(runs["with"])
    errs = {k: error_mm(v) for k, v in runs.items()}
    print("\n  t [s]   end-effector error [mm]   without RME   with RME")
    for t in (1.7, 2.0, 2.1, 2.25, 2.5, 3.0, 4.0):
        print(f"  {t:5.2f}   {'':24s}{errs['without'][at(runs['without'], t)]:11.2f}  {errs['with'][at(runs['with'], t)]:9.2f}")
    hist = [e for e in runs["with"]["history"] if e.accepted]
    k0 = at(runs["with"], t_attach - 0.05)
    print("\nsummary                           without RME   with RME")
    print(f"  error before the payload [mm]    {errs['without'][k0]:10.2f}  {errs['with'][k0]:9.2f}   (the plant is not "
          f"the nominal model)")
    print(f"  final error [mm]                 {errs['without'][-1]:10.2f}  {errs['with'][-1]:9.2f}")
    if hist:
        applied = runs["with"]["t"][np.argmax(runs["with"]["theta_hat"][:, 0] > 0)]
        print(f"  load change -> compensation          -      {1e3 * (applied - t_attach):6.0f} ms")
        print(f"  estimate time (network + VI)         -      {hist[0].seconds * 1e3:6.2f} ms")
    figure(args.plot, runs, f"static hold under CPIC ({args.preset} plant, seed {args.seed})",
           [Mark(t_attach, f"payload attached: {theta[0]} kg")])
    return runs


def basket(args):
    """Sequential adaptation (Sec. 5.3, Fig. 7): a basket is attached, two objects are added and removed, the
    basket is taken off, and a person pushes the arm sideways between the changes."""
    basket_, obj1, obj2 = (0.45, 0.0, 0.0, 0.12), (0.6, 0.04, 0.03, 0.10), (0.4, -0.03, -0.02, 0.10)
    steps = [(1.0, (basket_,), "basket attached"), (3.5, (basket_, obj1), "object 1 added"),
             (6.0, (basket_, obj1, obj2), "object 2 added"), (8.5, (basket_, obj2), "object 1 removed"),
             (11.0, (), "basket and object 2 removed")]
    loads = [(t, *combine(*parts)) for t, parts, _ in steps]
    pushes = [(2.2, 0.4, np.array([0.0, 20.0, 0.0])), (4.8, 0.4, np.array([-18.0, 0.0, 0.0])),
              (7.3, 0.4, np.array([0.0, -20.0, 0.0])), (9.8, 0.4, np.array([15.0, 10.0, 0.0]))]
    seconds = 13.0
    runs = {name: run(args, seconds, loads, pushes, use_rme=on) for name, on in (("without", False), ("with", True))}
    print(f"Basket experiment under CPIC ({args.preset} plant, seed {args.seed}): loads change, pushes in between.")
    events = sorted([(t, label) for t, _, label in steps] + [(t, f"push {f.tolist()} N for {d} s") for t, d, f in pushes])
    for t, label in events:
        print(f"  {t:6.3f} s  {label}")
    print_estimates(runs["with"])
    errs = {k: error_mm(v) for k, v in runs.items()}
    print("\n  just before the next change   true m [kg]   RME m [kg]   error [mm] without / with RME")
    for (t, parts, label), t_next in zip(steps, [s[0] for s in steps[1:]] + [seconds]):
        k = at(runs["with"], t_next - 0.05)
        print(f"  {label:30s} {runs['with']['theta'][k, 0]:8.3f}   {runs['with']['theta_hat'][k, 0]:9.3f}   "
              f"{errs['without'][k]:10.2f} / {errs['with'][k]:.2f}")
    figure(args.plot, runs, f"basket: sequential loads, pushes between them ({args.preset} plant, seed {args.seed})",
           [Mark(t, label) for t, _, label in steps] + [Mark(t, "push", "push", d) for t, d, _ in pushes])
    return runs


@dataclass(frozen=True)
class Args:
    """The demos' options, for calling a scenario from Python."""
    seed: int = 0
    preset: str = "realistic"
    view: bool = False
    plot: str | None = None


def limit_cycle_policy() -> LimitCycle:
    """The y-z limit cycle of the demo: radius 0.1 m, period 6 s, centred 0.1 m in front of the ready pose's ee."""
    p, R = Robot.panda().ee_pose(Q_READY)
    return LimitCycle(p + np.array([0.1, 0.0, 0.0]), R, radius=0.1, period=6.0)


def limit_cycle(args):
    """Tracking a stable limit cycle in the y-z plane (Sec. 5.3, Fig. 6); a payload is added at 4 s. Without RME
    the arm is pulled below the cycle; with RME it returns to it."""
    cycle = limit_cycle_policy()
    center = cycle.center
    theta, t_attach, seconds = np.array([2.0, 0.04, 0.0, 0.10]), 4.0, 12.0
    variants = [("without", False, None), ("with", True, None)]
    if args.preset == "realistic":
        # moving along the cycle, joint friction changes with the velocity all the time and the detector never sees
        # a settled torque; the robot's friction fitted from a log (the diagnosis tool) removes that
        print("fitting the robot's joint friction on a 12 s excitation log (the diagnosis tool) ...")
        config = PlantConfig.realistic(np.random.default_rng(args.seed))      # the robot run() builds
        variants.append(("with + friction", True, fit_friction_model(config, seed=args.seed + 1)))
    runs = {name: run(args, seconds, [(t_attach, theta, None)], policies=[(0.0, cycle)], use_rme=on,
                      correction=corr) for name, on, corr in variants}
    print(f"Limit cycle in the y-z plane, radius {cycle.radius} m, period {cycle.period} s ({args.preset} plant, "
          f"seed {args.seed}); payload m = {theta[0]} kg attached at {t_attach} s.")
    for name in runs:
        if name != "without":
            print(f"  RME {name[5:] or '(nominal model)'}:")
            print_estimates(runs[name])
    print("\n  window [s]   radial error [mm] (rms), out-of-plane error [mm], turns/s:  " + " | ".join(
        f"{k} RME" for k in runs))
    for t0, t1 in ((2.0, 4.0), (4.0, 6.0), (6.0, 8.0), (8.0, 10.0), (10.0, 12.0)):
        cols = []
        for k in runs:
            log = runs[k]
            sel = (log["t"] >= t0) & (log["t"] < t1)
            u = log["p"][sel] - center
            rho = np.hypot(u[:, 1], u[:, 2])
            phase = np.unwrap(np.arctan2(u[:, 2], u[:, 1]))
            cols.append((1e3 * np.sqrt(np.mean((rho - cycle.radius) ** 2)), 1e3 * np.sqrt(np.mean(u[:, 0] ** 2)),
                         (phase[-1] - phase[0]) / (2 * np.pi * (t1 - t0))))
        print(f"  {t0:4.1f}-{t1:4.1f}     " + "   |   ".join(f"{a:7.1f} {b:7.1f} {c:6.2f}" for a, b, c in cols))
    off = {k: 1e3 * np.hypot(np.hypot(*(r.p[:, 1:] - center[1:]).T) - cycle.radius, r.p[:, 0] - center[0])
           for k, r in runs.items()}                  # distance to the reference cycle
    figure(args.plot, runs, f"limit cycle in the y-z plane ({args.preset} plant, seed {args.seed})",
           [Mark(t_attach, f"payload attached: {theta[0]} kg")], errors=off,
           error_label="distance to the cycle [mm]", path_panel=cycle_panel(runs, cycle, t_attach))
    return runs


def pick_place(args):
    """Pick-and-place (App. C, Fig. 8): move to an object, grasp it (attach 0.7 kg), carry it, 0.5 kg is added
    mid-carry, place it (detach) and go back."""
    p0, R0 = Robot.panda().ee_pose(Q_READY)
    pick, place = p0 + np.array([0.15, -0.2, -0.15]), p0 + np.array([0.1, 0.25, -0.05])
    plan = [(0.0, p0, "start"), (0.5, pick, "go to the object"), (3.0, pick + [0, 0, 0.15], "grasped: lift"),
            (4.5, place, "carry to the box"), (8.5, p0, "placed: go back")]
    obj, extra = (0.7, 0.0, 0.0, 0.10), (0.5, 0.03, 0.0, 0.12)
    loads = [(2.5, *combine(obj)), (6.0, *combine(obj, extra)), (8.0, *combine())]
    seconds = 11.0
    runs = {name: run(args, seconds, loads, policies=[(t, Attractor(p, R0)) for t, p, _ in plan], use_rme=on,
                      expect=(2.5, 8.0)) for name, on in (("without", False), ("with", True))}   # grasp, release
    print(f"Pick and place under CPIC ({args.preset} plant, seed {args.seed}; the task tells RME of its grasp and "
          f"release: RME.expect_change).")
    for t, line in sorted([(t, label) for t, _, label in plan] + [(2.5, "object (0.7 kg) grasped"),
                                                                   (6.0, "0.5 kg added to it"),
                                                                   (8.0, "object placed (released)")]):
        print(f"  {t:6.3f} s  {line}")
    print_estimates(runs["with"])
    errs = {k: error_mm(v) for k, v in runs.items()}
    print("\n  phase end                      error to the current target [mm]  without / with RME")
    for t, label in ((2.45, "at the object"), (4.45, "lifted"), (5.95, "carrying"), (7.95, "at the box"),
                     (10.95, "back at the start")):
        print(f"  {t:5.2f} s {label:22s} {errs['without'][at(runs['without'], t)]:10.1f} / "
              f"{errs['with'][at(runs['with'], t)]:.1f}")
    if args.plot:                                     # the path the same arm takes with no load: its tracking
        free = run(args, seconds, [], policies=[(t, Attractor(p, R0)) for t, p, _ in plan], use_rme=False)
        figure(args.plot, runs, f"pick and place ({args.preset} plant, seed {args.seed})",
               [Mark(t, lab, "phase") for t, _, lab in plan[1:]] +
               [Mark(2.5, "grasp: 0.7 kg"), Mark(6.0, "+0.5 kg"), Mark(8.0, "release")],
               errors={k: 1e3 * np.linalg.norm(r.p - free.p, axis=1) for k, r in runs.items()},
               error_label="|p - p unloaded| [mm]")
    return runs


def fit_friction_model(config, seconds=12.0, seed=0):
    """Record an excitation log (no payload) on the robot `config` and fit its joint friction (Gaz sigmoid) on top of
    the nominal model: the better model RME can subtract (the diagnosis tool)."""
    raw = record_log(config, seconds, np.random.default_rng(seed))
    log = prepare({k: raw[k] for k in ("t", "q", "dq", "tau_J", "tau_ext")})
    model = Model.nominal(Robot.panda()).add("sigmoid")
    model.fit(log)
    return model


def hold_estimate(config, theta, seed, correction=None, t_attach=0.75, seconds=1.4, why=False):
    """First RME estimate after attaching theta during a CPIC hold at the ready pose on the plant `config` (None if
    there is none); with why: (that estimate or None, why there is none or "")."""
    plant = Plant(config, rng=np.random.default_rng(seed))
    robot = plant.robot
    ctrl = CPIC(robot, Attractor(*robot.ee_pose(Q_READY)))
    est = RME(robot, rng=np.random.default_rng(seed + 1), correction=correction)
    run_loop(plant, ctrl, seconds, estimator=est, events=[PayloadChange(t_attach, theta[0], theta[1:])], q0=Q_READY)
    first = est.history[0] if est.history else None
    if not why:
        return first
    left = seconds - t_attach
    reason = "" if first is not None else (
        "detected, but judged an external wrench, not a payload" if est.changes_not_payload else
        f"no change judged a payload in the {left:g} s after the load")
    return first, reason


def better_model(args):
    """Better estimates from a better model: joint friction holds part of a new load while the arm settles. RME takes
    out the published friction's mean (Gaz et al. 2019); on a robot whose joints hold twice that (the sticky preset)
    it reads the load a few % light. Friction fitted by the diagnosis tool on a 12 s excitation log of the same robot,
    subtracted from tau_ext instead, removes that bias."""
    rng = np.random.default_rng(args.seed)
    config = PlantConfig.preset("sticky", rng)
    print(f"a robot with twice the published joint friction (sticky plant, seed {args.seed}); fitting its friction on "
          f"a 12 s excitation log without payload ...")
    model = fit_friction_model(config, seed=args.seed + 1)
    print("  " + model.report().replace("\n", "\n  "))
    print("\n  payload (m, rx, ry, rz)          friction   RME error (m [kg], rx, ry, rz [m])")
    rows = []
    for i, theta in enumerate([(0.3, 0.03, 0.0, 0.13), (0.9, 0.05, -0.03, 0.13), (1.29, 0.05, 0.01, 0.13)]):
        found = [hold_estimate(config, np.array(theta), seed=args.seed + 10 * i, correction=c, why=True)
                 for c in (None, model)]
        errs = [None if e is None else e.mean - np.array(theta) for e, _ in found]
        rows.append(errs)
        for label, e, (_, why) in zip(("published", "fitted"), errs, found):
            txt = f"no estimate: {why}" if e is None else "  ".join(f"{v:+.4f}" for v in e)
            print(f"  {str(theta):32s} {label:10s} {txt}")
    return rows
