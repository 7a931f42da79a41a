"""franka.py: the 1 kHz loop end to end on the project's plant, the safety layer against closed forms, libfranka's
tau_ext sign, the backends' refusal to start without their package or robot, the warm-up, real-time priority and
CPU pinning (the worker process: test_worker.py; pylibfranka against franky-sim: test_franky_sim.py)."""
import json
import os
import socket
import sys
import time

import numpy as np
import pytest

import franka
import robot.loop as loop
from diagnosis.logs import load_log, read_npz
from dynamics import Robot
from rme import RME, RMESettings
from tests.helpers import ROOT

ROBOT = Robot.panda()
LIMIT = ROBOT.torque_limits()
T_ADD, M_ADD, R_ADD = 1.0, 1.0, (0.03, -0.02, 0.05)   # off the flange axis: estimated at once


@pytest.fixture(scope="module")
def hold_run(tmp_path_factory):
    """A 3 s hold on the realistic plant with 1 kg added at 1 s; the log saved and the plant kept."""
    backend = franka.SimBackend(np.random.default_rng(3), payload=[(T_ADD, M_ADD, R_ADD)])
    ctrl = franka.make_controller(ROBOT, backend.initial.q, "hold")
    est = RME(ROBOT, rng=np.random.default_rng(4))
    summary, log = franka.run_loop(backend, ROBOT, ctrl, est, seconds=3.0)
    path = tmp_path_factory.mktemp("franka") / "hold.npz"
    franka.save_log(path, log, est)
    return summary, log, path, backend


@pytest.mark.slow
def test_sim_hold_detects_kilogram_and_reads_its_mass_at_rest(hold_run):
    summary, log, _, backend = hold_run
    assert summary["cycles"] == 3000 and summary["stopped"] == "end"
    assert backend.plant.theta[0] == M_ADD                        # the plant did carry the load
    applied = [e for e in summary["estimates"] if e["accepted"]]
    assert applied and T_ADD < applied[0]["t"] < T_ADD + 1.0     # detected after it was added, within 1 s
    assert any(e["kind"] == "at rest" for e in applied)
    assert abs(summary["theta_hat"][0] - M_ADD) < 0.1
    assert summary["callback_ms"]["median"] > 0


def test_sim_hold_torques_within_limits_and_rate_and_finite(hold_run):
    _, log, _, _ = hold_run
    for key in ("q", "dq", "tau_J", "tau_ext", "tau", "tau_cmd"):
        assert np.all(np.isfinite(log[key])), key
    sent = log["tau_cmd"] + ROBOT.gravity(log["q"])               # what the drives deliver, recomputed here
    assert np.all(np.abs(sent) <= LIMIT + 1e-9)
    steps = np.diff(np.vstack([np.zeros((1, 7)), log["tau_cmd"]]), axis=0)
    assert np.abs(steps).max() <= 1.0 + 1e-9
    assert np.abs(steps).max() > 0.5                              # the limiter had something to do (load applied)


def test_loop_commands_exactly_what_the_checked_safety_gives_for_the_models_gravity(hold_run):
    """The loop takes G from the controller's step and the unchecked Safety path: replaying the logged tau through
    the public Safety.command with G = Robot.gravity(q) recomputed here gives every command bit for bit."""
    _, log, _, _ = hold_run
    safety = franka.Safety(LIMIT)
    replay = np.array([safety.command(tau, ROBOT.gravity(q)) for tau, q in zip(log["tau"], log["q"])])
    assert np.array_equal(replay, log["tau_cmd"]) and safety.held == 0


def test_sim_tau_ext_is_paper_sign_minus_the_load_torque(hold_run):
    """Paper sign (Eq. 1): tau_ext = model - tau_J, so a load the model lacks reads, at rest, as the torque its weight
    applies, +payload_torque (dynamics.py); libfranka's tau_ext_hat_filtered reads it negated."""
    summary, log, _, backend = hold_run
    t, first = log["t"], summary["estimates"][0]["t"]
    before = (t > T_ADD - 0.3) & (t < T_ADD)
    after = (t > first - 0.1) & (t < first)                       # loaded, not yet compensated
    change = log["tau_ext"][after].mean(0) - log["tau_ext"][before].mean(0)
    q = log["q"][after].mean(0)
    expected = ROBOT.payload_torque(q, np.array([M_ADD, *R_ADD]))
    big = np.abs(expected) > 1.0                                  # J2 and J4 at the ready pose
    assert big.sum() >= 2
    np.testing.assert_allclose(change[big], expected[big], rtol=0.25)


