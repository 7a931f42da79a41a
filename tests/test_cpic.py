"""Tests of cpic.py: the policies and the impedance law against closed forms, and CPIC in closed loop on the MuJoCo
plant (the QP solver's own tests are in test_qp.py)."""
import mujoco
import numpy as np
import pytest

from cpic import (CPIC, Attractor, CPICConfig, LimitCycle, damping_matrix, impedance_wrench, rotation_log,
                  solve_qp, storage)
from experiments.runner import ExactCompensation, PolicySwitch, Push
from experiments.runner import run as run_loop
from sim import Plant, PlantConfig, Q_READY

TAU_MAX = np.array([87.0] * 4 + [12.0] * 3)
THETA = np.array([0.9, 0.05, -0.03, 0.13])           # a Table 5 payload


# --- policies and the impedance law --------------------------------------------------------------------------
def rot(axis, angle):
    from scipy.spatial.transform import Rotation
    return Rotation.from_rotvec(np.asarray(axis, float) / np.linalg.norm(axis) * angle).as_matrix()


def test_rotation_log_matches_scipy_including_near_zero_and_pi():
    from scipy.spatial.transform import Rotation
    rng = np.random.default_rng(4)
    for angle in np.concatenate([rng.uniform(0, np.pi, 30), [0.0, 1e-9, 1e-7, np.pi - 1e-6, np.pi - 1e-3]]):
        axis = rng.normal(size=3)
        R = rot(axis, angle)
        ref = Rotation.from_matrix(R).as_rotvec()
        e = rotation_log(R)
        if angle > np.pi - 1e-3:                      # +-pi axis ambiguity: compare the rotations
            assert np.allclose(rot(e, np.linalg.norm(e)) if np.linalg.norm(e) else np.eye(3), R, atol=1e-9)
        else:
            assert np.allclose(e, ref, atol=1e-9)


def test_attractor_velocity_is_minus_gradient_of_its_lyapunov_function():
    rng = np.random.default_rng(5)
    pol = Attractor(np.array([0.4, 0.1, 0.5]), rot([1, 2, 3], 0.7))
    for _ in range(10):
        p, R = pol.p_star + 0.2 * rng.normal(size=3), rot(rng.normal(size=3), rng.uniform(0, 2.5)) @ pol.R_star
        f, _ = pol(p, R)
        h = 1e-6
        for i in range(3):                            # d V / d p_i = -f_v,i
            dp = h * np.eye(3)[i]
            dV = (sum(pol(p + dp, R)[1]) - sum(pol(p - dp, R)[1])) / (2 * h)
            assert abs(dV + f[i]) <= 1e-6
            dV = (sum(pol(p, rot(np.eye(3)[i], h) @ R)[1]) - sum(pol(p, rot(np.eye(3)[i], -h) @ R)[1])) / (2 * h)
            assert abs(dV + f[3 + i]) <= 1e-6        # world-frame angular velocity: dV = grad V . w dt
    f, V = pol(pol.p_star, pol.R_star)
    assert np.abs(f).max() == 0.0 and V == (0.0, 0.0)


def test_limit_cycle_lyapunov_function_decreases_and_cycle_is_invariant():
    rng = np.random.default_rng(6)
    pol = LimitCycle(np.array([0.3, 0.0, 0.5]), radius=0.1, period=4.0)
    for _ in range(20):
        p = pol.center + 0.15 * rng.normal(size=3)
        f, V = pol(p, np.eye(3))
        h = 1e-6
        grad = np.array([(pol(p + h * e, np.eye(3))[1][0] - pol(p - h * e, np.eye(3))[1][0]) / (2 * h)
                         for e in np.eye(3)])
        assert grad @ f[:3] <= 1e-9
    phi = 0.3
    p = pol.center + 0.1 * np.array([0.0, np.cos(phi), np.sin(phi)])
    f, V = pol(p, np.eye(3))
    assert V[0] == pytest.approx(0.0, abs=1e-15)
    assert np.allclose(f[:3], 2 * np.pi / 4.0 * 0.1 * np.array([0.0, -np.sin(phi), np.cos(phi)]), atol=1e-12)


