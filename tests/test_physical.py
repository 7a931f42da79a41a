"""Physically consistent fits in the diagnosis tool: bounded and rigid-body fits against reference solvers, findings
where the data ask for non-physical values, Coulomb friction of any width, an exact tilt, and saved models."""
import copy
import functools

import numpy as np
import pytest
from scipy.optimize import lsq_linear, minimize

from diagnosis import diagnose as D
from diagnosis.effect_model import Model
from diagnosis.effects import EffectConfig, Signals, custom
from diagnosis.excite import GAZ_FC, ExciteConfig, multisine
from diagnosis.heldout import BlockGrams, blocks_of
from diagnosis.logs import Log, prepare
from diagnosis.physical import Segment, pseudo_inertia, solve_physical
from dynamics import Q_READY, Robot
from experiments.episodes import sensing

ROBOT = Robot.panda()
FAST = ExciteConfig(speed=1.2, freq_scale=1.6)              # accelerations for inertial effects


def plant(armature=None, tilt=None) -> Robot:
    """The nominal arm as MuJoCo simulates it, with rotor inertia (7,) or gravity Ry(ay) Rx(ax) g (as sim.Plant)."""
    m = copy.deepcopy(ROBOT.model)
    if armature is not None:
        m.dof_armature[:] = armature
    if tilt is not None:
        c, s = np.cos, np.sin
        ax, ay = tilt
        Rx = np.array([[1, 0, 0], [0, c(ax), -s(ax)], [0, s(ax), c(ax)]])
        Ry = np.array([[c(ay), 0, s(ay)], [0, 1, 0], [-s(ay), 0, c(ay)]])
        m.opt.gravity[:] = Ry @ Rx @ ROBOT.g
    return Robot(m)


def synthetic(arm: Robot, extra=None, seconds: float = 5.0, excite=ExciteConfig(), seed: int = 0) -> Log:
    """A prepared log of the arm `arm` (MuJoCo's inverse dynamics) on a multi-sine, plus extra(q, dq, ddq) (T, 7),
    with the Panda's torque noise and quantisation (experiments.episodes.sensing), filtered like a recorded log."""
    rng = np.random.default_rng(seed)
    t = 1e-3 * np.arange(int(seconds * 1000))
    q, dq, ddq = multisine(t, excite, rng)
    tau = arm.inverse_dynamics(q, dq, ddq) + (0 if extra is None else extra(q, dq, ddq))
    sens = sensing()
    tau = tau + np.asarray(sens["tau_noise"]) * rng.normal(size=tau.shape)
    step = np.asarray(sens["tau_step"])
    return prepare({"t": t, "q": q, "dq": dq, "tau_J": np.round(tau / step) * step})


# --- the constrained solve against reference solvers -------------------------------------------------------------
def test_bounded_fit_matches_scipy_lsq_linear_on_the_stacked_rows():
    rng = np.random.default_rng(4)
    A = rng.normal(size=(400, 7)) @ np.diag([1, 3, 0.1, 1, 1, 10, 0.5]) + 0.5 * rng.normal(size=(400, 1))
    p_true = np.array([-0.4, 0.2, -3.0, 0.5, 0.3, -0.05, 1.0])
    y = A @ p_true + 0.1 * rng.normal(size=400)
    lo = np.array([0, 0, 0, -np.inf, -np.inf, 0, -np.inf])
    hi = np.array([np.inf, np.inf, np.inf, 0.4, np.inf, np.inf, np.inf])
    segs = [Segment("a", 0, 3, lo[:3], hi[:3], labels=("a1", "a2", "a3")), Segment("b", 3, 7, lo[3:], hi[3:])]
    c, info = solve_physical(A.T @ A, A.T @ y, segs)
    ref = lsq_linear(A, y, bounds=(lo, hi), tol=1e-12).x
    assert info["constrained"] and "a" in info["violations"] and "b" in info["violations"]
    np.testing.assert_allclose(c, ref, atol=1e-8)
    assert np.all(c >= lo) and np.all(c <= hi)