def test_log_loads_with_load_log_in_paper_sign(hold_run):
    _, log, path, _ = hold_run
    raw = read_npz(path)
    np.testing.assert_array_equal(raw["tau_ext"], log["tau_ext"])
    loaded = load_log(path)
    assert len(loaded) == len(log["t"])
    np.testing.assert_allclose(loaded.q, log["q"], atol=1e-3)
    np.testing.assert_allclose(loaded.tau_ext.mean(0), log["tau_ext"].mean(0), atol=0.01)   # smoothed, same sign
    with np.load(path) as z:
        assert str(z["tau_ext_sign"]) == "paper" and z["est_theta"].shape[1] == 4


# --- safety: closed forms ----------------------------------------------------------------------------------------
def test_safety_subtracts_gravity():
    s = franka.Safety(LIMIT)
    G = np.array([0.1, -0.3, 0.2, 0.4, -0.1, 0.05, 0.0])
    tau = G + np.array([0.5, -0.5, 0.25, 0.0, 0.1, -0.9, 0.3])   # within one rate step of zero
    np.testing.assert_allclose(s.command(tau, G), tau - G, atol=1e-15)


def test_safety_rate_limits_a_step_to_one_newton_metre_per_cycle():
    s, G = franka.Safety(LIMIT), np.full(7, 2.0)
    target = np.array([5.0, -5.0, 0.3, 2.5, -2.5, 0.0, 1.0])
    for k in range(1, 7):
        cmd = s.command(G + target, G)
        np.testing.assert_allclose(cmd, np.clip(target, -k, k))


def test_safety_clips_total_torque_to_limits_over_the_rate_limit():
    s = franka.Safety(LIMIT)
    G = np.array([10.0, -10.0, 0.0, 0.0, 1.0, -1.0, 0.0])
    s.last = LIMIT - G - 0.5                                      # half a Nm below the limit
    cmd = s.command(np.full(7, 1e3), G)
    np.testing.assert_allclose(cmd + G, LIMIT)
    s.last = LIMIT - G + 5.0                                      # beyond: the limit wins over the rate limit
    np.testing.assert_allclose(s.command(np.full(7, 1e3), G) + G, LIMIT)


def test_safety_holds_last_command_on_nan():
    s, G = franka.Safety(LIMIT), np.zeros(7)
    np.testing.assert_array_equal(s.command(np.full(7, np.nan), G), np.zeros(7))   # before any: zero
    good = s.command(np.full(7, 0.7), G)
    bad = np.full(7, 0.3)
    bad[2] = np.inf
    np.testing.assert_array_equal(s.command(bad, G), good)
    np.testing.assert_array_equal(s.command(np.full(7, 0.3), np.full(7, np.nan)), good)
    assert s.held == 3


def test_safety_ramps_down_to_zero_at_the_rate_limit():
    s = franka.Safety(LIMIT)
    s.last = np.array([3.5, -2.0, 0.0, 0.4, 0.0, 0.0, 0.0])
    seq = [s.ramp_down()[0] for _ in range(5)]
    assert seq == [2.5, 1.5, 0.5, 0.0, 0.0]


def test_safety_rejects_bad_limits_and_shapes():
    with pytest.raises(ValueError, match="tau_max"):
        franka.Safety([87.0, -1.0])
    with pytest.raises(ValueError, match="tau, G"):
        franka.Safety(LIMIT).command(np.zeros(6), np.zeros(7))


# --- sign, refusal, stop ------------------------------------------------------------------------------------------
def test_libfranka_sign_conversion_and_sim_backend_reports_libfranka_sign():
    x = np.array([1.0, -2.0, 3.0, 0.0, -0.5, 0.25, 7.0])
    np.testing.assert_array_equal(franka.paper_tau_ext(x), -x)
    b = franka.SimBackend(np.random.default_rng(0))
    b.write(np.ones(7))
    np.testing.assert_array_equal(b.read().tau_ext_hat_filtered, -b._s.tau_ext)
    np.testing.assert_array_equal(b.read().tau_J, b._s.tau_J)


