"""Every bad input a clear error: settings, constructors, the 1 kHz entry points and the command lines refuse what
they cannot use where it is given (ValueError naming it, or one line on stderr), on inputs drawn from seeded
generators; settings that pass construction survive a short stream with a load change."""
import dataclasses
import math
import subprocess
import sys

import numpy as np
import pytest

import vi
from changes import ChangeSettings
from cpic import CPIC, Attractor, CPICConfig
from detector import DetectorSettings
from dynamics import PANDA_XML, Q_READY, Robot, phi_of
from experiments.explore import ExploreSettings
from franka import SafetyConfig
from motion.compensation import InertiaSettings
from motion.inertia import FitSettings
from qp import solve_qp
from rme import RME, RMESettings
from sim import Plant, PlantConfig
from tests.helpers import ROOT

ROBOT = Robot.panda()
LIMITS = ROBOT.torque_limits()


@pytest.fixture(scope="module")
def est():
    return RME(ROBOT)


def ctrl(config=None, policy=None):
    return CPIC(ROBOT, policy or Attractor(*ROBOT.ee_pose(Q_READY)), config)


# --- settings and constructors: nothing accepted that fails later -------------------------------------------------
def rme(**kwargs):
    return RME(ROBOT, weights=None, **kwargs)


def cpic_with(**kwargs):
    return ctrl(CPICConfig(**kwargs))


@pytest.mark.parametrize("make, kwargs, name", [
    (RMESettings, dict(window=200.5), "settings.window"), (RMESettings, dict(window=None), "settings.window"),
    (RMESettings, dict(rest_speed=math.inf), "settings.rest_speed"), (RMESettings, dict(rate=math.inf), "settings.rate"),
    (RMESettings, dict(rate="1000"), "settings.rate"), (RMESettings, dict(max_mass=math.inf), "settings.max_mass"),
    (RMESettings, dict(max_com=math.inf), "settings.max_com"),
    (ChangeSettings, dict(short=40.5), "changes.short"), (ChangeSettings, dict(detect=math.nan), "changes.detect"),
    (ChangeSettings, dict(model_error=-0.1), "changes.model_error"),
    (ChangeSettings, dict(push_arm=math.inf), "changes.push_arm"),
    (vi.VISettings, dict(clip_norm=1e300), "clip_norm"), (vi.VISettings, dict(sigma_prior=(1e300,) * 4), "sigma_prior"),
    (vi.VISettings, dict(lr=1e300), "lr"), (vi.VISettings, dict(lr="0.1"), "lr"),
    (vi.VISettings, dict(noise_floor=1e300), "noise_floor"),
    (PlantConfig, dict(observer="momentum", observer_gain=math.nan), "config.observer_gain"),
    (rme, dict(correction="friction"), "correction"), (rme, dict(rng=42), "rng"),
    (rme, dict(executor="thread"), "executor"),
    (lambda **k: Attractor(np.zeros(3), **k), dict(gain_rot="8"), "gain_rot"),
    (cpic_with, dict(tau_max=(1e300,) * 7), "tau_max"),
    (cpic_with, dict(tau_max=(87.0,) * 7), "config.tau_max"),                  # joints 5-7 have 12 Nm drives
    (lambda **k: CPIC(**k, policy=Attractor(np.zeros(3))), dict(robot="panda"), "robot"),
    (Plant, dict(rng=3), "rng"), (Plant, dict(config="ideal"), "config"),
    (lambda **k: Robot.from_xml(PANDA_XML, **k), dict(ee=7), "ee"), (Robot.from_xml, dict(path=None), "path"),
])
def test_settings_that_would_fail_later_are_refused_where_given(make, kwargs, name):
    with pytest.raises(ValueError, match="^" + name.replace(".", r"\.") + ": expected"):
        make(**kwargs)


def test_an_ee_that_is_no_name_is_refused_not_a_crash():
    """MuJoCo's name lookup crashes the process on ee=None: the check runs before it (in a child process)."""
    code = ("from dynamics import Robot\ntry:\n    Robot.from_xml(%r, ee=None)\nexcept ValueError as e:\n"
            "    print(e)\n" % PANDA_XML)
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                         cwd=ROOT)
    assert run.returncode == 0 and run.stdout.startswith("ee: expected"), (run.returncode, run.stdout, run.stderr)


