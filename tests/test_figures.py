"""The demo and log figures hold what they must show (panels, curves, markers, shaded spans), read from the figure
object, not from pixels; on synthetic Records, so no simulation runs."""
import numpy as np
import pytest

pytest.importorskip("matplotlib")

from experiments.figures import Mark, applied_steps, cycle_panel, demo_figure, log_figure, spans  # noqa: E402
from experiments.runner import Record  # noqa: E402
from rme import Estimate  # noqa: E402


def estimate(t, applied, mean, kind="detection", accepted=True, reason="", rz_seen=False):
    e = Estimate(mean=np.array(mean, float), std=np.array([0.02, 0.01, 0.01, 0.05]), cov=np.eye(4), prior=np.zeros(4),
                 observed=np.array([True, True, True, rz_seen]), seconds=0.003, iterations=10, converged=True)
    e.t, e.applied, e.kind, e.accepted, e.reason = t, applied, kind, accepted, reason
    return e


def record(history, seconds=4.0, rng=None):
    """A Record of a hold: a 0.9 kg payload from 1 s, compensated as `history` says, a small random ee error."""
    rng = rng or np.random.default_rng(0)
    t = np.arange(0, seconds, 1e-3)
    T = len(t)
    theta = np.where((t >= 1.0)[:, None], [0.9, 0.05, -0.03, 0.13], 0.0)
    theta_hat = np.zeros((T, 4))
    for e in sorted((e for e in history if e.accepted), key=lambda e: e.applied):
        theta_hat[t >= e.applied] = e.mean
    z = np.zeros((T, 7))
    p = np.tile([0.3, 0.0, 0.5], (T, 1)) + rng.normal(0, 1e-3, (T, 3))
    return Record(t=t, q=z, dq=z, tau=z, tau_J=z, tau_ext=z, theta=theta, theta_hat=theta_hat,
                  target=np.tile([0.3, 0.0, 0.5], (T, 1)), V=np.zeros((T, 2)), fallback=np.zeros(T, bool), p=p,
                  R=None, history=list(history))


def labels(ax):
    return {line.get_label() for line in ax.get_lines()}


def span_labels(ax):
    return {c.get_label() for c in ax.collections + ax.patches}


HELD = "the level returned to what this earlier payload leaves"


def test_demo_figure_shows_estimate_band_truth_errors_and_events():
    hist = [estimate(1.15, 3.5, [0.86, 0.06, -0.03, 0.09], reason=HELD),
            estimate(2.2, np.nan, [4.0, 0.5, 0.0, 0.0], accepted=False, reason="beyond what the arm carries"),
            estimate(4.0 - 0.5, 3.504, [0.9, 0.05, -0.03, 0.1], kind="at rest")]
    runs = {"without": record([]), "with": record(hist)}
    fig = demo_figure(runs, "test", [Mark(1.0, "payload attached"), Mark(2.0, "push", "push", 0.4)])
    axes = fig.axes
    assert len(axes) == 5                                          # m, rx, ry, rz, error; one time axis
    assert all(ax.get_shared_x_axes().joined(axes[0], ax) for ax in axes)
    for ax in axes[:4]:
        assert {"with RME: compensated", "truth", "detection (its estimate)", "estimate at rest",
                "estimate refused (not a load)"} <= labels(ax)
        assert "with RME: +-2 std" in span_labels(ax)
    assert {"without RME", "with RME"} <= labels(axes[4])
    assert "compensation applied" in labels(axes[0])
    assert {"change held (reason below)", "push (a person)"} <= span_labels(axes[0])
    assert "payload change" in labels(axes[0])
    assert "rz: prior, not observed at this pose" in span_labels(axes[3])
    texts = [t.get_text() for t in fig.texts] + [t.get_text() for t in axes[0].texts]
    assert any(HELD in s.replace("\n", " ") for s in texts)           # the reason is written on the figure
    assert {"payload attached", "push"} <= set(texts)
    legend_box = axes[0].get_legend().get_window_extent(fig.canvas.get_renderer())
    data_box = axes[0].get_window_extent(fig.canvas.get_renderer())
    assert legend_box.x0 >= data_box.x1                            # the legend beside the data, not over it


def test_band_is_two_std_of_the_estimate_in_use_from_its_application():
    hist = [estimate(1.1, 1.2, [0.8, 0, 0, 0.1]), estimate(2.0, 2.5, [0.9, 0, 0, 0.1], kind="at rest", rz_seen=True)]
    t = np.arange(0, 3, 1e-3)
    std, observed = applied_steps(t, hist)
    assert np.all(np.isnan(std[t < 1.2])) and np.allclose(std[(t >= 1.2) & (t < 2.5)], hist[0].std)
    assert not observed[(t >= 1.2) & (t < 2.5), 3].any() and observed[t >= 2.5, 3].all()
    assert spans(np.array([0, 1, 1, 0, 1], bool), np.arange(5.0)) == [(1.0, 3.0), (4.0, 4.0)]


