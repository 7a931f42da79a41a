"""What several test files share: the repository's folder, RME streaming on the simulated plant held by CPIC
(hold, SYNC, SyncRME), the mass tolerance, a sensor offset drawn over the poses, a 3-joint planar arm's MJCF."""
import os

import numpy as np

from cpic import CPIC, Attractor
from dynamics import Q_READY
from experiments.runner import run
from rme import RME, RMESettings
from sim import GAZ_P1, GAZ_P2, GAZ_P3, Plant, PlantConfig

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))    # the repository: sim.py, rme.py, README.md

SYNC = RMESettings(asynchronous=False)          # estimates applied on their sample: runs repeat exactly


def hold(seed, seconds, events, q0=Q_READY, settings=SYNC, preset="realistic"):
    """CPIC holds q0 on a plant (seeded), RME in the loop: the Record and the estimator."""
    rng = np.random.default_rng(seed)
    plant = Plant(PlantConfig.preset(preset, rng), rng=rng)
    est = RME(plant.robot, settings=settings, rng=np.random.default_rng(seed + 1))
    rec = run(plant, CPIC(plant.robot, Attractor(*plant.robot.ee_pose(q0))), seconds, est, events, q0=q0)
    return rec, est


class SyncRME(RME):
    """RME with SYNC settings, built as the benchmarks build an estimator (robot, rng=...): its runs repeat exactly."""

    def __init__(self, robot, rng=None):
        super().__init__(robot, settings=SYNC, rng=rng)


def sensor_bias(rng, sigma, length, features=400, n=7):
    """A pose-dependent sensor offset b(q) (n,) [Nm] of an n-joint arm drawn from a Gaussian process of std sigma
    (n,) and squared-exponential length `length` [rad] in joint space, by random Fourier features (Rahimi and Recht
    2007): an independent construction of the covariance the model assumes."""
    w = rng.normal(0, 1 / length, (n, features, n))
    phase = rng.uniform(0, 2 * np.pi, (n, features))
    return lambda q: np.asarray(sigma) * np.sqrt(2 / features) * np.cos(w @ q + phase).sum(axis=1)


def gaz_friction(dq):
    """Gaz et al. 2019's identified sigmoid friction (n,) [Nm] at joint speeds dq (n,), along the motion (the plant's,
    sim.py; in tau_ext, the paper's sign, it is -gaz_friction(dq)): an independent statement of what a moving joint
    leaves in tau_ext."""
    p1, p2, p3 = (np.array(p) for p in (GAZ_P1, GAZ_P2, GAZ_P3))
    return p1 / (1 + np.exp(-p2 * (dq + p3))) - p1 / (1 + np.exp(-p2 * p3))


def within(m_hat, m):
    """A mass estimate m_hat within 10 % of m, or 50 g of a light m."""
    return abs(m_hat - m) <= max(0.1 * m, 0.05)


# a 3-joint planar arm (hinges about y), its tip a site
THREE_LINK = """
<mujoco><compiler angle="radian"/><option gravity="0 0 -9.81"/>
  <worldbody><body name="l1"><joint name="j1" type="hinge" axis="0 1 0"/>
    <inertial pos="0.2 0 0" mass="2" diaginertia="0.01 0.01 0.01"/>
    <body name="l2" pos="0.4 0 0"><joint name="j2" type="hinge" axis="0 1 0"/>
      <inertial pos="0.15 0 0" mass="1" diaginertia="0.01 0.01 0.01"/>
      <body name="l3" pos="0.3 0 0"><joint name="j3" type="hinge" axis="0 1 0"/>
        <inertial pos="0.1 0 0" mass="0.5" diaginertia="0.01 0.01 0.01"/>
        <site name="tip" pos="0.2 0 0"/></body></body></body></worldbody></mujoco>"""
