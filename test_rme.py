"""Tests of the foundation: dynamics.py against MuJoCo's own computations and finite differences, and the
sim.py plant's payload, push and sensor models. The pipeline (rme.py) is tested in tests/test_pipeline.py."""
import dataclasses

import mujoco
import numpy as np
import pytest

from changes import ChangeSettings
from dynamics import PANDA_XML, Robot, skew
from rme import RMESettings
from cpic import JointHold
from experiments.episodes import measure as record
from sim import N, Q_READY, Plant, PlantConfig
from tests.helpers import THREE_LINK

ROBOT = Robot.panda()
LO, HI = ROBOT.model.jnt_range[:, 0], ROBOT.model.jnt_range[:, 1]


def random_states(rng, count):
    q = rng.uniform(LO, HI, size=(count, N))
    return q, rng.normal(0, 1.5, size=(count, N)), rng.normal(0, 5.0, size=(count, N))


def mujoco_reference(model, q, dq, ddq, site):
    """J, M, bias, G and inverse dynamics straight from MuJoCo's pipeline on a fresh MjData."""
    d = mujoco.MjData(model)
    d.qpos[:], d.qvel[:] = q, dq
    mujoco.mj_forward(model, d)
    J = np.zeros((6, model.nv))
    mujoco.mj_jacSite(model, d, J[:3], J[3:], site)
    M = np.zeros((model.nv, model.nv))
    mujoco.mj_fullM(model, d, M)
    bias = d.qfrc_bias.copy()
    d.qacc[:] = ddq
    mujoco.mj_inverse(model, d)
    tau = d.qfrc_inverse.copy()
    d.qvel[:] = 0.0
    mujoco.mj_forward(model, d)
    return J, M, bias, d.qfrc_bias.copy(), tau


def test_model_terms_equal_mujoco_on_random_states():
    rng = np.random.default_rng(0)
    Q, DQ, DDQ = random_states(rng, 100)
    for q, dq, ddq in zip(Q, DQ, DDQ):
        J, M, b, G, tau = mujoco_reference(ROBOT.model, q, dq, ddq, ROBOT.site)
        np.testing.assert_allclose(ROBOT.jacobian(q), J, atol=1e-9)
        np.testing.assert_allclose(ROBOT.mass_matrix(q), M, atol=1e-9)
        np.testing.assert_allclose(ROBOT.bias(q, dq), b, atol=1e-9)
        np.testing.assert_allclose(ROBOT.gravity(q), G, atol=1e-9)
        np.testing.assert_allclose(ROBOT.inverse_dynamics(q, dq, ddq), tau, atol=1e-9)
        Jt, Mt, bt, Gt, pt, Rt = ROBOT.control_terms(q, dq)
        np.testing.assert_allclose(Jt, J, atol=1e-9)
        np.testing.assert_allclose(Mt, M, atol=1e-9)
        np.testing.assert_allclose(bt, b, atol=1e-9)
        np.testing.assert_allclose(Gt, G, atol=1e-9)
        d = mujoco.MjData(ROBOT.model)
        d.qpos[:] = q
        mujoco.mj_kinematics(ROBOT.model, d)
        np.testing.assert_allclose(pt, d.site_xpos[ROBOT.site], atol=1e-12)
        np.testing.assert_allclose(Rt, d.site_xmat[ROBOT.site].reshape(3, 3), atol=1e-12)
        for got, want in zip(ROBOT.terms(q, dq), (J, M, b)):
            np.testing.assert_allclose(got, want, atol=1e-9)


def test_jacobian_equals_central_differences_of_ee_pose():
    rng = np.random.default_rng(1)
    h = 1e-6
    for q in random_states(rng, 20)[0]:
        J = ROBOT.jacobian(q)
        for i in range(N):
            e = np.zeros(N)
            e[i] = h
            (p1, R1), (p0, R0) = ROBOT.ee_pose(q + e), ROBOT.ee_pose(q - e)
            np.testing.assert_allclose((p1 - p0) / (2 * h), J[:3, i], atol=1e-8)
            W = (R1 - R0) / (2 * h) @ ROBOT.ee_pose(q)[1].T          # dR/dq_i R^T = [w_i]x
            np.testing.assert_allclose(np.array([W[2, 1], W[0, 2], W[1, 0]]), J[3:, i], atol=1e-8)


