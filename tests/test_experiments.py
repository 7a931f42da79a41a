"""Tests of the closed-loop runner, the benchmarks' bookkeeping and the demos' command line."""
import sys

import numpy as np
import pytest

from cpic import CPIC, Attractor, JointHold
from dynamics import Q_READY
from experiments import cli, timing
from experiments.runner import ExactCompensation, PayloadChange, PolicySwitch, Push, run
from sim import Plant, PlantConfig


def test_runner_applies_events_at_their_times_and_records_what_the_controller_saw():
    plant = Plant(PlantConfig.ideal())
    robot = plant.robot
    p0, R0 = robot.ee_pose(Q_READY)
    far = Attractor(p0 + np.array([0.0, 0.0, 0.05]), R0)
    ctrl = CPIC(robot, Attractor(p0, R0))
    seen = []
    rec = run(plant, ctrl, 0.3, events=[PayloadChange(0.1, 0.5, (0.0, 0.0, 0.1)), PolicySwitch(0.2, far),
                                        Push(0.05, (0.0, 10.0, 0.0), 0.02)],
              q0=Q_READY, before_step=lambda k, s: seen.append(s.t))
    assert len(rec) == 300 and np.allclose(rec.t, np.arange(300) * 1e-3) and np.allclose(seen, rec.t)
    k = rec.at(0.1)
    assert rec.theta[k - 1, 0] == 0.0 and rec.theta[k, 0] == 0.5                 # the payload from t = 0.1 s
    assert np.allclose(rec.target[rec.at(0.2) - 1], p0) and np.allclose(rec.target[rec.at(0.2)], far.p_star)
    np.testing.assert_allclose(rec.p, robot.ee_pose(rec.q)[0], atol=1e-12)
    dy = rec.p[:, 1] - p0[1]
    assert abs(dy[rec.at(0.05)]) < 1e-4 and dy[rec.at(0.075)] > 1e-4            # the push moves the arm along +y
    assert np.all(np.isfinite(rec.V)) and not rec.fallback.any()


def test_runner_compensation_is_added_to_the_command():
    """JointHold adds the estimator's compensation: the command differs by exactly -payload_torque from t_on on."""
    theta = np.array([1.0, 0.02, 0.0, 0.1])
    recs = []
    for start in (0.05, 10.0):                         # compensation on at 50 ms, and never
        plant = Plant(PlantConfig.ideal())
        hold = JointHold(plant.robot, Q_READY)
        recs.append(run(plant, hold, 0.1, ExactCompensation(plant.robot, theta, start), q0=Q_READY))
    on, off = recs
    k = on.at(0.05)
    np.testing.assert_allclose(on.tau[:k], off.tau[:k], atol=1e-12)
    hold_torque = np.array([JointHold(on.robot, Q_READY).step(q, dq)[0] for q, dq in zip(on.q[k:], on.dq[k:])])
    np.testing.assert_allclose(on.tau[k:] - hold_torque, -on.robot.payload_torque(on.q[k:], theta), atol=1e-9)
    assert np.all(on.theta_hat[k:] == theta) and np.all(on.theta_hat[:k] == 0.0)


def test_runner_rejects_bad_arguments():
    plant = Plant(PlantConfig.ideal())
    hold = JointHold(plant.robot, Q_READY)
    for kwargs, match in [(dict(seconds=0.0, q0=Q_READY), "seconds"), (dict(seconds=0.1), "q0"),
                          (dict(seconds=0.1, q0=Q_READY, events=[(0.1, 1.0)]), "events")]:
        with pytest.raises(ValueError, match=match):
            run(plant, hold, **kwargs)


def test_detector_benchmark_counts_each_episode_once_and_survives_no_detection(monkeypatch):
    """Per episode: a detection within 0.5 s of a change is a hit, any other one is extra; nothing detected at all
    is a valid result (latencies are NaN then)."""
    fired = iter([[1.1, 2.7, 3.0], [1.2], []] + [[]] * 100)
    monkeypatch.setattr(timing, "detector_episode", lambda *a, **k: next(fired))
    monkeypatch.setattr(timing, "_update_us", lambda *a, **k: 1.0)
    out = timing.detector_benchmark(episodes=3)
    assert (out["detected"], out["missed"], out["extra_detections"]) == (3, 3, 1)
    assert out["latency_ms_median"] == pytest.approx(200.0)
    monkeypatch.setattr(timing, "detector_episode", lambda *a, **k: [])
    out = timing.detector_benchmark(episodes=2)
    assert (out["detected"], out["missed"], out["extra_detections"]) == (0, 4, 0)
    assert np.isnan(out["latency_ms_median"])


@pytest.mark.parametrize("argv", [["payload", "--plot", "x.png"], ["better-model", "--preset", "ideal"],
                                  ["bench", "--view"], ["timing", "--seed", "3"], ["not-a-demo"]])
