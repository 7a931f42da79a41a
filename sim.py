"""The MuJoCo Panda plant RME is tested on (paper Sec. 5 in simulation): 1 kHz torque control, a payload fixed at
the end-effector, human pushes, and what a real Franka reports (q, dq, tau_J, tau_ext) with realistic sensing.
`python sim.py --help` lists the demos and benchmarks (experiments/)."""
from __future__ import annotations

import dataclasses
import sys
from dataclasses import dataclass

import mujoco
import numpy as np

import checks
from dynamics import PANDA_XML, Q_READY, MomentumObserver, Robot, as_states, inertia_matrix

N = 7
PRESETS = ("realistic", "harsh", "noisy", "sticky", "slow-sensor")   # drawn plants (PlantConfig.preset), in the
#                                                                      order the benchmarks key their seeds by
BIG, SMALL = 4, 3                                 # joints 1-4 and 5-7 (panda_facts.md)


def _per_joint(big, small):
    return (big,) * BIG + (small,) * SMALL


# Gaz et al. 2019, supplementary: sigmoid friction tau_f(dq) = p1/(1+exp(-p2(dq+p3))) - p1/(1+exp(-p2 p3))
GAZ_P1 = (0.54615, 0.87224, 0.64068, 1.2794, 0.83904, 0.30301, 0.56489)         # Nm
GAZ_P2 = (5.1181, 9.0657, 10.136, 5.5903, 8.3469, 17.133, 10.336)               # s/rad
GAZ_P3 = (0.039533, 0.025882, -0.04607, 0.036194, 0.026226, -0.021047, 0.0035526)  # rad/s
GAZ_FO = (-0.1073, -0.1566, -0.0686, -0.2522, 0.0045, 0.0910, -0.0127)          # Nm, linear model's offsets