@pytest.mark.parametrize("cls, module", [(franka.PylibfrankaBackend, "pylibfranka"),
                                         (franka.PandaPyBackend, "panda_py")])
def test_backend_refuses_without_its_package(monkeypatch, cls, module):
    monkeypatch.setitem(sys.modules, module, None)                # import raises ImportError
    with pytest.raises(RuntimeError, match="not installed"):
        cls("127.0.0.1")


def test_cli_refuses_without_package_and_checks_arguments(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "pylibfranka", None)
    assert franka.main(["--robot-ip", "127.0.0.1", "--seconds", "0.1"]) == 2
    assert "not installed" in capsys.readouterr().err
    capsys.readouterr()
    for argv, name in [(["--stiffness-scale", "2"], "--stiffness-scale"), (["--seconds", "-1"], "--seconds"),
                       (["--seed", "-1"], "--seed"), (["--log", "/no/such/folder/run.npz"], "--log"),
                       (["--sim-payload", "nan"], "--sim-payload")]:
        with pytest.raises(SystemExit) as stop:        # refused by the parser, before any work: one line
            franka.main(["--sim"] + argv)
        err = capsys.readouterr().err
        assert stop.value.code == 2 and err.count("\n") == 1 and f"argument {name}: expected" in err, err


@pytest.mark.slow
@pytest.mark.parametrize("worker", ["thread", "process"])
def test_cli_runs_the_estimates_beside_the_loop_and_restores_the_switch_interval(capsys, worker):
    """RME's estimates run in a worker (the loop only polls them); --sync-estimate runs them in the loop."""
    switch = sys.getswitchinterval()
    # paced at 1 kHz of wall time, as on a robot: the loop waits for each state, so the worker (at the lowest
    # scheduling priority) finds idle CPU even on a busy machine; unpaced, the loop takes the whole core
    assert franka.main(["--sim", "--paced", "--seconds", "2.0", "--sim-payload", "1.0", "--json", "--worker",
                        worker]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["estimate_in"] == worker and sys.getswitchinterval() == switch
    applied = [e for e in summary["estimates"] if e["accepted"]]
    # asked, then applied within the run (the samples a worker's estimate takes depend on the machine's load)
    assert applied and 1.0 < applied[0]["t"] <= applied[0]["applied"] < 2.0
    assert abs(summary["theta_hat"][0] - 1.0) < 0.1 and summary["missed_cycles"] == 0
    flight = summary["callback_ms_estimate_in_flight"]          # may hold no cycle: a job can end within one
    assert set(flight) == {"median", "p99", "max", "cycles"} and flight["cycles"] <= summary["cycles"]


def _free_port_closed(host="127.0.0.1"):
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


def test_pylibfranka_refuses_when_no_robot_answers():
    pytest.importorskip("pylibfranka")
    t0 = time.monotonic()
    with pytest.raises(RuntimeError, match="no robot answered"):
        franka.PylibfrankaBackend("127.0.0.1", realtime=False)    # nothing listens on 127.0.0.1:1337
    assert time.monotonic() - t0 < 30


class _Failing:
    """A sim backend whose read() raises `error` at cycle `at`; records stop()."""

    def __init__(self, at, error):
        self.inner, self.at, self.error, self.k, self.stopped = franka.SimBackend(np.random.default_rng(1)), at, error, 0, 0
        self.initial = self.inner.initial

    def read(self):
        self.k += 1
        if self.k == self.at:
            raise self.error
        return self.inner.read()

    def write(self, cmd):
        self.inner.write(cmd)

    def stop(self):
        self.stopped += 1


class _Faulty(franka.SimBackend):
    """The sim backend reporting a faulty tau_ext_hat_filtered at the read cycles in `at`: NaN at odd cycles, 5000 Nm
    (beyond any joint torque sensor's range) at even ones."""

    def __init__(self, at, **kw):
        self.at, self.k = set(at), None
        super().__init__(np.random.default_rng(3), **kw)   # reads `initial`
        self.k = 0                                     # from now on, read k is the state of cycle k

    def read(self):
        s = super().read()
        if self.k is not None:
            if self.k in self.at:
                s.tau_ext_hat_filtered = np.full(len(s.q), np.nan if self.k % 2 else 5e3)   # NaN, or absurd
            self.k += 1
        return s


def test_a_faulty_tau_ext_sample_never_stalls_the_loop_nor_reaches_the_command():
    """Two faulty samples, one before 1 kg is added (0.6 s, 5000 Nm) and one while it is being detected (NaN): the
    loop runs to the end, RME drops both, the controller gets the last good tau_ext, every command is finite and within
    the limits, and the load is still read within 10 % at rest."""
    b = _Faulty((400, 701), payload=[(0.6, M_ADD, R_ADD)])
    est, ctrl, given = RME(ROBOT, rng=np.random.default_rng(4)), franka.make_controller(ROBOT, b.initial.q, "hold"), []
    step = ctrl.step
    ctrl.step = lambda q, dq, comp, tau_ext: given.append(np.array(tau_ext)) or step(q, dq, comp, tau_ext)
    summary, log = franka.run_loop(b, ROBOT, ctrl, est, seconds=2.5)
    given = given[-2500:]                             # (the warm-up's step before the loop comes first)
    for k in (400, 701):                              # the controller got the sample before, as logged
        np.testing.assert_array_equal(given[k], log["tau_ext"][k - 1])
        np.testing.assert_array_equal(given[k - 1], log["tau_ext"][k - 1])
    assert summary["stopped"] == "end" and summary["cycles"] == 2500
    assert summary["faulty_tau_ext"] == 2 and est.dropped == 2
    assert np.all(log["tau_ext"][400] == -5e3) and np.isnan(log["tau_ext"][701]).all()
    assert np.abs(np.delete(log["tau_ext"], [400, 701], 0)).max() < 100.0
    assert np.isfinite(log["tau_cmd"]).all() and np.all(np.abs(log["tau"]) <= LIMIT + 1e-9)
    assert any(e.kind == "at rest" for e in est.history) and abs(est.theta[0] - M_ADD) <= 0.1 * M_ADD


def test_loop_stops_cleanly_on_ctrl_c_and_on_errors():
    b = _Failing(300, KeyboardInterrupt())
    ctrl = franka.make_controller(ROBOT, b.initial.q, "limit-cycle", 0.5)
    summary, log = franka.run_loop(b, ROBOT, ctrl, None, seconds=1.0)
    assert summary["stopped"].startswith("interrupted") and summary["cycles"] == 299 and b.stopped == 1
    b = _Failing(200, RuntimeError("link lost"))
    with pytest.raises(RuntimeError, match="link lost"):
        franka.run_loop(b, ROBOT, franka.make_controller(ROBOT, b.initial.q), None, seconds=1.0)
    assert b.stopped == 1


def test_dry_run_prints_and_commands_nothing(capsys):
    b = franka.SimBackend(np.random.default_rng(2))
    sent = []
    write = b.write
    b.write = lambda cmd: (sent.append(np.array(cmd)), write(cmd))
    summary, _ = franka.run_loop(b, ROBOT, franka.make_controller(ROBOT, b.initial.q), None, seconds=0.2,
                                 dry_run=True, print_every=0.1)
    assert np.all(np.array(sent) == 0) and len(sent) == 200
    assert capsys.readouterr().out.count("would command") == 2


def test_realtime_priority_sets_sched_fifo_only_inside_and_restores_the_policy():
    before = os.sched_getscheduler(0)
    with franka.realtime_priority(10) as fifo:
        inside = os.sched_getscheduler(0)
    assert os.sched_getscheduler(0) == before
    policy = inside & ~getattr(os, "SCHED_RESET_ON_FORK", 0)           # the flag that children do not inherit it
    assert (policy == os.SCHED_FIFO) if fifo else (inside == before)   # without the permission: runs as it was


def test_threads_started_at_realtime_priority_do_not_inherit_it():
    import threading
    seen = []
    with franka.realtime_priority(10) as fifo:
        t = threading.Thread(target=lambda: seen.append(os.sched_getscheduler(0)))
        t.start()
        t.join(5.0)
    assert seen and (seen[0] != os.SCHED_FIFO or not fifo)


def test_the_warm_up_before_the_loop_changes_nothing_it_commands(monkeypatch):
    """run_loop exercises the cycle's code once before the first state (cold caches made the first cycle slow); the
    commands of a seeded run with a load are bit for bit those of the same run without it."""
    def hold(warm):
        if not warm:
            monkeypatch.setattr(loop, "_warm_up", lambda *args: None)
        q0 = franka.Q_START + np.array([0.2, -0.1, 0.1, 0.15, 0.0, -0.1, 0.3])   # not the warm-up's pose
        backend = franka.SimBackend(np.random.default_rng(5), q0=q0, payload=[(0.3, 1.0, R_ADD)])
        ctrl = franka.make_controller(ROBOT, backend.initial.q, "hold")
        est = RME(ROBOT, rng=np.random.default_rng(6), settings=RMESettings(asynchronous=False))
        _, log = franka.run_loop(backend, ROBOT, ctrl, est, seconds=0.8)
        monkeypatch.undo()
        return log, est
    (warm, est_warm), (cold, est_cold) = hold(True), hold(False)
    np.testing.assert_array_equal(warm["tau_cmd"], cold["tau_cmd"])
    assert [e.mean.tolist() for e in est_warm.history] == [e.mean.tolist() for e in est_cold.history] != []


def test_own_cpu_keeps_the_loop_on_one_cpu_and_other_processes_off_it_then_restores_them():
    import subprocess
    if len(os.sched_getaffinity(0)) < 2:
        pytest.skip("one CPU allowed here: nothing to keep apart")
    mine = os.sched_getaffinity(0)
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        theirs = os.sched_getaffinity(child.pid)
        with franka.own_cpu([child.pid]) as cpu:
            assert os.sched_getaffinity(0) == {cpu} and cpu in mine
            assert cpu not in os.sched_getaffinity(child.pid) and os.sched_getaffinity(child.pid) <= theirs
        assert os.sched_getaffinity(0) == mine and os.sched_getaffinity(child.pid) == theirs
    finally:
        child.kill()                                   # its own process id
        child.wait(timeout=10)


@pytest.mark.slow
def test_identify_cli_on_the_sim_reports_the_tool_in_the_flange_frame(tmp_path, capsys):
    """franka.py --identify --sim --sim-tool on a fresh plant and tool (seeded draw): --json's mass, com, inertia
    (flange frame) near the tool given, to the targets for mass (1 % or 10 g) and CoM (3 mm per axis) and to 40 % for
    the inertia's diagonal (its 15 % target is missed on some tools: docs/tool_identification.md); the motion slow
    and inside the limits, no push seen, its storage check passed; the forms beside them; tool.json written."""
    rng = np.random.default_rng(2032)
    c = rng.normal(size=3)
    tool = [rng.uniform(0.4, 1.5), *(c * rng.uniform(0.02, 0.1) / np.linalg.norm(c)), *rng.uniform(3e-3, 6e-3, 3)]
    path = tmp_path / "tool.json"
    log = tmp_path / "tool_run.npz"
    assert franka.main(["--identify", "--sim", "--seed", "2", "--sim-tool", *map(str, tool), "--json",
                        "--save", str(path), "--log", str(log)]) == 0
    out = json.loads(capsys.readouterr().out)
    import subprocess                                   # the same run's log through rme.py identify, no reference
    res = subprocess.run([sys.executable, "rme.py", "identify", str(log), "--json"], capture_output=True, text=True,
                         cwd=ROOT, timeout=120)
    from_log = json.loads(res.stdout)
    assert res.returncode == 0 and set(from_log) >= {"mass", "com", "inertia", "desk", "libfranka_set_load"}
    assert any("no reference motion" in n for n in from_log["fit"]["notes"])
    assert abs(out["mass"] - tool[0]) < max(0.01 * tool[0], 0.01) and np.abs(np.subtract(out["com"], tool[1:4])).max() < 0.003
    assert np.allclose(np.diag(out["inertia"]), tool[4:], rtol=0.4)
    assert out["libfranka_set_load"]["F_x_Cload"] == out["com"] and out["franka_ros2_set_load"]["mass"] == out["mass"]
    assert max(out["motion"]["max_abs_dq"]) < 0.5 and out["motion"]["min_limit_distance_rad"] >= 0.2
    assert out["motion"]["seconds"] <= 20.0 and out["motion"]["abandoned_at_s"] is None
    assert out["motion"]["storage"]["passive"] and out["motion"]["storage"]["seconds"] > 18
    saved = json.loads(path.read_text())
    assert saved["mass"] == out["mass"]


def test_rme_with_a_known_tool_estimates_only_the_load_added_to_it():
    """A window at rest whose tau_ext carries a tool and a 0.5 kg load: RME(tool=) finds the load, within the
    tolerance RME reaches on its own (test_rme.py's static windows)."""
    from motion.tool_forms import make_tool, phi_of_tool
    robot, rng = Robot.panda(), np.random.default_rng(8)
    tool = make_tool(0.9, [0.02, 0.01, 0.07], np.eye(3) * 3e-3)
    q = np.tile(franka.Q_START, (200, 1)) + rng.normal(0, 1e-4, (200, 7))
    load = np.array([0.5, 0.0, 0.0, 0.1])
    tau = robot.payload_regressor(q) @ (phi_of_tool(tool) + np.array([0.5, 0.0, 0.0, 0.05])) + \
        rng.normal(0, 0.02, (200, 7))
    est = RME(robot, tool=tool).estimate(q, tau)
    assert abs(est.mean[0] - load[0]) < 0.05 and np.abs(est.mean[1:3]).max() < 0.02
    plain = RME(robot).estimate(q, tau)                          # without the tool: the sum
    assert abs(plain.mean[0] - 1.4) < 0.1
    before = robot.payload_regressor(q).mean(axis=0) @ phi_of_tool(tool)   # the level before the load: the tool's
    referred = RME(robot, tool=tool).estimate(q, tau, baseline=before)     # it cancels there, not subtracted twice
    assert abs(referred.mean[0] - load[0]) < 0.05


def test_identify_refuses_a_dry_run_and_a_sim_tool_without_the_sim():
    with pytest.raises(ValueError, match="--identify"):
        franka.main(["--identify", "--robot-ip", "172.16.0.2", "--dry-run"])
    with pytest.raises(ValueError, match="--sim-tool"):
        franka.main(["--identify", "--robot-ip", "172.16.0.2", "--sim-tool", "1", "0", "0", "0.05", "1e-3", "1e-3",
                     "1e-3"])
    with pytest.raises(ValueError, match="--sim-tool.mass"):
        franka.main(["--identify", "--sim", "--sim-tool", "-1", "0", "0", "0.05", "1e-3", "1e-3", "1e-3"])


@pytest.mark.parametrize("tool, match", [({"mass": 1.0, "com": [0, 0, 0]}, "inertia"), ("/no/such/tool.json", "read"),
                                         ({"mass": -1, "com": [0, 0, 0], "inertia": np.eye(3).tolist()}, "mass"), (3, "tool")])
def test_rme_refuses_a_bad_tool_naming_it(tool, match):
    with pytest.raises(ValueError, match=match):
        RME(Robot.panda(), weights=None, tool=tool)


def test_estimator_spec_refuses_a_missing_tool_file():
    from robot.worker import EstimatorSpec
    with pytest.raises(ValueError, match="tool"):
        EstimatorSpec(tool="/no/such/tool.json")


def test_rme_with_a_tool_compensates_its_weight_from_the_first_sample():
    from motion.tool_forms import make_tool, phi_of_tool
    robot = Robot.panda()
    tool = make_tool(0.9, [0.02, 0.01, 0.07], np.eye(3) * 3e-3)
    q = np.array(franka.Q_START)
    tau = robot.payload_regressor(q) @ phi_of_tool(tool)
    comp = RME(robot, weights=None, tool=tool).update(q, np.zeros(7), tau)
    assert np.allclose(comp, -robot.payload_torque(q, [0.9, *(np.linalg.inv(_ee_in_f()) @ [0.02, 0.01, 0.07])]))


def _ee_in_f():
    """The ee frame's axes in the flange frame F: panda.xml's ee site relative to its flange site (MuJoCo's own)."""
    robot = Robot.panda()
    import mujoco
    m, d = robot.model, mujoco.MjData(robot.model)
    mujoco.mj_forward(m, d)
    ids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, s) for s in ("flange", "ee")]
    Rf, Re = (d.site_xmat[i].reshape(3, 3) for i in ids)
    return Rf.T @ Re
