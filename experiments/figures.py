"""The figures of the closed-loop demos (Sec. 5.2-5.3, Figs. 5-8) and of a franka.py log: the compensated estimate
theta_hat with its 2-sigma band against the truth, the end-effector error with and without RME, and the events that
explain them. Headless (matplotlib's Agg backend); matplotlib is optional: pyplot() says so when it is missing."""
from __future__ import annotations

import sys
import textwrap
from dataclasses import dataclass
from types import SimpleNamespace

import numpy as np

NAMES = ("m [kg]", "rx [m]", "ry [m]", "rz [m]")
COLORS = {"without": "tab:red", "with": "tab:blue", "with + friction": "tab:green"}
STYLE = {"detection": ("v", "detection (its estimate)"), "at rest": ("s", "estimate at rest"),
         "back": ("X", "back to an earlier payload")}


@dataclass(frozen=True)
class Mark:
    """An event on the time axis: at t [s] for `duration` [s] (0: an instant); kind "change" (the payload) or
    "push" (a person), "phase" (the task's target moves)."""
    t: float
    label: str
    kind: str = "change"
    duration: float = 0.0


def pyplot():
    """matplotlib.pyplot on the headless Agg backend, or None after a one-line message if matplotlib is missing."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("no figure: matplotlib is not installed (pip install matplotlib)", file=sys.stderr)
        return None
    return plt


def save(fig, path, out=None):
    """Write fig to path (the format from its suffix), close it, and say so on `out` (default stdout)."""
    fig.savefig(path, dpi=120, bbox_inches="tight")
    import matplotlib.pyplot as plt
    plt.close(fig)
    print(f"figure written to {path}", file=out or sys.stdout)


def applied_steps(t, history):
    """The std (T, 4) and `observed` (T, 4) of the estimate compensated at each time t (T,): each accepted estimate
    from its `applied` time on (NaN std and observed False before the first)."""
    std, observed = np.full((len(t), 4), np.nan), np.zeros((len(t), 4), dtype=bool)
    live = sorted((e for e in history if e.accepted and np.isfinite(e.applied)), key=lambda e: e.applied)
    for e in live:
        k = np.searchsorted(t, e.applied - 1e-9)
        std[k:], observed[k:] = e.std, e.observed
    return std, observed


def spans(mask, t):
    """[(t0, t1)] of the runs of True in mask (T,) over times t (T,)."""
    edges = np.flatnonzero(np.diff(np.r_[0, mask.astype(int), 0]))
    return [(t[a], t[min(b, len(t) - 1)]) for a, b in zip(edges[::2], edges[1::2])]


def estimate_panels(axes, t, theta_hat, history, truth=None, label="RME", color="tab:blue", band=True):
    """On axes (4,): each of theta = (m, rx, ry, rz) compensated over time (T, 4) with +-2 std of the estimate in
    use, the truth (T, 4) if given, and each estimate of `history` as a marker at its time (rejected: x)."""
    std, observed = applied_steps(t, history)
    for i, ax in enumerate(axes):
        ax.plot(t, theta_hat[:, i], color=color, lw=1.2, label=f"{label}: compensated")
        if band:
            ax.fill_between(t, theta_hat[:, i] - 2 * std[:, i], theta_hat[:, i] + 2 * std[:, i], color=color,
                            alpha=0.2, lw=0, label=f"{label}: +-2 std")
        if truth is not None:
            ax.plot(t, truth[:, i], color="k", ls="--", lw=1, label="truth")
        ax.set_ylabel(NAMES[i])
        for kind, (marker, text) in STYLE.items():
            es = [e for e in history if e.kind == kind and e.accepted]
            if es:
                ax.plot([e.t for e in es], [e.mean[i] for e in es], marker, color=color, ms=6, mfc="white",
                        ls="none", label=text)
        refused = [e for e in history if not e.accepted]
        if refused:
            ax.plot([e.t for e in refused], [e.mean[i] for e in refused], "x", color="0.3", ms=6, ls="none",
                    label="estimate refused (not a load)")
    blind = observed[:, 0] & ~observed[:, 3]       # a payload estimated, its rz the prior's
    for k, (t0, t1) in enumerate(spans(blind, t)):
        axes[3].axvspan(t0, t1, color="0.85", zorder=0, label=None if k else "rz: prior, not observed at this pose")
    applied = [e.applied for e in history if e.accepted and np.isfinite(e.applied)]
    if applied:
        axes[0].plot(applied, np.interp(applied, t, theta_hat[:, 0]), "|", color=color, ms=14, mew=2, ls="none",
                     label="compensation applied")


def held_spans(axes, history, min_wait=0.1, who=""):
    """Shade, on every axis, each change whose estimate waited more than min_wait [s] from its time to its
    compensation; return its reasons [(t0, t1, reason)] for the caption (prefixed by `who`: the run)."""
    def why(e):
        took = getattr(e, "seconds", np.nan)
        return e.reason or (f"the estimate itself took {took:.2f} s (network + VI beside the loop)"
                            if took >= 0.8 * (e.applied - e.t) else "(no reason recorded)")
    held = [(e.t, e.applied, who + why(e)) for e in history
            if e.accepted and np.isfinite(e.applied) and e.applied - e.t > min_wait]
    for k, (t0, t1, _) in enumerate(held):
        for ax in axes:
            ax.axvspan(t0, t1, facecolor="none", edgecolor="tab:purple", hatch="//", lw=0, zorder=0,
                       label=None if k or ax is not axes[0] else "change held (reason below)")
    return held


def event_marks(axes, marks):
    """Changes as dotted lines and pushes as shaded spans on every axis, labelled above the top axis (off the data);
    labels closer than 3 % of the time axis are stacked."""
    import matplotlib.transforms as mt
    top = axes[0]
    lo, hi = top.get_xlim()
    last, level, named = -np.inf, 0, set()
    legend = {"change": "payload change", "push": "push (a person)", "phase": "the task's target moves"}
    for m in sorted(marks, key=lambda m: m.t):
        for ax in axes:
            label = None if ax is not top or m.kind in named else legend.get(m.kind, m.kind)
            if m.duration > 0:
                ax.axvspan(m.t, m.t + m.duration, color="tab:orange", alpha=0.25, lw=0, zorder=0, label=label)
            else:
                ax.axvline(m.t, color="0.3" if m.kind == "change" else "0.7", ls=":", lw=1, zorder=0, label=label)
        named.add(m.kind)
        level = level + 1 if m.t - last < 0.03 * (hi - lo) else 0
        last = m.t
        top.text(m.t, 1.02 + 0.09 * level, m.label, rotation=25, fontsize=7, ha="left", va="bottom",
                 transform=mt.blended_transform_factory(top.transData, top.transAxes), clip_on=False)


def _legend(ax, others=()):
    """One legend outside the axis, on the right: its entries and those of `others` (axes), each label once."""
    keep = {}
    for a in (ax, *others):
        handles, labels = a.get_legend_handles_labels()
        keep.update({lab: h for lab, h in zip(labels, handles) if lab not in keep})
    if keep:
        ax.legend(keep.values(), keep.keys(), loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, frameon=False)


def demo_figure(runs: dict, title: str, marks=(), errors: dict | None = None, error_label="|p - p*| [mm]",
                path_panel=None):
    """One closed-loop demo with shared time: m, rx, ry, rz compensated by each RME run of `runs` ({name: Record},
    "without" has no estimator) with its 2-sigma band and the truth; below, the end-effector error of every run
    (errors: {name: (T,) [mm]}, default |p - target|). marks: Marks. path_panel(ax), if given, draws on an extra axis
    on the right (the limit cycle's y-z path). Returns the matplotlib Figure (None without matplotlib)."""
    plt = pyplot()
    if plt is None:
        return None
    wide = path_panel is not None
    fig = plt.figure(figsize=(13 if wide else 10, 10))
    grid = fig.add_gridspec(5, 2 if wide else 1, width_ratios=(2.2, 1) if wide else None, hspace=0.12, wspace=0.55)
    axes = [fig.add_subplot(grid[0, 0])]
    axes += [fig.add_subplot(grid[i, 0], sharex=axes[0]) for i in range(1, 5)]
    rme = [name for name in runs if name != "without"]
    first = runs[rme[0]] if rme else next(iter(runs.values()))
    for name in rme:
        r = runs[name]
        estimate_panels(axes[:4], r.t, r.theta_hat, r.history, r.theta if name == rme[0] else None,
                        label=f"{name} RME", color=COLORS.get(name, "tab:purple"), band=True)
    if not rme:
        for i, ax in enumerate(axes[:4]):
            ax.plot(first.t, first.theta[:, i], "k--", lw=1, label="truth")
            ax.set_ylabel(NAMES[i])
    errors = errors or {name: 1e3 * r.ee_error for name, r in runs.items()}
    for name, err in errors.items():
        axes[4].plot(runs[name].t, err, color=COLORS.get(name, "tab:purple"), lw=1, label=f"{name} RME")
    axes[4].set(ylabel=error_label, xlabel="t [s]")
    axes[0].set_xlim(first.t[0], first.t[-1])
    held = [h for name in rme for h in held_spans(axes, runs[name].history, who=f"{name} RME: " * (len(rme) > 1))]
    event_marks(axes, marks)
    for ax in axes[:4]:
        ax.tick_params(labelbottom=False)
    _legend(axes[0], axes[1:4])
    _legend(axes[4])
    if wide:
        path_panel(fig.add_subplot(grid[1:4, 1]))
    fig.suptitle(title, y=0.99 + 0.02 * bool(marks))
    _caption(fig, held)
    return fig


def _caption(fig, held):
    """The reasons of the held changes under the figure."""
    lines = [f"held {t0:.2f}-{t1:.2f} s: {why}" for t0, t1, why in held]
    if lines:
        fig.text(0.06, 0.05, "\n".join(textwrap.fill(s, 140) for s in lines), fontsize=7, va="top")


def cycle_panel(runs: dict, cycle, since: float):
    """path_panel for the limit cycle (Fig. 6): y-z path of each run from `since` [s] on, and the reference cycle
    (cycle.center (3,), cycle.radius [m])."""
    def draw(ax):
        a = np.linspace(0, 2 * np.pi, 200)
        ax.plot(cycle.center[1] + cycle.radius * np.cos(a), cycle.center[2] + cycle.radius * np.sin(a), "k--", lw=1,
                label="reference cycle")
        for name, r in runs.items():
            k = r.at(since)
            ax.plot(r.p[k:, 1], r.p[k:, 2], color=COLORS.get(name, "tab:purple"), lw=0.8, label=f"{name} RME")
        ax.set(xlabel="y [m]", ylabel="z [m]", aspect="equal", title=f"y-z path from {since:g} s")
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.15), fontsize=7, frameon=False)
    return draw


