"""The pose-dependent torque map (effect "pose_bias"): its regressor, a map fitted on a load-free hold log against the
plant's own Plant.pose_bias at poses it never held, and the saved map round trip RME reads."""
import dataclasses
import functools

import numpy as np
import pytest

from diagnosis.effect_model import Model
from diagnosis.effects import EffectConfig, Signals, pose_bias_block
from diagnosis.excite import HoldsConfig, hold_poses, hold_reference
from diagnosis.logs import Log
from dynamics import Q_READY, Robot
from experiments.bias_map import fit_bias_map, record_holds
from rme import RME
from sim import Plant, PlantConfig

ROBOT = Robot.panda()
WITH_MAP = EffectConfig(bias_joints=7)                  # the library offers pose_bias only when asked to
HOLDS = HoldsConfig(poses=30, hold=0.35, settle=0.2)


def test_the_pose_bias_regressor_is_a_constant_plus_first_harmonics_per_joint():
    """Against the sum written out joint by joint: tau_j = b_j + sum_k (a_jk sin q_k + c_jk cos q_k); the model's
    correction is the same torque in the tau_ext sign (negated)."""
    rng = np.random.default_rng(0)
    q = Q_READY + rng.uniform(-1.0, 1.0, size=(30, 7))
    P = rng.normal(size=(15, 7))                              # [basis function i, joint j]
    want = np.zeros((30, 7))
    for t in range(30):
        for j in range(7):
            want[t, j] = P[0, j] + sum(P[1 + k, j] * np.sin(q[t, k]) + P[8 + k, j] * np.cos(q[t, k])
                                       for k in range(7))
    model = Model.static(ROBOT, WITH_MAP).add("pose_bias", fixed=P.reshape(-1))
    assert "pose_bias" not in Model(ROBOT).library                          # not offered by default
    e = model.effect("pose_bias")
    log = Log(t=np.arange(30.0), q=q, dq=np.zeros_like(q), ddq=np.zeros_like(q), tau_J=None, tau_ext=np.zeros_like(q))
    np.testing.assert_allclose(e.block(Signals(log, ROBOT)) @ P.reshape(-1), want, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(model.correction(q), -want, rtol=1e-12, atol=1e-12)
    assert e.labels(7)[7 + 1] == "sin q1 J2" and e.size(7) == 105
    assert not any(name in e.explanation for name in ("friction", "velocity"))   # static: q only


def test_an_arm_with_fewer_joints_gets_zero_columns_for_the_missing_ones():
    q = np.random.default_rng(1).uniform(-1, 1, size=(5, 6))
    Y = pose_bias_block(q, WITH_MAP.bias_joints)                                # (5, 6, 15 * 6)
    assert Y.shape == (5, 6, 90)
    zero = [i * 6 + j for i in (7, 14) for j in range(6)]                       # sin q7, cos q7: no such joint
    assert np.all(Y[:, :, zero] == 0) and np.all(Y[:, np.arange(6), np.arange(6)] == 1)   # the constants


@functools.lru_cache(maxsize=None)
def calibrated():
    """A plant whose only departure from the nominal model is the realistic sensor (noise, quantisation, stale
    packets, pose-dependent bias), its map fitted on a load-free hold log around the ready pose: (plant, model)."""
    rng = np.random.default_rng(7)
    real = PlantConfig.realistic(np.random.default_rng(7))
    config = dataclasses.replace(PlantConfig.ideal(), **{k: getattr(real, k) for k in (
        "tau_noise", "tau_step", "q_noise", "dq_noise", "stale_prob", "bias_amp")})
    plant = Plant(config, rng=rng)
    raw, still = record_holds(plant, Q_READY, HOLDS, np.random.default_rng(8))
    model, info = fit_bias_map(raw, still, plant.robot)
    assert info["status"] == "ok"
    return plant, model


@pytest.mark.slow
def test_a_map_fitted_on_a_load_free_log_predicts_the_plant_pose_bias_at_poses_it_never_held():
    """Held-out poses drawn inside the calibrated box (80 % of its half-widths): the map (tau_ext sign) is the
    negated Plant.pose_bias within 0.02 Nm on every joint (a tenth of the bias's amplitude, about half the sensor's
    quantisation step on J1-J4), and it leaves under 10 % of the bias's variation over those poses."""
    plant, model = calibrated()
    held = hold_poses(Q_READY, dataclasses.replace(HOLDS, spans=tuple(0.8 * np.array(HOLDS.spans)), poses=60),
                      np.random.default_rng(99))[1:]
    bias = np.array([plant.pose_bias(q) for q in held])
    err = model.correction(held) + bias
    assert np.abs(err).max() < 0.02
    spread = np.sqrt(((bias - bias.mean(axis=0)) ** 2).mean())               # what the best constant would leave
    assert np.sqrt((err ** 2).mean()) < 0.1 * spread


def test_a_saved_map_round_trips_exactly_and_rme_subtracts_it(tmp_path):
    _, model = calibrated()
    model.save(tmp_path / "map.json")
    back = Model.load(tmp_path / "map.json")                # the saved config offers pose_bias again
    assert back.names == ["gravity", "pose_bias"] and back.fitted
    np.testing.assert_array_equal(back.params["pose_bias"], model.params["pose_bias"])
    q = Q_READY + np.random.default_rng(3).uniform(-0.3, 0.3, size=(200, 7))
    np.testing.assert_array_equal(back.correction(q), model.correction(q))
    tau = np.random.default_rng(4).normal(scale=0.1, size=(200, 7))
    a = RME(ROBOT, weights=None, correction=back).estimate(q, tau)
    b = RME(ROBOT, weights=None).estimate(q, tau - model.correction(q))
    np.testing.assert_allclose(a.mean, b.mean, rtol=1e-9, atol=1e-12)


def test_the_hold_reference_holds_still_where_it_is_fitted_and_keeps_its_speed_bound():
    cfg = HoldsConfig(poses=8)
    poses = hold_poses(Q_READY, cfg, np.random.default_rng(0))
    t, q, dq, ddq, still = hold_reference(poses, cfg)
    assert np.abs(dq).max() <= cfg.speed * (1 + 1e-9) and np.all(dq[still] == 0)
    integral = lambda v: np.concatenate([[0 * v[0]], np.cumsum(0.5 * (v[1:] + v[:-1]) * np.diff(t)[:, None], axis=0)])
    np.testing.assert_allclose(q[0] + integral(dq), q, atol=2e-3)         # dq and ddq are q's derivatives
    smooth = np.abs(ddq[2:] - ddq[:-2]).max(axis=1) < 0.05 * np.abs(ddq).max()   # away from the profile's corners
    assert smooth.mean() > 0.98
    np.testing.assert_allclose(np.gradient(dq, t, axis=0)[1:-1][smooth], ddq[1:-1][smooth], atol=1e-3 * np.abs(ddq).max())
    assert np.all(np.abs(dq[still]) == 0) and 0.1 * len(poses) <= still.sum() * 1e-3 < cfg.hold * len(poses)
    assert np.all(np.abs(poses - Q_READY) <= np.array(cfg.spans) + 1e-12)
    with pytest.raises(ValueError, match="center"):
        hold_poses(Q_READY[:6], cfg, np.random.default_rng(0))


@pytest.mark.slow
def test_the_command_line_fits_and_saves_a_map_from_a_hold_log(tmp_path, capsys):
    """`rme.py diagnose HOLDS.npz --add pose_bias --save map.json` on the whole load-free hold log (moves included:
    the nominal model's motion term covers them): the saved map loads by itself and predicts the plant's pose_bias at
    held-out poses as the Python recipe does (0.02 Nm, 10 % of the bias's variation)."""
    from diagnosis.diagnose import main
    real = PlantConfig.realistic(np.random.default_rng(7))
    config = dataclasses.replace(PlantConfig.ideal(), **{k: getattr(real, k) for k in (
        "tau_noise", "tau_step", "q_noise", "dq_noise", "stale_prob", "bias_amp")})
    plant = Plant(config, rng=np.random.default_rng(7))
    raw, _ = record_holds(plant, Q_READY, HOLDS, np.random.default_rng(8))
    np.savez(tmp_path / "holds.npz", **{k: raw[k] for k in ("t", "q", "dq", "tau_J", "tau_ext")}, tau_ext_sign="paper")
    assert main([str(tmp_path / "holds.npz"), "--add", "pose_bias", "--save", str(tmp_path / "map.json"), "--json"]) == 0
    capsys.readouterr()
    model = Model.load(tmp_path / "map.json")
    assert model.names == ["gravity", "motion", "pose_bias"]
    held = hold_poses(Q_READY, dataclasses.replace(HOLDS, spans=tuple(0.8 * np.array(HOLDS.spans)), poses=60),
                      np.random.default_rng(99))[1:]
    bias = np.array([plant.pose_bias(q) for q in held])
    err = model.correction(held) + bias
    assert np.abs(err).max() < 0.02
    assert np.sqrt((err ** 2).mean()) < 0.1 * np.sqrt(((bias - bias.mean(axis=0)) ** 2).mean())
