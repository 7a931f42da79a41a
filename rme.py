"""Rapid Mismatch Estimation, the pipeline (Sec. 4, Fig. 2): detector -> 200 ms window -> network prior ->
variational inference -> compensation tau_comp = -J^T [F_hat; r_hat x F_hat] (Eq. 5). `python rme.py diagnose LOG`
compares the nominal model with a robot log and finds the missing physical effect (diagnosis/)."""
from __future__ import annotations

import math
import os
import sys
import time
from dataclasses import dataclass

import numpy as np
from scipy.linalg import lapack

import checks
import vi
from detector import Detector, safe_theta
from dynamics import Robot, as_states
from error_model import ErrorModel, as_error_model
from motion.tool_forms import load_tool, phi_of_tool
from nn_numpy import WEIGHTS, MismatchNet
from rme_settings import RMESettings, faulty
from rme_levels import LevelMap, Levels
from rme_stream import Streaming

__all__ = ["RME", "RMESettings", "Estimate", "ErrorModel"]


@dataclass
class Estimate:
    """One RME estimate: the posterior over theta = (m [kg], rx, ry, rz [m] in the ee frame)."""
    mean: np.ndarray               # (4,)
    std: np.ndarray                # (4,) marginal std of the Laplace covariance at the mean (vi.noise_from_window)
    cov: np.ndarray                # (4, 4) that covariance
    prior: np.ndarray              # (4,) the prior mean VI started from (network output, zeros, or the broad one)
    observed: np.ndarray           # (4,) bool: the window(s) observed it (std well below the prior's; else the prior)
    seconds: float                 # wall time of network + VI
    iterations: int
    converged: bool
    t: float = float("nan")        # stream time the estimate was requested: the detection (update only)
    explained: float = float("nan")  # share of the window's change the new estimate explains (update only)
    accepted: bool = True            # False: the change did not look like a payload and was not compensated
    kind: str = "window"             # "detection", "at rest" (once the arm is still), "withdrawn" (back to the
                                     #   estimate before a change found at rest to be no payload), "monitor"
                                     #   (the compensation no longer explained tau_ext at rest) or "window"
    applied: float = float("nan")    # stream time the compensation started using it (update only)
    reason: str = ""                 # why it was not applied, or applied only later (update only)
    prior_source: str = "network"    # the prior VI started from: "network" (Sec. 4.1; zeros without weights), or
                                     #   "broad" (every plausible payload): for an absolute window, or where a
                                     #   referred window's evidence says the network's prior conflicts with it