@dataclass(frozen=True)
class PlantConfig:
    """How the simulated robot differs from the nominal model and how its sensors read. Zeros = ideal."""
    # sensing (panda_facts.md "Joint torque sensing")
    tau_noise: tuple = (0.0,) * N          # Nm, std of white noise on tau_J
    tau_step: tuple = (0.0,) * N           # Nm, quantisation step of tau_J (0 = none)
    q_noise: float = 0.0                   # rad, std of white noise on q
    dq_noise: float = 0.0                  # rad/s, std of white noise on dq
    stale_prob: float = 0.0                # probability that a sample repeats the previous one
    bias_amp: tuple = (0.0,) * N           # Nm, amplitude of the slowly varying pose-dependent bias
    torque_offset: tuple = (0.0,) * N      # Nm, constant offset of the tau_J reading
    # the plant's physics beyond the nominal model
    mass_scale: tuple = (1.0,) * N         # link mass of the plant / nominal
    com_shift: tuple = ((0.0, 0.0, 0.0),) * N   # m, link CoM shift in the link frame
    friction_sigmoid: tuple | None = None  # (p1, p2, p3) each (7,): Gaz sigmoid friction
    viscous: tuple = (0.0,) * N            # Nm s/rad
    coulomb: tuple = (0.0,) * N            # Nm, smoothed: fc tanh(dq / coulomb_width)
    coulomb_width: float = 0.05            # rad/s (narrower chatters at 1 kHz on the light wrist joints)
    armature: tuple = (0.0,) * N           # kg m^2, rotor inertia seen at the joint
    gravity_tilt: tuple = (0.0, 0.0)       # rad, base tilted about world x then y
    # the external-torque estimate
    observer: str = "exact"                # "exact": model(q, dq, ddq) - tau_J; "momentum": momentum observer
    observer_gain: float = 100.0           # 1/s, momentum observer bandwidth

    def __post_init__(self):
        """Every field checked (checks.py); the bounds lie far beyond any arm's (torque noise, offsets, friction of
        tens of Nm, CoM shifts of half a metre; viscous from -0.1: Gaz et al. identify -0.0132 on joint 6);
        observer_gain up to 1/dt = 1000 1/s, where the discrete observer r_k = K (... - dt r_(k-1)) alternates."""
        for name, interval in (("tau_noise", "[0, 10]"), ("tau_step", "[0, 10]"), ("bias_amp", "[0, 10]"),
                               ("torque_offset", "[-10, 10]"), ("mass_scale", "(0, 10]"), ("viscous", "[-0.1, 100]"),
                               ("coulomb", "[0, 100]"), ("armature", "[0, 10]")):
            checks.array(f"config.{name}", getattr(self, name), (N,), interval)
        checks.array("config.com_shift", self.com_shift, (N, 3), "[-0.5, 0.5]", "m")
        None if self.friction_sigmoid is None else checks.array("config.friction_sigmoid", self.friction_sigmoid,
                                                                 (3, N), "[-1e3, 1e3]", "(p1 Nm, p2 s/rad, p3 rad/s)")
        for name, interval in (("q_noise", "[0, 0.1]"), ("dq_noise", "[0, 1]"), ("stale_prob", "[0, 1)"),
                               ("coulomb_width", "(0, 10]"), ("observer_gain", "(0, 1000]")):
            checks.number(f"config.{name}", getattr(self, name), interval)
        checks.array("config.gravity_tilt", self.gravity_tilt, (2,), "[-1.5708, 1.5708]", "rad")
        checks.choice("config.observer", self.observer, ("exact", "momentum"))

    @staticmethod
    def ideal() -> "PlantConfig":
        """The plant is the nominal model and its sensors are perfect: exact tests."""
        return PlantConfig()

    @staticmethod
    def preset(name: str, rng: np.random.Generator | None = None) -> "PlantConfig":
        """'ideal', or one drawn from rng: 'realistic', 'harsh', or the realistic plant with one part stressed,
        'noisy' (3 x its torque noise, 2 x its pose offset), 'sticky' (2 x Gaz friction) or 'slow-sensor' (a
        momentum observer of 25 1/s): the presets the demos and benchmarks offer."""
        if name == "ideal":
            return PlantConfig.ideal()
        if name not in PRESETS:
            raise ValueError(f"preset: expected one of {('ideal',) + PRESETS}, found {name!r}")
        if rng is None:
            raise ValueError(f"rng: the {name} preset draws its link errors from a np.random.Generator, found None")
        if name in ("realistic", "harsh"):
            return getattr(PlantConfig, name)(rng)
        c = PlantConfig.realistic(rng)
        p1, p2, p3 = c.friction_sigmoid
        stressed = {"noisy": dict(tau_noise=tuple(3.0 * x for x in c.tau_noise),
                                  bias_amp=tuple(2.0 * x for x in c.bias_amp)),
                    "sticky": dict(friction_sigmoid=(tuple(2.0 * x for x in p1), p2, p3)),
                    "slow-sensor": dict(observer_gain=25.0)}
        return dataclasses.replace(c, **stressed[name])

    @staticmethod
    def realistic(rng: np.random.Generator) -> "PlantConfig":
        """A plant and sensors like a real Panda's (panda_facts.md), link errors drawn from rng: masses within
        +-8 %, CoM shifts of 5-20 mm."""
        return _drawn(rng, mass=0.08, shift=(0.005, 0.02))

    @staticmethod
    def harsh(rng: np.random.Generator) -> "PlantConfig":
        """A plant the estimator was never tuned on, to check that what works on the realistic one is not tuned to
        it: twice the realistic torque noise and pose bias, 1.5 x Gaz friction, a momentum observer of 50 1/s (twice
        as slow), link masses within +-12 % and CoM shifts of 5-30 mm, drawn from rng in the realistic order."""
        c = _drawn(rng, mass=0.12, shift=(0.005, 0.03))
        p1, p2, p3 = c.friction_sigmoid
        return dataclasses.replace(c, tau_noise=tuple(2.0 * x for x in c.tau_noise),
                                   bias_amp=tuple(2.0 * x for x in c.bias_amp),
                                   friction_sigmoid=(tuple(1.5 * x for x in p1), p2, p3), observer_gain=50.0)


