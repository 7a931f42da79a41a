"""Simulated episodes built on the runner: logs as a robot records them, the windows RME sees after a load change,
detector episodes, and excitation logs with chosen hidden physical effects (for the diagnosis tool)."""
from __future__ import annotations

import dataclasses

import numpy as np

from cpic import JointHold
from detector import Detector, DetectorSettings
from diagnosis.excite import GAZ_FC, GAZ_FV, ExciteConfig, Tracker, multisine
from dynamics import Q_READY, Robot
from experiments.runner import PayloadChange, Push, run
from sim import GAZ_FO, GAZ_P1, GAZ_P2, GAZ_P3, Plant, PlantConfig, Sample


def measure(plant: Plant, controller, seconds: float, first: Sample | None = None, q0=None, events=(),
            before_step=None) -> dict:
    """Run the loop and return what a robot logs after each 1 ms step: t (T,), q, dq, tau_J, tau_ext (T, n) and
    the true payload theta (T, 4); row k is the sample at time (k + 1) dt (the one the step produced)."""
    rec = run(plant, controller, seconds, events=events, q0=q0, first=first, before_step=before_step)
    last, out = rec.last, {}
    for k in ("t", "q", "dq", "tau_J", "tau_ext"):
        out[k] = np.concatenate([getattr(rec, k)[1:], [getattr(last, k)]])
    out["theta"] = np.concatenate([rec.theta[1:], [plant.theta]])
    return out


def save_log(path, log: dict):
    """Write a log in the format `python rme.py diagnose` reads: npz with t, q, dq, tau_J, tau_ext (paper sign)."""
    np.savez(path, **{k: np.asarray(v) for k, v in log.items()}, tau_ext_sign="paper")


def simulated_window(theta, rng, q0=None, delay=0.3, length=0.2, preset="realistic"):
    """A window as RME sees it: the plant holds q0 (JointHold), a payload theta (4,) is attached at 0.5 s, the window
    starts `delay` s later (about the detector's latency) and lasts `length` s. tau is tau_ext referred to its mean
    over the 100 ms before the attachment. Returns Y (T, 7, 4), tau (T, 7), q (T, 7)."""
    q0 = Q_READY if q0 is None else np.asarray(q0, dtype=float)
    plant = Plant(PlantConfig.preset(preset, rng), rng=rng)
    first = plant.reset(q0)
    plant.schedule_payload(0.5, theta[0], theta[1:])
    log = measure(plant, JointHold(plant.robot, q0), 0.5 + delay + length, first)
    t = log["t"]
    ref = log["tau_ext"][(t > 0.4) & (t <= 0.5)].mean(axis=0)
    sel = t > 0.5 + delay + 1e-9
    return plant.robot.payload_regressor(log["q"][sel]), log["tau_ext"][sel] - ref, log["q"][sel]


class DetectorProbe:
    """The detector alone in the loop, as an 'estimator' that never compensates: it records when it fires."""

    def __init__(self, robot: Robot, settings: DetectorSettings = DetectorSettings(), dt: float = 1e-3):
        self.robot, self.detector, self.dt = robot, Detector(settings, robot.n), dt
        self.fired, self.history, self._k = [], [], 0

    def update(self, q, dq, tau_ext):
        self._k += 1
        if self.detector.update(tau_ext, J=self.robot.jacobian(q)):
            self.fired.append((self._k - 1) * self.dt)
        return None


SOFT_HOLD = dict(kp=(100.0,) * 4 + (20.0,) * 3, kd=(20.0,) * 4 + (2.0,) * 3)   # a compliant joint hold (ours)


def detector_episode(seconds, rng, q0=None, payloads=(), pushes=(), motion=None, settings=DetectorSettings(),
                     soft=False):
    """The realistic plant under a joint hold at q0 (+ motion(t) (7,) if given), payload changes
    payloads = [(t, m, (rx, ry, rz))] and pushes = [(force (3,), start, duration)] on link7, the detector fed every
    sample. soft: compliant gains (SOFT_HOLD). Returns the detection times [s]."""
    q0 = Q_READY if q0 is None else np.asarray(q0, dtype=float)
    plant = Plant(PlantConfig.realistic(rng), rng=rng)
    hold = JointHold(plant.robot, q0, **(SOFT_HOLD if soft else {}))
    probe = DetectorProbe(plant.robot, settings, plant.dt)
    events = [PayloadChange(t, m, r) for t, m, r in payloads]
    events += [Push(start, force, duration) for force, start, duration in pushes]

    def move(k, s):
        hold.q0 = q0 + motion(s.t)

    run(plant, hold, seconds, estimator=probe, events=events, q0=q0, before_step=move if motion else None)
    return probe.fired


# --- excitation logs with hidden effects (the diagnosis tool's test data) ----------------------------------------
def sensing(realistic: bool = True) -> dict:
    """PlantConfig fields of the torque sensing: realistic = a real Panda's noise, quantisation and stale packets
    (panda_facts.md, as in PlantConfig.realistic); False = perfect sensors."""
    if not realistic:
        return {}
    return dict(tau_noise=(0.02,) * 4 + (0.01,) * 3, tau_step=(0.036,) * 4 + (0.006,) * 3, stale_prob=0.06)


