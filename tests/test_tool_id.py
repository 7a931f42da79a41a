"""The tool's identification: its frames and forms (against MuJoCo with the tool as a body on the flange), the
motion's bounds, the push that stops it (the fit on the realistic plant: test_franka.py, through franka.py)."""
import json
import os

import mujoco
import numpy as np
import pytest

import franka
from dynamics import PANDA_XML, Q_READY, Robot
from motion.tool_forms import (desk, load_tool, make_tool, params_of_tool, ros2_set_load, save_tool, set_load,
                               tool_of_desk, tool_of_params, tool_of_ros2, tool_of_set_load)
from motion.tool_id import fit_tool
from motion.tool_motion import ExcitationController, MotionSettings, excitation
from robot.identify import run_motion, sim_backend


def random_tool(rng):
    """A tool of the benchmark's range: 0.4-1.5 kg, CoM 2-10 cm from the flange, principal moments 1e-3..1e-2
    kg m^2 (physical), principal axes turned at random."""
    c = rng.normal(size=3)
    c *= rng.uniform(0.02, 0.10) / np.linalg.norm(c)
    while True:
        w = 10 ** rng.uniform(-3, -2, 3)
        if w.sum() >= 2 * w.max():
            break
    Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return make_tool(rng.uniform(0.4, 1.5), c, Q @ np.diag(w) @ Q.T)


def close(a, b):
    return np.isclose(a.mass, b.mass, atol=1e-12) and np.allclose(a.com, b.com, atol=1e-12) and \
        np.allclose(a.inertia, b.inertia, atol=1e-14)


def test_every_form_round_trips_and_the_inertia_is_column_major():
    rng = np.random.default_rng(11)
    for _ in range(5):
        tool = random_tool(rng)
        assert close(tool_of_set_load(set_load(tool)), tool)
        assert close(tool_of_ros2(ros2_set_load(tool)), tool)
        d = desk(tool)                                          # rounded to what Desk's fields take
        back = tool_of_desk(d)
        assert abs(back.mass - tool.mass) < 1e-4 and np.abs(back.com - tool.com).max() < 1e-5
        assert np.abs(back.inertia - tool.inertia).max() < 1e-6
        assert close(tool_of_params(params_of_tool(tool)), tool)
        col = np.array(set_load(tool)["load_inertia"])
        assert [col[1], col[2], col[5]] == [tool.inertia[1, 0], tool.inertia[2, 0], tool.inertia[2, 1]]


def test_tool_json_round_trips(tmp_path):
    tool = random_tool(np.random.default_rng(3))
    path = tmp_path / "tool.json"
    save_tool(path, tool, {"status": "ok"})
    assert close(load_tool(str(path)), tool)
    d = json.loads(path.read_text())
    assert d["identification"] == {"status": "ok"} and np.allclose(d["inertia"], tool.inertia)


def _with_tool_body(tool, path):
    """panda.xml with the tool as a MuJoCo body on the flange site (link 7's z, no rotation: libfranka's F)."""
    xml = open(PANDA_XML).read()
    I = tool.inertia
    body = (f'<body name="tool" pos="0 0 0.107"><inertial pos="{tool.com[0]} {tool.com[1]} {tool.com[2]}" '
            f'mass="{tool.mass}" fullinertia="{I[0, 0]} {I[1, 1]} {I[2, 2]} {I[0, 1]} {I[0, 2]} {I[1, 2]}"/></body>')
    marker = '<site name="flange" pos="0 0 0.107" size="0.01"/>'
    assert marker in xml
    open(path, "w").write(xml.replace(marker, marker + body))
    return mujoco.MjModel.from_xml_path(str(path))


def test_flange_frame_tool_matches_mujoco_with_the_tool_as_a_body(tmp_path):
    """-body_regressor(q, dq, ddq) @ params_of_tool(tool) (the project's ee frame) equals the inverse dynamics of
    MuJoCo's model with the tool added as a body in F, less the model without it, at random states."""
    rng = np.random.default_rng(5)
    robot = Robot.panda()
    for _ in range(3):
        tool = random_tool(rng)
        m = _with_tool_body(tool, tmp_path / "with_tool.xml")
        d = mujoco.MjData(m)
        for _ in range(3):
            q, dq, ddq = Q_READY + rng.uniform(-0.5, 0.5, 7), rng.normal(size=7), rng.normal(size=7)
            d.qpos[:], d.qvel[:], d.qacc[:] = q, dq, ddq
            mujoco.mj_inverse(m, d)
            extra = d.qfrc_inverse - robot.inverse_dynamics(q, dq, ddq)
            pred = -robot.body_regressor(q, dq, ddq) @ params_of_tool(tool)
            assert np.allclose(pred, extra, atol=1e-9), (pred, extra)


