"""The simple things every accuracy figure is measured beside: plain least squares on the window's means, RME with
the authors' range noise rule (their public code's sigma_lik = max(0.25 x the joint's range, 0.1 Nm)), and streaming
RME triggered by Algorithm 1 as printed instead of the model of what changed."""
from __future__ import annotations

import time

import numpy as np

import vi
from dynamics import Robot, theta_of
from detector import DetectorSettings
from rme import RME, Estimate, RMESettings

RIDGE = 1e-6    # relative to trace(Y^T Y): keeps phi finite where rz is not seen (a level pose), pulls it to 0


class LeastSquares:
    """theta from mean tau (n,) = mean Y (n, 4) phi, a tiny ridge; no prior, no uncertainty (std NaN)."""

    def __init__(self, robot: Robot | None = None):
        self.robot = Robot.panda() if robot is None else robot

    def estimate(self, q, tau_ext, baseline=None, referred=None) -> Estimate:
        start = time.perf_counter()
        Y = self.robot.payload_regressor(np.asarray(q, dtype=float)).mean(axis=0)        # (n, 4)
        t = np.asarray(tau_ext, dtype=float).mean(axis=0) - (0.0 if baseline is None else
                                                              np.atleast_2d(np.asarray(baseline, float)).mean(axis=0))
        G = Y.T @ Y
        phi = np.linalg.solve(G + RIDGE * np.trace(G) * np.eye(4), Y.T @ t)
        theta = theta_of(phi) if phi[0] > 0 else np.r_[phi[0], 0.0, 0.0, 0.0]
        nan = np.full(4, np.nan)
        return Estimate(theta, nan, np.full((4, 4), np.nan), np.zeros(4), np.zeros(4, bool),
                        time.perf_counter() - start, 0, True)


def range_rule(robot: Robot | None = None, seed: int = 0) -> RME:
    """RME whose likelihood takes the authors' range rule for its noise (VISettings(noise_rule="range"))."""
    return RME(robot, settings=RMESettings(vi=vi.VISettings(noise_rule="range")), rng=np.random.default_rng(seed))


def methods(robot: Robot | None = None, seed: int = 0, calibration=None) -> dict:
    """{name: estimator with .estimate(q, tau, baseline=..., referred=...)}: RME (calibrated if given) and the two
    baselines."""
    return {"RME": RME(robot, rng=np.random.default_rng(seed), calibration=calibration),
            "range rule": range_rule(robot, seed), "least squares": LeastSquares(robot)}


class Algorithm1RME(RME):
    """Streaming RME whose estimates Algorithm 1 as printed fires (App. A: its 230 ms checks, the raw ||tau_ext||^2
    test, a vertical force), each window estimated and applied if plausible: the paper's pipeline, the baseline of
    `python sim.py reliability --estimator experiments.baselines:Algorithm1RME`."""

    def __init__(self, robot: Robot | None = None, rng=None, **kwargs):
        settings = RMESettings(detector=DetectorSettings())
        super().__init__(robot, rng=rng, settings=settings, **kwargs)