def test_window_calls_equal_single_state_calls():
    rng = np.random.default_rng(2)
    Q, DQ, DDQ = random_states(rng, 30)
    theta = np.array([1.1, 0.05, 0.02, 0.13])
    p, R = ROBOT.ee_pose(Q)
    for name, batch, single in [
        ("ee_pose p", p, lambda t: ROBOT.ee_pose(Q[t])[0]),
        ("ee_pose R", R, lambda t: ROBOT.ee_pose(Q[t])[1]),
        ("jacobian", ROBOT.jacobian(Q), lambda t: ROBOT.jacobian(Q[t])),
        ("kinematics J", ROBOT.kinematics(Q)[2], lambda t: ROBOT.jacobian(Q[t])),
        ("kinematics R", ROBOT.kinematics(Q)[1], lambda t: ROBOT.ee_pose(Q[t])[1]),
        ("kinematics p", ROBOT.kinematics(Q)[0], lambda t: ROBOT.kinematics(Q[t])[0]),
        ("mass_matrix", ROBOT.mass_matrix(Q), lambda t: ROBOT.mass_matrix(Q[t])),
        ("bias", ROBOT.bias(Q, DQ), lambda t: ROBOT.bias(Q[t], DQ[t])),
        ("gravity", ROBOT.gravity(Q), lambda t: ROBOT.gravity(Q[t])),
        ("inverse_dynamics", ROBOT.inverse_dynamics(Q, DQ, DDQ), lambda t: ROBOT.inverse_dynamics(Q[t], DQ[t], DDQ[t])),
        ("payload_regressor", ROBOT.payload_regressor(Q), lambda t: ROBOT.payload_regressor(Q[t])),
        ("payload_torque", ROBOT.payload_torque(Q, theta), lambda t: ROBOT.payload_torque(Q[t], theta)),
        ("body_regressor", ROBOT.body_regressor(Q, DQ, DDQ), lambda t: ROBOT.body_regressor(Q[t], DQ[t], DDQ[t])),
    ]:
        np.testing.assert_allclose(batch, np.stack([single(t) for t in range(len(Q))]), atol=1e-12, err_msg=name)


def test_payload_torque_equals_plant_torque_difference_at_static_poses():
    """Ideal plant held still at a pose: tau_ext with the payload minus without it is the paper's tau_mm."""
    rng = np.random.default_rng(3)
    plant = Plant(PlantConfig.ideal())
    for q in random_states(rng, 20)[0]:
        theta = np.array([rng.uniform(0.1, 2.0), *rng.uniform(-0.15, 0.15, 3)])
        plant.set_payload(0.0)
        without = plant.reset(q).tau_ext
        plant.set_payload(theta[0], theta[1:])
        with_payload = plant.reset(q)
        np.testing.assert_allclose(with_payload.tau_ext - without, ROBOT.payload_torque(q, theta), atol=1e-8)
        phi = np.concatenate([[theta[0]], theta[0] * theta[1:]])
        np.testing.assert_allclose(ROBOT.payload_regressor(q) @ phi, ROBOT.payload_torque(q, theta), atol=1e-12)


def test_payload_torque_sign_is_the_weight_pulling_the_arm_down():
    """Paper sign: a hanging mass at the ready pose pulls the flange down, so tau_mm = -(extra holding torque)."""
    plant = Plant(PlantConfig.ideal())
    held = plant.reset(Q_READY).tau_J
    plant.set_payload(1.0)
    extra = plant.reset(Q_READY).tau_J - held            # what the drives must add (libfranka's sign)
    np.testing.assert_allclose(ROBOT.payload_torque(Q_READY, [1.0, 0, 0, 0]), -extra, atol=1e-10)
    J = ROBOT.jacobian(Q_READY)
    F = np.linalg.lstsq(J.T, ROBOT.payload_torque(Q_READY, [1.0, 0, 0, 0]), rcond=None)[0]
    np.testing.assert_allclose(F[:3], [0, 0, -9.81], atol=1e-9)    # the weight, pointing down