def test_the_fed_forward_point_mass_torque_is_mujocos_inertial_torque_of_that_mass(tmp_path):
    """motion.tool_motion.point_mass_inertial for a point mass phi = (m, m c) (what the push watch fits): minus the
    inverse dynamics of panda.xml with that mass added as a body on the flange, less the model without it, less the
    same at rest (its weight), at random states; and nothing below 0.05 kg."""
    from dynamics import phi_of
    from motion.tool_forms import EE_IN_F
    from motion.tool_motion import point_mass_inertial
    rng, robot = np.random.default_rng(29), Robot.panda()
    for _ in range(3):
        tool = make_tool(rng.uniform(0.4, 1.5), rng.uniform(-0.08, 0.08, 3), np.eye(3) * 1e-12)
        m = _with_tool_body(tool, tmp_path / "with_point.xml")
        d = mujoco.MjData(m)
        phi = phi_of(np.array([tool.mass, *(EE_IN_F.T @ tool.com)]))      # the ee frame, as the watch's
        q, dq, ddq = Q_READY + rng.uniform(-0.5, 0.5, 7), rng.normal(size=7), rng.normal(size=7)
        extra = []
        for v, a in ((dq, ddq), (np.zeros(7), np.zeros(7))):
            d.qpos[:], d.qvel[:], d.qacc[:] = q, v, a
            mujoco.mj_inverse(m, d)
            extra.append(d.qfrc_inverse - robot.inverse_dynamics(q, v, a))
        assert np.allclose(point_mass_inertial(robot, phi, q, dq, ddq), -(extra[0] - extra[1]), atol=1e-8)
    assert not point_mass_inertial(robot, np.array([0.04, 0.0, 0.0, 0.002]), Q_READY, np.ones(7), np.ones(7)).any()


@pytest.mark.parametrize("bad, match", [(dict(mass=-1.0), "mass"), (dict(com=[0, 0, 2.0]), "com"),
                                        (dict(inertia=np.diag([1e-3, 1e-3, 1e-2])), "inertia"),
                                        (dict(inertia=[[1e-3, 1e-4, 0], [0, 1e-3, 0], [0, 0, 1e-3]]), "inertia")])
def test_a_bad_tool_is_refused_naming_the_field(bad, match):
    args = dict(mass=1.0, com=[0.0, 0.0, 0.05], inertia=np.eye(3) * 1e-3) | bad
    with pytest.raises(ValueError, match=match):
        make_tool(**args)


def test_excitation_keeps_its_margin_speed_and_duration_from_random_start_poses():
    rng, robot, s = np.random.default_rng(7), Robot.panda(), MotionSettings()
    lo, hi = robot.model.jnt_range.T
    for _ in range(5):
        q0 = Q_READY + rng.uniform(-0.4, 0.4, 7)
        q, dq, ddq = excitation(robot, q0, s)
        assert np.all(q >= lo + s.margin - 1e-9) and np.all(q <= hi - s.margin + 1e-9)
        assert np.abs(dq).max() <= s.max_speed * 1.01 and len(q) / s.rate <= s.max_duration
        assert np.allclose(q[0], q0) and np.allclose(q[-1], q0) and np.abs(dq[[0, -1]]).max() < 1e-3
    q0 = Q_READY.copy()
    q0[5] = lo[5] + 0.1                                         # joint 6 within the margin of its limit
    with pytest.raises(ValueError, match="joint 6"):
        excitation(robot, q0, s)


def test_excitation_about_another_centre_starts_at_the_start_and_is_the_centres_motion_after_the_rest():
    """A start pose up to settings.max_shift from the centre (the reference's start, fresh draws): the set point starts
    at q0, reaches the centre at rest by the end of the first rest within the speed limit, and from there on is the
    motion about the centre to the sample; a start further away is refused naming the joint."""
    rng, robot, s = np.random.default_rng(17), Robot.panda(), MotionSettings()
    rest = int(round(s.rest * s.rate))
    for _ in range(3):
        center = Q_READY + rng.uniform(-0.3, 0.3, 7)
        q0 = center + rng.uniform(-s.max_shift, s.max_shift, 7)
        q, dq, ddq = excitation(robot, q0, s, center)
        own = excitation(robot, center, s)
        assert np.allclose(q[0], q0) and np.abs(dq[0]).max() < 1e-3 and np.abs(dq).max() <= s.max_speed * 1.01
        assert np.allclose(q[rest - 1], center, atol=1e-9) and np.abs(dq[rest - 1]).max() < 1e-3
        assert np.array_equal(q[rest + 1:], own[0][rest + 1:])
    q0 = Q_READY.copy()
    q0[3] += 1.5 * s.max_shift
    with pytest.raises(ValueError, match="joint 4"):
        excitation(robot, q0, s, Q_READY)


def test_identify_refuses_a_reference_started_elsewhere_before_any_motion(tmp_path, monkeypatch):
    """franka.py --identify --reference REF whose start pose lies further than max_shift from the arm's (joint 4, a
    seeded draw of 1.5-3 times the limit): ValueError naming --reference and the joint, and no motion run."""
    rng, s = np.random.default_rng(31), MotionSettings()
    q = np.tile(np.asarray(franka.Q_START), (2000, 1)) + rng.normal(0, 1e-5, (2000, 7))
    q[:, 3] += rng.uniform(1.5, 3.0) * s.max_shift * rng.choice([-1.0, 1.0])
    path = tmp_path / "empty.npz"
    np.savez(path, t=np.arange(2000) * 1e-3, q=q, dq=rng.normal(0, 1e-3, (2000, 7)),
             tau_J=rng.normal(0, 0.01, (2000, 7)))
    import robot.identify as identify
    monkeypatch.setattr(identify, "run_motion", lambda *a, **k: pytest.fail("a motion was run"))
    with pytest.raises(ValueError, match="--reference.*joint 4"):
        franka.main(["--identify", "--sim", "--reference", str(path), "--sim-tool", "0.8", "0.02", "0.04", "0.07",
                     "0.004", "0.003", "0.005"])


