"""libfranka's side of the real-robot bridge: the robot state as libfranka reports it (tau_ext_hat_filtered in its
sign, the opposite of the paper's Eq. 1) and the backends franka.py drives: pylibfranka, panda-python, and the
project's MuJoCo plant behind the same interface (read() -> State, write(cmd) without gravity, stop())."""
from __future__ import annotations

import os
import queue
import threading
import time
from dataclasses import dataclass

import numpy as np

Q_START = (0.0, -np.pi / 4, 0.0, -3 * np.pi / 4, 0.0, np.pi / 2, np.pi / 4)   # Franka's ready pose (panda_facts.md)

@dataclass
class State:
    """One robot state as libfranka reports it: q, dq [rad, rad/s], tau_J and tau_ext_hat_filtered [Nm] (7,) in
    libfranka's sign (tau_ext_hat_filtered = tau_J - model, the load configured in Desk included in the model);
    duration_s: time since the previous state [s] (1 ms per cycle; more means cycles were missed)."""
    q: np.ndarray
    dq: np.ndarray
    tau_J: np.ndarray
    tau_ext_hat_filtered: np.ndarray
    duration_s: float


def paper_tau_ext(tau_ext_hat_filtered) -> np.ndarray:
    """tau_ext (7,) in the paper's sign (Eq. 1, model - tau_J) from libfranka's tau_ext_hat_filtered (tau_J - model)."""
    return -np.asarray(tau_ext_hat_filtered, dtype=float)


# --- backends: read() -> State, write(cmd) with cmd excluding gravity, stop() --------------------------------------
class SimBackend:
    """The project's MuJoCo plant (sim.Plant, realistic preset) behind libfranka's interface: it reports
    tau_ext_hat_filtered = -tau_ext (the plant's tau_ext is in the paper's sign) and adds the nominal model's gravity
    to each command, as the robot does. payload: (t [s], m [kg], r (3,) [m][, inertia (3, 3) about the CoM]) changes
    scheduled on the plant (ee frame).
    paced: the states come at the plant's rate in wall time (1 kHz; late cycles are not caught up), else at once."""

    def __init__(self, rng: np.random.Generator, q0=Q_START, payload=(), preset="realistic", paced=False):
        from sim import Plant, PlantConfig
        self.plant = Plant(PlantConfig.preset(preset, rng), rng=rng)
        for t, m, r, *inertia in payload:              # (t, m, r) or (t, m, r, inertia about the CoM (3, 3))
            self.plant.schedule_payload(t, m, r, *inertia)
        self._s = self.plant.reset(q0)
        self.paced, self._tick = paced, None           # paced: read() returns at most one state per dt of wall time
        self.initial = self.read()                     # the state before control starts

    def read(self) -> State:
        if self.paced:                                 # as the robot: the next state 1 ms after the previous one
            now = time.perf_counter()
            self._tick = now if self._tick is None else max(self._tick + self.plant.dt, now)
            _wait_until(self._tick)
        s = self._s
        return State(s.q.copy(), s.dq.copy(), s.tau_J.copy(), -s.tau_ext, self.plant.dt)

    def write(self, cmd):
        self._s = self.plant.step(np.asarray(cmd, dtype=float) + self.plant.robot.gravity(self._s.q))

    def stop(self):
        pass


def _need(module, lib):
    try:
        return __import__(module)
    except ImportError as err:
        raise RuntimeError(f"--lib {lib}: the package is not installed ({err}); `pip install -r "
                           f"requirements-robot.txt` (pylibfranka) or `pip install panda-python` (panda-py)") from None


def _state_of(s, duration_s) -> State:
    return State(np.array(s.q, float), np.array(s.dq, float), np.array(s.tau_J, float),
                 np.array(s.tau_ext_hat_filtered, float), float(duration_s))