def test_body_regressor_equals_plant_torque_difference_under_motion():
    rng = np.random.default_rng(4)
    plant = Plant(PlantConfig.ideal())
    m, d = plant.model, plant.data
    Q, DQ, DDQ = random_states(rng, 25)
    for q, dq, ddq in zip(Q, DQ, DDQ):
        mass, c = rng.uniform(0.2, 2.0), rng.uniform(-0.1, 0.1, 3)
        A = rng.normal(size=(3, 3))
        Ic = A @ A.T * 0.005 + 1e-3 * np.eye(3)                       # about the CoM, ee frame
        taus, g = [], m.opt.gravity.copy()
        for weight in (g, np.zeros(3)):                               # with gravity, then in free space
            m.opt.gravity[:] = weight
            for payload in ((0.0, np.zeros(3), None), (mass, c, Ic)):
                plant.set_payload(*payload)
                d.qpos[:], d.qvel[:], d.qacc[:] = q, dq, ddq
                mujoco.mj_inverse(m, d)
                taus.append(d.qfrc_inverse.copy())
        m.opt.gravity[:] = g
        Io = Ic + mass * (c @ c * np.eye(3) - np.outer(c, c))         # parallel axis to the ee origin
        pi = np.array([mass, *(mass * c), Io[0, 0], Io[0, 1], Io[1, 1], Io[0, 2], Io[1, 2], Io[2, 2]])
        # same sign as payload_torque: the torque the payload applies to the arm = -(extra drive torque)
        np.testing.assert_allclose(ROBOT.body_regressor(q, dq, ddq) @ pi, -(taus[1] - taus[0]), atol=1e-9)
        np.testing.assert_allclose(ROBOT.body_regressor(q, dq, ddq, gravity=False) @ pi, -(taus[3] - taus[2]),
                                   atol=1e-9)
    q = Q[0]
    np.testing.assert_allclose(ROBOT.body_regressor(q, np.zeros(N), np.zeros(N))[:, :4],
                               ROBOT.payload_regressor(q), atol=1e-12)


def test_from_xml_works_on_a_three_joint_planar_arm(tmp_path):
    path = tmp_path / "arm3.xml"
    path.write_text(THREE_LINK)
    arm = Robot.from_xml(path, ee="tip")
    assert arm.n == 3
    q = np.array([0.3, -0.5, 0.8])
    # closed form: joints about y, links along x; angles a1 = -q1 (y-rotation of x towards -z), etc.
    a = np.cumsum(-q)
    L, com, mass = [0.4, 0.3, 0.2], [0.2, 0.15, 0.1], [2.0, 1.0, 0.5]
    x_joint = np.concatenate([[0], np.cumsum(np.array(L[:2]) * np.cos(a[:2]))])
    z_joint = np.concatenate([[0], np.cumsum(np.array(L[:2]) * np.sin(a[:2]))])
    p_tip = np.array([x_joint[2] + L[2] * np.cos(a[2]), 0.0, z_joint[2] + L[2] * np.sin(a[2])])
    np.testing.assert_allclose(arm.ee_pose(q)[0], p_tip, atol=1e-12)
    # the weight m g at lever dx about +y gives torque +m g dx; the holding torque G_i is its opposite
    x_com = x_joint + np.array(com) * np.cos(a)
    G = [-sum(mass[k] * 9.81 * (x_com[k] - x_joint[i]) for k in range(i, 3)) for i in range(3)]
    np.testing.assert_allclose(arm.gravity(q), G, atol=1e-10)
    # a 1 kg point payload at the tip: tau_mm = +m g (x_tip - x_joint_i), the torque its weight applies
    np.testing.assert_allclose(arm.payload_torque(q, [1.0, 0, 0, 0]), [9.81 * (p_tip[0] - x_joint[i]) for i in range(3)],
                               atol=1e-10)
    J, M, b, _, tau = mujoco_reference(arm.model, q, np.ones(3), np.ones(3), arm.site)
    np.testing.assert_allclose(arm.jacobian(np.stack([q, q]))[1], J, atol=1e-12)
    np.testing.assert_allclose(arm.inverse_dynamics(q, np.ones(3), np.ones(3)), tau, atol=1e-10)