def test_held_out_folds_are_fitted_under_the_bounds():
    """A custom effect with lower bounds 0: each fold of BlockGrams.heldout equals lsq_linear on its training rows."""
    k = np.array([0.3, -0.2, 0.3, -0.1, 0.2, -0.05, 0.1])                     # Nm s/rad, negative on J2, J4, J6
    log = synthetic(ROBOT, lambda q, dq, ddq: k * dq + 0.05 * np.sin(3 * q), seconds=4.0)
    eff = custom("drag", "a torque along the speed", lambda s: s.dq, ["k"], ["Nm s/rad"], per_joint_params=True,
                 lower=[0.0])
    s = Signals(log, ROBOT)
    y = log.tau_J - s.inverse_dynamics
    block = blocks_of(log.t, 0.5)
    grams = BlockGrams(y, block, ROBOT.g)
    grams.add("drag", eff.block(s), eff)
    _, params, infos = grams.heldout([["drag"], ["drag"]])
    for f in (0, 1):
        rows = block % 2 == f
        A = eff.block(s)[rows].reshape(-1, 7)
        ref = lsq_linear(A, y[rows].reshape(-1), bounds=(0, np.inf), tol=1e-12).x
        np.testing.assert_allclose(params[f], ref, atol=1e-8)
        assert infos[f]["constrained"] and np.all(ref[[1, 3, 5]] < 1e-12) and np.all(ref[[0, 2, 4, 6]] > 0.05)


def body_of_factor(J):
    """(m, h, I about the origin) (10,) of a pseudo-inertia J (4, 4) = [[tr(I)/2 E - I, h], [h^T, m]] (Wensing et al.
    2017), written out here independently of physical.body_params."""
    S = J[:3, :3]
    I = np.trace(S) * np.eye(3) - S
    return np.array([J[3, 3], J[0, 3], J[1, 3], J[2, 3], I[0, 0], I[0, 1], I[1, 1], I[0, 2], I[1, 2], I[2, 2]])


def test_rigid_payload_fit_is_physically_consistent_where_the_unconstrained_one_is_not():
    """A hidden 'payload' with negative Iyy, Izz (as a beam log asked for): the fit's pseudo-inertia is PSD, and no
    physical body fits better: the reference minimises over J = L L^T (any L: every PSD J) with scipy's BFGS."""
    p_bad = np.array([0.6, 0.0, 0.0, 0.05, 0.004, 0.0, -0.003, 0.0, 0.0, -0.002])
    body = lambda q, dq, ddq: -ROBOT.body_regressor(q, dq, ddq) @ p_bad        # noqa: E731  (tau_J sign)
    log = synthetic(ROBOT, body, seconds=3.0, excite=FAST)
    model = Model.nominal(ROBOT).add("rigid_payload")
    model.fit(log)
    p = model.params["rigid_payload"]
    assert "min eigenvalue of the pseudo-inertia" in dict(model.violations["rigid_payload"])
    assert np.linalg.eigvalsh(pseudo_inertia(p)).min() >= -1e-12
    s = Signals(log, ROBOT)
    A, y = (-s.body).reshape(-1, 10), (log.tau_J - s.inverse_dynamics).reshape(-1)
    G, b, yy = A.T @ A, A.T @ y, y @ y
    sse = lambda x: x @ G @ x - 2 * b @ x + yy                                # noqa: E731
    M = np.stack([body_of_factor(E.reshape(4, 4)) for E in np.eye(16)], axis=1)   # p = M vec(J)
    tril = np.tril_indices(4)

    def f(l):
        L = np.zeros((4, 4))
        L[tril] = l
        x = M @ (L @ L.T).ravel()
        Z = (M.T @ (2 * (G @ x - b))).reshape(4, 4)
        return sse(x), ((Z + Z.T) @ L)[tril]

    rng = np.random.default_rng(0)
    best = min((minimize(f, 0.1 * rng.normal(size=10), jac=True, method="BFGS", options={"gtol": 1e-10})
                for _ in range(3)), key=lambda r: r.fun)
    L = np.zeros((4, 4))
    L[tril] = best.x
    ref = M @ (L @ L.T).ravel()
    assert sse(p) <= best.fun * (1 + 1e-9), (sse(p), best.fun)
    np.testing.assert_allclose(p, ref, atol=1e-4 * np.abs(ref).max())
    free = np.linalg.lstsq(A, y, rcond=None)[0]                               # the unconstrained fit is not physical
    assert np.linalg.eigvalsh(pseudo_inertia(free)).min() < -1e-4