def test_the_momentum_observer_follows_mujocos_external_torque_with_its_first_order_lag():
    """dynamics.MomentumObserver in libfranka's sign on panda.xml (the model) while MuJoCo moves panda.xml with a
    random tool added as a body (the plant) under a spring and drawn torques (no joint limit reached): its r follows
    tau_x = tau_J - (M ddq + C dq + G) of the model at MuJoCo's own accelerations (libfranka's sign: what the tool
    adds) through dr/dt = K (tau_x - r), within 1 %."""
    from dynamics import MomentumObserver
    rng, robot = np.random.default_rng(23), Robot.panda()
    tool = random_tool(rng)
    R = np.array([[np.cos(-np.pi / 4), -np.sin(-np.pi / 4), 0], [np.sin(-np.pi / 4), np.cos(-np.pi / 4), 0], [0, 0, 1]])
    c, I = R.T @ tool.com, R.T @ tool.inertia @ R              # the ee frame: F turned -45 deg about z
    xml, marker = open(PANDA_XML).read(), '<site name="flange" pos="0 0 0.107" size="0.01"/>'
    body = (f'<body name="tool" pos="0 0 0.107" axisangle="0 0 1 -0.7853981633974483"><inertial pos="{c[0]} {c[1]} '
            f'{c[2]}" mass="{tool.mass}" fullinertia="{I[0, 0]} {I[1, 1]} {I[2, 2]} {I[0, 1]} {I[0, 2]} '
            f'{I[1, 2]}"/></body>')
    plant = mujoco.MjModel.from_xml_string(xml.replace(marker, marker + body))
    data, dt, K = mujoco.MjData(plant), plant.opt.timestep, 100.0
    data.qpos[:] = Q_READY
    mujoco.mj_forward(plant, data)
    terms = lambda q, dq: robot.terms(q, dq)[1:]
    observer = MomentumObserver(terms, K, sign=-1)
    lagged, phase = np.zeros(7), rng.uniform(0, 2 * np.pi, 7)
    for k in range(1500):
        q, dq = data.qpos.copy(), data.qvel.copy()
        tau_J = robot.gravity(q) + 100.0 * (Q_READY - q) - 5.0 * dq + 2.0 * np.sin(2 * np.pi * 0.7 * k * dt + phase)
        r = observer.update(q, dq, tau_J, dt)
        data.qfrc_applied[:] = tau_J
        mujoco.mj_step(plant, data)
        _, M, b = robot.terms(q, dq)
        tau_x = tau_J - (M @ data.qacc + b)                  # what moved the plant beyond the model
        lagged += K * dt * (tau_x - lagged) if k else 0.0
        if k > 300:
            assert np.abs(r - lagged).max() <= 0.01 * np.abs(tau_x).max() + 1e-3, (k, r, lagged)
    assert np.abs(lagged).max() > 1.0                        # the tool's torque is there to be followed


@pytest.mark.slow
def test_a_push_ends_the_run_within_its_stated_time():
    """A 25 N push on the hand at a drawn time and direction (fresh seeded draws, the realistic plant holding a random
    tool): confirmed within 50 ms of its start, and the run ends settings.stop_after later (the loop's last sample),
    its summary saying why and which joint."""
    rng, robot, s = np.random.default_rng(41), Robot.panda(), MotionSettings()
    for _ in range(2):
        tool = random_tool(rng)
        backend = sim_backend(int(rng.integers(1000)), tool, 0)
        start = float(rng.uniform(1.5, 5.0))
        force = rng.normal(size=3)
        force *= 25.0 / np.linalg.norm(force)
        backend.plant.push(force, body="link7", start=backend.plant.t + start, duration=0.5)
        log, summary, ctrl = run_motion(backend, robot, franka.run_loop, s)
        assert summary["abandoned_at_s"] is not None and start <= summary["abandoned_at_s"] <= start + 0.05, summary
        assert abs(log["t"][-1] - (summary["abandoned_at_s"] + s.stop_after)) <= 2e-3, (log["t"][-1], summary)
        assert summary["stopped"].startswith("push") and 1 <= summary["pushed_joint"] <= 7
        assert log["t"][-1] < ctrl.duration - 1.0


def _pushed_backend(seed, tool, start, run=0):
    backend = sim_backend(seed, tool, run)
    backend.plant.push([0.0, 25.0, 0.0], body="link7", start=backend.plant.t + start, duration=0.5)
    return backend


def test_identify_abandoned_by_a_push_fits_nothing_and_says_so(tmp_path, capsys, monkeypatch):
    """franka.py --identify on a backend pushed mid-motion, on the robot's path (the backend from make_backend) and on
    the --sim path (the reference run pushed): exit status 3 within stop_after + 50 ms of the push, the output says
    abandoned and when, no tool.json written, the --log marked so that rme.py identify and --reference refuse it."""
    from robot import identify
    tool = random_tool(np.random.default_rng(43))
    log, saved = tmp_path / "run.npz", tmp_path / "tool.json"
    monkeypatch.setattr(franka, "make_backend", lambda args, rng: _pushed_backend(3, tool, 1.5))
    assert franka.main(["--identify", "--robot-ip", "172.16.0.2", "--json", "--log", str(log),
                        "--save", str(saved)]) == 3
    out = json.loads(capsys.readouterr().out)
    assert out["fit"] is None and 1.5 <= out["abandoned_at_s"] <= 1.55 and "abandoned" in out["note"]
    assert out["seconds"] <= 1.55 + MotionSettings().stop_after and not saved.exists()
    assert identify.abandoned_in(log) == out["abandoned_at_s"]
    assert identify.log_main([str(log)]) == 2 and "abandoned" in capsys.readouterr().err
    with pytest.raises(ValueError, match="--reference"):
        franka.main(["--identify", "--robot-ip", "172.16.0.2", "--reference", str(log)])
    monkeypatch.setattr(identify, "sim_backend", lambda seed, t, run, preset="realistic": _pushed_backend(
        seed, t, 1.5, run))
    assert franka.main(["--identify", "--sim", "--sim-tool", "0.8", "0.02", "0.04", "0.07", "0.004", "0.003",
                        "0.005"]) == 3
    text = capsys.readouterr().out
    assert text.startswith("ABANDONED") and "reference" in text and "push" in text