# --- a franka.py log ------------------------------------------------------------------------------------------
def history_of(log) -> list:
    """The estimates a franka.py log holds (est_* arrays, see franka.save_log) as objects with t, applied, mean, std,
    observed, kind, accepted, reason, seconds (NaN, all True, True, "", NaN where the log lacks them)."""
    t = np.asarray(log.get("est_t", []), float)
    k = len(t)
    get = lambda key, default: np.asarray(log[key]) if key in log else default
    std, obs = get("est_std", np.full((k, 4), np.nan)), get("est_observed", np.ones((k, 4), dtype=bool))
    acc, why = get("est_accepted", np.ones(k, dtype=bool)), get("est_reason", np.full(k, ""))
    took = get("est_seconds", np.full(k, np.nan))
    return [SimpleNamespace(t=float(t[i]), applied=float(log["est_applied"][i]), mean=np.asarray(log["est_theta"][i]),
                            std=std[i], observed=obs[i].astype(bool), kind=str(log["est_kind"][i]),
                            accepted=bool(acc[i]), reason=str(why[i]), seconds=float(took[i])) for i in range(k)]


def log_figure(log, robot=None, title="franka.py run", history=None):
    """A franka.py log ({key: array}, as save_log writes it): m, rx, ry, rz compensated with their 2-sigma band (and
    the simulated truth `theta` if the log has it), the estimates (`history`, else the log's est_*) as markers, and
    how far the end effector moved from its first pose [mm]. Returns the Figure (None without matplotlib)."""
    plt = pyplot()
    if plt is None:
        return None
    from dynamics import Robot
    robot = robot or Robot.panda()
    t, hist = np.asarray(log["t"], float), history_of(log) if history is None else history
    fig, axes = plt.subplots(5, 1, figsize=(10, 9), sharex=True, gridspec_kw=dict(hspace=0.12))
    truth = np.asarray(log["theta"], float) if "theta" in log else None
    estimate_panels(axes[:4], t, np.asarray(log["theta_hat"], float), hist, truth)
    p, _ = robot.ee_pose(np.asarray(log["q"], float))
    axes[4].plot(t, 1e3 * np.linalg.norm(p - p[0], axis=1), color="tab:blue", lw=1, label="with RME")
    axes[4].set(ylabel="|p - p(0)| [mm]", xlabel="t [s]", xlim=(t[0], t[-1]))
    held = held_spans(list(axes), hist)
    _legend(axes[0], axes[1:4])
    _legend(axes[4])
    fig.suptitle(title)
    _caption(fig, held)
    return fig