class PylibfrankaBackend:
    """pylibfranka: Robot(ip, RealtimeConfig), start_torque_control() -> readOnce() / writeOnce(Torques). Torque
    control starts at the first read(), in the loop: from then on the robot applies only what the loop writes (a
    tool missing from its model falls meanwhile: on franky-sim, starting it at connection left the tens of ms of
    building the controller and warming the loop up before the first state, and a 1.4 kg tool dropped joint 4 at
    0.13-0.22 rad/s by then; started here, 0.01-0.02 rad/s)."""

    def __init__(self, ip: str, realtime: bool = True, control: bool = True):
        plf = _need("pylibfranka", "pylibfranka")
        self._plf, self._ctrl, self._control, self._ip = plf, None, control, ip
        rt = plf.RealtimeConfig.kEnforce if realtime else plf.RealtimeConfig.kIgnore
        try:
            self.robot = plf.Robot(ip, rt)
            self.initial = _state_of(self.robot.read_once(), 1e-3)     # the state before control starts
        except Exception as err:
            raise RuntimeError(f"--robot-ip {ip}: no robot answered through pylibfranka "
                               f"({type(err).__name__}: {err})") from None

    def read(self) -> State:
        if self._control and self._ctrl is None:
            try:
                self._ctrl = self.robot.start_torque_control()
            except Exception as err:
                raise RuntimeError(f"--robot-ip {self._ip}: torque control refused through pylibfranka "
                                   f"({type(err).__name__}: {err})") from None
        if self._ctrl is None:
            return _state_of(self.robot.read_once(), 1e-3)
        s, d = self._ctrl.readOnce()
        return _state_of(s, d.to_sec())

    def write(self, cmd):
        if self._ctrl is not None:
            self._ctrl.writeOnce(self._plf.Torques([float(x) for x in cmd]))

    def stop(self):
        self._control = False                          # no control is started after the loop
        if self._ctrl is not None:
            t = self._plf.Torques([0.0] * 7)
            t.motion_finished = True
            try:
                self._ctrl.writeOnce(t)
            finally:
                self._ctrl = None
                self.robot.stop()


class FrankySimBackend(PylibfrankaBackend):
    """pylibfranka against franky-sim, which reports tau_ext_hat_filtered = tau_J (no external-torque estimate; its
    tau_J is the torque applied to the joints): read() replaces it with what libfranka's is, the torque of whatever
    the arm carries beyond its model, without "the mass and dynamics of the robot" (libfranka's RobotState): De Luca's
    momentum observer (dynamics.MomentumObserver, gain `observer_gain`) on the simulated arm and hand (franky-sim's
    own MJCF, its rotor inertia and damping, fingers at `finger` m each), started at the first state's static estimate
    tau_J - G(q) (franky-sim's first tau_J in torque control is its own gravity alone: the estimate then rises to
    the tool's torque within about 3 / K, as the realistic plant's from zero; the push watch starts at 0.25 s)."""

    def __init__(self, ip: str, xml: str | None = None, finger: float = 0.04, observer_gain: float = 100.0,
                 **kwargs):     # xml: the sim's MJCF; observer_gain [1/s]: the realistic plant's (sim.PlantConfig)
        import mujoco
        if xml is None:
            import franky_sim
            xml = os.path.join(os.path.dirname(franky_sim.__file__), "assets", "fr3.xml")
        import xml.etree.ElementTree as ET
        root = ET.parse(xml).getroot()
        for c in root.iter("compiler"):               # the meshes sit in meshes/ beside the file
            c.set("meshdir", os.path.join(os.path.dirname(os.path.abspath(xml)), "meshes"))
        self._mj, self._model = mujoco, mujoco.MjModel.from_xml_string(ET.tostring(root, encoding="unicode"))
        self._data = mujoco.MjData(self._model)
        joints = [mujoco.mj_name2id(self._model, mujoco.mjtObj.mjOBJ_JOINT, f"fr3_joint{i}") for i in range(1, 8)]
        fingers = [mujoco.mj_name2id(self._model, mujoco.mjtObj.mjOBJ_JOINT, f"finger_joint{i}") for i in (1, 2)]
        if min(joints) < 0:
            raise ValueError(f"xml: expected the joints fr3_joint1..7 in {xml!r}, found ids {joints}")
        self._q_adr = [int(self._model.jnt_qposadr[j]) for j in joints]
        self._dof_adr = [int(self._model.jnt_dofadr[j]) for j in joints]
        for j in fingers:
            if j >= 0:
                self._data.qpos[self._model.jnt_qposadr[j]] = finger
        self._gain, self._observer = float(observer_gain), None
        super().__init__(ip, **kwargs)

    def joint_limits(self) -> np.ndarray:
        """(7, 2) [rad]: the simulated arm's own joint ranges (franky-sim's MJCF: an FR3's, not the Panda's)."""
        m = self._model
        return m.jnt_range[[int(m.dof_jntid[a]) for a in self._dof_adr]].copy()

    def gravity(self, q) -> np.ndarray:
        """G(q) (7,) [Nm] of the simulated arm and hand at rest."""
        m, d, mj = self._model, self._data, self._mj
        d.qpos[self._q_adr] = q
        d.qvel[:] = 0.0
        mj.mj_kinematics(m, d)
        mj.mj_comPos(m, d)
        out = np.empty(m.nv)
        mj.mj_rne(m, d, 0, out)
        return out[self._dof_adr]

    def terms(self, q, dq):
        """M(q) (7, 7) with the rotors' inertia and n = C dq + G + the joints' damping (7,) of the simulated arm."""
        m, d, mj, a = self._model, self._data, self._mj, self._dof_adr
        d.qpos[self._q_adr], d.qvel[:] = q, 0.0
        d.qvel[a] = dq
        mj.mj_kinematics(m, d)
        mj.mj_comPos(m, d)
        mj.mj_makeM(m, d)
        mj.mj_comVel(m, d)
        M, n = np.zeros((m.nv, m.nv)), np.empty(m.nv)
        mj.mj_fullM(m, d, M)
        mj.mj_rne(m, d, 0, n)
        return M[np.ix_(a, a)], n[a] + m.dof_damping[a] * dq

    def read(self) -> State:
        s = super().read()
        if self._observer is None:
            from dynamics import MomentumObserver
            self._observer = MomentumObserver(self.terms, self._gain, sign=-1, r0=s.tau_J - self.gravity(s.q))
        s.tau_ext_hat_filtered = self._observer.update(s.q, s.dq, s.tau_J, max(float(s.duration_s), 1e-3))
        return s