def test_a_motion_too_short_for_a_fit_is_refused():
    robot = Robot.panda()
    q = np.tile(Q_READY, (100, 1))
    with pytest.raises(ValueError, match="samples"):
        fit_tool(robot, q, 0 * q, 0 * q, 0 * q)


def test_ee_in_f_is_the_ee_site_seen_from_the_flange_site():
    from motion.tool_forms import EE_IN_F
    m = Robot.panda().model
    d = mujoco.MjData(m)
    d.qpos[:] = Q_READY + np.random.default_rng(1).uniform(-0.3, 0.3, 7)
    mujoco.mj_forward(m, d)
    Rf, Re = (d.site_xmat[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_SITE, s)].reshape(3, 3) for s in ("flange", "ee"))
    assert np.allclose(Rf.T @ Re, EE_IN_F, atol=1e-12)


def test_a_reference_of_another_motion_is_refused():
    robot, s = Robot.panda(), MotionSettings()
    q, dq, ddq = excitation(robot, Q_READY, s)
    other = excitation(robot, Q_READY + np.array([0, 0, 0, 0, 0.3, 0, 0]), s)
    with pytest.raises(ValueError, match="same motion"):
        fit_tool(robot, q, dq, ddq, 0 * q, reference=(other[0], other[1], other[2], 0 * q))


@pytest.mark.slow
def test_the_motion_stores_no_energy_beyond_what_its_set_point_does():
    """The storage check (MuJoCo's mass matrix of the plant holding the tool, its weight cancelled exactly) over the
    whole motion of a fresh random tool: no 1 ms step raises S = 1/2 dq^T M dq + 1/2 e^T Kp e by more than the set
    point's work in it (1e-6 J: rounding and the step), and the dampers dissipate. The check can fail: the same tool
    with the weight of one 0.3 kg lighter cancelled feeds the rest of the weight's power in over the first 2 s."""
    from motion.tool_storage import storage_check
    tool = random_tool(np.random.default_rng(21))
    res = storage_check(tool)
    assert res.passive and res.max_rise <= 1e-6 and res.dissipated > 0 and res.seconds > 18
    light = make_tool(tool.mass - 0.3, tool.com, tool.inertia)
    wrong = storage_check(tool, seconds=2.0, compensated=light)
    assert not wrong.passive and wrong.max_rise > 1e-5


def test_an_offset_drift_between_the_reference_and_the_tool_run_leaves_the_fit_within_its_targets():
    """The motion's states, tau_ext = Y(q, dq, ddq) pi of a fresh random tool (closed form) + the arm's own error
    (the same in both runs) + 2 mNm white noise per run, and the tool run's offsets drifted by 0.05 Nm per joint (the
    drift between windows on the beam logs): mass within 10 g, each CoM axis within 3 mm. The same fit without the
    drift term takes the drift for the tool and misses these targets (the term is what holds them)."""
    from motion.tool_id import ToolFitSettings, truth_of
    rng, robot = np.random.default_rng(17), Robot.panda()
    q, dq, ddq = excitation(robot, Q_READY, MotionSettings())
    tool = random_tool(rng)
    every = slice(None, None, 5)                                # 200 Hz: the fit takes every 10th row of these
    q, dq, ddq = q[every], dq[every], ddq[every]
    arm = 0.2 * np.sin(q @ rng.normal(size=(7, 7)) + rng.uniform(0, 6, 7))   # a pose-dependent error (T, 7) [Nm]
    tau_tool = robot.body_regressor(q, dq, ddq) @ params_of_tool(tool)
    drift = 0.05 * rng.choice([-1.0, 1.0], size=7)
    noise = lambda: 0.002 * rng.normal(size=q.shape)
    reference = (q, dq, ddq, arm + noise())
    run = (q, dq, ddq, tau_tool + arm + drift + noise())
    truth = truth_of(tool)
    for drift_term, holds in ((True, True), (False, False)):
        fit = fit_tool(robot, *run, reference=reference, settings=ToolFitSettings(every=2, edge=10, drift=drift_term),
                       dt=5e-3)
        com_error = max(abs(fit.value[k] - truth[k]) for k in ("com_x", "com_y", "com_z"))
        assert (abs(fit.value["mass"] - truth["mass"]) <= 0.01 and com_error <= 0.003) == holds, (drift_term,
                                                                                                 fit.value, truth)