def test_damping_matrix_has_first_eigenvector_along_f():
    rng = np.random.default_rng(7)
    lam = np.array([100.0, 150.0, 200.0])
    for f in list(rng.normal(size=(20, 3))) + [np.zeros(3), np.array([0.0, 0.0, 1e-15])]:
        D = damping_matrix(f, lam)
        assert np.allclose(D, D.T, atol=1e-12)
        assert np.allclose(np.linalg.eigvalsh(D), lam, atol=1e-9)
        if np.linalg.norm(f) > 1e-12:
            assert np.allclose(D @ f, lam[0] * f, atol=1e-9 * np.linalg.norm(f) * lam[0])


def test_impedance_wrench_matches_closed_form():
    rng = np.random.default_rng(8)
    for _ in range(10):
        G_x, xdot, f = rng.normal(size=(3, 6))
        lp, lr = (100.0, 150.0, 150.0), (2.0, 5.0, 5.0)
        F = impedance_wrench(G_x, xdot, f, lp, lr)
        ref = []
        for s, (l1, l2, _) in ((slice(0, 3), lp), (slice(3, 6), lr)):
            u = f[s] / np.linalg.norm(f[s])
            ref.append((l2 * np.eye(3) + (l1 - l2) * np.outer(u, u)) @ (xdot[s] - f[s]))
        assert np.allclose(F, G_x - np.concatenate(ref), atol=1e-12)
        # distinct eigenvalues go through the explicit Q Lambda Q^T
        F3 = impedance_wrench(G_x, xdot, f, (100.0, 150.0, 200.0), lr)
        assert np.allclose(F3[:3], G_x[:3] - damping_matrix(f[:3], (100.0, 150.0, 200.0)) @ (xdot - f)[:3])


# --- the controller ------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def robot():
    return Plant(PlantConfig.ideal()).robot


def test_unconstrained_qp_torque_equals_JT_Fc_plus_null_space_term(robot):
    """Appendix D: with no constraint active tau = J^T F_c; the 7-DoF arm adds N tau_0 in the null space of J."""
    rng = np.random.default_rng(9)
    p0, R0 = robot.ee_pose(Q_READY)
    config = CPICConfig(damping_pos=(100.0, 150.0, 150.0), damping_rot=(5.0, 5.0, 5.0))
    ctrl = CPIC(robot, Attractor(p0 + np.array([0.02, -0.01, 0.03]), rot([1, 0, 0], 0.01) @ R0), config)
    # a state near the attractor: the light nominal wrist (joint 7, ~0.005 kg m^2) turns a larger velocity error
    # into more than the E-CBF's k1 h ~ 110 rad/s^2 and would make a constraint active
    q, dq = Q_READY + 0.003 * rng.normal(size=7), 0.01 * rng.normal(size=7)
    tau, info = ctrl.step(q, dq)
    assert len(info.active) == 0 and not info.fallback
    J, G = robot.jacobian(q), robot.gravity(q)
    p, R = robot.ee_pose(q)
    from scipy.spatial.transform import Rotation
    pol = ctrl.policy
    f = np.concatenate([-pol.gain_pos * (p - pol.p_star),
                        -pol.gain_rot * Rotation.from_matrix(R @ pol.R_star.T).as_rotvec()])
    u = f[:3] / np.linalg.norm(f[:3])
    D = np.zeros((6, 6))
    D[:3, :3] = 150.0 * np.eye(3) - 50.0 * np.outer(u, u)
    D[3:, 3:] = 5.0 * np.eye(3)
    F_c = np.linalg.pinv(J).T @ G - D @ (J @ dq - f)                     # Eq. 7, G_x = J^+T G
    N = np.eye(7) - np.linalg.pinv(J) @ J
    assert np.allclose(info.F_c, F_c, atol=1e-9)
    assert np.allclose(info.tau_qp, J.T @ F_c + N @ (G - 1.0 * dq), atol=1e-8)
    assert np.allclose(np.linalg.pinv(J.T) @ tau, F_c, atol=1e-8)        # J^-T tau = F_c exactly
    x, qp_info = solve_qp(*ctrl.qp(q, dq))                                # the QP itself has that optimum
    assert len(qp_info.active) == 0 and np.allclose(x, info.tau_qp, atol=1e-8)
    # the compensation is added after the QP and does not change it (Appendix B)
    comp = -robot.payload_torque(q, THETA)
    tau_c, info_c = ctrl.step(q, dq, comp)
    assert np.allclose(info_c.tau_qp, info.tau_qp, atol=1e-9) and np.allclose(tau_c, tau + comp, atol=1e-9)