def plot_run(path, log, history, robot, title, quiet=False):
    """franka.py --plot: log_figure of the run just made, written to path (said on stderr if quiet: --json)."""
    fig = log_figure(log, robot, title, history)
    if fig is not None:
        save(fig, path, sys.stderr if quiet else None)


def plot_main(argv, prog: str = "rme.py plot") -> int:
    """`python rme.py plot LOG [--out FILE]`: the figure of a franka.py --log .npz (default FILE: LOG with .png);
    returns the exit status."""
    import argparse
    ap = argparse.ArgumentParser(prog=prog, description="the figure of a franka.py --log run: the estimate "
                                 "over time with its 2-sigma band, the estimates, how far the hand moved")
    ap.add_argument("log", metavar="LOG", help="the .npz franka.py --log wrote")
    ap.add_argument("--out", metavar="FILE", help="the figure (default: LOG with .png)")
    args = ap.parse_args(argv)
    out = args.out or (args.log[:-4] if args.log.endswith(".npz") else args.log) + ".png"
    try:
        with np.load(args.log) as z:
            log = {k: z[k] for k in z.files}
    except (OSError, ValueError) as err:
        print(f"rme.py plot: cannot read {args.log}: {err}", file=sys.stderr)
        return 2
    missing = [k for k in ("t", "q", "theta_hat", "est_t", "est_applied", "est_theta", "est_kind") if k not in log]
    if missing:
        print(f"rme.py plot: {args.log} is not a franka.py --log file (it lacks {', '.join(missing)})", file=sys.stderr)
        return 2
    fig = log_figure(log, title=f"franka.py run: {args.log}")
    if fig is None:
        return 1
    save(fig, out)
    return 0