# --- findings -------------------------------------------------------------------------------------------------
def test_a_too_heavy_nominal_model_gets_no_negative_rotor_inertia_and_a_finding_names_the_joints():
    """The model's motion terms are 5 % too large (k_M fixed at 1.05); the plant has rotor inertia on all joints but
    2 and 4, where the data then ask for a negative one."""
    arm = np.array([0.05, 0.0, 0.05, 0.0, 0.02, 0.02, 0.02])
    log = synthetic(plant(armature=arm), seconds=5.0, excite=FAST)
    model = Model(ROBOT).add("gravity", fixed=[1.0]).add("motion", fixed=[1.05])
    d = D.diagnose(model, log)
    if "rotor" in d.model.names:
        assert np.all(d.model.params["rotor"] >= 0), d.model.params["rotor"]
    found = next(f for f in d.findings if f["effect"] == "rotor")
    named = {int(lbl.split("J")[1]) for lbl, v in found["violations"] if v < 0}
    assert {2, 4} <= named and not named & {5, 6, 7}, found          # the wrist's rotors outweigh 5 % of its M
    assert "negative rotor inertia on J2" in found["text"] and "`motion`" in found["text"]
    assert found["text"] in D.format_diagnosis(d)
    for e in d.model.free:                                  # every selected effect is physical
        lo, hi = e.bounds(7)
        assert np.all(d.model.params[e.name] >= lo) and np.all(d.model.params[e.name] <= hi)


def test_an_effect_that_helps_only_when_non_physical_is_not_selected_and_the_finding_says_why():
    """The model's gravity is 3 % too strong (k_G fixed at 1.03): a payload would fit only with a negative mass, a
    tilt only by shrinking |g|; neither is selected, and both findings point at the gravity scale."""
    d = D.diagnose(Model(ROBOT).add("gravity", fixed=[1.03]).add("motion", fixed=[1.0]),
                   synthetic(ROBOT, seconds=4.0, seed=7))
    assert "payload" not in d.selected and "tilt" not in d.selected, d.selected
    found = {f["effect"]: f for f in d.findings}
    m = dict(found["payload"]["violations"])["m"]
    text = found["payload"]["text"]
    assert m < -0.05 and "negative payload mass" in text and "not selected" in text, text
    ratio = dict(found["tilt"]["violations"])["|g + dg| / |g| - 1"]
    assert abs(ratio + 0.03) < 0.005 and "`gravity`" in found["tilt"]["text"]     # the data want |g| 3 % smaller


# --- friction of any width, an exact tilt ---------------------------------------------------------------------
@functools.lru_cache(maxsize=None)
def coulomb_log(width: float) -> Log:
    return synthetic(ROBOT, lambda q, dq, ddq: np.asarray(GAZ_FC) * np.tanh(dq / width), seconds=4.0, seed=2)


@pytest.mark.parametrize("width", [0.01, 0.05, 0.1])
def test_coulomb_friction_of_any_width_is_named_coulomb_with_its_width(width):
    d = D.diagnose(Model.nominal(ROBOT), coulomb_log(width))
    assert d.selected == ["coulomb"], (d.selected, [r["effect"] for r in d.ranking])
    np.testing.assert_allclose(d.model.params["coulomb"], GAZ_FC, rtol=0.05)
    np.testing.assert_allclose(d.model.nl["coulomb"][:, 0], width, rtol=0.1)


def test_a_five_degree_tilt_is_named_tilt_alone_with_its_angles():
    angles = np.radians([5.0, -3.0])
    d = D.diagnose(Model.nominal(ROBOT), synthetic(plant(tilt=angles), seconds=4.0, seed=3))
    assert d.selected == ["tilt"], d.selected
    np.testing.assert_allclose(d.model.params["tilt"], angles, atol=1e-4)          # 0.006 deg
    assert "deg)" in d.model.report()


