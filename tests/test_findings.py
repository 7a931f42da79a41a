"""Tests of what a diagnosis must say instead of fitting: the offset/payload ambiguity at one pose, a CoM bounded to the
hand's reach, a refused save, a vibration of the load and a load step in the log (simulated Panda logs)."""
import functools
import json

import numpy as np
import pytest

from diagnosis import diagnose as D
from diagnosis.anomalies import oscillation
from diagnosis.effect_model import Model
from diagnosis.effects import EffectConfig
from diagnosis.excite import QUASI_STATIC, ExciteConfig
from diagnosis.logs import prepare
from dynamics import Robot
from error_model import ErrorModel
from experiments.episodes import plant_config, record_log, save_log

ROBOT = Robot.panda()
HOLD = ExciteConfig(speed=0.0)                    # the arm held still at ExciteConfig.center: one pose


@functools.lru_cache(maxsize=None)
def held(name: str, seconds: float = 10.0) -> dict:
    """Raw log of the plant holding one pose with exactly the hidden effects in name ("none", "offset", "payload")."""
    config, payload = plant_config(() if name == "none" else (name,))
    return record_log(config, seconds, np.random.default_rng(5), HOLD, payload=payload)


@functools.lru_cache(maxsize=None)
def sweep() -> dict:
    """Raw 5 s log of a slow sweep of the plain plant (every payload direction identifiable)."""
    return record_log(plant_config(())[0], 5.0, np.random.default_rng(8), QUASI_STATIC)


def with_torque(raw: dict, extra: np.ndarray) -> dict:
    """raw with a torque the drives add (T, 7) in tau_J, and tau_ext (paper sign, model - tau_J) changed with it."""
    return dict(raw, tau_J=raw["tau_J"] + extra, tau_ext=raw["tau_ext"] - extra)


def load_weight(q, theta) -> np.ndarray:
    """The torque (T, 7) the drives add to hold a load theta = (m, r) (ee frame): minus tau_mm = Y phi (Eqs. 4-5)."""
    phi = np.concatenate([[theta[0]], theta[0] * np.asarray(theta[1:])])
    return -ROBOT.payload_regressor(q) @ phi


# --- what one pose cannot tell -----------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("hidden", ["offset", "payload"])
def test_static_log_at_one_pose_yields_the_ambiguity_finding_not_an_offset(hidden):
    d = D.diagnose(Model.nominal(ROBOT), prepare(held(hidden)))
    assert d.selected == [], (d.selected, d.stop)
    kinds = {f.get("kind"): f for f in d.findings}
    assert "ambiguity" in kinds, [f["text"] for f in d.findings]
    text = kinds["ambiguity"]["text"]
    assert "offset" in text and "payload" in text and "at one pose" in text, text
    assert d.info["excitation"]["poses"] == 1 and d.info["excitation"]["moving"] < 0.01


def test_a_fit_that_would_put_a_com_metres_away_is_bounded_and_reported():
    """A torque that only a load 2 m from the hand makes, on a slow sweep (every payload direction identifiable):
    the fit keeps |r| <= 0.3 m and reports what the unconstrained fit asked for."""
    raw = sweep()
    far = (0.4, 2.0, 0.0, 0.0)                                       # kg, m: a CoM 2 m along the hand's x
    log = prepare(with_torque(raw, load_weight(raw["q"], far)))
    model = Model.nominal(ROBOT).add("payload")
    model.fit(log)
    p = model.params["payload"]
    assert p[0] > 0 and np.linalg.norm(p[1:]) <= 0.3 * p[0] * (1 + 1e-4), p
    asked = dict(model.violations["payload"])
    assert abs(asked["|r| [m]"] - 2.0) < 0.1, asked                   # the unconstrained fit: 2 m, reported
    assert "held to its physical constraints" in model.report()
    d = D.diagnose(Model.nominal(ROBOT), log, candidates=["payload", "offset"])
    texts = " ".join(f["text"] for f in d.findings)
    assert "m from the hand, beyond the 0.3 m" in texts, texts


