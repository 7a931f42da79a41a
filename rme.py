"""Rapid Mismatch Estimation, the pipeline (Sec. 4, Fig. 2): detector -> 200 ms window -> network prior ->
variational inference -> compensation tau_comp = -J^T [F_hat; r_hat x F_hat] (Eq. 5). `python rme.py diagnose LOG`
compares the nominal model with a robot log and finds the missing physical effect (diagnosis/)."""
from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field

import numpy as np

import vi
from detector import Detector, DetectorSettings, pseudo_force
from dynamics import Robot, as_states
from nn_numpy import WEIGHTS, MismatchNet



@dataclass(frozen=True)
class RMESettings:
    window: int = 200              # samples of the estimation window: 200 ms at 1 kHz (Sec. 4, App. E)
    reference: int = 30            # samples at the start of the detector's buffer whose mean tau_ext is the
                                   #   reference the window is referred to (ours: removes the pose-dependent bias);
                                   #   the detector checks that samples 1-30 precede the change (detector.py)
    rate: float = 1000.0           # Hz, the control loop (Franka's 1 kHz)
    use_network: bool = True       # prior mean from the network (False: zero prior mean, Table 1's ablation)
    asynchronous: bool = True      # ours: compensation starts once the estimate's own wall time has passed, as if
                                   #   the estimate ran beside the loop (False: applied on the detection sample)
    max_mass: float = 3.0          # kg, Panda's rated payload: the compensation never assumes more
    min_explained: float = 0.9     # ours: a detection is applied only if the new estimate explains at least this
                                   #   share of the torque change in its window; a change of the pose-dependent bias
                                   #   after a large move (not a load) explains 0.6-0.7, real loads 0.97-1.0 (sim.py
                                   #   pick-place and basket, realistic preset)
    refine: bool = True            # ours: estimate again once the arm is still after a detection (friction held
                                   #   part of the load while it moved: the first estimate reads light by a few %)
    rest_speed: float = 0.01       # rad/s, every joint slower than this counts as still (dq noise is 1e-3)
    refine_within: float = 2.0     # s after the detection; later, no estimate at rest is made
    vi: vi.VISettings = field(default_factory=vi.VISettings)
    detector: DetectorSettings = field(default_factory=DetectorSettings)

    def __post_init__(self):
        keep, settled = self.detector.window, self.detector.settled_window[1]
        checks = [("window", self.window, 20 <= self.window <= keep, f"20..{keep} samples (the detector's window)"),
                  ("reference", self.reference, 1 <= self.reference <= settled,
                   f"1..{settled} samples (the detector checks those precede the change)"),
                  ("rate", self.rate, self.rate > 0, "a rate > 0 Hz"),
                  ("max_mass", self.max_mass, self.max_mass > 0, "a mass > 0 kg"),
                  ("min_explained", self.min_explained, self.min_explained <= 1, "a share <= 1"),
                  ("rest_speed", self.rest_speed, self.rest_speed > 0, "a speed > 0 rad/s"),
                  ("refine_within", self.refine_within, self.refine_within > 0, "a time > 0 s")]
        for name, value, ok, want in checks:
            if not ok or (isinstance(value, float) and np.isnan(value)):
                raise ValueError(f"settings.{name}: expected {want}, found {value!r}")


@dataclass
class Estimate:
    """One RME estimate: the posterior over theta = (m [kg], rx, ry, rz [m] in the ee frame)."""
    mean: np.ndarray               # (4,)
    std: np.ndarray                # (4,) marginal std of the Laplace covariance at the mean (honest intervals;
                                   #   the mean-field sigma under-covers the correlated m-r directions, vi.py)
    cov: np.ndarray                # (4, 4) that covariance
    prior: np.ndarray              # (4,) the prior mean (network output, or zeros)
    seconds: float                 # wall time of network + VI
    iterations: int
    converged: bool
    t: float = float("nan")        # stream time of the detection (update only)
    explained: float = float("nan")  # share of the window's change the new estimate explains (update only)
    accepted: bool = True            # False: the change did not look like a payload and was not compensated
    kind: str = "window"             # "detection", "at rest" (once the arm is still), "at deadline" or "window"
    applied: float = float("nan")    # stream time the compensation started using it (update only)