class PandaPyBackend:
    """panda-python: libfranka.Robot.control(callback) owns the 1 kHz loop, so it runs in a thread and hands each
    state to read() (the newest: one the loop has not taken is replaced) and sends the command write() gives for
    that state; one the loop answers later than `timeout` (0.9 ms) gets the newest command written before, and a
    command answering an older state is never taken for the answer to a newer one (the loop would stay a cycle
    behind for good after a single late cycle).
    control=False (dry run) only reads states (Panda.get_state). panda: a connected panda_py.Panda (or anything with
    its get_robot() and get_state()) to use instead of connecting to ip. Control starts at the first read(), in the
    loop (as PylibfrankaBackend's: until the loop answers, the robot gets zero torque beyond its model)."""

    def __init__(self, ip: str, control: bool = True, timeout: float = 0.9e-3, panda=None):
        panda_py = _need("panda_py", "panda-py")
        from panda_py import libfranka
        try:
            self.panda = panda_py.Panda(ip) if panda is None else panda
            self.robot = self.panda.get_robot()
            self.initial = _state_of(self.panda.get_state(), 1e-3)     # the state before control starts
        except Exception as err:
            raise RuntimeError(f"--robot-ip {ip}: no robot answered through panda-python "
                               f"({type(err).__name__}: {err})") from None
        self._lf, self._timeout, self._control = libfranka, timeout, control
        self._states, self._cmds = queue.Queue(maxsize=1), queue.Queue(maxsize=1)
        self._last, self._done, self._error = [0.0] * 7, threading.Event(), None
        self._seq, self._read, self._thread = 0, 0, None   # states sent by the callback; the one the loop read last

    def _run(self):
        def callback(state, duration):
            self._seq += 1
            seq, deadline = self._seq, time.perf_counter() + self._timeout
            try:
                self._states.get_nowait()              # a state the loop never took: the newer one replaces it
            except queue.Empty:
                pass
            self._states.put_nowait((seq, _state_of(state, duration.to_sec())))
            while True:                                # the answer to this state, or the newest one by the deadline
                try:
                    answered, self._last = self._cmds.get(timeout=max(deadline - time.perf_counter(), 0.0))
                except queue.Empty:
                    break
                if answered >= seq:
                    break
            t = self._lf.Torques(self._last)
            t.motion_finished = self._done.is_set()
            return t
        try:
            self.robot.control(callback)
        except Exception as err:                       # reported by the next read()
            self._error = err
        self._done.set()

    def read(self) -> State:
        if not self._control:
            return _state_of(self.panda.get_state(), 1e-3)
        if self._thread is None and not self._done.is_set():
            self._thread = threading.Thread(target=self._run, daemon=True)
            self._thread.start()
        while True:
            if self._error is not None or (self._done.is_set() and self._states.empty()):
                raise RuntimeError(f"panda-python control ended: {self._error}")
            try:
                self._read, s = self._states.get(timeout=0.1)
                return s
            except queue.Empty:
                continue

    def write(self, cmd):
        if self._control:
            try:
                self._cmds.get_nowait()                # a command the callback never took: replaced
            except queue.Empty:
                pass
            self._cmds.put_nowait((self._read, [float(x) for x in cmd]))   # the answer to the state last read

    def stop(self):
        self._done.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)




def _wait_until(t):
    """Return at perf_counter() >= t: sleep, then a busy wait over the last 0.2 ms (sleep alone overshoots)."""
    ahead = t - time.perf_counter()
    if ahead > 2e-4:
        time.sleep(ahead - 2e-4)
    while time.perf_counter() < t:
        pass