def _drawn(rng: np.random.Generator, mass: float, shift: tuple) -> PlantConfig:
    """The realistic plant with link masses within +-mass (relative) and CoM shifts of shift (lo, hi) [m] in random
    directions, drawn from rng."""
    direction = rng.normal(size=(N, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    com = direction * rng.uniform(*shift, size=(N, 1))
    return PlantConfig(
        tau_noise=_per_joint(0.02, 0.01),          # 0.005 quiescent, 0.03-0.09 while moving
        tau_step=_per_joint(0.036, 0.006),         # steps seen in a real 1 kHz log
        q_noise=1e-5, dq_noise=1e-3,
        stale_prob=0.06,                           # about 6 % stale repeats in a real log
        bias_amp=_per_joint(0.3, 0.1),             # a few tenths of a Nm, pose dependent
        torque_offset=GAZ_FO,
        mass_scale=tuple(1.0 + rng.uniform(-mass, mass, N)),
        com_shift=tuple(map(tuple, com)),
        friction_sigmoid=(GAZ_P1, GAZ_P2, GAZ_P3),
        armature=_per_joint(0.05, 0.02),           # assumption: rotor inertia order of magnitude
        observer="momentum")


@dataclass
class Sample:
    """What the robot reports at time t [s]: q, dq [rad, rad/s], tau_J and tau_ext [Nm] (7,) each."""
    t: float
    q: np.ndarray
    dq: np.ndarray
    tau_J: np.ndarray
    tau_ext: np.ndarray


@dataclass
class _Push:
    force: np.ndarray
    body: int
    offset: np.ndarray
    start: float
    stop: float


class Plant:
    """The simulated Panda at 1 kHz. step(tau) applies the joint torque tau for one time step and returns the
    Sample at the new time: tau_J is the torque the drives deliver (the command, clipped), read through the
    sensor model; tau_ext = (nominal M ddq + C dq + G) - tau_J in the paper's sign, or a momentum observer."""

    def __init__(self, config: PlantConfig | None = None, rng: np.random.Generator | None = None,
                 xml: str = PANDA_XML):
        self.config = config = PlantConfig.ideal() if config is None else checks.instance("config", config, PlantConfig)
        None if rng is None else checks.generator("rng", rng)
        if rng is None and _needs_rng(config):
            raise ValueError("rng: a np.random.Generator is needed for noisy sensors, found None")
        self.rng = rng
        self.robot = Robot.from_xml(xml, ee="ee")           # the nominal model
        self.model = m = mujoco.MjModel.from_xml_path(xml)  # the plant
        self.data = mujoco.MjData(m)
        self.dt = m.opt.timestep
        self.payload_body = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, "payload")
        self.payload_geom = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, "payload")
        m.body_sameframe[self.payload_body] = 0        # its CoM moves at run time: no compile-time shortcut
        m.geom_sameframe[self.payload_geom] = 0
        self._apply_config()
        self.tau_max = m.actuator_ctrlrange[:, 1].copy()
        # pose-dependent bias: sum of 3 slow sinusoids of q per joint (spatial period of a few rad)
        if any(config.bias_amp):
            self._bias_w = rng.normal(0.0, 0.6, size=(N, 3, N))
            self._bias_phase = rng.uniform(0, 2 * np.pi, size=(N, 3))
        self.theta = np.zeros(4)                      # current payload (m, r) in the ee frame
        self._events, self._pushes, self.viewer = [], [], None
        self.reset(Q_READY)

    def _apply_config(self):
        m, c = self.model, self.config
        links = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, f"link{i + 1}") for i in range(N)]
        for i, b in enumerate(links):
            m.body_mass[b] *= c.mass_scale[i]
            m.body_inertia[b] *= c.mass_scale[i]
            m.body_ipos[b] += np.asarray(c.com_shift[i])
        m.dof_armature[:] = c.armature
        ax, ay = c.gravity_tilt
        Rx = np.array([[1, 0, 0], [0, np.cos(ax), -np.sin(ax)], [0, np.sin(ax), np.cos(ax)]])
        Ry = np.array([[np.cos(ay), 0, np.sin(ay)], [0, 1, 0], [-np.sin(ay), 0, np.cos(ay)]])
        m.opt.gravity[:] = Ry @ Rx @ m.opt.gravity     # the robot's base is not level

    # --- set-up --------------------------------------------------------------------------------
    def reset(self, q0, dq0=None) -> Sample:
        """Put the arm at q0 (7,), at rest unless dq0 is given, with the drives holding it against gravity."""
        q0, _ = as_states("q0", q0, N, allow_window=False)
        dq0 = np.zeros(N) if dq0 is None else as_states("dq0", dq0, N, allow_window=False)[0][0]
        m, d = self.model, self.data
        mujoco.mj_resetData(m, d)
        d.qpos[:], d.qvel[:] = q0[0], dq0
        mujoco.mj_forward(m, d)
        tau = np.clip(d.qfrc_bias + self._friction(dq0), -self.tau_max, self.tau_max)   # holding torque
        self._last, self._observer = None, None
        return self._advance(tau, integrate=False)

    def set_payload(self, m, r=(0.0, 0.0, 0.0), inertia=None):
        """Fix a payload of mass m [kg] with CoM r (3,) [m] in the ee frame and, optionally, inertia (3, 3)
        about its CoM in the ee frame (default: a point mass). m = 0 removes the payload."""
        m, r, I = _check_payload(m, r, inertia)
        md, b = self.model, self.payload_body
        w, V = np.linalg.eigh(I)
        if np.linalg.det(V) < 0:
            V[:, 0] *= -1
        quat = np.empty(4)
        mujoco.mju_mat2Quat(quat, V.ravel())
        md.body_mass[b], md.body_ipos[b], md.body_inertia[b], md.body_iquat[b] = m, r, np.maximum(w, 0), quat
        md.geom_pos[self.payload_geom] = r
        md.geom_size[self.payload_geom, 0] = 0.02 + 0.02 * np.cbrt(m)
        md.geom_rgba[self.payload_geom, 3] = 1.0 if m > 0 else 0.0
        self.theta = np.array([m, *r])

    def schedule_payload(self, t, m, r=(0.0, 0.0, 0.0), inertia=None):
        """Change the payload at simulation time t [s] (m = 0 removes it); checked now, applied then."""
        t, (m, r, inertia) = checks.number("t", t, "[0, 1e6]", "s"), _check_payload(m, r, inertia)
        self._events.append((float(t), (m, r, inertia)))
        self._events.sort(key=lambda e: e[0])

    def push(self, force, body="link7", offset=(0.0, 0.0, 0.0), start=0.0, duration=0.5):
        """A human push: world force (3,) [N] at a point `offset` (body frame) of `body`, from start for duration [s]."""
        f = checks.array("force", force, (3,), "[-1e4, 1e4]", "N")
        if not isinstance(body, str) or (bid := mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_BODY, body)) < 0:
            raise ValueError(f"body: expected the name of a body of the plant, found {body!r}")   # (None crashes)
        o = checks.array("offset", offset, (3,), "[-2, 2]", "m")
        start, duration = (checks.number(k, v, "[0, 1e6]", "s") for k, v in (("start", start), ("duration", duration)))
        self._pushes.append(_Push(f, bid, o, start, start + duration))

    # --- stepping ------------------------------------------------------------------------------
    @property
    def t(self) -> float:
        return self.data.time

    def step(self, tau) -> Sample:
        """Apply joint torque tau (7,) [Nm] (clipped to 87/12 Nm) for one time step; the Sample at the new time."""
        if (a := checks.real_array(tau)) is None or a.shape != (N,):      # bool, complex: refused, never cast
            raise ValueError(f"tau: expected shape ({N},) of real values, found "
                             f"{checks.kind(tau) if a is None else a.shape}")
        tau = a.astype(float)
        if not np.all(np.isfinite(tau)):
            raise ValueError(f"tau: expected finite torques, found {tau.tolist()} (a real drive would fault)")
        return self._advance(np.clip(tau, -self.tau_max, self.tau_max), integrate=True)

    def _advance(self, tau, integrate):
        m, d = self.model, self.data
        d.ctrl[:] = tau
        if integrate:
            mujoco.mj_step2(m, d)                      # acceleration at t under tau, then integrate to t + dt
        while self._events and self._events[0][0] <= d.time + 1e-9:
            m_, r_, inertia = self._events.pop(0)[1]
            self.set_payload(m_, r_, inertia)
        mujoco.mj_step1(m, d)                          # position and velocity stages at the new time
        d.qfrc_applied[:] = -self._friction(d.qvel) + self._push_forces()
        mujoco.mj_forwardSkip(m, d, mujoco.mjtStage.mjSTAGE_VEL, 1)   # ddq at the new time under tau
        s = self._measure(tau)
        if self.viewer is not None:
            self._sync_viewer()
        return s

    def _friction(self, dq):
        c = self.config
        tf = np.asarray(c.viscous) * dq + np.asarray(c.coulomb) * np.tanh(dq / c.coulomb_width)
        if c.friction_sigmoid is not None:
            p1, p2, p3 = (np.asarray(p) for p in c.friction_sigmoid)
            # 1 / (1 + exp(-x)) = (1 + tanh(x / 2)) / 2, without overflow
            tf = tf + 0.5 * p1 * (np.tanh(0.5 * p2 * (dq + p3)) - np.tanh(0.5 * p2 * p3))
        return tf

    def _push_forces(self):
        qfrc = np.zeros(N)
        for p in self._pushes:
            if p.start <= self.data.time < p.stop:
                x = self.data.xpos[p.body] + self.data.xmat[p.body].reshape(3, 3) @ p.offset
                mujoco.mj_applyFT(self.model, self.data, p.force, np.zeros(3), x, p.body, qfrc)
        return qfrc

    def pose_bias(self, q):
        """The slowly varying pose-dependent torque bias (7,) [Nm] the realistic sensor adds."""
        if not any(self.config.bias_amp):
            return np.zeros(N)
        s = np.sin(self._bias_w @ q + self._bias_phase)        # (7, 3)
        return np.asarray(self.config.bias_amp) * s.sum(axis=1) / np.sqrt(1.5)

    def _measure(self, tau):
        c, d, rng = self.config, self.data, self.rng
        if self._last is not None and c.stale_prob > 0 and rng.random() < c.stale_prob:
            s = dataclasses.replace(self._last, t=d.time)      # a dropped packet: the last reading again
            self._last = s
            return s
        q, dq = d.qpos.copy(), d.qvel.copy()
        tau_J = tau + np.asarray(c.torque_offset) + self.pose_bias(q)
        if rng is not None:
            q = q + c.q_noise * rng.normal(size=N)
            dq = dq + c.dq_noise * rng.normal(size=N)
            tau_J = tau_J + np.asarray(c.tau_noise) * rng.normal(size=N)
        step = np.asarray(c.tau_step)
        tau_J = np.where(step > 0, np.round(tau_J / np.where(step > 0, step, 1)) * step, tau_J)
        if c.observer == "exact":
            tau_ext = self.robot.inverse_dynamics(q, dq, d.qacc) - tau_J
        else:
            tau_ext = self._momentum_observer(q, dq, tau_J)
        s = Sample(d.time, q, dq, tau_J, tau_ext)
        self._last = s
        return s

    def _momentum_observer(self, q, dq, tau_J):
        """tau_ext (paper sign) from dynamics.MomentumObserver on the nominal model, from rest at the first state."""
        if self._observer is None:
            self._observer = MomentumObserver(lambda q, dq: self.robot.terms(q, dq)[1:], self.config.observer_gain)
        return self._observer.update(q, dq, tau_J, self.dt)

    # --- viewer --------------------------------------------------------------------------------
    def open_viewer(self):
        """Open MuJoCo's passive viewer when a display exists; returns False (and stays headless) otherwise."""
        import os
        if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
            print("--view: no display found, running headless")
            return False
        import mujoco.viewer
        self.viewer = mujoco.viewer.launch_passive(self.model, self.data)
        self._wall = None
        return True

    def _sync_viewer(self):
        import time
        if int(round(self.data.time / self.dt)) % 16:
            return
        now = time.perf_counter()
        self._wall = now - self.data.time if self._wall is None else self._wall
        time.sleep(max(0.0, self._wall + self.data.time - now))   # real time
        self.viewer.sync()