def _bad_values(default, rng):
    """Values no field with this default can use: wrong type, NaN, inf, huge and complex entries, an extra axis."""
    huge = float(np.sign(rng.normal()) * 10.0 ** rng.uniform(200, 308))
    if isinstance(default, bool):
        return [None, "yes", 1.5, 2]
    if isinstance(default, str):
        return [None, "no-such-option", 3, True]
    if isinstance(default, (int, float)):
        return [None, str(default), complex(default, 1.0), True, math.nan, math.inf, -math.inf, huge, [default] * 2]
    shape = np.shape(default) if default is not None else (7,)
    return [np.full(shape, v).tolist() for v in (math.nan, math.inf, huge, 1 + 1j, True, "1")] + \
        [np.zeros(shape + (2,)).tolist(), math.nan]


@pytest.mark.parametrize("cls, prefix", [(RMESettings, "settings."), (vi.VISettings, ""), (DetectorSettings, ""),
                                         (CPICConfig, ""), (PlantConfig, "config."), (SafetyConfig, "config."),
                                         (InertiaSettings, "settings."), (FitSettings, ""),
                                         (ExploreSettings, "settings.")])
def test_every_field_refuses_generated_bad_values_naming_itself(cls, prefix):
    """Each field, given a wrong type, NaN, inf, a huge or complex number, bool for a number or the wrong shape
    (fresh draws, seeded), is refused by a ValueError whose message starts with the field's name."""
    rng = np.random.default_rng(31)
    for f in dataclasses.fields(cls):
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
        if dataclasses.is_dataclass(default):
            with pytest.raises(ValueError, match=f"^{prefix}{f.name}: expected"):
                cls(**{f.name: "fast"})
            continue
        for bad in _bad_values(default, rng):
            if bad is None and "None" in str(f.type):    # None is one of its documented values
                continue
            with pytest.raises(ValueError, match=rf"^{prefix}{f.name}(\[\d+\])?: expected") as err:
                cls(**{f.name: bad})
            assert len(str(err.value)) < 400, str(err.value)


def _edge_settings(rng):
    """RMESettings with a random subset of fields at the edges of what they accept."""
    edges = dict(window=20, rate=float(rng.choice([10.0, 1e4])), max_mass=50.0, max_com=1.0, rest_speed=1.0,
                 max_abs_torque=1e4, use_network=False)
    change_edges = dict(short=int(rng.choice([10, 250])), rest_noise=(1e-6,) * 7, friction=(100.0,) * 7,
                        friction_slope=(1e-6,) * 7, model_error=float(rng.choice([0.0, 1.0])), push_force=1e4,
                        push_arm=1e-3, detect=float(rng.choice([1e-6, 1e6])), confidence=0.999999)
    vi_edges = dict(sigma_prior=(1e3,) * 4, lr=1.0, clip_norm=1e3, noise_floor=10.0, noise_scale=1e3,
                    tol=10.0, map_steps=0, offset_std=10.0, motion_gain=100.0, motion_max=100.0, load_share=1.0,
                    slow_gain=10.0, observed_ratio=1.0, min_iterations=0, check_every=10000, average=0.0)
    det_edges = dict(activation_threshold=1e12, stabilisation_threshold=1e12, side_force_limit=1e4, refractory=0,
                     lam=10.0)
    pick = lambda d: {k: v for k, v in d.items() if rng.random() < 0.5}
    detector = DetectorSettings(**pick(det_edges)) if rng.random() < 0.5 else None    # Algorithm 1 or the model
    return RMESettings(**pick(edges), vi=vi.VISettings(**pick(vi_edges)), changes=ChangeSettings(**pick(change_edges)),
                       detector=detector)


def test_settings_at_the_edges_of_what_they_accept_survive_a_stream_with_a_load_change():
    """Eight draws of edge settings (seeded): 0.8 s of samples at the ready pose, a 1.5 kg load from 0.4 s; every
    compensation is finite and within the torque limits (what the estimates are worth is not asked here)."""
    rng = np.random.default_rng(5)
    Y, phi = ROBOT.payload_regressor(Q_READY), phi_of([1.5, 0.03, -0.02, 0.08])
    for draw in range(8):
        while True:                                     # (some edges exclude others)
            try:
                settings = _edge_settings(rng)
                break
            except ValueError:
                pass
        est = RME(ROBOT, settings=settings, rng=np.random.default_rng(draw))
        for k in range(800):
            tau = rng.normal(0.0, 0.01, 7) + (Y @ phi if k >= 400 else 0.0)
            comp = est.update(Q_READY + rng.normal(0.0, 1e-5, 7), rng.normal(0.0, 1e-3, 7), tau)
            assert np.all(np.isfinite(comp)) and np.all(np.abs(comp) <= LIMITS), (draw, settings, k)