# --- saved models ---------------------------------------------------------------------------------------------
def test_models_with_widths_angles_and_bodies_round_trip_and_correct_exactly(tmp_path):
    """Coulomb widths, tilt angles, a rigid payload and a constrained rotor survive save/load bit for bit, and the
    correction is the torque they stand for (the tilt against MuJoCo's gravity on a tilted base)."""
    log = synthetic(plant(armature=np.full(7, 0.03), tilt=(0.06, 0.02)),
                    lambda q, dq, ddq: np.asarray(GAZ_FC) * np.tanh(dq / 0.03), seconds=3.0, excite=FAST, seed=5)
    model = Model.nominal(ROBOT).add("coulomb").add("tilt").add("rotor").add("rigid_payload")
    model.fit(log)
    model.save(tmp_path / "m.json")
    back = Model.load(tmp_path / "m.json")
    for name in model.names:
        np.testing.assert_array_equal(back.params[name], model.params[name])
    np.testing.assert_array_equal(back.nl["coulomb"], model.nl["coulomb"])
    assert np.abs(model.nl["coulomb"][:, 0] - 0.05).max() > 1e-3                    # the width was fitted
    rng = np.random.default_rng(6)
    q, dq = Q_READY + 0.3 * rng.normal(size=(40, 7)), 0.2 * rng.normal(size=(40, 7))
    np.testing.assert_array_equal(back.correction(q, dq), model.correction(q, dq))
    fc, w, tilt = model.params["coulomb"], model.nl["coulomb"][:, 0], model.params["tilt"]
    body = model.params["rigid_payload"]
    want = -(fc * np.tanh(dq / w) + plant(tilt=tilt).gravity(q) - ROBOT.gravity(q)
             - ROBOT.body_regressor(q, dq, 0 * q) @ body)
    np.testing.assert_allclose(model.correction(q, dq), want, atol=1e-9)


@pytest.mark.slow
def test_bounded_offsets_and_a_payload_cone_far_from_the_data_match_a_reference_solver():
    """Data that ask for offsets of thousands of Nm beside a payload 2 m from the hand: the solve stays inside the +-1 Nm box
    and the 0.3 m cone and is no worse than scipy's trust-constr on the same convex problem (fresh seeded draws)."""
    from scipy.optimize import Bounds, NonlinearConstraint
    from diagnosis.effects import segments
    lib = Model(ROBOT, EffectConfig(offset_max=1.0)).library
    segs = segments([lib["offset"], lib["payload"]], 7, ROBOT.g)
    for seed in range(2):
        rng = np.random.default_rng(seed)
        A = rng.normal(size=(60, 11)) * np.r_[np.ones(7), 3.0, np.ones(3)]
        c_true = np.r_[rng.uniform(-2000, 2000, 7), 0.5, 1.0, -0.3, 0.2]
        y = A @ c_true + 0.01 * rng.normal(size=60)
        c, info = solve_physical(A.T @ A, A.T @ y, segs)
        assert info["constrained"] and np.all(np.abs(c[:7]) <= 1 + 1e-9), c
        assert 0 <= c[7] <= 4 and np.linalg.norm(c[8:]) <= 0.3 * c[7] * (1 + 1e-6) + 1e-9, c
        cone = NonlinearConstraint(lambda x: 0.09 * x[7] ** 2 - x[8:] @ x[8:], 0, np.inf)
        cost = lambda x: 0.5 * np.sum((A @ x - y) ** 2)                     # noqa: E731
        ref = minimize(cost, np.r_[np.zeros(7), 1.0, np.zeros(3)], jac=lambda x: A.T @ (A @ x - y),
                       hess=lambda x: A.T @ A, method="trust-constr", constraints=[cone],
                       bounds=Bounds(np.r_[-np.ones(7), 0, -np.inf * np.ones(3)], np.r_[np.ones(7), 4, np.inf * np.ones(3)]),
                       options={"gtol": 1e-10, "xtol": 1e-12, "maxiter": 1000})
        assert cone.fun(ref.x) >= -1e-6 and np.all(np.abs(ref.x[:7]) <= 1 + 1e-6), ref     # a feasible reference
        assert cost(c) <= cost(ref.x) * (1 + 1e-6) + 1e-9, (cost(c), cost(ref.x))