# Hidden effects at realistic size: PlantConfig fields, and a payload (m, r, inertia) for the payload effects.
HIDDEN = {
    "viscous": dict(viscous=GAZ_FV),
    "coulomb": dict(coulomb=GAZ_FC, coulomb_width=0.05),       # narrower widths chatter at 1 kHz on the light wrist
    "sigmoid": dict(friction_sigmoid=(GAZ_P1, GAZ_P2, GAZ_P3)),
    "offset": dict(torque_offset=GAZ_FO),
    "rotor": dict(armature=(0.05,) * 4 + (0.02,) * 3),         # as PlantConfig.realistic (an order of magnitude)
    "tilt": dict(gravity_tilt=(0.010, -0.007)),                  # rad, a base 0.6 and 0.4 deg off level
    "payload": dict(payload=(0.7, (0.06, 0.0, 0.13), None)),     # Table 5 payload 3
    "rigid_payload": dict(payload=(1.1, (0.05, 0.02, 0.10), np.diag([0.0017, 0.0042, 0.0042]))),  # ~0.2x0.1x0.1 m box
}


def plant_config(hidden=(), realistic_sensing: bool = True) -> tuple:
    """(PlantConfig with exactly the named hidden effects + the sensing, payload or None)."""
    fields, payload = sensing(realistic_sensing), None
    for name in hidden:
        if name not in HIDDEN:
            raise ValueError(f"hidden: expected names from {sorted(HIDDEN)}, found {name!r}")
        extra = dict(HIDDEN[name])
        payload = extra.pop("payload", payload)
        fields.update(extra)
    return dataclasses.replace(PlantConfig.ideal(), **fields), payload


def make_plant(config: PlantConfig, rng: np.random.Generator, view: bool = False) -> Plant:
    """The plant for record_log: config without its stale packets (record_log adds them to the log afterwards)."""
    plant = Plant(dataclasses.replace(config, stale_prob=0.0), rng=rng)
    if view:
        plant.open_viewer()
    return plant


def record_log(config: PlantConfig, seconds: float, rng: np.random.Generator, excite: ExciteConfig = ExciteConfig(),
               payload=None, view: bool = False, plant: Plant | None = None) -> dict:
    """Drive the plant along a multi-sine with the Tracker and keep `seconds` of it after excite.settle seconds (the
    start-up transient: hidden effects the nominal tracker does not know pull the arm off the reference at first).
    Returns t, q, dq, tau_J, tau_ext (paper sign) (T, 7), theta (T, 4), t from 0, as a real robot logs them:

    - row k pairs q at t_k with the torque of the step from t_k to t_k+1 (a Sample at t_k+1 reports the torque of
      the step that just ended: one sample after the state it acted on, dG/dt x 1 ms ~ 0.01 Nm of error otherwise)
      and with dq at the step's middle, (dq_k + dq_k+1) / 2, so that central differences of dq give that step's
      acceleration (the plant's velocity changes in steps; without this, ddq lags by half a sample);
    - stale rows (probability config.stale_prob) repeat the previous row exactly, as dropped packets do.
    payload: (m, r, inertia) attached from the start, or None. plant: reuse a make_plant(config) plant (the same
    robot, sensor bias included)."""
    plant = plant if plant is not None else make_plant(config, rng, view)
    total = seconds + excite.settle
    t = plant.dt * np.arange(int(round(total / plant.dt)) + 2)
    q_d, dq_d, ddq_d = multisine(t, excite, rng)
    lo, hi = plant.model.jnt_range.T
    if np.any(q_d < lo) or np.any(q_d > hi):
        raise ValueError(f"excite: the reference leaves the joint limits (speed {excite.speed} rad/s, freq_scale "
                         f"{excite.freq_scale}); expected a smaller speed / freq_scale ratio")
    plant.set_payload(*(payload if payload is not None else (0.0, (0.0, 0.0, 0.0), None)))
    first = plant.reset(q_d[0], dq_d[0])
    log = measure(plant, Tracker(plant.robot, t, q_d, dq_d, ddq_d, excite), total, first)
    state = {k: np.concatenate([[getattr(first, k)], log[k]]) for k in ("t", "q", "dq")}
    state = {k: v[:-1] if k != "dq" else 0.5 * (v[:-1] + v[1:]) for k, v in state.items()}
    out = dict(state, tau_J=log["tau_J"], tau_ext=log["tau_ext"], theta=log["theta"])
    stale = np.flatnonzero(rng.random(len(out["t"])) < config.stale_prob)
    for i in stale[stale > 0]:                         # in order, so runs of stale rows repeat the same packet
        for k in ("q", "dq", "tau_J", "tau_ext"):
            out[k][i] = out[k][i - 1]
    keep = out["t"] > excite.settle - 1e-9
    out = {k: v[keep] for k, v in out.items()}
    out["t"] = out["t"] - out["t"][0]
    return out