@pytest.mark.slow
def test_the_intervals_carry_the_drives_model_of_the_two_motions_difference():
    """The tool run lags the reference by 2-5 ms and swings up to 2 % wider (the tool changes how the arm tracks);
    each run's drives add Gaz et al.'s sigmoid friction (sim.GAZ_P*) and a rotor inertia (0.05 / 0.02 kg m^2), a
    torque the fit's nuisance basis (dq, tanh, ddq of the difference) holds only in part, seen through dq and ddq
    with noise (1e-3 rad/s, 0.03 rad/s^2), tau with 3 mNm: fresh random tools (closed form, Y pi). With the drives'
    spread in the std at most 40 % of mass, CoM and the inertia's diagonal lie beyond 2 std; with the noise's std
    alone more than 60 % do (the spread is what covers them)."""
    from motion.tool_id import NAMES, ToolFitSettings, truth_of
    from sim import GAZ_P1, GAZ_P2, GAZ_P3
    rng, robot = np.random.default_rng(1), Robot.panda()
    p1, p2, p3 = (np.asarray(p) for p in (GAZ_P1, GAZ_P2, GAZ_P3))
    rotor = np.array([0.05] * 4 + [0.02] * 3)
    drives = lambda dq, ddq: 0.5 * p1 * (np.tanh(0.5 * p2 * (dq + p3)) - np.tanh(0.5 * p2 * p3)) + rotor * ddq
    q = excitation(robot, Q_READY, MotionSettings())[0]
    beyond = {True: 0, False: 0}
    for _ in range(4):
        tool, lag, gain = random_tool(rng), int(rng.integers(2, 6)), 1.0 + rng.uniform(0.0, 0.02)
        q_tool = np.vstack([np.tile(q[0], (lag, 1)), q[0] + gain * (q[:-lag] - q[0])])    # (T, 7) 1 kHz
        runs = []
        for Q, with_tool in ((q, False), (q_tool, True)):
            dQ = np.gradient(Q, 1e-3, axis=0)
            Q, dQ, ddQ = Q[::5], dQ[::5], np.gradient(dQ, 1e-3, axis=0)[::5]
            tau = -drives(dQ, ddQ) + 0.003 * rng.normal(size=Q.shape)       # paper sign: model - tau_J
            tau = tau + (robot.body_regressor(Q, dQ, ddQ) @ params_of_tool(tool) if with_tool else 0.0)
            runs.append((Q, dQ + 1e-3 * rng.normal(size=Q.shape), ddQ + 0.03 * rng.normal(size=Q.shape), tau))
        truth = truth_of(tool)
        for spread in (True, False):
            fit = fit_tool(robot, *runs[1], reference=runs[0],
                           settings=ToolFitSettings(every=2, edge=10, drive_spread=spread), dt=5e-3)
            beyond[spread] += sum(abs(fit.value[k] - truth[k]) > 2 * fit.std[k] for k in NAMES[:7])
    assert beyond[True] <= 0.4 * 28 and beyond[False] > 0.6 * 28, beyond


def test_rows_where_the_drives_model_of_the_difference_dwarfs_the_noise_count_for_less():
    """The tool run's arm sags 10-20 mrad on joints 2 and 4 over the first 0.75 s and is lifted back while the
    reference stands still; both runs carry a rotor inertia and an arm's own inertia error coupling the joints (a
    random symmetric M_err @ ddq, which each joint's own ddq column holds only in part), 2 mNm of torque noise: fresh
    random tools (closed form, Y pi). Weighting the rows by the drives' model (ToolFitSettings.drive_share) leaves mass
    and CoM within 2 std and cuts the mass's 2 std by at least 40 % against the unweighted fit, which leans on that
    model over the lift-back (measured: by 51-70 %)."""
    from motion.tool_id import ToolFitSettings, truth_of
    rng, robot = np.random.default_rng(5), Robot.panda()
    q = excitation(robot, Q_READY, MotionSettings())[0]
    t = np.arange(len(q)) * 1e-3
    bump = np.where(t < 0.75, np.sin(np.pi * t / 0.75) ** 2, 0.0)[:, None]
    for _ in range(3):
        tool, sag = random_tool(rng), np.array([0, 1, 0, -1, 0, 0, 0]) * rng.uniform(0.01, 0.02)
        A = rng.normal(scale=0.15, size=(7, 7))
        inertia_error = A @ A.T + 0.2 * np.eye(7)                 # kg m^2: the arm's own error and the rotors
        runs = []
        for Q, with_tool in ((q, False), (q + bump * sag, True)):
            dQ = np.gradient(Q, 1e-3, axis=0)
            Q, dQ, ddQ = Q[::5], dQ[::5], np.gradient(dQ, 1e-3, axis=0)[::5]
            tau = ddQ @ inertia_error + 0.002 * rng.normal(size=Q.shape)
            tau = tau + (robot.body_regressor(Q, dQ, ddQ) @ params_of_tool(tool) if with_tool else 0.0)
            runs.append((Q, dQ + 1e-4 * rng.normal(size=Q.shape), ddQ + 0.003 * rng.normal(size=Q.shape), tau))
        truth = truth_of(tool)
        fits = [fit_tool(robot, *runs[1], reference=runs[0], settings=ToolFitSettings(every=2, edge=10,
                                                                                     drive_share=share), dt=5e-3)
                for share in (0.0, ToolFitSettings().drive_share)]
        assert all(abs(fits[1].value[k] - truth[k]) <= 2 * fits[1].std[k] for k in ("mass", "com_x", "com_y", "com_z"))
        assert fits[1].std["mass"] <= 0.6 * fits[0].std["mass"], (fits[0].std["mass"], fits[1].std["mass"])