# --- the 1 kHz path and the estimate ---------------------------------------------------------------------------
def _bad_arrays(shape, rng):
    """(value, whether it is only not finite or beyond physics: a documented finite result, not a type error)."""
    good = rng.normal(size=shape)
    out = [(good.astype(complex) + 1j, False), (good > 0, False), (good[..., :-1], False), (good.tolist() + [0], False),
           ("q", False), (None, False), ({"q": 1}, False)]
    for v in (math.nan, math.inf, -math.inf, float(10.0 ** rng.uniform(200, 308))):
        bad = good.copy()
        bad[tuple(rng.integers(0, s) for s in shape)] = v
        out.append((bad, True))
    return out


def test_update_refuses_a_wrong_type_or_shape_and_drops_a_faulty_sample(est):
    """Wrong type or shape of q, dq or tau_ext: ValueError naming it, at once. A tau_ext not finite or beyond
    max_abs_torque: dropped (counted), the last compensation returned: finite, within the limits."""
    rng = np.random.default_rng(7)
    q, dq, tau = Q_READY, np.zeros(7), np.zeros(7)
    for i, name in enumerate(("q", "dq", "tau_ext")):
        for bad, faulty in _bad_arrays((7,), rng):
            args = [q, dq, tau]
            args[i] = bad
            if faulty and name == "tau_ext":
                dropped = est.dropped
                comp = est.update(*args)
                assert est.dropped == dropped + 1 and np.all(np.isfinite(comp)) and np.all(np.abs(comp) <= LIMITS)
            elif faulty and np.isfinite(bad).all():       # a huge finite angle or speed: a finite answer
                assert np.all(np.abs(est.update(*args)) <= LIMITS)
            else:
                with pytest.raises(ValueError, match=f"^{name}: expected"):
                    est.update(*args)


def test_estimate_refuses_torques_beyond_max_abs_torque_and_complex_or_bool_windows(est):
    """A baseline of 1e300 Nm or torques of 1e200 Nm gave NaN: now a ValueError naming them; torques up to
    max_abs_torque give a finite estimate."""
    q, tau = np.tile(Q_READY, (200, 1)), np.zeros((200, 7))
    for kwargs, name in [(dict(tau_ext=tau, baseline=np.full(7, 1e300)), "baseline"),
                         (dict(tau_ext=np.full((200, 7), 1e200)), "tau_ext"), (dict(tau_ext=tau + 0j), "tau_ext"),
                         (dict(tau_ext=tau.astype(bool)), "tau_ext"),
                         (dict(tau_ext=tau, baseline=np.ones(7) + 1j), "baseline")]:
        with pytest.raises(ValueError, match=f"^{name}: expected"):
            est.estimate(q, **kwargs)
    rng = np.random.default_rng(3)
    for _ in range(3):
        e = est.estimate(q, rng.uniform(-1, 1, (200, 7)) * est.settings.max_abs_torque)
        assert np.all(np.isfinite(e.mean)) and np.all(np.isfinite(e.cov))


def test_step_refuses_garbage_compensation_and_wrong_types_at_once():
    """CPIC.step: a compensation beyond what any payload up to payload_mass can need (compensation = 1e6 was clipped
    to full torque on every joint) and wrong types or shapes of every argument: ValueError naming it."""
    c, rng = ctrl(), np.random.default_rng(9)
    with pytest.raises(ValueError, match="^compensation: expected what a payload up to 3 kg"):
        c.step(Q_READY, np.zeros(7), np.full(7, 1e6))
    comp = -ROBOT.payload_torque(Q_READY, [3.0, 0.3, -0.3, 0.3])        # the heaviest payload allowed: accepted
    assert np.all(np.abs(c.step(Q_READY, np.zeros(7), comp)[0]) <= LIMITS)
    for i, name in enumerate(("q", "dq", "compensation", "tau_ext")):
        for bad, faulty in _bad_arrays((7,), rng):
            args = [Q_READY, np.zeros(7), np.zeros(7), np.zeros(7)]
            args[i] = bad
            if bad is None and i >= 2:                  # None: no compensation, no measured tau_ext (documented)
                continue
            if faulty and name != "compensation" and np.isfinite(bad).all():   # a huge finite state or tau_ext:
                with np.errstate(all="ignore"):                                  #   finite, within the limits
                    tau = c.step(*args)[0]
                assert np.all(np.isfinite(tau)) and np.all(np.abs(tau) <= LIMITS)
                continue
            with pytest.raises(ValueError, match=f"^{name}: expected"):
                c.step(*args)


