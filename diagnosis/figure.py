"""The figure of a diagnosis (diagnose.run's output): the residual over time before and after each added effect,
the residual left for the top effect against the signal it depends on, and the per-joint RMS before and after."""
from __future__ import annotations

import numpy as np


def plot(path, out: dict):
    """The error falling, per joint: on the left the residual tau_J - model over time before and after each added
    effect (in the order added, fitted on the whole log); on the right the residual left for the top effect against
    the signal it depends on, with its fitted torque; below, per-joint RMS before and after each. Legends outside."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    log, stages = out["log"], _stages(out)
    n = stages[0][1].shape[1]
    fig = plt.figure(figsize=(11, 1.6 * n + 2.6))
    grid = fig.add_gridspec(n + 2, 2, height_ratios=[1] * n + [0.5, 1.8], hspace=0.35)   # a gap, then the RMS
    top, step = _top_effect(out), max(1, len(log.t) // 4000)
    for j in range(n):
        ax = fig.add_subplot(grid[j, 0])
        for k, (name, r) in enumerate(stages):
            ax.plot(log.t[::step], r[::step, j], lw=0.6, color=f"C{k}", label=name)
        ax.set_ylabel(f"J{j + 1} [Nm]")
        if top is not None:
            side = fig.add_subplot(grid[j, 1])
            x = top["x"][::step, j]
            side.plot(x, top["residual"][::step, j], ".", ms=1, color="0.5", label="residual without it")
            side.plot(x, top["fitted"][::step, j], ".", ms=1, color="C3", label=f"fitted {top['name']}")
            if j == 0:
                side.set_title(f"residual left for '{top['name']}' vs what it depends on", fontsize=9)
                side.legend(loc="lower left", bbox_to_anchor=(0, 1.25), ncol=2, markerscale=8, fontsize=7)
        if j == 0:
            ax.set_title("residual tau_J - model over time", fontsize=9)
            ax.legend(loc="lower left", bbox_to_anchor=(0, 1.25), ncol=len(stages), fontsize=7)
    ax.set_xlabel("t [s]")
    if top is not None:
        side.set_xlabel(top["xlabel"])
    bars = fig.add_subplot(grid[n + 1, :])
    width = 0.8 / len(stages)
    for k, (name, r) in enumerate(stages):
        bars.bar(np.arange(n) + (k - (len(stages) - 1) / 2) * width, np.sqrt(np.mean(r ** 2, axis=0)), width,
                 color=f"C{k}", label=name)
    bars.set(xticks=range(n), xticklabels=[f"J{j + 1}" for j in range(n)], ylabel="RMS [Nm]",
             title="per-joint RMS of the residual")
    bars.legend(loc="upper left", bbox_to_anchor=(1.01, 1), fontsize=7, frameon=False)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return fig


def _stages(out: dict) -> list:
    """[(label, residual (T, n))]: the starting model's, then with each added effect, in the order added (the
    parameters of the fit with all of them, so the last is exactly the residual after)."""
    stages = [(" + ".join(out["model"].names), out["before"].residual)]
    if "added" not in out:
        return stages
    added, s = out["added"], out["added"].signals(out["log"])
    new = added.effects[len(out["model"].effects):]
    after = added.residual(s)
    for k, e in enumerate(new):
        stages.append(("+ " + e.name, after + added.torque(s, new[k + 1:])))
    return stages


def _top_effect(out: dict):
    """The first selected (else best-ranked) effect: its fitted torque, the residual without it, its signal."""
    d, log = out["diagnosis"], out["log"]
    name = d.selected[0] if d.selected else (d.ranking[0]["effect"] if d.ranking else None)
    if name is None:
        return None
    if name in d.model.names:
        m = d.model
    else:
        m = out["model"].copy().add(d.ranking[0]["obj"])
        m.fit(log)
    e = next(e for e in m.effects if e.name == name)
    s = m.signals(log)
    fitted = m.torque(s, [e])
    signals = {"q": (log.q, "q [rad]"), "dq": (log.dq, "dq [rad/s]"), "ddq": (log.ddq, "ddq [rad/s^2]"),
               "t": (np.broadcast_to(log.t[:, None], fitted.shape), "t [s]")}
    x, xlabel = signals.get(e.signal, (fitted, "its torque [Nm]"))
    return {"name": name, "fitted": fitted, "residual": m.residual(s) + fitted, "x": x, "xlabel": xlabel}
