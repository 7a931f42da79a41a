"""Tests of RME's calibrated uncertainty: 2-sigma coverage and sharpness on realistic simulated windows (and that
a sigma 2x too wide or too narrow would fail), a hidden correlated bias covered, which parameters a window observed,
the prior widened outside the network's training range, and weights files without that range."""
import numpy as np
import pytest

import nn_numpy as nn
import vi
from dynamics import Q_READY, Robot
from experiments.calibration import calibration_windows
from experiments.episodes import simulated_window
from rme import RME

ROBOT = Robot.panda()


@pytest.fixture(scope="module")
def calibration():
    """24 realistic windows (half at the ready pose, half at random poses), RME's estimates: errors and stds of
    m, rx, ry (the parameters every window observes)."""
    windows = calibration_windows(24, np.random.default_rng(1))
    est = RME(rng=np.random.default_rng(0))
    E = [est.estimate(w["q"], w["tau"], referred=True) for w in windows]
    return (np.array([e.mean - w["theta"] for e, w in zip(E, windows)])[:, :3], np.array([e.std for e in E])[:, :3])


@pytest.mark.slow
def test_two_sigma_intervals_cover_90_to_99_percent_and_are_sharp(calibration):
    err, std = calibration
    assert 0.90 <= np.mean(np.abs(err) < 2 * std) <= 0.99
    assert np.all(std.mean(axis=0) <= 2.0 * np.sqrt(np.mean(err**2, axis=0)))     # mean sigma <= 2 x RMS error


@pytest.mark.slow
@pytest.mark.parametrize("scale", [0.5, 2.0])
def test_a_sigma_twice_too_narrow_or_too_wide_would_fail_the_band(calibration, scale):
    err, std = calibration
    assert not 0.90 <= np.mean(np.abs(err) < 2 * scale * std) <= 0.99


def test_window_with_a_hidden_correlated_bias_is_covered():
    """A realistic window plus a per-joint error that does not average down over the window (an offset and a
    drift of up to 0.05 and 0.1 Nm, as friction or a changing sensor bias leave): the truth stays inside 2 sigma."""
    rng = np.random.default_rng(3)
    theta = np.array([1.2, 0.04, -0.03, 0.12])
    Y, tau, _ = simulated_window(theta, rng, Q_READY + 0.3 * rng.uniform(-1, 1, 7))
    t = np.linspace(-1, 1, len(tau))[:, None]
    tau = tau + rng.uniform(-0.05, 0.05, 7) + t * rng.uniform(-0.1, 0.1, 7)
    p = vi.fit(Y, tau, theta + np.array([0.3, 0.01, -0.01, 0.03]), vi.VISettings(), rng)
    assert np.all(np.abs(p.mean - theta)[:3] < 2 * p.marginal_std[:3])
    naive = vi.fit(Y, tau, theta, vi.VISettings(load_share=0.0, slow_gain=0.0, offset_std=0.0), rng)
    assert np.any(np.abs(naive.mean - theta)[:3] > 2 * naive.marginal_std[:3])   # unmodelled, it would not be


def test_rz_is_not_observed_at_the_ready_pose_and_is_after_a_wrist_turn():
    rng = np.random.default_rng(4)
    theta = np.array([0.9, 0.03, 0.01, 0.13])
    _, tau_a, q_a = simulated_window(theta, rng, Q_READY)
    _, tau_b, q_b = simulated_window(theta, rng, Q_READY + np.array([0, 0, 0, 0, 0, 0.6, 0]))
    est = RME(ROBOT, rng=np.random.default_rng(0))
    one, two = est.estimate(q_a, tau_a, referred=True), est.estimate([q_a, q_b], [tau_a, tau_b], referred=True)
    assert one.observed.tolist() == [True, True, True, False]
    assert two.observed.tolist() == [True, True, True, True]
    assert abs(two.mean[3] - theta[3]) < 2 * two.std[3]


def test_prior_widens_where_the_stored_range_excludes_the_prediction():
    net = nn.MismatchNet.load()
    sp = np.array(vi.VISettings().sigma_prior)
    inside = np.array([1.0, 0.0, 0.0, 0.1])
    np.testing.assert_array_equal(net.prior_std(inside, sp), sp)
    other = nn.MismatchNet(net.params, net.stats, net.meta, theta_range=((0.1, -0.1, -0.1, 0.15), (2.0, 0.1, 0.1, 0.35)))
    wide = other.prior_std(inside, sp)                 # rz = 0.1 lies below this range's 0.15
    np.testing.assert_array_equal(wide[:3], sp[:3])
    assert wide[3] == pytest.approx(0.1)               # the range's half-width
    tilted = net.prior_std(inside, sp, ROBOT.ee_pose(Q_READY + np.array([0, 0, 0, 0, 0, 0.6, 0]))[1])
    assert tilted[1] > sp[1] and tilted[3] > sp[3]     # along gravity: the network is unsure there too


def test_prior_keeps_the_papers_width_along_gravity_at_any_orientation():
    """At the ready pose (ee z vertical) the prior is the paper's; turned, the diagonal prior's precision along gravity
    g, sum_i g_i^2 / sp_i^2, stays <= 1 / sp_rz^2 (the network does not see r along g); no r std falls below the
    across-gravity part sp_perp sqrt(1 - g_i^2); m's is untouched (random orientations R)."""
    net, sp = nn.MismatchNet.load(), np.array(vi.VISettings().sigma_prior)
    inside = np.array([1.0, 0.0, 0.0, 0.1])
    np.testing.assert_allclose(net.prior_std(inside, sp, ROBOT.ee_pose(Q_READY)[1]), sp, rtol=1e-9)
    rng = np.random.default_rng(6)
    for _ in range(50):
        R = np.linalg.qr(rng.standard_normal((3, 3)))[0]
        out, g = net.prior_std(inside, sp, R), R[2]
        assert out[0] == sp[0] and np.all(out[1:] >= sp[1:3].max() * np.sqrt(1 - g**2) - 1e-12)
        assert np.sum(g**2 / out[1:] ** 2) <= 1 / sp[3] ** 2 * (1 + 1e-9)


def test_weights_file_without_the_range_still_loads_with_the_default_range(tmp_path):
    with np.load(nn.WEIGHTS) as f:
        arrays = {k: f[k] for k in f.files if not k.startswith("range.")}
    np.savez(tmp_path / "old.npz", **arrays)
    old, new = nn.MismatchNet.load(tmp_path / "old.npz"), nn.MismatchNet.load()
    np.testing.assert_array_equal(old.theta_range, nn.DEFAULT_RANGE)
    x = new.stats["x_mean"] + new.stats["x_std"] * np.random.default_rng(5).standard_normal((20, 6))
    np.testing.assert_array_equal(old.predict(x), new.predict(x))