@pytest.mark.parametrize("call, match", [
    (lambda: ROBOT.jacobian(np.zeros(6)), r"q: expected shape \(7,\) or \(T, 7\), found \(6,\)"),
    (lambda: ROBOT.mass_matrix(np.zeros((5, 3))), r"q: expected shape"),
    (lambda: ROBOT.bias(np.zeros(7), np.full(7, np.nan)), r"dq: expected finite values, found nan"),
    (lambda: ROBOT.gravity([0, 0, np.inf, 0, 0, 0, 0]), r"q: expected finite values, found inf"),
    (lambda: ROBOT.payload_torque(np.zeros(7), [1.0, 0.0]), r"theta: expected shape \(4,\)"),
    (lambda: ROBOT.inverse_dynamics(np.zeros((3, 7)), np.zeros((4, 7)), np.zeros((3, 7))), r"same number of rows"),
    (lambda: ROBOT.payload_regressor("abc"), r"q: expected a real array"),
    (lambda: Robot.from_xml("/nonexistent/arm.xml"), r"path: expected an MJCF file, found no file"),
    (lambda: Robot(ROBOT.model, ee="tool0"), r"ee: no site named 'tool0'"),
    (lambda: Plant(PlantConfig.ideal()).step(np.zeros(3)), r"tau: expected shape \(7,\)"),
    (lambda: Plant(PlantConfig.ideal()).set_payload(-1.0), r"m: expected a mass in \[0, 100\] kg, found -1.0"),
    (lambda: Plant(PlantConfig.realistic(np.random.default_rng(0))), r"rng: a np.random.Generator is needed"),
    (lambda: Plant(PlantConfig.ideal()).schedule_payload(np.nan, 1.0), r"t: expected a number in \[0, 1e6\] s"),
    (lambda: Plant(PlantConfig.ideal()).schedule_payload(0.1, 1.0, r=0.1), r"r: expected .*\[-2, 2\] m .*"),
    (lambda: Plant(PlantConfig.ideal()).set_payload("heavy"), r"m: expected a mass in \[0, 100\] kg, found 'heavy'"),
    (lambda: Plant(PlantConfig.ideal()).push([0, 10.0, 0], offset=(1, 2)), r"offset: expected numbers in \[-2, 2\] m"),
    (lambda: PlantConfig(mass_scale=(1.0,) * 6), r"config.mass_scale: expected .*, shape \(7,\), found shape \(6,\)"),
    (lambda: RMESettings(rate=0.0), r"settings.rate: expected a number in \[10, 1e4\] Hz"),
    (lambda: RMESettings(window=10), r"settings.window: expected an integer in 20..500 samples"),
    (lambda: RMESettings(changes=None), r"settings.changes: expected an instance of ChangeSettings"),
    (lambda: RMESettings(detector=0.7), r"settings.detector: expected an instance of DetectorSettings"),
    (lambda: ChangeSettings(friction=(1.0,) * 7 + (np.nan,)), r"changes.friction: .* found nan at index 7"),
    (lambda: ChangeSettings(confidence=0.3), r"changes.confidence: expected a number in \(0.5, 1\)"),
    (lambda: ChangeSettings(push_force=-1.0), r"changes.push_force: expected a number in \(0, 1e4\] N"),
])
def test_bad_input_raises_value_error_naming_the_argument(call, match):
    with pytest.raises(ValueError, match=match):
        call()


def test_plant_clips_torques_and_refuses_nan():
    plant = Plant(PlantConfig.ideal())
    plant.reset(Q_READY)
    s = plant.step(np.array([200.0, -200.0, 0.0, 0.0, 50.0, -50.0, 1.0]))
    np.testing.assert_array_equal(s.tau_J, [87.0, -87.0, 0.0, 0.0, 12.0, -12.0, 1.0])
    assert np.all(np.isfinite(s.q)) and np.all(np.isfinite(s.tau_ext))
    with pytest.raises(ValueError, match=r"tau: expected finite torques"):
        plant.step(np.array([0.0] * 6 + [np.nan]))