class RME:
    """The estimator. estimate(q, tau_ext) for a window; update(q, dq, tau_ext) once per 1 ms sample for streaming
    use, returning the compensation torque (7,) to add to the controller's torque."""

    def __init__(self, robot: Robot | None = None, weights: str | None = WEIGHTS, settings: RMESettings = RMESettings(),
                 rng: np.random.Generator | None = None, correction=None):
        self.robot = Robot.panda() if robot is None else robot
        self.settings, self.correction = settings, correction
        self.rng = np.random.default_rng(0) if rng is None else rng
        self.net = self._load_network(weights) if settings.use_network else None
        if not isinstance(settings, RMESettings):
            raise ValueError(f"settings: expected an RMESettings, found {type(settings).__name__}")
        self.detector = Detector(settings.detector, n=self.robot.n)
        n, keep = self.robot.n, settings.detector.window
        self._q, self._dq, self._tau = np.zeros((keep, n)), np.zeros((keep, n)), np.zeros((keep, n))   # ring buffers
        self._k = 0                                    # samples seen
        self.theta = np.zeros(4)                       # the estimate being compensated
        self._phi = np.zeros(4)                        # its phi = (m, m r), kept with it for the 1 kHz loop
        self._pending = None                           # (sample index when it applies, Estimate)
        self._refine, self._still = None, 0            # a pending estimate at rest; samples the arm has been still
        self.history: list[Estimate] = []
        self._limit = self.robot.torque_limits()          # the compensation never asks for more than the drives give

    @staticmethod
    def _load_network(weights):
        """The network prior; weights=None runs without it (zero prior mean). A file that cannot be used is a
        ValueError naming the file and the array (MismatchNet.load), never silently replaced."""
        return None if weights is None else MismatchNet.load(weights)

    # --- one window ----------------------------------------------------------------------------
    def estimate(self, q, tau_ext, baseline=None, dq=None) -> Estimate:
        """Posterior of theta from a window q, tau_ext (T, n) (paper sign), T about 200 at 1 kHz.
        baseline (n,): the tau_ext seen before the change, subtracted first (default: none).
        dq (T, n): joint velocities, needed only by a velocity-dependent correction (e.g. fitted friction)."""
        n = self.robot.n
        q_in, tau_in = q, tau_ext
        q, qb = as_states("q", q, n)
        tau, tb = as_states("tau_ext", tau_ext, n)
        if not (qb and tb) or q.shape != tau.shape:
            raise ValueError(f"q, tau_ext: expected two windows of the same shape (T, {n}), found "
                             f"{np.shape(q_in)} and {np.shape(tau_in)}")
        if q.shape[0] < 20:
            raise ValueError(f"q: expected a window of at least 20 samples (the network reads 20), found {q.shape[0]}")
        if baseline is not None:
            tau = tau - as_states("baseline", baseline, n, allow_window=False)[0]
        if self.correction is not None:
            dq = np.zeros_like(q) if dq is None else as_states("dq", dq, n)[0]
            if dq.shape != q.shape:
                raise ValueError(f"dq: expected shape {q.shape} like q, found {dq.shape}")
            tau = tau - self.correction.correction(q, dq)
        return self._estimate(q, tau)[0]

    def _estimate(self, q, tau):
        """Network prior and VI on a checked, referred and corrected window: (Estimate, Y = payload_regressor(q))."""
        start = time.perf_counter()
        _, R, J = self.robot.kinematics(q)                     # one forward-kinematics pass for the window
        Y = self.robot.payload_regressor_from(J, R)
        prior = self.net.predict_window(self.robot, q, tau, (R, J)) if self.net is not None else np.zeros(4)
        if not np.all(np.isfinite(prior)):             # the network overflowed on absurd torques: no prior mean
            prior = np.zeros(4)
        post = vi.fit(Y, tau, prior, self.settings.vi, self.rng)
        seconds = time.perf_counter() - start
        return Estimate(post.mean, post.marginal_std, post.cov, np.asarray(prior, float), seconds, post.iterations,
                        post.converged), Y

    # --- streaming -----------------------------------------------------------------------------
    def update(self, q, dq, tau_ext) -> np.ndarray:
        """Feed one 1 kHz sample (paper sign tau_ext); returns the compensation torque (n,) = -tau_mm(q, theta_hat).
        Never NaN, never beyond the torque limits; re-estimates at every change the detector finds."""
        n, keep = self.robot.n, self.settings.detector.window
        q, _ = as_states("q", q, n, allow_window=False)
        tau, _ = as_states("tau_ext", tau_ext, n, allow_window=False)
        dq, _ = as_states("dq", dq, n, allow_window=False)
        q, dq, tau = q[0], dq[0], tau[0]
        i = self._k % keep
        self._q[i], self._dq[i], self._tau[i] = q, dq, tau
        self._k += 1
        # the detector watches what the current estimate does not explain, r = tau_ext - tau_mm(q, theta_hat):
        # a known load carried to another pose changes tau_ext but not r (ours; Alg. 1 watches tau_ext itself)
        _, R, J = self.robot.kinematics(q)                            # one kinematics pass per sample
        Y = self.robot.payload_regressor_from(J, R)
        tau_mm = Y @ self._phi
        r = tau - tau_mm if self.correction is None else tau - tau_mm - self.correction.correction(q, dq)
        fired = self.detector.update(r, pseudo_force(J, r, self.settings.detector.lam, check=False)) and self._k >= keep
        if fired and self._refine is None:
            self._on_detection()
        # while an estimate at rest is pending, the arm is still moving in answer to the last compensation and the
        # detector's reference is not settled: detections are ignored, and the estimate at rest (or, if the arm
        # never rests, the one at the deadline) covers any change meanwhile, being referred to before the change
        self._still = self._still + 1 if np.abs(dq).max() < self.settings.rest_speed else 0
        if self._refine is not None and self._pending is None:
            if self._still >= self.settings.window:
                self._on_rest("at rest")
            elif self._k > self._refine["deadline"]:
                self._on_rest("at deadline")
        if self._pending is not None and self._k >= self._pending[0]:
            self.theta = _safe_theta(self._pending[1].mean, self.theta, self.settings.max_mass)
            self._phi = vi.phi_of(self.theta)
            self._pending[1].applied = self._k / self.settings.rate
            self._pending, self._still = None, 0         # the arm answers the new compensation: wait for rest again
            tau_mm = Y @ self._phi
        return np.clip(-tau_mm, -self._limit, self._limit)

    def _buffer(self):
        """The last `detector.window` samples, oldest first: q, tau_ext less any fitted correction."""
        keep = self.settings.detector.window
        order = (np.arange(keep) + self._k) % keep
        Q, TAU = self._q[order], self._tau[order]
        if self.correction is not None:                               # the effects a better model explains
            TAU = TAU - self.correction.correction(Q, self._dq[order])
        return Q, TAU

    def _on_detection(self):
        """Estimate the total payload from the newest window, referred to the torque before the change."""
        s = self.settings
        Q, TAU = self._buffer()
        q_ref, tau_ref = Q[:s.reference], TAU[:s.reference]
        # bias = what the previous estimate does not explain before the change: tau_ref - tau_mm(q_ref, theta_prev)
        bias = (tau_ref - self.robot.payload_regressor(q_ref) @ self._phi).mean(axis=0)
        e = self._change(Q[-s.window:], TAU[-s.window:] - bias, self.theta, "detection")
        if e.accepted and s.refine:
            self._refine = dict(bias=bias, before=self.theta.copy(), deadline=self._k + int(s.refine_within * s.rate))

    def _on_rest(self, kind):
        """Once the arm has been still for a whole window after a detection, estimate again from that window: joint
        friction no longer holds part of the load, and the arm is back near the pose it had before the change. If it
        never rests within refine_within, estimate at the deadline so that no change in between is lost."""
        s, r = self.settings, self._refine
        self._refine = None
        Q, TAU = self._buffer()
        self._change(Q[-s.window:], TAU[-s.window:] - r["bias"], r["before"], kind)
        self.detector.reset()               # its reference predates the estimate: start a fresh window

    def _change(self, Qw, Tw, theta_before, kind) -> Estimate:
        """Estimate on a referred window, judge it against the payload before the change, schedule it if accepted."""
        s, k = self.settings, self._k
        e, Y = self._estimate(Qw, Tw)
        e.t, e.kind = k / s.rate, kind
        before = np.sum((Tw - Y @ vi.phi_of(theta_before)) ** 2)        # what the estimate before leaves unexplained
        e.explained = 1.0 - np.sum((Tw - Y @ vi.phi_of(e.mean)) ** 2) / before
        e.accepted = bool(e.explained >= s.min_explained)
        self.history.append(e)
        if e.accepted:
            delay = math.ceil(e.seconds * s.rate) if s.asynchronous else 0
            self._pending = (k + delay, e)
        return e


def _safe_theta(new, old, max_mass):
    """The estimate to compensate: finite, mass in [0, max_mass], CoM within 1 m; otherwise keep the current one."""
    new = np.asarray(new, dtype=float)
    if new.shape != (4,) or not np.all(np.isfinite(new)):
        return old
    return np.array([min(max(new[0], 0.0), max_mass), *np.clip(new[1:], -1.0, 1.0)])


if __name__ == "__main__":          # python rme.py diagnose LOG ...: the script's entry, not part of the module
    if len(sys.argv) < 2 or sys.argv[1] != "diagnose":
        print("usage: python rme.py diagnose LOG [--add EFFECT ...] [--json] [--plot FILE]\n"
              "(the estimator itself is a library: from rme import RME; demos: python sim.py --help)")
        sys.exit(2)
    from diagnosis.diagnose import main
    sys.exit(main(sys.argv[2:], prog="rme.py diagnose"))
