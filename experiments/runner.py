"""The one closed loop: plant + controller + optional estimator + scheduled events (payload changes, pushes, policy
switches), 1 kHz, returning a Record. Every demo, benchmark and test that runs the loop goes through `run`."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from rme_settings import RMESettings, faulty
from sim import Plant, Sample


@dataclass(frozen=True)
class PayloadChange:
    """At time t [s] the payload becomes m [kg], CoM r (3,) [m] in the ee frame, inertia (3, 3) about the CoM or
    None (a point mass); m = 0 removes it."""
    t: float
    m: float
    r: tuple = (0.0, 0.0, 0.0)
    inertia: object = None


@dataclass(frozen=True)
class Push:
    """A person pushes with the world force (3,) [N] at `offset` (body frame) of `body` from t for `duration` [s]."""
    t: float
    force: tuple
    duration: float
    body: str = "link7"
    offset: tuple = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class PolicySwitch:
    """At time t [s] the controller's policy (its DS, e.g. cpic.Attractor) becomes `policy`."""
    t: float
    policy: object


@dataclass
class Record:
    """What one run saw, one row per 1 ms control step (the sample the controller acted on):
    t (T,); q, dq, tau (command), tau_J, tau_ext (paper sign) (T, n); theta (T, 4) the true payload and theta_hat
    (T, 4) the compensated estimate; p (T, 3), R (T, 3, 3) the ee pose; target (T, 3) the policy's p* (or the
    limit cycle's centre, NaN without either); V (T, 2), fallback (T,) from the controller when it reports them;
    history: the estimator's estimates."""
    t: np.ndarray
    q: np.ndarray
    dq: np.ndarray
    tau: np.ndarray
    tau_J: np.ndarray
    tau_ext: np.ndarray
    theta: np.ndarray
    theta_hat: np.ndarray
    target: np.ndarray
    V: np.ndarray
    fallback: np.ndarray
    p: np.ndarray = None
    R: np.ndarray = None
    history: list = field(default_factory=list)
    robot: object = None
    exploration: list = field(default_factory=list)   # the explorer's Explorations (run(..., explorer=...))

    def __getitem__(self, key):                       # log["q"] reads like the dicts the demos print from
        return getattr(self, key)

    def __len__(self):
        return len(self.t)

    @property
    def ee_error(self) -> np.ndarray:
        """|p - target| [m] (T,)."""
        return np.linalg.norm(self.p - self.target, axis=1)

    def at(self, t: float) -> int:
        """Index of the first row at or after time t (the last row if t is past the end)."""
        return min(int(np.searchsorted(self.t, t - 1e-9)), len(self.t) - 1)


class ExactCompensation:
    """An oracle 'estimator': from time `start` [s] on it compensates the true payload theta (4,) exactly,
    -robot.payload_torque(q, theta): the best any estimator can do. Time: clock() if given (e.g. the plant's),
    else one update per dt, the first at t = 0."""

    def __init__(self, robot, theta, start=0.0, dt=1e-3, clock=None):
        self.robot, self.start, self.dt, self.clock = robot, float(start), float(dt), clock
        self.theta_true = np.asarray(theta, dtype=float)
        self.theta, self.history, self._k = np.zeros(4), [], 0

    def update(self, q, dq, tau_ext):
        t, self._k = (self._k * self.dt if self.clock is None else self.clock()), self._k + 1
        if t < self.start:
            return None
        self.theta = self.theta_true
        return -self.robot.payload_torque(q, self.theta_true)


def _target(policy, n=3):
    for name in ("p_star", "center"):
        if hasattr(policy, name):
            return getattr(policy, name)
    return np.full(n, np.nan)