@pytest.mark.slow
def test_save_refuses_a_model_held_at_a_bound_and_force_saves_it(tmp_path, capsys):
    raw = sweep()
    save_log(tmp_path / "far.npz", with_torque(raw, load_weight(raw["q"], (0.4, 2.0, 0.0, 0.0))))
    args = [str(tmp_path / "far.npz"), "--add", "payload", "--save", str(tmp_path / "m.json")]
    assert D.main(args) == 2
    err = capsys.readouterr().err
    assert not (tmp_path / "m.json").exists() and "--force" in err and len(err.strip().splitlines()) == 1, err
    assert D.main(args + ["--force", "--json"]) == 0
    doc = json.loads((tmp_path / "m.json").read_text())
    assert doc["robot"] == {"name": "panda", "ee": "ee", "n": 7}           # no absolute path to the arm's MJCF
    loaded = Model.load(tmp_path / "m.json")
    np.testing.assert_allclose(loaded.params["payload"], json.loads(capsys.readouterr().out)["after"]["params"]
                               ["payload"], atol=1e-6)


def test_each_joints_offset_bound_holds_a_fit_and_says_where_it_comes_from():
    """Offsets of 0.3 Nm on J2 and 0.9 Nm on J6 on a slow sweep: J2 is fitted free, J6 is held to its bound (a real
    Panda's static error there reaches 0.52 Nm), and the report says the value asked for, the bound and its source;
    with one 1 Nm bound for every joint nothing is held."""
    raw = sweep()
    hidden = np.array([0.0, 0.3, 0.0, 0.0, 0.0, 0.9, 0.0])
    log = prepare(with_torque(raw, np.broadcast_to(hidden, raw["q"].shape)))
    model = Model.nominal(ROBOT).add("offset")
    model.fit(log)
    p, lo_hi = model.params["offset"], model.library["offset"].bounds(7)
    assert abs(p[1] - 0.3) < 0.02 and p[5] == pytest.approx(lo_hi[1][5], abs=1e-6) and lo_hi[1][5] < 0.9, p
    asked = dict(model.violations["offset"])
    assert list(asked) == ["tau_0 J6"] and abs(asked["tau_0 J6"] - 0.9) < 0.02, asked
    assert [lbl for lbl, _ in model.at_bounds["offset"]] == ["tau_0 J6"], model.at_bounds
    text = model.report()
    assert f"(bound {lo_hi[1][5]:.4g})" in text and "calibrated on 36 beam logs" in text, text
    assert f"at its bounds: tau_0 J6 {lo_hi[1][5]:.4g}" in text, text
    wide = Model.nominal(ROBOT, EffectConfig(offset_max=1.0)).add("offset")
    wide.fit(log)
    assert not wide.violations and not wide.at_bounds and abs(wide.params["offset"][5] - 0.9) < 0.02, wide.params


def test_an_offset_bound_grows_where_the_log_leaves_the_calibrated_gravity_torques():
    """offset_bounds of a calibration with a gravity range: |offset| + 3 std at a pose within it; at a pose 20 Nm
    beyond it on J2 the std there is sqrt(std^2 + (0.05 x 20)^2) (the gravity model's share), the other joints kept."""
    from diagnosis.effects import offset_bounds
    absolute, offset = np.array([0.3, 0.2, 0.2, 0.2, 0.1, 0.1, 0.1]), np.array([0.1, -0.5, 0, -0.4, 0, 0.2, 0])
    lo, hi = np.full(7, -1.0), np.full(7, 1.0)
    em = ErrorModel(tuple(absolute), (0.01,) * 7, tuple(offset), gravity_range=(tuple(lo), tuple(hi)))
    inside, source = offset_bounds(em, np.zeros((3, 7)))
    np.testing.assert_allclose(inside, np.abs(offset) + 3 * absolute, atol=1e-3)
    beyond = np.zeros((2, 7))
    beyond[1, 1] = 21.0
    want = np.abs(offset) + 3 * absolute
    want[1] = 0.5 + 3 * np.hypot(0.2, 0.05 * 20.0)
    np.testing.assert_allclose(offset_bounds(em, beyond)[0], want, atol=1e-3)
    assert "3 std" in source