def run(preset_payload, ctrl_factory, seconds, push=None, comp=None, use_tau_ext=False, q0=Q_READY):
    """CPIC on the ideal plant through the runner; comp: a payload theta (4,) compensated exactly from t = 0."""
    plant = Plant(PlantConfig.ideal())
    if preset_payload is not None:
        plant.set_payload(*preset_payload)
    events = [] if push is None else [Push(0.02, push, 0.3)]
    ctrl = ctrl_factory(plant.robot)
    est = None if comp is None else ExactCompensation(plant.robot, comp)
    return run_loop(plant, ctrl, seconds, est, events, q0=q0, tau_ext_to_controller=use_tau_ext), ctrl, plant


def limit_inside_free_motion(robot, free, fraction=0.4):
    """Limits that the joint moving most in the barrier-free run `free` would pass: at `fraction` of its excursion."""
    excursion = free["q"] - free["q"][0]
    j = int(np.argmax(np.abs(excursion).max(axis=0)))
    e = excursion[np.argmax(np.abs(excursion[:, j])), j]
    q_min, q_max = robot.model.jnt_range[:, 0].copy(), robot.model.jnt_range[:, 1].copy()
    (q_max if e > 0 else q_min)[j] = free["q"][0, j] + fraction * e
    return j, e, CPICConfig(q_min=tuple(q_min), q_max=tuple(q_max))


WIDE = CPICConfig(q_min=(-9.0,) * 7, q_max=(9.0,) * 7)                    # no barrier in reach


def test_joint_limit_holds_while_attractor_drives_joint_past_it(robot):
    p0, R0 = robot.ee_pose(Q_READY)
    target = Attractor(p0 + np.array([0.0, 0.25, -0.1]), R0)
    free, _, _ = run(None, lambda r: CPIC(r, target, WIDE), 1.0)
    j, e, config = limit_inside_free_motion(robot, free)
    assert abs(e) > 0.2                                                   # the attractor moves the joint a lot
    log, ctrl, _ = run(None, lambda r: CPIC(r, target, config), 1.0)
    assert (log["q"] >= ctrl.q_min).all() and (log["q"] <= ctrl.q_max).all()
    assert np.abs(log["q"][:, j] - Q_READY[j]).max() > 0.3 * 0.4 * abs(e)  # ... and it did approach the limit
    assert np.isfinite(log["tau"]).all() and (np.abs(log["tau"]) <= TAU_MAX).all()


def test_joint_limit_holds_under_a_push_with_measured_tau_ext(robot):
    p0, R0 = robot.ee_pose(Q_READY)
    hold = Attractor(p0, R0)
    push = np.array([0.0, 0.0, -60.0])
    free, _, _ = run(None, lambda r: CPIC(r, hold, WIDE), 0.4, push=push)
    j, e, config = limit_inside_free_motion(robot, free)
    assert abs(e) > 0.1                                                   # the push alone would pass the limit
    log, ctrl, _ = run(None, lambda r: CPIC(r, hold, config), 0.4, push=push, use_tau_ext=True)
    assert (log["q"] >= ctrl.q_min).all() and (log["q"] <= ctrl.q_max).all()
    assert np.isfinite(log["tau"]).all() and (np.abs(log["tau"]) <= TAU_MAX).all() and not log["fallback"].any()


def test_torques_stay_within_limits_when_the_policy_asks_for_more(robot):
    p0, R0 = robot.ee_pose(Q_READY)
    far = Attractor(p0 + np.array([0.1, 0.2, -0.1]), rot([1, 1, 0], 0.5) @ R0)
    low = np.array([15.0] * 4 + [2.0] * 3)                               # lowered limits the demand exceeds
    log, ctrl, _ = run(None, lambda r: CPIC(r, far, CPICConfig(tau_max=tuple(low))), 0.3)
    assert np.isfinite(log["tau"]).all() and (np.abs(log["tau"]) <= low).all() and not log["fallback"].any()
    assert np.isclose(np.abs(log["tau"]) / low, 1.0).any()                 # a limit was reached, none passed


def plant_mass_matrix(plant, q):
    d, M = mujoco.MjData(plant.model), np.zeros((7, 7))
    d.qpos[:] = q
    mujoco.mj_forward(plant.model, d)
    mujoco.mj_fullM(plant.model, d, M)
    return M


def null_projector(robot, q):
    """N = I - J^+ J (7, 7) at q (numpy's pinv: independent of the controller's own formula)."""
    J = robot.jacobian(q)
    return np.eye(7) - np.linalg.pinv(J) @ J