class RME(Streaming):
    """The estimator. estimate(q, tau_ext) for a window; update(q, dq, tau_ext) once per 1 ms sample for streaming
    use, returning the compensation torque (7,) to add to the controller's torque. executor (ours): runs each streamed
    estimate beside the loop, applied once update finds it done (settings.asynchronous moot); None: within update.
    calibration: the robot's error model (error_model.ErrorModel, or the JSON of `python rme.py calibrate LOG --save`;
    None: an uncalibrated Panda), which says how far tau_ext may stray from the payload's torque in a window taken
    as it is (absolute) and in one referred to the level before a change.
    tool (ours): a known tool on the flange (motion.tool_forms: a Tool, a dict with mass, com, inertia in the flange
    frame F, or a tool.json path) that Desk does not have: its weight's torque Y(q) phi_tool is subtracted from
    tau_ext as each sample arrives (so RME estimates only what is added to it; a window referred to a level taken with
    the tool on has it cancelled already) and its compensation is returned with RME's. Its inertial torque in motion
    is not (below 0.05 Nm at the arm's usual speeds)."""

    def __init__(self, robot: Robot | None = None, weights: str | None = WEIGHTS, settings: RMESettings = RMESettings(),
                 rng: np.random.Generator | None = None, correction=None, executor=None, calibration=None, tool=None):
        self.robot = Robot.panda() if robot is None else checks.instance("robot", robot, Robot)
        self.error_model = as_error_model(calibration, self.robot.n)
        if len(self.error_model.absolute) != self.robot.n:
            raise ValueError(f"calibration: expected an error model of the robot's {self.robot.n} joints, found one of "
                             f"{len(self.error_model.absolute)} ({self.error_model.source})")
        self.tool = None if tool is None else load_tool(tool)        # ValueError naming what is wrong
        self._tool_phi = np.zeros(4) if tool is None else phi_of_tool(self.tool)   # (m, m c) in the ee frame
        self.settings = checks.instance("settings", settings, RMESettings)
        self.correction = None if correction is None else checks.has_methods("correction", correction, "correction")
        self.executor = executor if executor is None else checks.has_methods("executor", executor, "submit")
        self._job, self._queued, self._steps = None, None, None   # (future, request, sample, received) in flight;
                                                       #   a request; (generator, sample): a detection's steps
        self.rng = np.random.default_rng(0) if rng is None else checks.generator("rng", rng)
        if not (weights is None or isinstance(weights, (str, os.PathLike))):
            raise ValueError(f"weights: expected a weights file's path or None, found {weights!r:.60}")
        self.net = MismatchNet.load(weights) if settings.use_network and weights is not None else None  # or ValueError
        self.detector = Detector(settings.detector, n=self.robot.n)
        n, keep = self.robot.n, settings.detector.window
        self._q, self._dq, self._tau = np.zeros((keep, n)), np.zeros((keep, n)), np.zeros((keep, n))   # ring buffers
        self._r = np.zeros((keep, n))                  # ring of residuals tau_ext - tau_mm(q, theta) (- correction)
        self._k = 0                                    # samples seen
        self._fq, self._P = np.full(n, np.inf), None   # the pose (1e-3 rad) of the pseudo-force map P (3, n)
        self.dropped = 0                               # samples refused as non-finite or beyond max_abs_torque
        self.changes_not_payload, self.changes_held = 0, 0   # detections no payload explains (not estimated); held
        self._held = None                              # the sample since which a change has been held (_held_back)
        self._expected = 0                             # before this sample a change is expected (expect_change)
        self._slow_rejected = LevelMap(settings.pose_tolerance, size=1)   # the level a slow arm's check estimated in vain
        self._stays = LevelMap(settings.pose_tolerance, size=1)   # the level where a small load was found left (_gone)
        self._evidence = []                            # (q, tau) windows of the compensated payload (accumulate)
        self._lv = Levels(settings.pose_tolerance, settings.monitor_threshold)   # residual levels by pose
        self._last = np.zeros(n)                       # the last compensation returned
        self.theta, self._phi = np.zeros(4), np.zeros(4)   # the estimate compensated; its phi = (m, m r) (1 kHz loop)
        self._undo = None                              # (phi before the change theta answers, until): _on_line
        self._pending = None                           # (sample index when it applies, Estimate, level, theta before)
        self._refine, self._still, self._calm, self._slow = None, 0, 0, 0   # a pending estimate at rest; samples
                                                       #   the arm has been still, slower than monitor_speed, than
                                                       #   monitor_slow[0]
        self.history: list[Estimate] = []
        c, m = settings.max_com, settings.max_mass                  # every plausible payload: a weak prior (1 sigma
        self._broad = (np.array([m / 2, 0, 0, 0]), np.array([m / 2, c, c, c]),   # to the box's edge) truncated to
                       np.array([0.0, -c, -c, -c]), np.array([m, c, c, c]))     # the box (vi.log_evidence)
        self._limit = self.robot.torque_limits()          # the compensation never asks for more than the drives give

    @property
    def settled(self) -> bool:
        """Whether the stream has judged the first steady level it saw (the sensor's bias, or a load) and has no
        estimate due, queued or in flight."""
        return bool(len(self._lv.explained)) and self._pending is None and self._job is None and \
            self._queued is None and self._steps is None and self._refine is None

    def expect_change(self, seconds: float = 2.0):
        """The task expects a load change within `seconds` from now (it closes or opens the gripper): a change that
        adds a force through the flange's line (a load centred below the hand, as a grasped object mostly is) is
        then estimated at its detection (or by the monitor's check of a slow arm), not held as a possible press
        (RMESettings.hold_axial). A person pressing on the hand meanwhile is taken for the load it looks like, as
        with hold_axial = 0."""
        checks.number("seconds", seconds, "[0, 3600]", "s")
        self._expected = max(self._expected, self._k + 1 + int(round(seconds * self.settings.rate)))   # (a shorter
                                                                                        #   call keeps a longer one)

    # --- one window ----------------------------------------------------------------------------
    def estimate(self, q, tau_ext, baseline=None, dq=None, referred: bool | None = None) -> Estimate:
        """Posterior of theta from a window q, tau_ext (T, n) (paper sign), T about 200 at 1 kHz; or from lists of
        windows [q_a, q_b], [tau_a, tau_b] of one payload (each (T_i, n); baseline and dq lists too, or None): one
        posterior, their evidence combined (vi.combine), the prior mean the network's mean over them.
        baseline (n,): the tau_ext seen before the change at the same pose, subtracted first. Pass it when you have
        it: the robot model's own error at the pose cancels (ErrorModel.referred, a few mNm); without it the window
        is absolute and carries that error (ErrorModel.absolute, tenths of a Nm; its calibrated offset subtracted).
        dq (T, n): joint velocities, needed only by a velocity-dependent correction (e.g. fitted friction).
        referred: None: the window is referred exactly when a baseline is given; True: tau_ext is already less the
        level before the change (you subtracted it); False: absolute even with a baseline."""
        if referred is not None and not isinstance(referred, (bool, np.bool_)):
            raise ValueError(f"referred: expected True, False or None, found {referred!r}")
        if referred is False and baseline is not None:
            raise ValueError("referred: expected True or None with a baseline (a window less the level before a "
                             "change is referred), found False")
        ref = lambda b: bool(b is not None if referred is None else referred)
        if not isinstance(q, (list, tuple)):
            return self._estimate(*self._window(q, tau_ext, baseline, dq, ref(baseline)), referred=ref(baseline))[0]
        each = lambda v: [None] * len(q) if v is None else list(v) if isinstance(v, (list, tuple)) else []
        if not (q and len(each(tau_ext)) == len(q) == len(each(baseline)) == len(each(dq))):
            raise ValueError(f"q, tau_ext, baseline, dq: expected lists of {len(q)} windows (or None), found other")
        windows = [self._window(*w, ref(w[2])) for w in zip(q, each(tau_ext), each(baseline), each(dq))]
        return self._estimate([w[0] for w in windows], [w[1] for w in windows],
                              referred=[ref(b) for b in each(baseline)])[0]

    def _window(self, q, tau_ext, baseline, dq, referred):
        """A checked (q, tau) (T, n) window, less the baseline and the correction."""
        n, q_in, tau_in = self.robot.n, q, tau_ext
        q, qb = as_states("q", q, n)
        tau, tb = self._torques("tau_ext", tau_ext)
        if not (qb and tb) or q.shape != tau.shape:
            raise ValueError(f"q, tau_ext: expected two windows of the same shape (T, {n}), found "
                             f"{np.shape(q_in)} and {np.shape(tau_in)}")
        if q.shape[0] < 20:
            raise ValueError(f"q: expected a window of at least 20 samples (the network reads 20), found {q.shape[0]}")
        if baseline is not None:
            tau = tau - self._torques("baseline", baseline, allow_window=False)[0]
        if not referred:                                             # an absolute window: the calibrated mean
            tau = tau - np.asarray(self.error_model.offset)          #   model error, and the known tool's weight
            if self.tool is not None:
                tau = tau - self.robot.payload_regressor(q) @ self._tool_phi
        if self.correction is not None:
            dq = np.zeros_like(q) if dq is None else as_states("dq", dq, n)[0]
            if dq.shape != q.shape:
                raise ValueError(f"dq: expected shape {q.shape} like q, found {dq.shape}")
            tau = tau - self.correction.correction(q, dq)
        return q, tau

    def _torques(self, name, x, allow_window=True):
        """as_states, every torque within settings.max_abs_torque (beyond it a sensor fault, not a load)."""
        tau, batched = as_states(name, x, self.robot.n, allow_window)
        if (big := np.argwhere(np.abs(tau) > self.settings.max_abs_torque)).size:
            i = tuple(int(k) for k in big[0])
            raise ValueError(f"{name}: expected torques within settings.max_abs_torque = "
                             f"{self.settings.max_abs_torque:g} Nm, found {tau[i]:g} at index {i if batched else i[1]}")
        return tau, batched

    def _estimate(self, q, tau, referred=True):
        """Network prior and VI on checked, corrected windows (or lists): (Estimate, S) with S (n + 5, 4) what
        judging it needs of the newest window (regressor Y, torques T): mean Y, sum Y^T Y, sum Y^T T (rows).
        referred: the window is less the level before the change (else absolute; a list with lists of windows).
        The network was trained on referred windows (nn_train: tau_ext less its mean before the attachment): its
        prior stands for those, checked against the window's evidence (vi.prior_conflict); an absolute window, which
        holds the robot's own model error too, gets the broad prior over every plausible payload."""
        start, many, Ys, priors = time.perf_counter(), isinstance(q, list), [], []
        referred = ([referred] * len(q) if isinstance(referred, bool) else referred) if many else referred
        network = self.net is not None and bool(np.all(referred))
        for qi, ti in zip(q if many else [q], tau if many else [tau]):
            _, R, J = self.robot.kinematics(qi)                     # one forward-kinematics pass per window
            Ys.append(self.robot.payload_regressor_from(J, R))
            priors.append(self.net.predict_window(self.robot, qi, ti, (R, J)) if network else np.zeros(4))
        prior = np.mean(priors, axis=0)
        prior = prior if np.all(np.isfinite(prior)) else np.zeros(4)   # the network overflowed on absurd torques
        speed = [vi.joint_speed(qi, 1 / self.settings.rate) for qi in q] if many else vi.joint_speed(q, 1 / self.settings.rate)
        em, s = self.error_model, self.settings
        bias = [em.referred if r else em.absolute_cov for r in referred] if many else \
            (em.referred if referred else em.absolute_cov)
        if network:                                    # the network's prior, checked against the broad one
            sp, alternative = self.net.prior_std(prior, s.vi.sigma_prior, R[-1]), self._broad
        elif np.all(referred):                         # no weights: the zero prior mean with the paper's widths
            sp, alternative = None, None
        else:                                          # an absolute window: the broad prior
            (prior, sp), alternative = self._broad[:2], None
        post = vi.fit(Ys if many else Ys[0], tau, prior, s.vi, self.rng, speed=speed, bias_std=bias, sigma_prior=sp,
                      alternative=alternative)
        e = Estimate(post.mean, post.marginal_std, post.cov, post.prior_mean, post.observed,
                     time.perf_counter() - start, post.iterations, post.converged)
        e.prior_source = post.prior if np.all(referred) else "broad"
        return e, np.vstack([
            Ys[-1].mean(axis=0), np.einsum("tij,tik->jk", Ys[-1], Ys[-1]), (tau[-1] if many else tau).ravel() @
            Ys[-1].reshape(-1, 4)])

    # --- streaming -----------------------------------------------------------------------------
    def update(self, q, dq, tau_ext) -> np.ndarray:
        """Feed one 1 kHz sample (paper sign tau_ext); returns the compensation torque (n,) = -tau_mm(q, theta_hat),
        never NaN nor beyond the torque limits. A non-finite or absurd sample (beyond max_abs_torque) is dropped and
        counted in `dropped`. Estimates of the total payload come from the event detector (Alg. 1, on the residual
        the estimate leaves) and, as a backstop, the consistency monitor: once the arm is calm with a steady residual
        level, that level must stay within monitor_threshold of the level explained there, or RME estimates again."""
        n, keep, s = self.robot.n, self.settings.detector.window, self.settings
        q, dq = as_states("q", q, n, allow_window=False)[0][0], as_states("dq", dq, n, allow_window=False)[0][0]
        tau = tau_ext if type(tau_ext) is np.ndarray and tau_ext.dtype == np.float64 else checks.real_array(tau_ext)
        if tau is None or tau.shape != (n,):             # (not finite: dropped below, as a sensor fault)
            raise ValueError(f"tau_ext: expected real values of shape ({n},), found "
                             f"{checks.kind(tau_ext) if tau is None else tau.shape}")
        if faulty(tau, s.max_abs_torque):
            self.dropped += 1                          # a sensor fault, not a load: never reaches the estimator
            return self._last
        i = self._k % keep
        self._q[i], self._dq[i], self._tau[i] = q, dq, tau
        self._k += 1
        # the detector watches what the current estimate does not explain, r = tau_ext - tau_mm(q, theta_hat):
        # a known load carried to another pose changes tau_ext but not r (ours; Alg. 1 watches tau_ext itself)
        _, R, J = self.robot.kinematics(q)                            # one kinematics pass per sample
        Y = self.robot.payload_regressor_from(J, R)
        tool = None
        if self.tool is not None:                                      # the known tool's weight: not RME's to find
            tool = Y @ self._tool_phi
            tau = self._tau[i] = tau - tool
        tau_mm = Y @ self._phi
        r = tau - tau_mm if self.correction is None else tau - tau_mm - self.correction.correction(q, dq)
        self._r[i] = r if self.correction is None or np.isfinite(r).all() else tau - tau_mm
        if np.abs(q - self._fq).max() > 1e-3:                         # the pseudo-force map F = P r, per pose
            A = J @ J.T                                                # (J J^T + lam I)^-1 J by Cholesky (LAPACK:
            A.flat[::7] += s.detector.lam                              # a third of np.linalg.solve's time here)
            _, PJ, bad = lapack.dposv(A, J)
            self._fq, self._P = q, (PJ if not bad else np.linalg.lstsq(A, J, rcond=None)[0])[:3]
        if self.detector.push(self._r[i], self._P @ self._r[i]) and self._k >= keep:
            if self._job is None and self._steps is None and (self.executor is None or self._pending is None):
                self._on_detection()
            else:                                      # formed once the job in flight is done (the newest wins)
                self._queued = self._k
        if self._steps is not None and self._steps[1] < self._k and next(self._steps[0], True):
            self._steps = None                         # with an executor: one step per sample, from the next one
        speed = np.abs(dq).max()
        self._still = self._still + 1 if speed < s.rest_speed else 0
        self._calm = self._calm + 1 if speed < s.monitor_speed else 0
        self._slow = self._slow + 1 if speed < s.monitor_slow[0] else 0
        if self._job is not None and self._job[2] < self._k:           # polled from the next sample on
            if self._job[3]:                           # received on the sample before: judged now
                (future, request, *_), self._job = self._job, None
                self._judge(*request, *future.result())
            elif self._job[0].done():
                self._job = (*self._job[:3], True)
        idle = self._pending is None and self._job is None and self._queued is None and self._steps is None
        calm = self._calm >= s.monitor_window          # the monitor's checks, every 10th sample: of a calm arm, and
        slow = not calm and self._slow >= s.window and not self.detector.active   # of a slow one (a change in the
        check = s.monitor and idle and self._k % 10 == 0                            #   detector's window is its)
        if self._refine is not None and idle:
            r = self._refine                           # (a held change is estimated once it has lasted, moving or not)
            if self._still >= s.window or (calm and self._k > r["deadline"] - s.rate / 2) or (r.get("held") and (
                    self._k - r["since"] >= s.hold_axial * s.rate or self._k < self._expected)):   # or expected now
                self._on_rest(Y, J)
            elif self._k > r["deadline"] + 2 * s.refine_within * s.rate:
                self._refine = self._held = None       # the arm never rested: the monitor checks it when it does
            elif check and slow and not r.get("held"):
                self._check_consistency(Y, J, moving=True)   # a change while the arm still creeps after the last one
        elif check and (calm or slow):
            self._check_consistency(Y, J, moving=not calm)
        if self._pending is not None and self._k >= self._pending[0]:
            self._apply(*self._pending[1:], Y, J)
            tau_mm = Y @ self._phi
        if self._queued is not None and self._job is None and self._steps is None and self._pending is None:
            asked, self._queued = self._queued, None   # under the compensation just applied
            self._on_detection(asked)
        comp = -tau_mm if tool is None else -tau_mm - tool
        self._last = np.minimum(np.maximum(comp, -self._limit), self._limit)
        return self._last

    def _plausible(self, theta) -> bool:
        """Whether theta (4,) is a payload the arm can carry: mass <= 1.2 max_mass and, from 0.1 kg on, CoM within max_com."""
        s = self.settings
        return bool((theta[0] < 0.1 or np.all(np.abs(theta[1:]) <= s.max_com)) and theta[0] <= 1.2 * s.max_mass)

    def _apply(self, e, level, before, Y, J):
        """Compensate the estimate e from now on; the detector's buffer is re-expressed in the new residual. level:
        (q, residual level) the new compensation should leave at pose q (its reference), or None; before: the estimate
        compensated before the change e answers (None: not known)."""
        self._lv.muted, self._lv.rejected = LevelMap(self.settings.pose_tolerance), None   # judged before it; the
        self._lv.doubtful = self._lv.renewing = False     # levels are now what a compensation was accepted against
        if level is not None:
            self._lv.explained.put(*level)
        theta = safe_theta(e.mean, self.theta, self.settings.max_mass)
        phi = vi.phi_of(theta)
        d = Y @ (phi - self._phi)                                      # the change of tau_mm at this pose
        lift = before is not None and before[0] > theta[0] >= 0.1      # part of the load gone, part still there
        self._undo = (vi.phi_of(before), self._k + int(self.settings.hold_axial * self.settings.rate)) if lift else None
        self.theta, self._phi = theta, phi
        self.detector.shift(d, self._P @ d)                             # the pseudo-force map at this pose
        self._r -= d                                                   # the arm is near this pose over the buffer
        e.applied = self._k / self.settings.rate
        self._pending, self._still, self._calm, self._slow, self._held = None, 0, 0, 0, None   # the arm answers: wait for rest
        self._slow_rejected = LevelMap(self.settings.pose_tolerance, size=1)
        self._stays = LevelMap(self.settings.pose_tolerance, size=1)

    def _buffer(self):
        """The last `detector.window` samples, oldest first: q, tau_ext less any fitted correction, residual."""
        keep = self.settings.detector.window
        order = (np.arange(keep) + self._k) % keep
        Q, TAU = self._q[order], self._tau[order]
        if self.correction is not None:                               # the effects a better model explains
            TAU = TAU - self.correction.correction(Q, self._dq[order])
        return Q, TAU, self._r[order]

    def _change(self, Qw, TAUw, bias, theta_before, kind, then, accept=None, level=None, asked=None, evidence=(),
                Tw=None):
        """Estimate on the window Qw, Tw = TAUw - bias (referred to the torque before a change; with the windows of
        `evidence`, combined) now, or as a job on the executor (judged once update finds it done)."""
        Tw = TAUw - bias if Tw is None else Tw
        request = (self._k if asked is None else asked, Qw, Tw, bias, theta_before, kind, then, accept, level)
        args = ([x[0] for x in evidence] + [Qw], [x[1] for x in evidence] + [Tw]) if evidence else (Qw, Tw)   # their own
        if self.executor is None:
            return self._judge(*request, *self._estimate(*args))
        self._job = (self.executor.submit(self._estimate, *args), request, self._k, False)

    def _judge(self, k, Qw, Tw, bias, theta_before, kind, then, accept, level, e, S):
        """Judge the estimate e of the window requested at sample k against the payload before the change, schedule
        it if accepted (accept(e, Tw, Ybar) with Ybar the window's mean regressor, default: explained share >=
        min_explained) and hand it to then(e, Ybar); level: the residual level it will leave. S: see _estimate
        (|Tw - Y phi|^2 summed over the window = |Tw|^2 - 2 phi.sum Y^T Tw + phi^T sum Y^T Y phi, in O(1))."""
        s, n, tt = self.settings, self.robot.n, float(np.vdot(Tw, Tw))
        Ybar, left = S[:n], lambda phi: tt - 2.0 * (S[n + 4] @ phi) + phi @ S[n:n + 4] @ phi
        e.t, e.kind = k / s.rate, kind
        before = max(left(vi.phi_of(theta_before)), 1e-12)          # what the estimate before leaves
        e.explained = 1.0 - left(vi.phi_of(e.mean)) / before
        plausible = self._plausible(e.mean)
        e.accepted = plausible and bool(e.explained >= s.min_explained if accept is None else accept(e, Tw, Ybar))
        if not plausible:
            e.reason = (f"its mass {e.mean[0]:.2f} kg or CoM {np.round(e.mean[1:], 3).tolist()} m is beyond what the "
                        f"arm carries (max_mass {s.max_mass} kg, max_com {s.max_com} m)")
        elif not e.accepted:
            e.reason = (f"explains only {100 * e.explained:.0f} % of the change" if accept is None else
                        "it does not make the compensation consistent with tau_ext")
        self.history.append(e)
        if e.accepted:                     # with an executor, on the sample after the job is found done
            self._evidence = (self._evidence + [(Qw, Tw, bias)])[-4:] if kind == "accumulated" else [(Qw, Tw, bias)]
            delay = math.ceil(e.seconds * s.rate) if s.asynchronous else 0
            self._pending = [self._k + delay if self.executor is None else self._k + 1, e, level,    # from now
                             theta_before if kind in ("detection", "at rest") else None]
        then(e, Ybar)


if __name__ == "__main__":          # python rme.py diagnose|calibrate|identify|plot LOG ...: the script's entry
    COMMANDS = {"diagnose": ("diagnosis.diagnose", "main"), "calibrate": ("diagnosis.calibrate", "main"),
                "identify": ("robot.identify", "log_main"), "plot": ("experiments.figures", "plot_main")}
    if sys.argv[1:2] and sys.argv[1] in COMMANDS:
        import importlib
        module, function = COMMANDS[sys.argv[1]]
        sys.exit(getattr(importlib.import_module(module), function)(sys.argv[2:], prog=f"rme.py {sys.argv[1]}"))
    print("usage: python rme.py diagnose LOG [--add EFFECT ...] [--json] [--plot FILE]\n"
          "       python rme.py calibrate LOG [LOG ...] [--load none|fit] [--save FILE] [--json]\n"
          "       python rme.py identify LOG [--reference REF] [--json] [--save tool.json]\n"
          "       python rme.py plot LOG [--out FILE]   (a franka.py --log run over time)\n"
          "(the estimator itself is a library: from rme import RME; demos: python sim.py --help)", file=sys.stderr)
    sys.exit(2)