@pytest.mark.slow
def test_save_refuses_an_offset_at_its_bound_unless_the_robots_calibration_allows_it(tmp_path, capsys):
    """The same log: `--add offset --save` is refused with the default bounds; with --calibration of a robot whose
    J6 offset is 0.8 Nm (absolute std 0.1 Nm) the bound there is 0.8 + 3 x 0.1 = 1.1 Nm, the fit is free and saved,
    and the JSON names the bound per joint and its source."""
    raw = sweep()
    hidden = np.array([0.0, 0.3, 0.0, 0.0, 0.0, 0.9, 0.0])
    save_log(tmp_path / "off.npz", with_torque(raw, np.broadcast_to(hidden, raw["q"].shape)))
    args = [str(tmp_path / "off.npz"), "--add", "offset", "--save", str(tmp_path / "m.json"), "--json"]
    assert D.main(args) == 2
    assert "tau_0 J6" in capsys.readouterr().err and not (tmp_path / "m.json").exists()
    absolute = np.array([0.3, 0.2, 0.2, 0.2, 0.1, 0.1, 0.1])
    offset = np.array([0.1, -0.5, 0.0, -0.4, 0.0, 0.8, 0.0])
    ErrorModel(tuple(absolute), (0.01,) * 7, tuple(offset), source="robot 7 on the bench").save(tmp_path / "r.json")
    assert D.main(args + ["--calibration", str(tmp_path / "r.json")]) == 0
    out = json.loads(capsys.readouterr().out)
    np.testing.assert_allclose(out["bounds"]["offset"]["bound"], np.abs(offset) + 3 * absolute, atol=1e-3)
    assert "robot 7 on the bench" in out["bounds"]["offset"]["source"] and not out["after"]["held_to_constraints"]
    np.testing.assert_allclose(out["after"]["params"]["offset"], hidden, atol=0.02)
    assert Model.load(tmp_path / "m.json").config.offset_source == out["bounds"]["offset"]["source"]
    assert D.main(args + ["--calibration", str(tmp_path / "none.json")]) == 2
    assert "none.json" in capsys.readouterr().err


# --- what is no effect: a vibration, a step --------------------------------------------------------------------
def ringing(t, t0, f, decay, shape) -> np.ndarray:
    """A load's decaying vibration from t0: exp(-decay (t - t0)) sin(2 pi f (t - t0)) times the joint shape (7,)."""
    tt = np.maximum(t - t0, 0.0)
    return ((t >= t0) * np.exp(-decay * tt) * np.sin(2 * np.pi * f * tt))[:, None] * np.asarray(shape)[None, :]


@pytest.mark.slow
def test_a_decaying_vibration_is_found_with_its_frequency_within_5_percent(tmp_path, capsys):
    raw = held("none")
    shape = np.array([0.0, 0.15, 0.0, 0.3, 0.05, 0.1, 0.0])           # Nm, mostly the shoulder and elbow
    save_log(tmp_path / "ring.npz", with_torque(raw, ringing(raw["t"], 1.0, 2.5, 0.4, shape)))
    assert D.main([str(tmp_path / "ring.npz"), "--json"]) == 0
    vib = json.loads(capsys.readouterr().out)["vibration"]
    assert abs(vib["frequency"] - 2.5) <= 0.05 * 2.5, vib
    zeta = 0.4 / np.hypot(0.4, 2 * np.pi * 2.5)
    assert abs(vib["damping"] - zeta) <= 0.3 * zeta and vib["joint"] == 4, vib
    rng = np.random.default_rng(12)                                    # fresh draws: frequency, decay, start
    base = prepare(raw)
    r0 = base.tau_J - Model.nominal(ROBOT).predict(base)
    assert oscillation(base.t, r0, base.dq) is None                     # the plain hold: no vibration
    for _ in range(3):
        f, decay, t0 = rng.uniform(1.5, 8.0), rng.uniform(0.1, 1.5), rng.uniform(0.5, 2.0)
        log = prepare(with_torque(raw, ringing(raw["t"], t0, f, decay, shape)))
        r = log.tau_J - Model.nominal(ROBOT).predict(log)
        vib = oscillation(log.t, r, log.dq)
        assert vib is not None and abs(vib["frequency"] - f) <= 0.05 * f, (f, decay, vib)


@pytest.mark.slow
def test_a_load_step_is_found_within_50_ms_and_each_segment_is_diagnosed(tmp_path, capsys):
    raw = held("none")
    rng = np.random.default_rng(21)
    for _ in range(2):
        ts = rng.uniform(3.6, 6.4)                                     # s, when 1 kg is put in the hand
        step = (raw["t"] >= ts)[:, None] * load_weight(raw["q"], (1.0, 0.0, 0.0, 0.1))
        save_log(tmp_path / "step.npz", with_torque(raw, step))
        assert D.main([str(tmp_path / "step.npz"), "--json"]) == 0
        out = json.loads(capsys.readouterr().out)
        assert len(out["steps"]) == 1 and abs(out["steps"][0]["t"] - ts) <= 0.05, (ts, out["steps"])
        segs = out["segments"]
        assert len(segs) == 2 and all("selected" in s and "error" not in s for s in segs), segs
        assert segs[0]["t1"] == segs[1]["t0"] == out["steps"][0]["t"]
    save_log(tmp_path / "plain.npz", raw)                              # the same hold without the load: no step
    assert D.main([str(tmp_path / "plain.npz"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["steps"] == []