def posture_potential(robot, q, q_rest, k_p=CPICConfig().null_stiffness):
    """P = k_p / 2 (q - q_rest)^T N_rest (q - q_rest) (T,) for q (T, 7), N_rest = N(q_rest)."""
    e = np.atleast_2d(q) - q_rest
    return 0.5 * k_p * np.einsum("ti,ij,tj->t", e, null_projector(robot, q_rest), e)


def free_torque(robot, pol, q, dq, q_rest):
    """Closed form of CPIC's torque with no constraint active (default config, D = 150 I and 5 I): J^T F_c +
    N (G - k_n dq) - k_p N_rest (q - q_rest), F_c = J^+T G - D (J dq - f) (Eq. 7), f the Attractor's closed form."""
    from scipy.spatial.transform import Rotation
    c, J, G = CPICConfig(), robot.jacobian(q), robot.gravity(q)
    p, R = robot.ee_pose(q)
    f = np.concatenate([-pol.gain_pos * (p - pol.p_star),
                        -pol.gain_rot * Rotation.from_matrix(R @ pol.R_star.T).as_rotvec()])
    F_c = np.linalg.pinv(J).T @ G - np.diag([150.0] * 3 + [5.0] * 3) @ (J @ dq - f)
    return (J.T @ F_c + null_projector(robot, q) @ (G - c.null_damping * dq)
            - c.null_stiffness * null_projector(robot, q_rest) @ (q - q_rest))


def storage_along(log, plant, robot, q_rest):
    """S = 1/2 dq^T M dq + lambda_1 V + P (T,) along a run, with the plant's true M (payload included)."""
    M = [plant_mass_matrix(plant, q) for q in log["q"]]
    kinetic = np.array([0.5 * dq @ Mk @ dq for dq, Mk in zip(log["dq"], M)])
    return kinetic + 150.0 * log["V"][:, 0] + 5.0 * log["V"][:, 1] + posture_potential(robot, log["q"], q_rest)


def test_storage_function_never_increases_with_exact_compensation(robot):
    """Prop. 4.1 with Delta F_mm = 0, F_ext = 0: S = 1/2 dq^T M dq + lambda_1 V + P is non-increasing (the plant's
    true M, payload included; joint-space kinetic energy = 1/2 xdot^T M_x xdot + null-space motion)."""
    p0, R0 = robot.ee_pose(Q_READY)
    pol = Attractor(p0 + np.array([0.03, -0.04, 0.05]), rot([0, 0, 1], 0.2) @ R0)
    log, ctrl, plant = run((THETA[0], THETA[1:]), lambda r: CPIC(r, pol), 0.5, comp=THETA)
    S = storage_along(log, plant, robot, Q_READY)                      # rest pose: the q of the first step
    assert np.diff(S).max() <= 1e-9                                    # tolerance: rounding [J]
    assert S[-1] < 0.1 * S[0]


