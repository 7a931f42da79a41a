"""Tests of cpic.py's safety: bad input is refused at the entry, and whatever the state, the policy or the QP does,
the controller returns a finite torque within the Panda's limits (the safe fallback, clipped)."""
import numpy as np
import pytest

from cpic import CPIC, Attractor, CPICConfig, LimitCycle
from dynamics import Robot
from sim import Q_READY

TAU_MAX = np.array([87.0] * 4 + [12.0] * 3)


@pytest.fixture(scope="module")
def robot():
    return Robot.panda()


def test_step_rejects_bad_input(robot):
    p0, R0 = robot.ee_pose(Q_READY)
    ctrl = CPIC(robot, Attractor(p0, R0))
    for args, name in [((np.zeros(3), np.zeros(7)), "q"), ((Q_READY, np.full(7, np.nan)), "dq"),
                       ((Q_READY, np.zeros(7), np.zeros(6)), "compensation"),
                       ((Q_READY, np.zeros(7), None, np.full(7, np.inf)), "tau_ext")]:
        with pytest.raises(ValueError, match=f"^{name}:"):
            ctrl.step(*args)
    with pytest.raises(ValueError, match="tau_max"):
        CPIC(robot, Attractor(p0, R0), CPICConfig(tau_max=(87.0,) * 6))


def test_infeasible_qp_or_singular_jacobian_falls_back_to_safe_torque(robot):
    p0, R0 = robot.ee_pose(Q_READY)
    ctrl = CPIC(robot, Attractor(p0, R0))
    q, dq = Q_READY.copy(), np.zeros(7)
    q[1], dq[1] = ctrl.q_max[1] - 1e-3, 2.0       # joint 2 at its limit, 2 rad/s outwards: 87 Nm cannot stop it
    tau, info = ctrl.step(q, dq)
    assert info.fallback and info.status == "fallback: QP infeasible"
    ref = np.clip(robot.gravity(q) - np.array(CPICConfig().fallback_damping) * dq, -TAU_MAX, TAU_MAX)
    assert np.allclose(tau, ref) and np.isfinite(tau).all()
    tau, info = ctrl.step(np.zeros(7), np.zeros(7))   # arm straight up: J loses rank (shoulder-wrist aligned)
    assert info.fallback and np.allclose(tau, np.clip(robot.gravity(np.zeros(7)), -TAU_MAX, TAU_MAX))


def test_fallback_torque_is_clipped_to_the_wrist_limits(robot):
    """The safe torque G - K dq of a fallback (here: singular J, arm straight up) is clipped: 10 rad/s on joint 6
    asks 30 Nm of damping from a 12 Nm joint."""
    ctrl = CPIC(robot, Attractor(*robot.ee_pose(Q_READY)))
    dq = np.zeros(7)
    dq[5] = 10.0
    tau, info = ctrl.step(np.zeros(7), dq)
    unclipped = robot.gravity(np.zeros(7)) - np.array(CPICConfig().fallback_damping) * dq
    assert info.fallback and abs(unclipped[5]) > 12.0
    assert np.array_equal(tau, np.clip(unclipped, -TAU_MAX, TAU_MAX)) and tau[5] == -12.0


