"""The diagnosis figure shows the error falling: the residual before and after each added effect over time, per-joint
RMS before and after, legends off the data (read from the figure object, on a short synthetic log)."""
import numpy as np
import pytest

pytest.importorskip("matplotlib")

from diagnosis.diagnose import run  # noqa: E402
from diagnosis.figure import plot  # noqa: E402
from diagnosis.effects import Signals, _sigmoid_shape  # noqa: E402
from diagnosis.excite import ExciteConfig, multisine  # noqa: E402
from diagnosis.logs import Log, prepare  # noqa: E402
from dynamics import Robot  # noqa: E402
from sim import GAZ_FO, GAZ_P1, GAZ_P2, GAZ_P3  # noqa: E402


def test_diagnosis_figure_shows_the_residual_and_its_rms_fall_with_each_added_effect(tmp_path):
    rng, robot = np.random.default_rng(3), Robot.panda()
    t = 1e-3 * np.arange(3000)
    q, dq, ddq = multisine(t, ExciteConfig(), rng)
    s = Signals(Log(t, q, dq, ddq, None, np.zeros_like(q)), robot)
    tau_J = s.inverse_dynamics + np.asarray(GAZ_P1) * _sigmoid_shape(dq, np.asarray(GAZ_P2), np.asarray(GAZ_P3))
    tau_J += np.asarray(GAZ_FO) + 0.02 * rng.normal(size=q.shape)
    out = run(prepare({"t": t, "q": q, "dq": dq, "tau_J": tau_J}), add=["sigmoid", "offset"], robot=robot)
    fig = plot(tmp_path / "d.png", out)
    n = robot.n
    assert len(fig.axes) == 2 * n + 1                  # residual over time and vs signal per joint; the RMS bars
    left = fig.axes[0]
    stages = [line.get_label() for line in left.get_lines()]
    assert stages == ["gravity + motion", "+ sigmoid", "+ offset"]
    last = left.get_lines()[-1].get_ydata()
    step = len(t) // len(last) if len(last) < len(t) else 1
    assert np.allclose(last, out["after"].residual[::step, 0][:len(last)])   # the last stage is the residual after
    bars = fig.axes[-1]
    heights = np.array([p.get_height() for p in bars.patches]).reshape(3, n)  # stage by joint
    assert np.allclose(heights[0], out["before"].rms) and np.allclose(heights[-1], out["after"].rms)
    assert np.all(heights[-1] < 0.5 * heights[0])       # the hidden friction and offsets explained
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    r = FigureCanvasAgg(fig).get_renderer()            # (plot closed the figure)
    for ax in fig.axes:
        legend = ax.get_legend()
        if legend is not None:
            box, data = legend.get_window_extent(r), ax.get_window_extent(r)
            assert box.y0 >= data.y1 or box.x0 >= data.x1  # above or beside the axes, not over the data