def test_storage_counts_the_posture_spring_and_never_increases_away_from_its_rest_pose(robot):
    """The posture spring is the gradient of P = k_p/2 (q - q_rest)^T N_rest (q - q_rest), so with its rest pose
    0.3 rad away from the start (P = 0.23 J at t = 0) S = 1/2 dq^T M dq + lambda_1 V + P never increases, also
    late in the approach where a spring projected with N(q) instead of N_rest feeds energy in (S rose by 5e-8 J per
    step after 1.8 s), and settles where P = 0. cpic.storage and CPIC.posture_potential agree with the closed forms."""
    p0, R0 = robot.ee_pose(Q_READY)
    q_rest = Q_READY + np.array([0.3, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    pol = Attractor(p0 + np.array([0.03, -0.04, 0.05]), rot([0, 0, 1], 0.2) @ R0)
    config = CPICConfig(q_rest=tuple(q_rest))
    log, ctrl, plant = run((THETA[0], THETA[1:]), lambda r: CPIC(r, pol, config), 2.0, comp=THETA)
    P = posture_potential(robot, log["q"], q_rest)
    S = storage_along(log, plant, robot, q_rest)
    assert P[0] > 0.2 and np.diff(S).max() <= 1e-9                     # tolerance: rounding [J]
    assert S[-1] < 1e-5 * S[0] and P[-1] < 1e-8 and not log["fallback"].any()
    for k in (0, 1000, 1999):
        q, dq = log["q"][k], log["dq"][k]
        assert ctrl.posture_potential(q) == pytest.approx(P[k], rel=1e-9, abs=1e-15)
        assert storage(dq, plant_mass_matrix(plant, q), log["V"][k], ctrl.config, P[k]) == pytest.approx(S[k],
                                                                                                          rel=1e-12)


def test_posture_torque_is_minus_the_gradient_of_its_potential(robot):
    """With no constraint active the controller's torque minus J^T F_c + N (G - k_n dq) is -dP/dq (central
    differences of the closed-form P), at states away from the rest pose."""
    rng = np.random.default_rng(15)
    p0, R0 = robot.ee_pose(Q_READY)
    q_rest = Q_READY + 0.1 * rng.normal(size=7)
    pol = Attractor(p0, R0)
    ctrl = CPIC(robot, pol, CPICConfig(q_min=(-9.0,) * 7, q_max=(9.0,) * 7, q_rest=tuple(q_rest)))   # no barrier
    for _ in range(5):
        q, dq = Q_READY + 0.003 * rng.normal(size=7), 0.01 * rng.normal(size=7)   # near the attractor (see above)
        tau, info = ctrl.step(q, dq)
        assert len(info.active) == 0 and not info.fallback
        grad = np.array([(posture_potential(robot, q + 1e-6 * e, q_rest) - posture_potential(robot, q - 1e-6 * e,
                                                                                            q_rest))[0] / 2e-6
                         for e in np.eye(7)])
        np.testing.assert_allclose(info.tau_qp - free_torque(robot, pol, q, dq, q), -grad, atol=1e-8)
        np.testing.assert_allclose(info.tau_qp, free_torque(robot, pol, q, dq, q_rest), atol=1e-8)


def test_reset_and_a_policy_switch_retake_the_rest_pose_from_the_current_configuration(robot):
    """The posture spring's rest pose is the q of the first step after construction, reset() or a policy change
    (config.q_rest, when given, stays). At rest on its own target after a reset the command is gravity alone."""
    p0, R0 = robot.ee_pose(Q_READY)
    q_b = Q_READY + np.array([0.3, -0.2, 0.25, 0.1, -0.3, 0.2, 0.3])
    hold_b = Attractor(*robot.ee_pose(q_b))
    for restart in ("reset", "policy"):
        ctrl = CPIC(robot, Attractor(p0, R0) if restart == "policy" else hold_b)
        ctrl.step(Q_READY, np.zeros(7))                               # rest pose: Q_READY
        if restart == "reset":
            ctrl.reset()
        else:
            ctrl.policy = hold_b
        tau, info = ctrl.step(q_b, np.zeros(7))                       # rest pose: q_b
        np.testing.assert_allclose(tau, robot.gravity(q_b), atol=1e-9)
        assert np.array_equal(ctrl.q_rest, q_b) and not info.fallback
    fixed = CPIC(robot, hold_b, CPICConfig(q_min=(-9.0,) * 7, q_max=(9.0,) * 7, q_rest=tuple(Q_READY)))
    for _ in range(2):
        fixed.reset()
        tau, _ = fixed.step(q_b, np.zeros(7))
        np.testing.assert_allclose(tau, free_torque(robot, hold_b, q_b, np.zeros(7), Q_READY), atol=1e-8)
    assert np.array_equal(fixed.q_rest, Q_READY)


def test_policy_switch_in_closed_loop_restarts_the_posture_spring_at_the_switch(robot):
    """Pick-and-place style: move to one attractor, switch to a second at 0.4 s (runner PolicySwitch). From the switch
    on, the command is the closed form with the rest pose taken at the switch, not the first pose."""
    p0, R0 = robot.ee_pose(Q_READY)
    first = Attractor(p0 + np.array([0.0, 0.15, -0.05]), R0)
    config = CPICConfig(q_min=(-9.0,) * 7, q_max=(9.0,) * 7)                 # no barrier in reach
    before = run_loop(Plant(PlantConfig.ideal()), CPIC(robot, first, config), 0.4, q0=Q_READY)
    second = Attractor(before.p[-1] + np.array([0.02, -0.02, 0.0]), before.R[-1])   # a small next move
    log = run_loop(Plant(PlantConfig.ideal()), CPIC(robot, first, config), 0.6, events=[PolicySwitch(0.4, second)],
                   q0=Q_READY)
    k = log.at(0.4)
    assert np.abs(log["q"][k] - Q_READY).max() > 0.1                  # the arm did move before the switch
    for i in (k, k + 1, k + 100, len(log) - 1):
        np.testing.assert_allclose(log["tau"][i], free_torque(robot, second, log["q"][i], log["dq"][i], log["q"][k]),
                                   atol=1e-8)


def test_uncompensated_payload_sags_to_the_predicted_spurious_equilibrium(robot):
    """Appendix D: Delta F_mm = F_c at the spurious equilibrium: lambda_1 a_p (p* - p) + m g = 0, i.e. a sag of
    m g / (lambda_1 a_p) = 19.6 mm straight down; exact compensation returns the arm to the attractor."""
    p0, R0 = robot.ee_pose(Q_READY)
    hold = Attractor(p0, R0)
    none, _, _ = run((THETA[0], THETA[1:]), lambda r: CPIC(r, hold), 1.5)
    p_end = robot.ee_pose(none["q"][-1])[0]
    sag = THETA[0] * 9.81 / (CPICConfig().damping_pos[0] * hold.gain_pos)
    assert np.allclose(p_end - p0, [0.0, 0.0, -sag], atol=3e-4)
    assert np.abs(none["dq"][-1]).max() < 0.01                              # settled: an equilibrium
    exact, _, _ = run((THETA[0], THETA[1:]), lambda r: CPIC(r, hold), 1.5, comp=THETA)
    assert np.linalg.norm(robot.ee_pose(exact["q"][-1])[0] - p0) < 3e-4


def test_limit_cycle_is_tracked_in_closed_loop(robot):
    p0, R0 = robot.ee_pose(Q_READY)
    pol = LimitCycle(p0 - np.array([0.0, 0.1, 0.0]), R0, radius=0.1, period=4.0)
    log, _, _ = run(None, lambda r: CPIC(r, pol), 1.5)
    e = robot.ee_pose(log["q"])[0] - pol.center
    late = log["t"] > 0.5
    assert np.abs(np.hypot(e[late, 1], e[late, 2]) - 0.1).max() < 0.005 and np.abs(e[late, 0]).max() < 0.005
    phase = np.unwrap(np.arctan2(e[late, 2], e[late, 1]))
    rate = (phase[-1] - phase[0]) / (log["t"][late][-1] - log["t"][late][0])
    assert rate == pytest.approx(2 * np.pi / 4.0, rel=0.05)


def test_default_damping_leaves_no_alternating_mode_in_the_1khz_loop():
    """The torque is held over each 1 ms step, so damping acts explicitly: too much of it on the light nominal wrist
    gives an eigenvalue near or below -1 (chatter). Linearise plant + controller at the hold (central differences
    of one closed-loop step, the rest pose held fixed): asymptotically stable (the posture spring restores the
    null-space self-motion, which alone has the eigenvalue 1) and every alternating mode decays at least by half."""
    plant = Plant(PlantConfig.ideal())
    robot = plant.robot
    ctrl = CPIC(robot, Attractor(*robot.ee_pose(Q_READY)), CPICConfig(q_rest=tuple(Q_READY)))   # kept by reset()

    def next_state(x):
        ctrl.reset()
        s = plant.reset(x[:7], x[7:])
        s = plant.step(ctrl.step(s.q, s.dq)[0])
        return np.concatenate([s.q, s.dq])
    x0, h = np.concatenate([Q_READY, np.zeros(7)]), 1e-6
    z = np.linalg.eigvals(np.column_stack([(next_state(x0 + h * e) - next_state(x0 - h * e)) / (2 * h)
                                           for e in np.eye(14)]))
    assert np.abs(z).max() < 0.999 and z.real.min() > -0.5                 # measured: 0.9970 and -0.088


def test_realistic_plant_keeps_torques_finite_and_within_limits():
    rng = np.random.default_rng(11)
    plant = Plant(PlantConfig.realistic(rng), rng=rng)
    robot, first = plant.robot, plant.reset(Q_READY)
    plant.schedule_payload(0.1, *THETA[:1], THETA[1:])
    plant.push(np.array([20.0, 0.0, 0.0]), start=0.2, duration=0.1)
    p0, R0 = robot.ee_pose(Q_READY)
    log = run_loop(plant, CPIC(robot, Attractor(p0, R0)), 0.4, first=first)
    assert np.isfinite(log["tau"]).all() and (np.abs(log["tau"]) <= TAU_MAX).all() and not log["fallback"].any()
    assert np.linalg.norm(robot.ee_pose(log["q"][-1])[0] - p0) < 0.03