@pytest.mark.parametrize("policy", [lambda p, R: None, lambda p, R: (np.zeros(5), (0.0, 0.0)),
                                    lambda p, R: (np.zeros(6), None), lambda p, R: (["a"] * 6, (0.0, 0.0)),
                                    lambda p, R: (np.zeros(6) + 1j, (0.0, 0.0)), lambda p, R: np.zeros(6)])
def test_a_policy_output_of_the_wrong_type_or_shape_is_a_value_error(policy):
    with pytest.raises(ValueError, match="^policy: expected"):
        ctrl(policy=policy).step(Q_READY, np.zeros(7))


def test_cpic_configs_at_the_edges_of_what_they_accept_give_finite_torques_within_limits():
    """Random CPICConfigs at the edges of their ranges (seeded), on random states near the joint limits with a heavy
    payload's compensation: every torque finite and within tau_max."""
    rng = np.random.default_rng(12)
    edges = dict(damping_pos=(1e4,) * 3, damping_rot=(1e3, 1e-6, 1e-6), k1=1e4, k2=1e-6, null_weight=1e6,
                 null_damping=1e3, null_stiffness=1e4, fallback_damping=(1e3,) * 7, max_iterations=1, payload_mass=50.0,
                 payload_com=1.0, q_rest=tuple(Q_READY + 50.0), tau_max=tuple(LIMITS * 1e-3))
    lo, hi = ROBOT.model.jnt_range[:, 0], ROBOT.model.jnt_range[:, 1]
    for draw in range(20):
        config = CPICConfig(**{k: v for k, v in edges.items() if rng.random() < 0.5})
        c, q = ctrl(config), rng.uniform(lo - 0.1, hi + 0.1)
        comp = -ROBOT.payload_torque(q, [3.0, *rng.uniform(-0.3, 0.3, 3)])
        for _ in range(5):
            tau = c.step(q, rng.normal(0.0, 1.0, 7), comp, rng.normal(0.0, 5.0, 7))[0]
            assert np.all(np.isfinite(tau)) and np.all(np.abs(tau) <= np.asarray(config.tau_max) + 1e-12), draw


def test_detector_update_and_joint_hold_refuse_complex_and_bool():
    from cpic import JointHold
    from detector import Detector
    J = ROBOT.jacobian(Q_READY)
    z = np.zeros(7)
    for kwargs, name in [(dict(tau_ext=z + 0j, J=J), "tau_ext"), (dict(tau_ext=z > 0, J=J), "tau_ext"),
                         (dict(tau_ext=np.zeros(7), J=J + 0j), "J"),
                         (dict(tau_ext=np.zeros(7), force=[True] * 3), "force")]:
        with pytest.raises(ValueError, match=f"^{name}: expected"):
            Detector().update(**kwargs)
    hold = JointHold(ROBOT, Q_READY)
    for args, name in [((Q_READY, np.zeros(7) + 1j), "dq"), ((Q_READY, np.zeros(7), np.zeros(7) > 0), "compensation")]:
        with pytest.raises(ValueError, match=f"^{name}: expected"):
            hold.step(*args)
    with pytest.raises(ValueError, match="^kp: expected"):
        JointHold(ROBOT, Q_READY, kp="600")


def test_network_refuses_complex_and_bool_input(est):
    import nn_numpy
    q, tau = np.tile(Q_READY, (200, 1)), np.zeros((200, 7))
    for call, name in [(lambda: nn_numpy.features(ROBOT, q, tau + 0j), "tau_ext"),
                       (lambda: nn_numpy.features(ROBOT, q > 0, tau), "q"),
                       (lambda: est.net.predict(np.zeros((20, 6)) + 1j), "x")]:
        with pytest.raises(ValueError, match=f"^{name}: expected real numbers, found"):
            call()


