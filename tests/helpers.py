"""What several test files share: the repository's folder, RME streaming on the simulated plant held by CPIC
(hold, SYNC), the randomised episodes regression cases were found in (found_episode), a synthetic tau_ext stream at
the ready pose, the mass tolerance, a 3-joint planar arm's MJCF."""
import os

import numpy as np

from cpic import CPIC, Attractor
from dynamics import Q_READY, Robot
from experiments.runner import run
from rme import RME, RMESettings
from sim import Plant, PlantConfig

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


def within(m_hat, m):
    """A mass estimate m_hat within 10 % of m, or 50 g of a light m."""
    return abs(m_hat - m) <= max(0.1 * m, 0.05)


def found_episode(seed, loads=True, settings=None):
    """The randomised 7 s episode of `seed` in which a regression case was found: CPIC holds a random pose of the
    realistic plant, up to 3 loads (0.1-3 kg) attached, changed or removed 0.2-2 s apart from 1-2.5 s on (load
    episodes), 5-60 N pushes of 0.1-2 s at the flange (a quarter vertical), RME (settings, default RMESettings()) in
    the loop. A dict: the Record, the RME, the drawn `changes` [(t, m, r)] and `pushes` [(t, force, duration)], and
    per change its `m`, the compensated `m_hat` at the next change (or the end), `latency_ms` to the first estimate
    applied after it and `right_ms` to the first compensation within tolerance (None if none)."""
    from experiments.runner import PayloadChange, Push
    from nn_train import DataConfig, random_pose
    rng = np.random.default_rng(seed)
    plant = Plant(PlantConfig.realistic(rng), rng=rng)
    q0 = random_pose(plant.robot, rng, DataConfig())
    changes, pushes = _found_changes(rng, loads), []
    for _ in range(rng.integers(0 if loads else 1, 4)):
        direction = np.array([0.0, 0.0, rng.choice([-1.0, 1.0])]) if rng.random() < 0.25 else rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        duration = rng.uniform(0.1, 2.0)
        start = (changes[rng.integers(len(changes))][0] + rng.uniform(-0.3, 0.3)
                 if changes and rng.random() < 0.3 else rng.uniform(0.5, 6.0))
        pushes.append((float(np.clip(start, 0.5, 4.0 - duration)), rng.uniform(5.0, 60.0) * direction, duration))
    est = RME(plant.robot, rng=np.random.default_rng(seed + 1), **({} if settings is None else {"settings": settings}))
    events = [PayloadChange(t, m, r) for t, m, r in changes]
    events += [Push(t, f, d, body="link7", offset=(0.0, 0.0, 0.107)) for t, f, d in sorted(pushes, key=lambda p: p[0])]
    rec = run(plant, CPIC(plant.robot, Attractor(*plant.robot.ee_pose(q0))), 7.0, est, events, q0=q0)
    out = []
    for (t, m, _), t_next in zip(changes, [c[0] for c in changes[1:]] + [7.0]):
        applied = [e.applied for e in est.history if t <= e.t < t_next and e.accepted and e.applied is not None]
        right = np.flatnonzero((rec.t >= t) & (rec.t < t_next) & (np.abs(rec.theta_hat[:, 0] - m) <= max(0.1 * m, 0.05)))
        out.append(dict(m=m, m_hat=float(rec.theta_hat[rec.at(t_next) - 1, 0]),
                        latency_ms=1e3 * (applied[0] - t) if applied else None,
                        right_ms=1e3 * (rec.t[right[0]] - t) if len(right) else None))
    return dict(rec=rec, est=est, changes=changes, pushes=pushes, scored=out,
                final_error_mm=float(1e3 * rec.ee_error[-1]))


def _found_changes(rng, loads):
    changes, t, m = [], rng.uniform(1.0, 2.5), 0.0
    for _ in range(rng.integers(1, 4) if loads else 0):
        if m > 0 and (t + 3.0 > 6.8 or rng.random() < 0.5):
            changes.append((t, 0.0, np.zeros(3)))
            m = 0.0
        else:
            m = rng.uniform(0.1, 3.0)
            changes.append((t, m, np.array([*rng.uniform(-0.15, 0.15, 2), rng.uniform(0.0, 0.15)])))
        t += rng.uniform(0.2, 2.0)
        if t > 4.0:
            break
    return changes


def synthetic_stream(settings, bias, seconds, load=None, t_load=0.0, move=None, drift=None, seed=8, expect=None):
    """A synthetic stream at the ready pose: tau_ext = bias (None: drawn, 0.1 Nm per joint) + noise, plus the payload
    `load` theta (4,) from t_load, plus from t0 a payload-shaped drift of `offset` [Nm] along the payload theta_d,
    ramped in over 0.1 s, if drift = (theta_d, offset, t0); joint j moving at w rad/s over [t0, t1) if move =
    (j, w, t0, t1); RME.expect_change(s) called at t if expect = (t, s). The RME after `seconds`."""
    from dynamics import phi_of
    robot, rng = Robot.panda(), np.random.default_rng(seed)
    est, q = RME(robot, settings=settings, rng=np.random.default_rng(seed + 1)), Q_READY.copy()
    bias = rng.normal(0.0, 0.1, robot.n) if bias is None else bias
    phi = None if load is None else phi_of(load)
    if drift is not None:
        d_phi = phi_of(drift[0])
        scale = drift[1] / np.linalg.norm(robot.payload_regressor(Q_READY) @ d_phi)
    for k in range(int(seconds * 1000)):
        t, dq = k / 1000, np.zeros(robot.n)
        if move is not None and move[2] <= t < move[3]:
            dq[move[0]] = move[1]
        q = q + dq * 1e-3
        Y = robot.payload_regressor(q)
        tau = bias + rng.normal(0.0, 0.005, robot.n)
        if phi is not None and t >= t_load:
            tau = tau + Y @ phi
        if drift is not None and t >= drift[2]:
            tau = tau + min(1.0, (t - drift[2]) / 0.1) * scale * (Y @ d_phi)
        if expect is not None and k == int(round(expect[0] * 1000)):
            est.expect_change(expect[1])
        est.update(q, dq + rng.normal(0.0, 1e-3, robot.n), tau)
    return est


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
