"""Exciting logs from the simulated Panda for model diagnosis (issue 6): a smooth multi-sine joint trajectory tracked by
computed torque on the nominal model (Eq. 1) + PD, a plant with chosen hidden effects, realistic torque sensing."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

import sim
from dynamics import Robot
from sim import GAZ_FO, GAZ_P1, GAZ_P2, GAZ_P3, Plant, PlantConfig

# Gaz et al. 2019, supplementary: linear friction model tau_f = fv dq + fc sign(dq) + fo (panda_facts.md)
GAZ_FV = (0.0665, 0.1987, 0.0399, 0.2257, 0.1023, -0.0132, 0.0638)    # Nm s/rad
GAZ_FC = (0.2450, 0.1523, 0.1827, 0.3591, 0.2669, 0.1658, 0.2109)     # Nm


@dataclass(frozen=True)
class ExciteConfig:
    """The multi-sine reference q_d(t) = center + sum_i (v / (K w_ij)) sin(w_ij t + phase_ij) and its tracking gains."""
    center: tuple = (0.0, -0.2, 0.0, -1.9, 0.0, 1.9, 0.8)   # rad, >= 1.1 rad from every limit (panda_facts.md)
    freqs: tuple = (0.13, 0.29, 0.47, 0.71)   # Hz, components (x (1 + 0.07 j) on joint j so joints decorrelate)
    speed: float = 1.0                         # rad/s, peak joint speed (about half the Panda's 2.2 rad/s limits)
    freq_scale: float = 1.0                    # > 1: faster oscillations, larger accelerations
    kp: float = 400.0                          # 1/s^2, computed-torque stiffness (20 rad/s closed-loop bandwidth)
    kd: float = 40.0                           # 1/s, critical damping for kp
    settle: float = 0.5                        # s, dropped from the start (5 time constants of the tracking loop)


# slow sweeps: the payload's own motion torques stay below ~0.005 Nm, so a static payload model (Eqs. 4-5) fits them
QUASI_STATIC = ExciteConfig(speed=0.1, freq_scale=0.05)


def multisine(t, config: ExciteConfig, rng: np.random.Generator):
    """q_d, dq_d, ddq_d (T, n) at times t (T,); phases drawn from rng."""
    t = np.asarray(t, dtype=float)[:, None, None]
    n, K = len(config.center), len(config.freqs)
    w = 2 * np.pi * config.freq_scale * np.outer(1 + 0.07 * np.arange(n), config.freqs)      # (n, K)
    phase = rng.uniform(0, 2 * np.pi, size=(n, K))
    amp = config.speed / K / w                                                              # (n, K)
    arg = w * t + phase                                                                     # (T, n, K)
    q = np.asarray(config.center) + (amp * np.sin(arg)).sum(-1)
    return q, (amp * w * np.cos(arg)).sum(-1), -(amp * w ** 2 * np.sin(arg)).sum(-1)


class Tracker:
    """Computed torque on the nominal model: tau = M(q) (ddq_d + kp e + kd de) + C dq + G, on the sensed sample."""

    def __init__(self, robot: Robot, t, q_d, dq_d, ddq_d, config: ExciteConfig):
        self.robot, self.t0, self.dt = robot, t[0], t[1] - t[0]
        self.ref, self.config = (q_d, dq_d, ddq_d), config

    def __call__(self, s) -> np.ndarray:
        k = min(int(round((s.t - self.t0) / self.dt)), len(self.ref[0]) - 1)
        q_d, dq_d, ddq_d = (r[k] for r in self.ref)
        _, M, b = self.robot.terms(s.q, s.dq)
        return M @ (ddq_d + self.config.kp * (q_d - s.q) + self.config.kd * (dq_d - s.dq)) + b


def sensing(realistic: bool = True) -> dict:
    """PlantConfig fields of the torque sensing: realistic = a real Panda's noise, quantisation and stale packets
    (panda_facts.md, as in PlantConfig.realistic); False = perfect sensors."""
    if not realistic:
        return {}
    return dict(tau_noise=(0.02,) * 4 + (0.01,) * 3, tau_step=(0.036,) * 4 + (0.006,) * 3, stale_prob=0.06)


# Hidden effects at realistic size: PlantConfig fields, and a payload (m, r, inertia) for the payload effects.
HIDDEN = {
    "viscous": dict(viscous=GAZ_FV),
    "coulomb": dict(coulomb=GAZ_FC, coulomb_width=0.05),     # the plant's default 0.01 rad/s makes its explicit
                                                               # 1 kHz friction chatter on the light wrist joints
    "sigmoid": dict(friction_sigmoid=(GAZ_P1, GAZ_P2, GAZ_P3)),
    "offset": dict(torque_offset=GAZ_FO),
    "rotor": dict(armature=(0.05,) * 4 + (0.02,) * 3),       # as PlantConfig.realistic (an order of magnitude)
    "tilt": dict(gravity_tilt=(0.010, -0.007)),                # rad, a base 0.6 and 0.4 deg off level
    "payload": dict(payload=(0.7, (0.06, 0.0, 0.13), None)),   # Table 5 payload 3
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
    log = sim.record(plant, Tracker(plant.robot, t, q_d, dq_d, ddq_d, excite), total, first)
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


def payload_lstsq(robot: Robot, q, tau_ext) -> np.ndarray:
    """theta = (m, r) (4,) from the least-squares phi of tau_ext (T, n) ~ payload_regressor(q) phi (paper Eqs. 4-5)."""
    Y = robot.payload_regressor(q).reshape(-1, 4)
    phi = np.linalg.lstsq(Y, np.asarray(tau_ext).reshape(-1), rcond=None)[0]
    return np.concatenate([[phi[0]], phi[1:] / phi[0]])


def demo(args):
    """`python sim.py hidden-effect`: a plant hiding Gaz friction and joint torque offsets (panda_facts.md) records a
    12 s multi-sine; compare -> diagnose -> add -> compare; then a 0.9 kg payload (Table 5) in a slow sweep is
    estimated by least squares from tau_ext with and without model.correction (issue item 7).
    args: seed, preset ("realistic": realistic torque sensing; "ideal": perfect sensors), plot, json, view."""
    import json

    from diagnose import _jsonable, plot, run
    from logs import prepare
    rng = np.random.default_rng(args.seed)
    hidden = ("sigmoid", "offset")
    config, _ = plant_config(hidden, realistic_sensing=args.preset == "realistic")
    plant = make_plant(config, rng, args.view)
    log = prepare(record_log(config, 12.0, rng, plant=plant), source="simulated")
    out = run(log, add=["auto"], robot=plant.robot)
    theta = np.array([0.9, 0.05, -0.03, 0.13])           # Table 5 payload 4
    sweep = prepare(record_log(config, 5.0, rng, QUASI_STATIC, payload=(theta[0], theta[1:], None), plant=plant))
    fix = out["added"].correction(sweep.q, sweep.dq, sweep.ddq)
    before, after = payload_lstsq(plant.robot, sweep.q, sweep.tau_ext), payload_lstsq(plant.robot, sweep.q,
                                                                                      sweep.tau_ext - fix)
    if args.plot:
        plot(args.plot, out)
    if args.json:
        js = dict(out["json"], hidden=list(hidden), preset=args.preset,
                  payload={"true": theta, "uncorrected": before, "corrected": after})
        print(json.dumps(_jsonable(js)))
        return js
    before_rms, after_rms = out["before"].rms, out["after"].rms
    print(f"hidden-effect demo ({args.preset} sensing, seed {args.seed}): the plant hides Gaz sigmoid friction and "
          "joint torque offsets (Gaz et al. 2019 values, panda_facts.md) that the nominal model lacks\n")
    print(out["text"])
    print("\nthe error fell (RMS per joint [Nm], nominal -> with the selected effects):")
    for j in range(len(before_rms)):
        ratio = before_rms[j] / max(after_rms[j], 1e-9)
        print(f"  J{j + 1}  {before_rms[j]:.3f} -> {after_rms[j]:.3f}  ({ratio:.0f}x)")
    print(f"\nbetter estimates (item 7): payload theta = (m, rx, ry, rz) = {theta} held in a 5 s slow sweep, "
          "least squares on tau_ext ~ payload_regressor(q) phi")
    Y = plant.robot.payload_regressor(sweep.q)
    for name, est in (("tau_ext", before), ("tau_ext - model.correction", after)):
        err = est - theta
        torque = np.sqrt(np.mean((Y @ (np.r_[est[0], est[0] * est[1:]] - np.r_[theta[0], theta[0] * theta[1:]])) ** 2))
        print(f"  {name:27s} m = {est[0]:.3f} kg, r = ({est[1]:.3f}, {est[2]:.3f}, {est[3]:.3f}) m;  error: "
              f"{abs(err[0]):.3f} kg, {1000 * np.linalg.norm(err[1:]):.1f} mm, payload torque {torque:.4f} Nm RMS")
    return out