def test_solve_qp_refuses_complex_and_bool_arrays():
    H, g, A, b = np.eye(3), np.ones(3), np.eye(3), -np.ones(3)
    for i, name in enumerate("HgAb"):
        for bad in ((H, g, A, b)[i] + 0j, (H, g, A, b)[i] > 0):
            args = [H, g, A, b]
            args[i] = bad
            with pytest.raises(ValueError, match=f"^{name}: expected"):
                solve_qp(*args)


def test_momentum_observer_at_its_highest_gain_stays_finite():
    """observer_gain up to 1/dt is accepted: the plant's tau_ext stays finite over 0.3 s with a payload."""
    plant = Plant(PlantConfig(observer="momentum", observer_gain=1000.0))
    plant.set_payload(2.0, (0.0, 0.0, 0.1))
    c = ctrl()
    s = plant.reset(Q_READY)
    for _ in range(300):
        s = plant.step(c.step(s.q, s.dq)[0])
        assert np.all(np.isfinite(s.tau_ext))


# --- command lines: every argument checked by its parser, one line on stderr -------------------------------------
@pytest.mark.parametrize("argv", [["reliability", "--episodes", "0"], ["calibration", "--windows", "0"],
                                  ["static", "--seed", "-1"], ["static", "--plot", "/no/such/folder/f.png"],
                                  ["bench", "--seed", "1.5"], ["reliability", "--episodes", "1e9"],
                                  ["reliability", "--jobs", "0"]])
def test_sim_command_line_refuses_bad_arguments_in_its_parser(argv, capsys):
    from experiments import cli
    with pytest.raises(SystemExit) as stop:
        cli.main(argv)
    err = capsys.readouterr().err
    assert stop.value.code == 2 and err.count("\n") == 1 and f"argument {argv[1]}: expected" in err, err


@pytest.mark.parametrize("argv", [["train", "--episodes", "0"], ["train", "--episodes", "x"], ["train", "--seed", "-1"],
                                  ["train", "--out", "/no/such/folder/w.npz"], ["bench", "--out", "/no/such/w.npz"],
                                  ["fly"]])
def test_nn_command_line_refuses_bad_arguments_before_any_work(argv, capsys, monkeypatch):
    from experiments import training
    monkeypatch.setattr(training, "train_from_scratch", lambda *a, **k: pytest.fail("training started"))
    monkeypatch.setattr(training, "benchmark", lambda *a, **k: pytest.fail("benchmark started"))
    with pytest.raises(SystemExit) as stop:
        training.main(argv)
    err = capsys.readouterr().err
    assert stop.value.code == 2 and err.count("\n") == 1 and "error:" in err, err


def test_a_failing_command_is_one_line_on_stderr_without_traceback(tmp_path):
    """A weights file that cannot be read: nn_numpy.py bench says so in one line, exit status 1."""
    bad = tmp_path / "w.npz"
    bad.write_bytes(b"not a weights file")
    run = subprocess.run([sys.executable, "nn_numpy.py", "bench", "--out", str(bad)], capture_output=True, text=True,
                         timeout=120, cwd=ROOT)
    assert run.returncode == 1 and run.stderr.count("\n") == 1 and "Traceback" not in run.stderr, run.stderr
    assert "could not read weights file" in run.stderr


# --- the helper itself -----------------------------------------------------------------------------------------
def test_checks_refuse_every_kind_of_bad_number_and_accept_numpy_scalars():
    import checks
    for bad in (None, "3", True, np.bool_(True), 3 + 0j, math.nan, math.inf, 10 ** 400, 2.5, 0, 101):
        with pytest.raises(ValueError, match=r"^x: expected an integer in 1\.\.100 samples, found"):
            checks.number("x", bad, "1..100", "samples")
    assert checks.number("x", np.int64(7), "1..100") == 7 and checks.number("x", np.float32(0.5), "(0, 1]") == 0.5
    for bad in (0.0, 1.0 + 1e-12, -math.inf):
        with pytest.raises(ValueError, match=r"^x: expected a number in \(0, 1\]"):
            checks.number("x", bad, "(0, 1]")
    assert checks.array("v", [1, 2], (None,), "[1, 2]").dtype == float
    with pytest.raises(ValueError, match="^v: expected .* found ragged nesting"):
        checks.array("v", [[1, 2], [3]], (2, None))