def test_scheduled_payload_appears_in_tau_ext_at_its_time_and_leaves_on_removal():
    plant = Plant(PlantConfig.ideal())
    theta = np.array([0.7, 0.06, 0.0, 0.13])
    plant.schedule_payload(0.1, theta[0], theta[1:])
    plant.schedule_payload(0.3, 0.0)
    first = plant.reset(Q_READY)
    log = record(plant, JointHold(plant.robot, Q_READY), 0.4, first)
    on = np.flatnonzero(log["theta"][:, 0] > 0)
    assert abs(log["t"][on[0]] - 0.1) < 1.5e-3 and abs(log["t"][on[-1]] - 0.3) < 1.5e-3
    # exact observer, ideal plant: tau_ext is the payload's rigid-body torque under the arm's motion.
    # Sample k reports ddq under the torque held since the last command, tau_J[k]; the step to k+1 integrates
    # (semi-implicit Euler, no damping) the acceleration under the next command tau_J[k+1], so
    # ddq_k = (dq_k+1 - dq_k) / dt - M_plant^-1 (tau_J[k+1] - tau_J[k]).
    m, c = theta[0], theta[1:]
    Io = m * (c @ c * np.eye(3) - np.outer(c, c))                          # point mass about the ee origin
    pi = np.r_[m, m * c, Io[0, 0], Io[0, 1], Io[1, 1], Io[0, 2], Io[1, 2], Io[2, 2]]
    d = mujoco.MjData(plant.model)
    plant.set_payload(theta[0], theta[1:])
    for k in on[5:-1:40]:
        d.qpos[:] = log["q"][k]
        mujoco.mj_forward(plant.model, d)
        M_plant = np.zeros((N, N))
        mujoco.mj_fullM(plant.model, d, M_plant)
        ddq = (log["dq"][k + 1] - log["dq"][k]) / plant.dt - np.linalg.solve(M_plant, log["tau_J"][k + 1] - log["tau_J"][k])
        np.testing.assert_allclose(log["tau_ext"][k], ROBOT.body_regressor(log["q"][k], log["dq"][k], ddq) @ pi,
                                   atol=1e-7)
    np.testing.assert_allclose(log["tau_ext"][on[-1] + 2:], 0.0, atol=1e-9)   # removed: nothing left


def test_push_shows_up_as_its_jacobian_torque():
    plant = Plant(PlantConfig.ideal())
    force = np.array([0.0, 15.0, 0.0])
    plant.push(force, body="link7", start=0.05, duration=0.1)
    first = plant.reset(Q_READY)
    log = record(plant, JointHold(plant.robot, Q_READY), 0.1, first)
    k = 80                                                                 # t = 0.081 s, during the push
    d = mujoco.MjData(plant.model)
    d.qpos[:] = log["q"][k]
    mujoco.mj_kinematics(plant.model, d)
    mujoco.mj_comPos(plant.model, d)
    Jp = np.zeros((3, N))
    body = mujoco.mj_name2id(plant.model, mujoco.mjtObj.mjOBJ_BODY, "link7")
    mujoco.mj_jac(plant.model, d, Jp, None, d.xpos[body], body)
    np.testing.assert_allclose(log["tau_ext"][k], Jp.T @ force, atol=1e-8)


def test_momentum_observer_tracks_tau_ext_with_first_order_lag():
    config = dataclasses.replace(PlantConfig.ideal(), observer="momentum", observer_gain=50.0)
    plant = Plant(config)
    exact = Plant(PlantConfig.ideal())
    theta = (0.9, 0.05, -0.03, 0.13)
    for p in (plant, exact):
        p.schedule_payload(0.05, theta[0], theta[1:])
    logs = [record(p, JointHold(p.robot, Q_READY), 0.4, p.reset(Q_READY)) for p in (plant, exact)]
    r, true = logs[0]["tau_ext"], logs[1]["tau_ext"]
    np.testing.assert_allclose(logs[0]["q"], logs[1]["q"], atol=1e-12)   # same motion
    # discrete first-order filter of the exact tau_ext with the observer's gain (an independent recursion)
    filt, a = np.zeros(N), 50.0 * plant.dt
    ref = np.empty_like(true)
    for k in range(len(true)):
        ref[k] = filt = filt + a * (true[k] - filt) if k else filt
    assert np.abs(r[100:] - ref[100:]).max() < 0.05 * np.abs(true).max()
    assert np.abs(r[-1] - true[-1]).max() < 0.02


def test_realistic_sensor_quantises_repeats_and_biases_reproducibly():
    def run(seed):
        rng = np.random.default_rng(seed)
        plant = Plant(PlantConfig.realistic(rng), rng=rng)
        return record(plant, JointHold(plant.robot, Q_READY), 1.0, plant.reset(Q_READY))
    a, b, c = run(5), run(5), run(6)
    np.testing.assert_array_equal(a["tau_J"], b["tau_J"])
    assert not np.array_equal(a["tau_J"], c["tau_J"])
    steps = np.array([0.036] * 4 + [0.006] * 3)
    np.testing.assert_allclose(np.round(a["tau_J"] / steps) * steps, a["tau_J"], atol=1e-9)
    stale = np.mean(np.all(a["tau_J"][1:] == a["tau_J"][:-1], axis=1) & np.all(a["q"][1:] == a["q"][:-1], axis=1))
    assert 0.03 < stale < 0.09                                              # about 6 % stale repeats
    rest = a["tau_ext"][200:]
    assert np.abs(rest.mean(axis=0)[:4]).max() > 0.05                       # a bias, not zero-mean noise
    assert np.abs(rest.mean(axis=0)).max() < 3.0