def _check_payload(m, r, inertia):
    """(m, r (3,), I (3, 3) about the CoM in the ee frame) checked; inertia None = point mass, (6,) = pinocchio order."""
    m = checks.number("m", m, "[0, 100]", "kg", what="a mass")        # (beyond any arm's payload)
    r = checks.array("r", r, (3,), "[-2, 2]", "m (the CoM in the ee frame)")
    I = np.zeros((3, 3)) if inertia is None else checks.array("inertia", inertia, (None,) * np.ndim(inertia),
                                                              "[-1e3, 1e3]", "kg m^2")
    if I.shape == (6,):
        I = inertia_matrix(I)
    if I.shape != (3, 3) or not np.all(np.isfinite(I)) or not np.allclose(I, I.T) or np.linalg.eigvalsh(I).min() < -1e-12:
        raise ValueError(f"inertia: expected a symmetric positive semi-definite (3, 3), found {I.tolist()}")
    return m, r, I


def _needs_rng(c: PlantConfig) -> bool:
    return bool(any(c.tau_noise) or c.q_noise or c.dq_noise or c.stale_prob or any(c.bias_amp))


if __name__ == "__main__":          # python sim.py [DEMO]: the script's entry into the demos, not part of the module
    from experiments.cli import main
    sys.exit(main(sys.argv[1:]))