def test_drives_columns_from_q_undo_the_bias_that_noisy_dq_leaves_in_the_tool():
    """Joint 7 over 18.6 s at 1 kHz: the reference run's q at 1.1, 1.3, 1.5 Hz (0.6-1 rad/s^2 each), the tool run's
    1 % wider and 0.010-0.015 rad later (the tool changes how the joint tracks; their difference lags ddq by 45-56 deg,
    as joint 7's, correlated about 0.6); tau = b x + a (ddq_t - ddq_r),
    x the tool run's ddq (the tool's column), a = -0.02 kg m^2 (a rotor inertia), 0.2 mNm noise. The rotor-inertia
    column built as the log is (ddq the differences of Savitzky-Golay-smoothed dq with 1e-3 rad/s of noise) reads b
    as the errors-in-variables closed form says (population least squares of tau on x and the column with its
    measured noise variance: biased); built from q (3e-6 rad of noise, tool_id._from_q) it reads b within 20 % of
    that bias; and _from_q's ddq is the true ddq within 1 % rms (its second derivative passes 1.5 Hz at 0.991)."""
    from scipy.signal import savgol_filter
    from motion.tool_id import _from_q, partial_out
    rng, dt, b, a = np.random.default_rng(29), 1e-3, 0.004, -0.02
    t, f = np.arange(18600) * dt, 2 * np.pi * np.array([1.1, 1.3, 1.5])
    rows = np.arange(50, len(t) - 50, 10)
    for _ in range(4):
        amp, phase, lag = rng.uniform(0.6, 1.0, 3) / f ** 2, rng.uniform(0, 6.3, 3), rng.uniform(0.010, 0.015, 3)
        runs = {}
        for name, A, p in (("r", amp, phase), ("t", 1.01 * amp, phase - lag)):
            runs[name] = {"q": (A * np.sin(f * t[:, None] + p)).sum(1),
                          "dq": (A * f * np.cos(f * t[:, None] + p)).sum(1),
                          "ddq": -(A * f ** 2 * np.sin(f * t[:, None] + p)).sum(1)}
        s_true = runs["t"]["ddq"] - runs["r"]["ddq"]
        x = runs["t"]["ddq"]
        tau = (b * x + a * s_true + 2e-4 * rng.normal(size=len(t)))[rows, None]
        logged = sum(sign * np.gradient(savgol_filter(runs[k]["dq"] + 1e-3 * rng.normal(size=len(t)), 77, 3), dt)
                     for sign, k in ((1, "t"), (-1, "r")))
        from_q = {k: _from_q((runs[k]["q"] + 3e-6 * rng.normal(size=len(t)))[:, None], dt, 0.075)[1][:, 0]
                  for k in runs}
        assert np.sqrt(np.mean((from_q["r"] - runs["r"]["ddq"])[50:-50] ** 2)) <= 0.01 * runs["r"]["ddq"].std()
        Y = np.zeros((len(rows), 1, 10))
        Y[:, 0, 0] = x[rows]

        def b_of(column):
            Z = np.stack([np.ones(len(rows)), column[rows]], axis=1)[:, None, :]
            Yr, tr = partial_out(Y, tau, Z)
            return float(Yr[:, 0, 0] @ tr[:, 0] / (Yr[:, 0, 0] @ Yr[:, 0, 0]))
        xc, sc = x[rows] - x[rows].mean(), s_true[rows] - s_true[rows].mean()
        noise = np.var((logged - s_true)[rows])
        V = np.array([[xc @ xc, xc @ sc], [xc @ sc, sc @ sc + len(rows) * noise]])
        predicted = np.linalg.solve(V, [b * xc @ xc + a * xc @ sc, b * xc @ sc + a * sc @ sc])[0]
        noisy, clean = b_of(logged), b_of(from_q["t"] - from_q["r"])
        assert abs(predicted - b) > 0.01 * b, predicted
        assert abs(noisy - predicted) <= 0.15 * abs(predicted - b), (noisy, predicted, b)
        assert abs(clean - b) <= 0.2 * abs(predicted - b), (clean, predicted, b)