def test_policies_and_config_reject_bad_values_with_named_value_error(robot):
    p0, R0 = robot.ee_pose(Q_READY)
    nan3 = np.array([np.nan, 0.0, 0.0])
    bad = [(lambda: Attractor(nan3), "p_star"), (lambda: Attractor(p0[:2]), "p_star"),
           (lambda: Attractor(p0, 2.0 * R0), "R_star"), (lambda: Attractor(p0, -R0), "R_star"),
           (lambda: Attractor(p0, R0, gain_pos=-1.0), "gain_pos"),
           (lambda: Attractor(p0, R0, gain_rot=np.inf), "gain_rot"),
           (lambda: LimitCycle(nan3), "center"), (lambda: LimitCycle(p0, radius=0.0), "radius"),
           (lambda: LimitCycle(p0, period=np.inf), "period"), (lambda: LimitCycle(p0, gain_pos=np.nan), "gain_pos"),
           (lambda: CPICConfig(k1=np.nan), "k1"), (lambda: CPICConfig(k2=-1.0), "k2"),
           (lambda: CPICConfig(damping_pos=(150.0, np.nan, 150.0)), "damping_pos"),
           (lambda: CPICConfig(damping_rot=(5.0, 5.0)), "damping_rot"),
           (lambda: CPICConfig(null_weight=0.0), "null_weight"),
           (lambda: CPICConfig(null_stiffness=-1.0), "null_stiffness"),
           (lambda: CPICConfig(max_iterations=0), "max_iterations"),
           (lambda: CPICConfig(tau_max=(87.0, np.nan)), "tau_max"),
           (lambda: CPICConfig(q_rest=(np.nan,) * 7), "q_rest"),
           (lambda: CPICConfig(fallback_damping=(-1.0,) * 7), "fallback_damping"),
           (lambda: CPIC(robot, Attractor(p0, R0), CPICConfig(q_rest=(0.0,) * 6)), "config.q_rest"),
           (lambda: CPIC(robot, "hold"), "policy")]
    for make, name in bad:
        with pytest.raises(ValueError, match=f"^{name}: expected"):
            make()
    ctrl = CPIC(robot, lambda p, R: (np.zeros(5), (0.0, 0.0)))
    with pytest.raises(ValueError, match="^policy: expected"):
        ctrl.step(Q_READY, np.zeros(7))


def test_step_returns_a_finite_torque_within_limits_for_any_finite_state(robot):
    """Random finite states up to |dq| = 1e200, policies that return NaN, inf or 1e200, large compensations (up to
    what a 50 kg payload can need, config.payload_mass) and external torques: the command is always finite and within
    tau_max; broken numbers end in the fallback."""
    rng = np.random.default_rng(16)
    p0, R0 = robot.ee_pose(Q_READY)
    policies = [Attractor(p0, R0), Attractor(p0 + np.array([0.3, 0.3, -0.3]), R0),
                lambda p, R: (np.full(6, np.nan), (0.0, 0.0)), lambda p, R: (np.full(6, np.inf), (np.inf, 0.0)),
                lambda p, R: (np.full(6, 1e200), (1e200, 0.0))]
    lo, hi = robot.model.jnt_range[:, 0], robot.model.jnt_range[:, 1]
    statuses = []
    for i in range(300):
        k = i % len(policies)
        ctrl = CPIC(robot, policies[k], CPICConfig(payload_mass=50.0, payload_com=1.0))
        q = rng.uniform(lo - 0.1, hi + 0.1)
        dq = rng.choice([-1.0, 1.0], 7) * 10.0 ** rng.uniform(-3, 1 if i % 3 else 200, 7)
        comp = rng.normal(size=7) * 10.0 ** rng.uniform(-2, 3)
        tau_ext = rng.normal(size=7) * 10.0 ** rng.uniform(-2, 3) if i % 2 else None
        with np.errstate(all="ignore"):
            tau, info = ctrl.step(q, dq, comp, tau_ext)
        assert tau.shape == (7,) and np.isfinite(tau).all() and (np.abs(tau) <= TAU_MAX).all(), (i, info.status)
        assert (k >= 2) == info.status.startswith("fallback: policy")   # every broken policy, and only those
        statuses.append("QP solved" if len(info.active) and not info.fallback else info.status)
    assert {"QP solved", "fallback: QP infeasible"} <= set(statuses)       # each path is taken (31 and 49 times)
    assert sum(s.startswith("fallback: model terms") for s in statuses) > 20   # absurd dq overflows the model
    ctrl = CPIC(robot, Attractor(p0, R0))
    with np.errstate(all="ignore"):
        tau, info = ctrl.step(Q_READY, np.full(7, 1e200))
    assert info.fallback and np.array_equal(np.abs(tau), TAU_MAX)     # damping saturates every joint