def test_each_demo_accepts_only_its_own_flags(argv, capsys):
    with pytest.raises(SystemExit) as stop:
        cli.main(argv)
    assert stop.value.code == 2
    assert "unrecognized arguments" in capsys.readouterr().err or argv == ["not-a-demo"]


def test_plot_without_matplotlib_is_refused_before_the_demo_runs(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "matplotlib", None)          # import matplotlib now raises ImportError
    monkeypatch.setattr(cli, "DEMOS", dict(cli.DEMOS, **{"hidden-effect": ("", "experiments.no_such_module:f",
                                                                             ("preset", "seed", "plot", "view", "json"))}))
    with pytest.raises(SystemExit) as stop:                       # the demo would fail to import if it ran
        cli.main(["hidden-effect", "--plot", "f.png"])
    assert stop.value.code == 2 and "matplotlib" in capsys.readouterr().err


def test_default_demo_is_static_with_its_flags():
    args = cli.parser().parse_args(["static", "--seed", "4", "--preset", "ideal"])
    assert (args.demo, args.seed, args.preset, args.plot, args.view) == ("static", 4, "ideal", None, False)
    assert cli.DEMOS["static"][1] == "experiments.scenarios:static_hold"


def test_the_bench_tables_hold_each_method_on_the_same_windows(monkeypatch, capsys):
    """The paper's tables' bookkeeping on windows whose answer is known: noise-free torques of four payloads along a
    motion that observes every parameter, at rest and at the detection alike. Plain least squares (the baseline) is
    what it gives on those windows directly, near the truth, RME near it too; Table 5 and the latencies are what the
    trials returned, and the printed tables name every row."""
    from experiments import bench
    from experiments.baselines import LeastSquares
    from nn_train import DataConfig, random_pose
    robot, rng, cfg = Plant().robot, np.random.default_rng(21), DataConfig()
    lo, hi = np.array([cfg.m_range[0], *cfg.r_low]), np.array([cfg.m_range[1], *cfg.r_high])

    def window(theta, q0):
        s = np.linspace(0.0, 2 * np.pi, 300)               # the wrist turned 1.2 rad three ways: every parameter seen
        q = q0 + 1.2 * np.stack([0 * s] * 4 + [np.sin(s), np.cos(s) - 1.0, np.sin(2 * s)], axis=1)
        return q, robot.payload_torque(q, theta)

    data = []
    for _ in range(4):
        theta = rng.uniform(lo, hi)
        (q, tau), (q_rest, tau_rest) = (window(theta, random_pose(robot, rng, cfg)) for _ in range(2))
        data.append(dict(theta=theta, q=q, tau=tau, q_rest=q_rest, tau_rest=tau_rest, detected=True, at_rest=True,
                         delay=50.0))
    monkeypatch.setattr(bench, "datasets", lambda *a, **k: data)
    trial = {"calls": 0}

    def closed_loop_trial(theta, seed, calibration=None):
        trial["calls"] += 1
        e = bench.RME(rng=np.random.default_rng(seed)).estimate(*window(theta, Q_READY), referred=True)
        return e, e, 100.0 + trial["calls"]

    monkeypatch.setattr(bench, "closed_loop_trial", closed_loop_trial)
    res = bench.tables(n_datasets=4, trials=2, log=lambda *a: None)
    ls = [LeastSquares(robot).estimate(d["q_rest"][-200:], d["tau_rest"][-200:], referred=True).mean - d["theta"]
          for d in data]                                                       # the same windows, directly
    np.testing.assert_allclose(res["table1_baselines"]["least squares"], np.mean(np.square(ls), axis=0), rtol=1e-12)
    assert max(res["table1_baselines"]["least squares"]) < 1e-5                # (its ridge's bias alone: 3 mm rms)
    assert res["table1"]["nn"][0] < 1e-4 and max(res["table1"]["nn"][1:]) < 1e-4     # (10 g, 1 cm rms)
    assert set(res["table4"]) == set(res["table4_first"]) == {"50", "100", "200", "300"}
    assert trial["calls"] == 2 * len(bench.TABLE5) and res["table1_detected"] == res["table1_at_rest"] == 4
    assert res["attach_to_compensation_ms_median"] == np.median(100.0 + np.arange(1, 2 * len(bench.TABLE5) + 1))
    for row, applied in zip(res["table5"], bench.TABLE5):
        assert row["detected"] == row["trials"] == 2 and np.allclose(row["mean"], applied, atol=0.02)
    bench.print_tables(res)
    out = capsys.readouterr().out
    assert all(f"Table 4 {k:>3} ms" in out for k in res["table4"]) and "least squares" in out and "at rest:" in out