def schedule(plant: Plant, events) -> list:
    """Give the plant its payload changes and pushes; return the policy switches sorted by time."""
    switches = []
    for e in events:
        if isinstance(e, PayloadChange):
            plant.schedule_payload(e.t, e.m, e.r, e.inertia)
        elif isinstance(e, Push):
            plant.push(np.asarray(e.force, dtype=float), body=e.body, offset=e.offset, start=e.t, duration=e.duration)
        elif isinstance(e, PolicySwitch):
            switches.append(e)
        else:
            raise ValueError(f"events: expected PayloadChange, Push or PolicySwitch, found {type(e).__name__}")
    return sorted(switches, key=lambda e: e.t)


def run(plant: Plant, controller, seconds: float, estimator=None, events=(), q0=None, dq0=None,
        first: Sample | None = None, tau_ext_to_controller: bool = True, before_step=None, explorer=None) -> Record:
    """Run `controller` on `plant` for `seconds` at the plant's rate.

    Each 1 ms step: policy switches due; comp = estimator.update(q, dq, tau_ext) (if an estimator); tau, info =
    controller.step(q, dq, comp, tau_ext) (tau_ext only if tau_ext_to_controller: CPIC's barriers use it, Eq. 8);
    the plant applies tau. The plant starts from plant.reset(q0, dq0) unless `first` (a Sample it already returned)
    is given. before_step(k, sample), if given, runs first in each step (e.g. to move a hold's set point, or to make
    a sample faulty: a tau_ext that is not finite or beyond RME's max_abs_torque reaches the controller as the last
    good one, as in franka.py).
    explorer (off by default): an experiments.explore.Explorer; it wraps the estimator (an RME) and moves the
    controller's Attractor target to observe the CoM along gravity (Record.exploration lists what it did).
    """
    if not (np.isfinite(seconds) and seconds > 0):
        raise ValueError(f"seconds: expected a finite duration > 0 s, found {seconds}")
    pending = schedule(plant, events)
    if explorer is not None:
        estimator = explorer.attach(controller, estimator)
    if first is None:
        if q0 is None:
            raise ValueError("q0: expected a start pose (n,) or a first Sample, found neither")
        first = plant.reset(q0, dq0)
    s, n, steps = first, plant.robot.n, int(round(seconds / plant.dt))
    rec = {k: np.empty((steps,) + shape) for k, shape in
           (("t", ()), ("q", (n,)), ("dq", (n,)), ("tau", (n,)), ("tau_J", (n,)), ("tau_ext", (n,)),
            ("theta", (4,)), ("theta_hat", (4,)), ("target", (3,)), ("V", (2,)))}
    rec["fallback"] = np.zeros(steps, dtype=bool)
    rec["V"][:] = np.nan
    good = np.zeros(n)                                 # the last good tau_ext; beyond limit a sample is faulty
    limit = getattr(getattr(estimator, "settings", None), "max_abs_torque", RMESettings.max_abs_torque)
    for k in range(steps):
        if before_step is not None:
            before_step(k, s)
        while pending and pending[0].t <= s.t:
            controller.policy = pending.pop(0).policy
        comp = estimator.update(s.q, s.dq, s.tau_ext) if estimator is not None else None
        good = good if faulty(s.tau_ext, limit) else s.tau_ext
        tau, info = controller.step(s.q, s.dq, comp, good if tau_ext_to_controller else None)
        rec["t"][k], rec["q"][k], rec["dq"][k], rec["tau"][k] = s.t, s.q, s.dq, tau
        rec["tau_J"][k], rec["tau_ext"][k], rec["theta"][k] = s.tau_J, s.tau_ext, plant.theta
        rec["theta_hat"][k] = getattr(estimator, "theta", 0.0) if estimator is not None else 0.0
        rec["target"][k] = _target(getattr(controller, "policy", None))
        if info is not None:
            rec["V"][k], rec["fallback"][k] = getattr(info, "V", np.nan), getattr(info, "fallback", False)
        s = plant.step(tau)
    out = Record(**rec, history=list(getattr(estimator, "history", [])), robot=plant.robot,
                 exploration=list(getattr(explorer, "log", [])))
    out.p, out.R = plant.robot.ee_pose(out.q)
    out.last = s                                       # the sample after the last step
    return out