def test_the_noise_std_of_rows_with_ar1_correlated_noise_matches_the_closed_form_and_the_spread_over_draws():
    """Rows whose noise is AR(1) (rho 0.7, as filtered and subsampled noise is correlated from row to row) on
    regressors that are AR(1) too (phi 0.9, a slowly varying motion): least squares' variance is the white one times
    the scores' correlation summed over lags, (1 + r) / (1 - r), r = rho phi (independent columns), 2.1 times the
    white std here. The spread of the estimates over 150 seeded draws is that std within 3 sd of a sample sd of 150
    (+-18 %) per parameter and within 8 % on average; fit_tool's sandwich is the closed form of its Bartlett sum over
    30 rows, 1 + 2 sum_k (1 - k / 31) r^k (3.4 % short of the whole sum in std), within 8 % (what is left: the fitted
    residuals, orthogonal to the regressors, carry less low-frequency power than the noise)."""
    import motion.tool_id as ti
    from scipy.signal import lfilter
    from motion.inertia import FitSettings, fit_inertia, rigid_body
    rho, phi, T, n, sd = 0.7, 0.9, 2000, 2, np.array([0.01, 0.003])
    s = ti.ToolFitSettings(fit=FitSettings(prior_std=(1e3,) * 4, inertia_std=1e3, offsets=False))
    pi = rigid_body(1.0, [0.02, -0.01, 0.05], np.diag([4e-3, 5e-3, 3e-3]))
    ar = lambda x, a: lfilter([np.sqrt(1 - a ** 2)], [1.0, -a], x, axis=0)     # unit-variance AR(1) along rows
    rng = np.random.default_rng(71)
    est, sandwich, white, closed = [], [], [], []
    for _ in range(150):
        Y = ar(rng.normal(size=(T, n, 10)), phi)
        tau = Y @ pi + sd * ar(rng.normal(size=(T, n)), rho)
        _, info = fit_inertia(Y, tau, np.zeros(4), None, s.fit)
        G = np.einsum("j,tji,tjk->ik", 1.0 / sd ** 2, Y, Y)
        closed.append(np.sqrt(np.diag(np.linalg.inv(G)) * (1 + rho * phi) / (1 - rho * phi)))
        est.append(info.unconstrained)
        sandwich.append(np.sqrt(np.diag(ti._sandwich(Y, tau, info, s))))
        white.append(info.std)
    closed = np.sqrt(np.mean(np.square(closed), axis=0))
    r = rho * phi
    bartlett = np.sqrt((1 + 2 * sum((1 - k / 31) * r ** k for k in range(1, 31))) * (1 - r) / (1 + r))
    spread = np.std(est, axis=0, ddof=1) / closed
    by_sandwich = np.sqrt(np.mean(np.square(sandwich), axis=0)) / (bartlett * closed)
    by_white = np.sqrt(np.mean(np.square(white), axis=0)) / closed
    assert np.all(np.abs(spread - 1) < 0.18) and abs(spread.mean() - 1) < 0.08, spread
    assert np.all(np.abs(by_sandwich - 1) < 0.08), by_sandwich
    assert np.all(by_white < 0.6), by_white             # the correlation matters: 1 / 2.1 without it


def test_a_stale_row_gets_the_torque_the_robot_applied_there_not_its_neighbours_mean():
    """A log where tau_J measures the command of the cycle before plus a smooth torque (gravity, offset), with
    rows that repeat the last one (6 %, as the realistic plant's packets) and a controller that reacts to each
    repeated state by a step in its next command: the filled tau_J at those rows is the applied torque (the
    command before plus the smooth part: linear interpolation of a 2 Nm, 0.5 Hz sine over 2 ms misses it by at most
    2 (pi)^2 (1 ms)^2 / 2 = 9.9e-6 Nm), where
    interpolating tau_J across the row misses it by half the step."""
    from robot.identify import _stale_filled
    rng = np.random.default_rng(72)
    T, n = 4000, 7
    t = np.arange(T) * 1e-3
    smooth = 2.0 * np.sin(2 * np.pi * 0.5 * t)[:, None] + np.arange(n)
    stale, last = np.zeros(T, bool), -3
    for k in np.flatnonzero(rng.random(T) < 0.06):             # repeats 3 rows apart at least: each one's
        if k >= 2 and k - last >= 3:                           # neighbours measure no other step
            stale[k], last = True, k
    cmd = np.cos(2 * np.pi * 0.7 * t)[:, None] * np.ones(n)
    kick = rng.uniform(0.05, 0.2, size=(T, n))
    cmd[stale] += kick[stale]                                   # the step taken on the repeated state
    applied = np.concatenate([cmd[:1], cmd[:-1]]) + smooth      # what tau_J measures at each row
    q = np.cumsum(rng.normal(size=(T, n)), axis=0)
    raw = {"t": t, "q": q, "dq": q.copy(), "tau_J": applied.copy()}
    for k in np.flatnonzero(stale):                             # the last row again
        for key in ("q", "dq", "tau_J"):
            raw[key][k] = raw[key][k - 1]
    out, filled = _stale_filled(raw, cmd)
    assert filled == stale.sum() > 100
    assert np.abs(out["tau_J"] - applied).max() < 1e-5
    i = np.arange(T)
    across = np.stack([np.interp(i, i[~stale], raw["tau_J"][~stale, j]) for j in range(n)], axis=1)
    missed = np.abs(across - applied)[stale]
    assert np.all(np.abs(missed - kick[stale] / 2) < 1e-3)