def test_limit_cycle_figure_adds_the_y_z_path_and_the_reference_cycle():
    runs = {"without": record([]), "with": record([estimate(1.2, 1.21, [0.9, 0.05, -0.03, 0.1])])}

    class Cycle:
        center, radius = np.array([0.3, 0.0, 0.5]), 0.1
    fig = demo_figure(runs, "cycle", [Mark(1.0, "attach")], path_panel=cycle_panel(runs, Cycle, 1.0))
    assert len(fig.axes) == 6
    path = fig.axes[5]
    assert {"reference cycle", "without RME", "with RME"} <= labels(path)
    ref = next(line for line in path.get_lines() if line.get_label() == "reference cycle")
    assert np.allclose(np.hypot(ref.get_xdata() - 0.0, ref.get_ydata() - 0.5), 0.1)


def test_log_figure_reads_a_franka_log():
    hist = [estimate(1.15, 1.3, [0.86, 0.06, -0.03, 0.09])]
    rec = record(hist)
    log = {"t": rec.t, "q": np.tile([0, -0.785, 0, -2.356, 0, 1.571, 0.785], (len(rec.t), 1)),
           "theta_hat": rec.theta_hat, "theta": rec.theta, "est_t": np.array([1.15]), "est_applied": np.array([1.3]),
           "est_theta": np.array([hist[0].mean]), "est_kind": np.array(["detection"]),
           "est_std": np.array([hist[0].std]), "est_observed": np.array([hist[0].observed]),
           "est_accepted": np.array([True]), "est_reason": np.array([HELD])}
    fig = log_figure(log)
    assert len(fig.axes) == 5
    assert {"RME: compensated", "truth", "detection (its estimate)"} <= labels(fig.axes[0])
    assert "RME: +-2 std" in span_labels(fig.axes[0])
    assert "change held (reason below)" in span_labels(fig.axes[0])


def test_a_saved_franka_log_keeps_what_the_figure_needs(tmp_path):
    import franka
    from experiments.figures import history_of
    hist = [estimate(1.15, 3.5, [0.86, 0.06, -0.03, 0.09], reason=HELD),
            estimate(2.0, np.nan, [4.0, 0.5, 0, 0], accepted=False, reason="beyond what the arm carries")]
    rec = record(hist)
    est = type("Est", (), {"history": hist})()
    franka.save_log(tmp_path / "run.npz", {"t": rec.t, "q": rec.q, "theta_hat": rec.theta_hat}, est)
    with np.load(tmp_path / "run.npz") as z:
        back = history_of({k: z[k] for k in z.files})
    for a, b in zip(hist, back):
        assert (a.t, a.kind, a.accepted, a.reason) == (b.t, b.kind, b.accepted, b.reason)
        assert np.allclose(a.std, b.std) and np.array_equal(a.observed, b.observed) and np.allclose(a.mean, b.mean)


def test_without_matplotlib_a_plot_is_one_line_not_a_traceback(monkeypatch, capsys):
    import sys
    from experiments import cli, figures
    monkeypatch.setitem(sys.modules, "matplotlib", None)         # import matplotlib now raises ImportError
    assert figures.pyplot() is None
    with pytest.raises(SystemExit) as stop:                      # said before any simulation runs
        cli.main(["basket", "--plot", "x.png"])
    err = capsys.readouterr().err.strip().splitlines()
    assert stop.value.code == 2 and len(err) == 2 and all("matplotlib" in line for line in err)


@pytest.mark.parametrize("demo, axes, marks, error_label", [
    ("static_hold", 5, {"payload attached: 0.9 kg"}, "|p - p*| [mm]"),
    ("basket", 5, {"basket attached", "object 1 added", "push"}, "|p - p*| [mm]"),
    ("limit_cycle", 6, {"payload attached: 2.0 kg"}, "distance to the cycle [mm]"),
    ("pick_place", 5, {"grasp: 0.7 kg", "+0.5 kg", "release"}, "|p - p unloaded| [mm]")])
def test_each_demo_draws_its_figure(demo, axes, marks, error_label, monkeypatch, capsys):
    """The demos' wiring, with the closed loop replaced by synthetic Records (no simulation)."""
    from experiments import scenarios
    drawn = []
    monkeypatch.setattr(scenarios, "run", lambda args, seconds, loads, *a, use_rme=True, **k: record(
        [estimate(1.2, 1.21, [0.9, 0.05, -0.03, 0.1])] if use_rme else [], seconds))
    monkeypatch.setattr(scenarios, "save", lambda fig, path: drawn.append(fig))
    getattr(scenarios, demo)(scenarios.Args(preset="ideal", plot="figure.png"))
    fig, = drawn
    assert len(fig.axes) == axes
    assert marks <= {t.get_text() for t in fig.axes[0].texts}
    assert fig.axes[4].get_ylabel() == error_label
    assert {"without RME", "with RME"} <= labels(fig.axes[4])