def test_plant_differs_from_nominal_in_realistic_preset_only():
    rng = np.random.default_rng(7)
    config = PlantConfig.realistic(rng)
    plant = Plant(dataclasses.replace(config, tau_noise=(0.0,) * N, tau_step=(0.0,) * N, q_noise=0.0,
                                      dq_noise=0.0, stale_prob=0.0, bias_amp=(0.0,) * N,
                                      torque_offset=(0.0,) * N, observer="exact"))
    gap = np.abs(plant.reset(Q_READY).tau_ext)
    assert 0.05 < gap.max() < 3.0                                           # link errors: tenths of a Nm to ~1 Nm
    assert np.abs(Plant(PlantConfig.ideal()).reset(Q_READY).tau_ext).max() < 1e-10
    assert np.all(skew([1.0, 2.0, 3.0]) @ [4.0, 5.0, 6.0] == np.cross([1.0, 2.0, 3.0], [4.0, 5.0, 6.0]))


def test_window_kinematics_respect_a_joint_reference_angle(tmp_path):
    path = tmp_path / "arm3_ref.xml"
    path.write_text(THREE_LINK.replace('<joint name="j2" type="hinge" axis="0 1 0"/>',
                                       '<joint name="j2" type="hinge" axis="0 1 0" ref="0.5"/>'))
    arm = Robot.from_xml(path, ee="tip")
    Q = np.random.default_rng(12).uniform(-1, 1, (5, 3))
    np.testing.assert_allclose(arm.ee_pose(Q)[0], np.stack([arm.ee_pose(q)[0] for q in Q]), atol=1e-12)
    np.testing.assert_allclose(arm.payload_regressor(Q), np.stack([arm.payload_regressor(q) for q in Q]), atol=1e-12)


def _panda_with_actuators(tmp_path, make):
    """panda.xml with each motor line replaced by make(joint_number) (an actuator element as text)."""
    text = open(PANDA_XML).read()
    for i in range(1, 8):
        start = text.index(f'<motor name="tau{i}"')
        text = text[:start] + make(i) + text[text.index("/>", start) + 2:]
    path = tmp_path / "panda_variant.xml"
    path.write_text(text)
    return Robot.from_xml(str(path), ee="ee")


def test_torque_limits_come_from_force_limits_not_from_a_servo_set_point_range(tmp_path):
    np.testing.assert_array_equal(Robot.panda().torque_limits(), [87.0] * 4 + [12.0] * 3)   # motors: ctrlrange
    servo = _panda_with_actuators(tmp_path, lambda i: f'<position name="p{i}" joint="joint{i}" kp="300" '
                                                      f'ctrlrange="-0.07 -0.01"/>')
    assert np.all(np.isinf(servo.torque_limits()))            # a set point range in rad is no torque limit
    limited = _panda_with_actuators(tmp_path, lambda i: f'<position name="p{i}" joint="joint{i}" kp="300" '
                                                        f'ctrlrange="-3 3" forcelimited="true" forcerange="-{i} {i}"/>')
    np.testing.assert_array_equal(limited.torque_limits(), np.arange(1.0, 8.0))
    geared = _panda_with_actuators(tmp_path, lambda i: f'<motor name="m{i}" joint="joint{i}" gear="10" ctrlrange="-2 2"/>')
    np.testing.assert_array_equal(geared.torque_limits(), np.full(7, 20.0))


def test_rme_compensation_is_not_capped_by_a_servo_set_point_range(tmp_path):
    from rme import RME
    servo = _panda_with_actuators(tmp_path, lambda i: f'<position name="p{i}" joint="joint{i}" kp="300" '
                                                      f'ctrlrange="-3.14 3.14"/>')
    est = RME(robot=servo, weights=None, settings=RMESettings(asynchronous=False))
    theta = np.array([3.0, 0.1, 0.0, 0.1])
    est.theta, est._phi = theta, np.r_[theta[0], theta[0] * theta[1:]]
    comp = est.update(Q_READY, np.zeros(7), np.zeros(7))
    np.testing.assert_allclose(comp, -servo.payload_torque(Q_READY, theta), atol=1e-9)
    assert np.abs(comp).max() > 3.14