def test_rows_near_a_missed_cycle_are_left_out_of_the_fit():
    """A run that missed cycles: its log's stamps skip them, and on a robot the torque around them is not the one the
    log's interpolation shows. Synthetic runs of the motion (a fresh random tool's closed-form torque, 2 mNm noise)
    with 40 gaps in the tool run whose neighbouring rows (2 ms each side) carry a 0.3 Nm error: near_gaps marks the
    rows within GAP_MARGIN of each gap and no other, and fit_logs, which leaves them out, meets the targets (mass 10 g,
    CoM 3 mm) where fitting every row misses them."""
    from diagnosis.logs import Log
    from motion.tool_id import truth_of
    from robot.identify import GAP_MARGIN, fit_logs, near_gaps
    rng, robot = np.random.default_rng(23), Robot.panda()
    q, dq, ddq = excitation(robot, Q_READY, MotionSettings())
    every = slice(None, None, 5)
    q, dq, ddq = q[every], dq[every], ddq[every]
    dt, T = 5e-3, len(q)
    t = dt * np.arange(T)
    tool = random_tool(rng)
    tau_tool = robot.body_regressor(q, dq, ddq) @ params_of_tool(tool)
    noise = lambda: 0.002 * rng.normal(size=q.shape)
    starts = np.sort(rng.choice(np.arange(50, T - 50, 60), size=40, replace=False))
    bad = np.zeros(T, dtype=bool)
    for i in starts:
        bad[i - 1:i + 2] = True                          # (2 rows of 5 ms each side of the missed stamp: within 5 ms)
    tau_run = tau_tool + noise() + 0.3 * bad[:, None] * rng.choice([-1.0, 1.0], size=(T, 7))
    log = lambda tau, gaps: Log(t=t, q=q, dq=dq, ddq=ddq, tau_J=None, tau_ext=tau,
                                info={"dt": dt, "gap_intervals": [(t[i] - 0.5 * dt, t[i] + 0.5 * dt) for i in gaps]})
    run, reference = log(tau_run, starts), log(noise(), [])
    near = near_gaps(run)
    want = np.zeros(T, dtype=bool)
    for i in starts:
        want |= np.abs(t - t[i]) < 0.5 * dt + GAP_MARGIN
    assert np.array_equal(near, want) and not near_gaps(reference).any()
    truth = truth_of(tool)
    within = lambda fit: abs(fit.value["mass"] - truth["mass"]) <= 0.01 and max(
        abs(fit.value[k] - truth[k]) for k in ("com_x", "com_y", "com_z")) <= 0.003
    assert within(fit_logs(robot, run, reference))
    assert not within(fit_logs(robot, log(tau_run, []), reference))


@pytest.mark.slow
def test_a_log_file_pairs_its_rows_by_control_cycle_as_the_run_does(tmp_path, capsys):
    """rme.py identify LOG --reference REF reads each file as the run it records: one row per control cycle, the
    robot's stamps skipping the cycles it missed. Synthetic runs of the motion: what both runs carry (a random hand
    already on the flange, a reflected rotor inertia 0.3 ddq and friction 0.3 tanh(dq / 0.02) Nm), and a fresh
    random tool's closed-form torque in one, whose stamps skip 40 runs of 1-10 cycles. Written as .npz and as a
    libfranka CSV (tau_ext_hat_filtered, its sign), both give the in-memory run's fit, meet the targets (mass
    10 g, CoM 3 mm) and report the skips and cycles missed; paired in robot time (load_log, resampled on the clock) the hand's torque at other states is
    left in the fit and they are missed."""
    from diagnosis.logs import load_log
    from motion.tool_id import truth_of
    from robot import identify
    rng, robot = np.random.default_rng(29), Robot.panda()
    q, dq, ddq = (x[::2] for x in excitation(robot, Q_READY, MotionSettings()))   # 500 Hz: half the file's rows
    T, n, dt = len(q), robot.n, 2e-3
    tool = random_tool(rng)
    hand = robot.body_regressor(q, dq, ddq) @ params_of_tool(random_tool(rng))
    arm = hand + 0.3 * ddq + 0.3 * np.tanh(dq / 0.02)
    noise = lambda: 0.002 * rng.normal(size=q.shape)
    skipped = np.zeros(T)
    skipped[rng.choice(np.arange(100, T - 100), size=40, replace=False)] = rng.integers(1, 11, size=40)
    runs = {"reference": dict(t=dt * np.arange(T), q=q, dq=dq, tau_ext=arm + noise()),
            "tool": dict(t=dt * (np.arange(T) + np.cumsum(skipped)), q=q, dq=dq,
                         tau_ext=arm + robot.body_regressor(q, dq, ddq) @ params_of_tool(tool) + noise())}
    for name, run in runs.items():
        np.savez(tmp_path / f"{name}.npz", **run, tau_ext_sign="paper")
        cols = ["time"] + [f"state.{k}[{i}]" for k in ("q", "dq", "tau_ext_hat_filtered") for i in range(n)]
        rows = np.column_stack([1e3 * run["t"], run["q"], run["dq"], -run["tau_ext"]])
        np.savetxt(tmp_path / f"{name}.csv", rows, delimiter=",", header=",".join(cols), comments="", fmt="%.17g")
    truth = truth_of(tool)
    within = lambda v: abs(v["mass"] - truth["mass"]) <= 0.01 and max(
        abs(v[k] - truth[k]) for k in ("com_x", "com_y", "com_z")) <= 0.003
    in_memory = identify.fit_logs(robot, identify.prepared(runs["tool"]), identify.prepared(runs["reference"]))
    assert within(in_memory.value)
    for ext in ("npz", "csv"):
        assert identify.log_main([str(tmp_path / f"tool.{ext}"), "--reference", str(tmp_path / f"reference.{ext}"),
                                  "--json"]) == 0
        rep = json.loads(capsys.readouterr().out)
        assert (rep["rows"]["tool"]["skips"], rep["rows"]["tool"]["cycles_missed"]) == (40, skipped.sum())
        assert rep["rows"]["reference"]["cycles_missed"] == 0
        values = {k: p["value"] for k, p in rep["fit"]["parameters"].items()}
        assert all(np.isclose(values[k], in_memory.value[k], rtol=0, atol=1e-6) for k in ("mass", "com_x", "com_y",
                                                                                            "com_z"))
        clock = identify.fit_logs(robot, load_log(tmp_path / f"tool.{ext}", identify.LOG),
                                  load_log(tmp_path / f"reference.{ext}", identify.LOG))
        assert not within(clock.value)
