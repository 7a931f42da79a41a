"""Quick start: RME on the simulated Panda. A payload arrives while CPIC holds a pose; RME estimates it from one
window (with and without the baseline), then runs in the 1 kHz loop, once per sample, and compensates it (Eq. 5).
Run from the repository: python examples/quickstart.py (about 10 s)."""
import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))   # the repository's modules

import numpy as np  # noqa: E402

from cpic import CPIC, Attractor  # noqa: E402
from dynamics import Q_READY  # noqa: E402
from experiments.runner import PayloadChange, run  # noqa: E402
from rme import RME  # noqa: E402
from sim import Plant, PlantConfig  # noqa: E402

THETA = (0.9, 0.05, -0.03, 0.13)             # m [kg], CoM rx, ry, rz [m] in the ee frame (Table 5, payload 4)

# 1. One window. Hold the ready pose; the payload arrives at 1.0 s; no estimator in the loop.
rng = np.random.default_rng(0)
plant = Plant(PlantConfig.realistic(rng), rng=rng)
ctrl = CPIC(plant.robot, Attractor(*plant.robot.ee_pose(Q_READY)))
rec = run(plant, ctrl, 2.5, events=[PayloadChange(1.0, THETA[0], THETA[1:])], q0=Q_READY)   # a Record, 1 kHz
before = rec.tau_ext[(rec.t >= 0.8) & (rec.t < 1.0)].mean(axis=0)   # (7,): tau_ext before the change
w = (rec.t >= 2.2) & (rec.t < 2.4)                                   # 200 ms after it, the arm settled
est = RME(plant.robot, rng=np.random.default_rng(1))
for baseline in (None, before):
    e = est.estimate(rec.q[w], rec.tau_ext[w], baseline=baseline)    # q, tau_ext (200, 7), paper sign
    print(f"window, baseline {'given' if baseline is not None else 'none '}: m = {e.mean[0]:.3f} +- "
          f"{2 * e.std[0]:.3f} kg, r = {np.round(e.mean[1:], 3)} m, observed {e.observed}  (truth {THETA})")

# 2. Streaming: RME.update once per 1 ms sample; it detects the change, estimates, and returns the compensation.
rng = np.random.default_rng(0)
plant = Plant(PlantConfig.realistic(rng), rng=rng)
ctrl = CPIC(plant.robot, Attractor(*plant.robot.ee_pose(Q_READY)))
est = RME(plant.robot, rng=np.random.default_rng(1))
plant.schedule_payload(1.0, THETA[0], THETA[1:])
s = plant.reset(Q_READY)
for k in range(2500):
    tau_comp = est.update(s.q, s.dq, s.tau_ext)          # (7,): -J^T [F_hat; r_hat x F_hat]
    tau, info = ctrl.step(s.q, s.dq, tau_comp, s.tau_ext)  # CPIC adds it after its QP
    s = plant.step(tau)
for e in est.history:                                    # every estimate: time, kind, applied, why
    print(f"stream: {e.t:.3f} s {e.kind}: m = {e.mean[0]:.3f} kg, r = {np.round(e.mean[1:], 3)} m, "
          f"{'applied at %.3f s' % e.applied if e.accepted else 'refused'} {e.reason}")
print(f"compensated at the end: theta_hat = {np.round(est.theta, 3)}")
