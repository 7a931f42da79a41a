"""Rapid Mismatch Estimation, the pipeline (Sec. 4, Fig. 2): detector -> 200 ms window -> network prior ->
variational inference -> compensation tau_comp = -J^T [F_hat; r_hat x F_hat] (Eq. 5). `python rme.py diagnose LOG`
compares the nominal model with a robot log and finds the missing physical effect (diagnosis/)."""
from __future__ import annotations

import math
import sys
from collections import deque
from dataclasses import dataclass

import numpy as np

import checks
from changes import ChangeModel, Payloads
from detector import Detector, safe_theta
from dynamics import Robot, as_states, phi_of, theta_of
from error_model import ErrorModel
from nn_numpy import WEIGHTS
from rme_settings import RMESettings, faulty
from window import Estimate, WindowEstimator

__all__ = ["RME", "RMESettings", "Estimate", "ErrorModel"]


@dataclass
class _Due:
    """An estimate decided on, of `kind`: applied from sample `at`; refine: estimate again once the arm is still (its
    window was taken in motion, friction in it) against `level`; job: the executor's future while it runs."""
    estimate: Estimate | None
    at: int
    kind: str
    refine: bool = False
    level: np.ndarray | None = None
    job: object = None
    phi_cov: np.ndarray | None = None    # for "back": the covariance (4, 4) of the earlier phi restored
    asked: int = 0                       # the sample the estimate was asked at (its Estimate.t)
    departure: np.ndarray | None = None  # the level's departure (n,) from the reference then


@dataclass
class _Owed:
    """The estimate on the full window a change is owed, against the reference `level` (n,) before that change: its
    window may read samples from `since` (the change's) on; error: the mass error [kg] (motion's, the pose's) the last
    window of this change could carry (RME._window_error); full: whether that window was the full one."""
    level: np.ndarray
    since: int
    error: tuple
    full: bool


@dataclass
class _Departure:
    """The residual's level away from the reference, as judged so far (a fresh one when it returns)."""
    since: int | None = None              # the sample the level first departed from the reference
    level: np.ndarray | None = None       #   and settled at this departure d (n,)
    wrench: bool = False                  # judged a wrench (counted once in RME.changes_not_payload)
    held: np.ndarray | None = None        # the settled level (n,) of a wrench still acting, if any
    still: bool = False                   #   held with the arm still
    best: str | None = None               # the most probable hypothesis
    best_since: int = 0                   #   and since which sample
    refused: np.ndarray | None = None     # a departure d (n,) not to estimate again (its estimate refused, or made
    #                                       and applied) until it moves


class RME(WindowEstimator):
    """The estimator. estimate(q, tau_ext) for a window (window.WindowEstimator); update(q, dq, tau_ext) once per 1
    ms sample for streaming use, returning the compensation torque (7,) to add to the controller's torque. Streaming
    decisions come from one model of what changed (changes.py, docs/streaming.md). executor (ours): runs each
    streamed estimate beside the loop, applied once update finds it done (settings.asynchronous moot); None: within
    update.
    calibration: the robot's error model (error_model.ErrorModel, or the JSON of `python rme.py calibrate LOG --save`;
    None: an uncalibrated Panda), which says how far tau_ext may stray from the payload's torque in a window taken
    as it is (absolute) and in one referred to the level before a change, and how far the sensors' pose-dependent
    offset may move the streamed level as the pose changes (its absolute).
    tool (ours): a known tool on the flange (motion.tool_forms: a Tool, a dict with mass, com, inertia in the flange
    frame F, or a tool.json path) that Desk does not have: its weight's torque Y(q) phi_tool is subtracted from
    tau_ext as each sample arrives (so RME estimates only what is added to it; a window referred to a level taken with
    the tool on has it cancelled already) and its compensation is returned with RME's. Its inertial torque in motion
    is not (below 0.05 Nm at the arm's usual speeds)."""

    def __init__(self, robot: Robot | None = None, weights: str | None = WEIGHTS, settings: RMESettings = RMESettings(),
                 rng: np.random.Generator | None = None, correction=None, executor=None, calibration=None, tool=None):
        super().__init__(robot, weights, settings, rng, correction, calibration, tool)   # the window's estimate
        s, n = self.settings, self.robot.n
        self.executor = executor if executor is None else checks.has_methods("executor", executor, "submit")
        self.detector = None if s.detector is None else Detector(s.detector, n=n)   # Algorithm 1 instead of the model
        keep = max(s.window, 2 * s.changes.short, 0 if s.detector is None else s.detector.window)
        self._q, self._dq, self._tau = np.zeros((keep, n)), np.zeros((keep, n)), np.zeros((keep, n))   # ring buffers
        self._k = 0                                    # samples seen
        self.model = ChangeModel(s.changes, n, keep, self.error_model.absolute)   # the residual's level, its
        #                                              reference, the posterior; the sensors' pose offset's size
        self.payloads = Payloads.plausible(s.max_mass, s.max_com)   # what a new payload may be; the earlier ones
        self.dropped = 0                               # samples refused as non-finite or beyond max_abs_torque
        self.failed, self.failure = 0, ""                # estimates that failed beside the loop; the last one's error
        self.changes_not_payload = 0                   # departures the model judged an external wrench
        self._due: _Due | None = None                  # an estimate decided on, running or waiting for its time
        self._dep = _Departure()                       # the departure from the reference under judgement
        self._owed: _Owed | None = None                # the estimate at rest a change is owed, if any
        self._quiet = None                             # the sample the level last came to sit at the compensation's
                                                       #   own (None: it does not now)
        self._own = None                               # the sample since which every judgement found the level the
                                                       #   compensation's own: quiet, or a steady departure judged
                                                       #   noise
        self._settled = False                          # it has sat there for `patience` since the compensation took
                                                       #   its present value: a state to return to
        self._still = 0                                # samples every joint has been slower than rest_speed
        self._expected = 0                             # before this sample a change is expected (expect_change)
        self.paused = False                            # True: departures are not judged (a caller moving the arm
                                                       #   on purpose: experiments.explore); the compensation stays
        self._last = np.zeros(n)                       # the last compensation returned
        self.theta, self._phi = np.zeros(4), np.zeros(4)   # the estimate compensated; its phi = (m, m r) (1 kHz loop)
        self.history: list[Estimate] = []
        self.verdicts = deque(maxlen=1000)             # (t, changes.Verdict): what the model judged, and why
        self._limit = self.robot.torque_limits()          # the compensation never asks for more than the drives give

    @property
    def settled(self) -> bool:
        """Whether the stream has its reference level and no change under judgement, estimate due or owed."""
        return self.model.reference is not None and self._dep.since is None and self._due is None and \
            self._owed is None

    def expect_change(self, seconds: float = 2.0):
        """The task expects a load change within `seconds` from now (it closes or opens the gripper): until then the
        payload hypothesis' prior odds are 10 to 1 (changes.EXPECTED), so a change the torques leave ambiguous is
        taken for a load sooner."""
        checks.number("seconds", seconds, "[0, 3600]", "s")
        self._expected = max(self._expected, self._k + 1 + int(round(seconds * self.settings.rate)))
    # --- streaming -----------------------------------------------------------------------------
    def update(self, q, dq, tau_ext) -> np.ndarray:
        """Feed one 1 kHz sample (paper sign tau_ext); returns the compensation torque (n,) = -tau_mm(q, theta_hat),
        never NaN nor beyond the torque limits. A non-finite or absurd sample (beyond max_abs_torque) is dropped and
        counted in `dropped`. What the compensation leaves, r = tau_ext - Y(q) phi_hat, is compared with its reference
        level; a departure is judged by the model of what changed (changes.ChangeModel): a new payload is estimated
        (network + VI on the window referred to the reference), an earlier one restored, a wrench or noise waited
        out."""
        n, s = self.robot.n, self.settings
        q, dq = as_states("q", q, n, allow_window=False)[0][0], as_states("dq", dq, n, allow_window=False)[0][0]
        tau = tau_ext if type(tau_ext) is np.ndarray and tau_ext.dtype == np.float64 else checks.real_array(tau_ext)
        if tau is None or tau.shape != (n,):             # (not finite: dropped below, as a sensor fault)
            raise ValueError(f"tau_ext: expected real values of shape ({n},), found "
                             f"{checks.kind(tau_ext) if tau is None else tau.shape}")
        if faulty(tau, s.max_abs_torque):
            self.dropped += 1                          # a sensor fault, not a load: never reaches the estimator
            return self._last
        _, R, J = self.robot.kinematics(q)                            # one kinematics pass per sample
        Y = self.robot.payload_regressor_from(J, R)
        tool = None
        if self.tool is not None:                                      # the known tool's weight: not RME's to find
            tool = Y @ self._tool_phi
            tau = tau - tool
        i = self._k % len(self._q)
        self._q[i], self._dq[i], self._tau[i] = q, dq, tau
        self._k += 1
        r = tau - Y @ self._phi
        if self.correction is not None:
            c = self.correction.correction(q, dq)
            r = r - c if np.isfinite(c).all() else r
        self.model.push(r, dq)
        self._still = self._still + 1 if np.abs(dq).max() < s.rest_speed else 0
        due, S = self._due, s.changes.short
        if due is not None and due.job is not None and due.job.done():
            self._received(due)
        elif due is None and self.detector is not None:
            self._algorithm_1(q, r, J)
        elif due is None and self.model.reference is None:            # the first level: the robot's own bias
            if self._k >= 2 * S and (self._still >= 2 * S or self._k >= s.window):
                self.model.set_reference(q, self._gradient(q))
        elif due is None and self._k % 5 == 0 and not self.paused:
            self._step(q, Y, J)
        elif self.paused:
            self._own = None                 # (samples not judged: no window over them is the compensation's own)
        due = self._due
        if due is not None and due.job is None and self._k >= due.at:
            self._apply(due, Y, J)
        comp = -(Y @ self._phi) if tool is None else -(Y @ self._phi) - tool
        self._last = np.minimum(np.maximum(comp, -self._limit), self._limit)
        return self._last

    def _received(self, due):
        """An estimate run beside the loop is back: decided on; one that failed there (the executor's result raises)
        is counted in `failed` with its message in `failure`, and the change is judged again (the loop goes on)."""
        try:
            e = due.job.result()
        except Exception as err:                       # (any: the 1 kHz loop never stops for an estimate)
            self.failed, self.failure, self._due = self.failed + 1, f"{type(err).__name__}: {err}", None
            return
        self._decided(e, due.level, due.kind, due.refine, due.asked, due.departure)

    def _step(self, q, Y, J):
        """Every 5th sample: judge a departure from the reference, learn the noise at rest, take the reference again
        on an arm that moves on, or make the estimate on the full window a change first estimated on the short one
        (or in motion) is owed."""
        m, s, k, S = self.model, self.settings, self._k, self.settings.changes.short
        m.inertial = self._inertial(J)
        moving = m.settling() > s.changes.detect
        departed = m.departure(q, Y) > s.changes.detect
        quiet = not (moving or departed)     # (how long the level has sat at the compensation's own)
        self._quiet = (k if self._quiet is None else self._quiet) if quiet else None
        self._settled = self._settled or (quiet and k - self._quiet >= s.changes.patience * s.rate)
        if not departed:                     # (a departure's `_own`: as judged, below)
            self._own = (k if self._own is None else self._own) if quiet else None
            if quiet and k - self._own >= s.window and self._may_refine(Y, J, q):
                return self._estimate_owed()   # (what the compensation leaves is its own error, over the
                #                                window: no other change, no push, inside it)
            if moving:
                return self._quick_return(q, Y, J)   # on its way somewhere: not yet a departure, not quiet either
            self._dep = _Departure()
            if self._still >= 2 * S and k % S == 0 and self._owed is None:
                m.learn_noise()              # (not while an estimate at rest is owed: the level holds its error)
            elif self._owed is None and quiet and k - max(self._quiet, m.reference.k) >= s.changes.patience * \
                    s.rate and m.settling(friction=False) <= s.changes.detect and \
                    m.sees_better_here(q, Y, self.payloads.std):
                m.set_reference(q, self._gradient(q))   # an arm moving on: a level quiet for `patience` (nothing
                #                                  changed that waiting would still show) and as steady as at rest
                #                                  (no speed change's friction or inertia on its way out of it),
                #                                  taken here with its friction, sees a new payload's mass better
                #                                  than the one the pose has left behind
            return
        v = m.judge(Y, J, self._phi, q, self.payloads, expected=k < self._expected, held=self._dep.held,
                    still=self._dep.still)
        self.verdicts.append((k / s.rate, v))
        if self._dep.since is None or moving or not m.same(v.d, self._dep.level, q, Y):
            self._dep.since, self._dep.level = k, v.d  # the level's age: since it settled where it is now
        self._own = (k if self._own is None else self._own) if v.best == "noise" and not moving else None
        own = k if self._own is None else self._own
        if v.best in ("noise", "payload") and k - min(self._dep.since, own) >= s.window and \
                self._may_refine(Y, J, q):
            return self._estimate_owed()     # (not under a wrench; the level steady over the whole window, or
            #                                  the compensation's own throughout it, near the departure's bar as
            #                                  it creeps while the arm sags: the estimate covers what is on the
            #                                  flange now, no change inside it)
        if v.best != self._dep.best:
            self._dep.best, self._dep.best_since = v.best, k
        young = max(k - self._dep.since, k - self._dep.best_since) < s.changes.patience * s.rate   # (a level
        #   younger than that may still change; a level drifting with friction on an arm that keeps moving is never
        #   steady, yet a hypothesis the most probable for that long has had the evidence waiting would add)
        if not self._decided_on(v, Y, young) or (moving and not (
                v.best == "payload" or (v.best == "back" and self._is_return(v, q, Y)))):
            return self._quick_return(q, Y, J) if moving else None
            #                   undecided; or the level still moves, when only a payload whose mass the data pin
            #                   down (below) or a return the level matches within the noise alone is informed
            #                   by the data rather than by the hypotheses' prior volumes
        self._act(v, q, Y, young)
        if v.best == "wrench" and (self._still >= S or not young):   # acted on, not moving (friction allowed),
            self._dep.held, self._dep.still = v.d, self._still >= S   # and with the arm moving older than patience:
            #                                  held, a return may step from it (the arm still: a payload too)

    def _quick_return(self, q, Y, J):
        """A level still on its way, judged on the newest short / 2 samples alone: a return to an earlier payload
        (no free parameter to estimate) is made when that shorter level has departed, the return is the most
        probable and decided on (as young), and the shorter level matches it within the noise alone."""
        m, s = self.model, self.settings
        if not self.payloads.earlier and not np.any(self._phi):
            return
        L = s.changes.short // 2
        if m.departure(q, Y, look=L) <= s.changes.detect:
            return
        v = m.judge(Y, J, self._phi, q, self.payloads, expected=self._k < self._expected, held=self._dep.held,
                    still=self._dep.still, look=L)
        if v.best != "back" or not self._decided_on(v, Y, True) or not self._is_return(v, q, Y, look=L):
            return
        self.verdicts.append((self._k / s.rate, v))
        self._act(v, q, Y, True)

    def _is_return(self, v, q, Y, look=None) -> bool:
        """Whether the level (of `look` samples) is the return v judged, within the noise alone: the earlier
        payload's torque less the compensation's, plus the held wrench's level it steps from, if any."""
        return self.model.explains(Y @ (v.phi - self._phi) + (0 if v.under is None else v.under), q, Y, look=look)

    def _decided_on(self, v, Y, young: bool) -> bool:
        """Whether the most probable hypothesis of v is acted on now. A compensation's change (a payload, a return)
        when the expected loss of making it (changes.Verdict.loss) is at most (1 - confidence) / confidence of keeping
        the compensation, while the level is young (waiting may still show which), or below it once it is not; the
        others, which leave the compensation as it is, when their posterior is at least `confidence`, or above 1/2.
        Where every other hypothesis keeps the compensation, the two are the same rule."""
        c = self.settings.changes.confidence
        if v.best in ("noise", "wrench"):
            return v.sure >= c if young else v.sure > 0.5
        act, keep = v.loss(Y, v.means[v.best]), v.loss(Y, self._phi)
        return act <= (1 - c) / c * keep if young else act < keep

    def _act(self, v, q, Y, young: bool):
        """Act on the verdict v the departure was decided by (docs/streaming.md, "When it acts"): estimate a new
        payload, return to an earlier one, correct the one held or take the level as the new reference; a wrench is
        counted and left alone."""
        m, s, k, S = self.model, self.settings, self._k, self.settings.changes.short
        if v.best == "payload":
            if v.mass_std > max(0.05 * v.phi[0], 0.025) and young and m.arriving() > s.changes.detect:
                return                       # its mass not yet known to half the compensation's tolerance (10 %
                #                              or 50 g) and the level may still be on its way (its move beyond the
                #                              friction's change: changes.ChangeModel.arriving)
            if self._dep.refused is not None and m.same(v.d, self._dep.refused, q, Y):
                return                       # this level's estimate was refused: not again until it moves
            W, level = s.detection_window, self._still_level()
            if v.under is None:
                self._estimate_now(W, level, "detection", refine=W < s.window or self._still < W)
            else:                            # under a held wrench: less its level too (the payload's step alone);
                #                              not again at rest, when the wrench may be gone from that level
                self._estimate_now(W, level + v.under, "detection", refine=False)
        elif v.best.startswith("back"):                     # (under a wrench too: the payload part is known)
            e = Estimate(np.nan_to_num(theta_of(v.phi)), np.zeros(4), np.zeros((4, 4)), np.zeros(4),   # (no mass: r 0)
                         np.zeros(4, dtype=bool), 0.0,
                         0, True, t=k / s.rate, kind="back", prior_source="")
            e.reason = "the level returned to what this earlier payload leaves"
            self.history.append(e)
            self._due = _Due(e, k, "back", phi_cov=v.cov)
        elif v.best == "noise" and (theta := self._corrected(v)) is not None:
            self._correct(v, theta)          # nothing changed, yet the data move the compensated mass by more than
            #                                  half the tolerance: the estimate was off (a window in motion)
        elif v.best == "noise" and self._still >= 2 * S and self._owed is None:
            m.set_reference(q, self._gradient(q))      # the bias moved with the pose: its new level
            self._dep.since = None                                     # (still: no friction in it)
        elif not self._dep.wrench:
            self.changes_not_payload, self._dep.wrench = self.changes_not_payload + 1, True

    def _inertial(self, J) -> np.ndarray:
        """The variance (n,) [Nm^2] of the compensated payload's inertial force in the level over the last `short`
        samples (the payload regressor holds the weight alone); zeros with nothing compensated."""
        S = self.settings.changes.short
        if self.theta[0] == 0.0:
            return np.zeros(self.robot.n)
        return self._inertial_force(J, self._dq[np.arange(self._k - S, self._k) % len(self._dq)], S // 4) ** 2

    def _inertial_force(self, J, dq, L) -> np.ndarray:
        """The joint torques (n,) of the compensated payload's inertial force m a through J_v^T over a window dq
        (W, n): a (3,) the flange's mean acceleration across it, J (mean dq of its last L samples less that of its
        first L) over their span."""
        a = J[:3] @ (dq[-L:].mean(axis=0) - dq[:L].mean(axis=0)) * self.settings.rate / (len(dq) - L)
        return J[:3].T @ (self.theta[0] * a)

    def _good(self) -> float:
        """A quarter of the tolerance the compensated mass is judged by (10 % or 50 g) [kg]: half the bar a mass is
        acted on at."""
        return max(0.025 * self.theta[0], 0.0125)

    def _may_refine(self, Y, J, q) -> bool:
        """Whether the full-window estimate a change is owed may be made now (computed only where everything else
        allows it): the window past the change, and the mass error it could carry (_window_error: motion's share and
        the pose's) small enough. After a short window: motion's share within a quarter of the tolerance or half of
        what it left in the last window (both carry the pose's share alike). After a full-window estimate made in
        motion: in motion, only while that one's motion share was above the quarter, the same, and the error no
        larger in all; with the arm still over the window, its error at most half that one's, else (what is left is
        the pose's, which waiting does not shrink) no estimate is owed any more."""
        W, owed = self.settings.window, self._owed
        if owed is None or self._k - owed.since < W:
            return False
        motion, pose = self._window_error(Y, J, q)
        last_motion, last_pose = owed.error
        if not owed.full:
            return motion <= max(self._good(), last_motion / 2)
        if self._still >= W:
            self._owed = owed if motion + pose <= (last_motion + last_pose) / 2 else None
            return self._owed is not None
        return (last_motion > self._good() and motion <= max(self._good(), last_motion / 2)
                and motion + pose <= last_motion + last_pose)

    def _window_error(self, Y, J, q) -> tuple[float, float]:
        """The mass error [kg] an estimate on the newest `window` samples, referred to the level owed against, could
        carry, at most (_carried's torques, signs unknown, magnitudes summed): motion's and the level's (what the
        pose's change since that level's pose carries, twice the offset's std, and that level's own friction), each
        joint's torque carried into the mass by the least squares of the regressor Y (n, 4) at this pose."""
        motion, friction, g, bias = self._carried(J, q, self.settings.window)
        p = np.linalg.pinv(Y)[0]
        return float(np.abs(p) @ motion), float(abs(p @ g) + 2 * math.sqrt(p * p @ bias) + np.abs(p) @ friction)

    def _carried(self, J, q, W):
        """What a window of the newest W samples, referred to the reference level, holds besides the payload, per
        joint [Nm]: motion's torque (n,) (the joints' friction at their mean speeds over it,
        changes.ChangeModel.friction, and the compensated payload's inertial force m a, a (3,) the flange's mean
        acceleration over it, J dq differentiated across it), the level's friction std (n,), and the pose's change
        since the level's pose (changes.ChangeModel.carried: the robot model's error g (n,) along the gravity
        torque's change, the variance (n,) [Nm^2] of the sensors' pose-dependent offset)."""
        dq = self._dq[np.arange(self._k - W, self._k) % len(self._dq)]                 # (W, n)
        motion = self.model.friction(np.abs(dq).mean(axis=0)) + np.abs(self._inertial_force(J, dq, min(20, W // 4)))
        return (motion, self.model.reference.friction) + self.model.carried(q)

    def _carried_cov(self, Y, J, q, W) -> np.ndarray:
        """The covariance (4, 4) of the error in phi an estimate of the newest W samples carries from _carried (each
        part a std, signs unknown) through the least squares of Y (n, 4)."""
        motion, friction, g, bias = self._carried(J, q, W)
        P = np.linalg.pinv(Y)
        return (P * (motion ** 2 + friction ** 2 + bias)) @ P.T + np.outer(P @ g, P @ g)

    def _corrected(self, v):
        """theta (4,) the noise hypothesis' posterior v.kept (4,) compensates (within what the arm carries: safe_theta),
        or None when its mass is within half the tolerance (10 % or 50 g) of the compensated one, or not finite, or
        its CoM beyond max_com (a posterior outside what the arm carries, clipped, would leave the level where it is
        and be corrected again)."""
        if not np.all(np.isfinite(v.kept)):
            return None
        if v.kept[0] > 0 and np.abs(v.kept[1:]).max() > self.settings.max_com * v.kept[0]:
            return None                      # no payload a hand carries (its CoM beyond max_com): a move of the
            #                                  level's bias, not of the payload's estimate
        theta = safe_theta(np.nan_to_num(theta_of(v.kept)), self.theta, self.settings.max_mass)
        return theta if abs(theta[0] - self.theta[0]) > max(0.05 * theta[0], 0.025) else None

    def _correct(self, v, theta):
        """Compensate the payload held as the noise hypothesis' posterior says (v.kept, v.kept_cov; theta (4,) its
        _corrected): the same payload, its estimate corrected by the level's departure; the estimate at rest stays
        owed."""
        s = self.settings
        D = np.linalg.inv(_phi_jacobian(theta)) if theta[0] > 1e-3 else np.diag([1.0, 0, 0, 0])   # theta's cov
        cov = D @ v.kept_cov @ D.T                         #   from phi's (no mass: its own variance, no CoM to have)
        held = next((h for h in reversed(self.history) if h.accepted and math.isfinite(h.applied)), None)
        observed = np.zeros(4, dtype=bool) if held is None else held.observed.copy()   # (the payload it corrects)
        e = Estimate(theta, np.sqrt(np.maximum(np.diag(cov), 0.0)), cov, np.zeros(4), observed, 0.0, 0, True,
                     t=self._k / s.rate, kind="correction", prior_source="")
        e.reason = "nothing changed, and the level says the compensated payload's estimate was off"
        self.history.append(e)
        self._due = _Due(e, self._k, "correction", phi_cov=v.kept_cov, departure=v.d)

    def _estimate_owed(self):
        """The estimate on the full window a change first estimated on the short one (or in motion) is owed, against
        the level before that change (_may_refine says when); made only while the level is the compensation's own,
        noise's or a payload's (not a wrench's holding the arm still), and owed again while the arm moved in that
        window (a window of the arm still may do better)."""
        level, self._owed = self._owed.level, None
        return self._estimate_now(self.settings.window, level, "at rest", refine=self._still < self.settings.window)

    def _algorithm_1(self, q, r, J):
        """Algorithm 1 (settings.detector) on the residual: each detection estimated on its window of tau_ext as it
        is (the whole payload, as the paper does), applied if plausible."""
        if self.detector.watch(r, q, J) and self._k >= self.detector.settings.window:
            self._estimate_now(self.settings.detection_window, np.zeros(self.robot.n), "detection", refine=False)

    def _gradient(self, q):
        """d G / d q (n, n) of the nominal gravity torque at q (central differences): the direction the robot
        model's error moves in as the pose changes (changes.ChangeModel.covariance)."""
        h, E = 1e-4, np.eye(self.robot.n) * 1e-4
        return np.stack([(self.robot.gravity(q + e) - self.robot.gravity(q - e)) / (2 * h) for e in E], axis=1)

    def _still_level(self) -> np.ndarray:
        """The reference level (n,) as the arm at rest would leave it: less the joints' friction it holds
        (changes.ChangeModel.friction_in), which a window's samples have taken out as well (_estimate_now); as it
        is with a correction, which takes the calibrated friction out of every sample, the level's too."""
        ref = self.model.reference
        return ref.level if self.correction is not None or ref.moving is None else ref.level - ref.moving

    def _estimate_now(self, W, level, kind, refine):
        """Network + VI on the newest W samples less `level` (the residual the compensation left before the change,
        as the arm at rest would leave it: _still_level) and less the joints' friction each sample holds (the
        correction's, else changes.ChangeModel.friction_in; not for Algorithm 1): what remains is the whole payload's
        torque, now or as a job on the executor."""
        idx = np.arange(self._k - W, self._k) % len(self._q)
        Qw, Tw = self._q[idx], self._tau[idx] - level
        m = self.model
        now = None if m.reference is None else m.mean(self.settings.changes.short) - m.reference.level
        if self.correction is not None:
            Tw = Tw - self.correction.correction(Qw, self._dq[idx])
        elif self.detector is None:          # (Algorithm 1 estimates its window of tau_ext as it is, as printed)
            Tw = Tw - m.friction_in(self._dq[idx])
        if self.executor is None:
            return self._decided(self._estimate(Qw, Tw), level, kind, refine, departure=now)
        prepare = getattr(self.executor, "prepare", None)
        if prepare is not None:
            prepare(Qw, Tw)
        self._due = _Due(None, -1, kind, refine, level, self.executor.submit(self._estimate, Qw, Tw), asked=self._k,
                         departure=now)

    def _decided(self, e, level, kind, refine, asked=None, departure=None):
        """An estimate of the window referred to `level`, asked at sample `asked` (None: now), is back: applied
        (after its own wall time, if settings.asynchronous, or from the next sample with an executor) if the arm can
        carry it."""
        s = self.settings
        e.t, e.kind = (self._k if asked is None else asked) / s.rate, kind
        e.accepted = self._plausible(e.mean)
        self.history.append(e)
        self._due = None
        if not e.accepted:
            e.reason = (f"its mass {e.mean[0]:.2f} kg or CoM {np.round(e.mean[1:], 3).tolist()} m is beyond what the "
                        f"arm carries (max_mass {s.max_mass} kg, max_com {s.max_com} m)")
            self._dep.refused = self.model.mean(s.changes.short) - self.model.reference.level \
                if self.model.reference is not None else None
            return
        delay = (math.ceil(e.seconds * s.rate) if s.asynchronous else 0) if self.executor is None else 1
        self._due = _Due(e, self._k + delay, kind, refine, level, departure=departure)

    def _plausible(self, theta) -> bool:
        """Whether theta (4,) is a payload the arm can carry: mass <= 1.2 max_mass and, from 0.1 kg on, CoM within
        max_com."""
        s = self.settings
        return bool((theta[0] < 0.1 or np.all(np.abs(theta[1:]) <= s.max_com)) and theta[0] <= 1.2 * s.max_mass)

    def _apply(self, due, Y, J):
        """Compensate the decided estimate from now on; the residuals held are re-expressed under it. An estimate is
        the payload hypothesis' posterior for the level it was made of: what it leaves (the robot's error at this
        pose beyond the reference's) is not estimated again until the level moves (it would return the same); one
        made on the short window or in motion is made again on the full one at rest, as owed."""
        self._due, s = None, self.settings
        theta = safe_theta(due.estimate.mean, self.theta, self.settings.max_mass)
        phi = phi_of(theta)
        if due.kind == "back":               # the change undone: not a state to return to (a press let go); its
            due.level = self.payloads.forget(phi)            # estimate at rest owed again, if it was owed then
            due.refine = due.level is not None
        elif due.kind not in ("at rest", "correction") and self._settled:
            self.payloads.remember(self._phi, self.model.error,       # a state whose level settled
                                   None if self._owed is None else self._owed.level)
        if due.kind != "at rest":            # (not an estimate in motion the next corrected; one made again at rest
            self._settled, self._quiet, self._own = False, None, None     #   is the same state refined)
        m = self.model                       # its error: a window's, referred to the reference level, holds that
        held = np.zeros((4, 4)) if m.reference is None else m.reference.held   # level's error too; an earlier
        own = _phi_cov(theta, due.estimate.cov) if due.phi_cov is None else due.phi_cov   # payload's is its own,
        m.error, m.compensated = (own, own + held) if due.kind == "back" else (own + held, own)   # the level shows
        #                                                                  it beside the reference's
        if due.kind in ("detection", "at rest") and m.reference is not None:   # and what its window carried
            m.error = m.error + self._carried_cov(Y, J, self._q[(self._k - 1) % len(self._q)],
                                                  s.detection_window if due.kind == "detection" else s.window)
        d = Y @ (phi - self._phi)                                      # the change of tau_mm at this pose
        self.theta, self._phi = theta, phi
        self.model.shift(d)
        if self.detector is not None:
            self.detector.shift_watched(d)
        due.estimate.applied = self._k / self.settings.rate
        self._dep = _Departure()
        if due.kind != "correction":         # (a correction leaves the estimate at rest owed as it was)
            self._owed = None if not due.refine or due.level is None else _Owed(
                due.level, round(due.estimate.t * s.rate) - s.detection_window,
                self._window_error(Y, J, self._q[(self._k - 1) % len(self._q)]), due.kind == "at rest")
        if due.kind != "back" and due.departure is not None:
            self._dep.refused = due.departure - d        # (the level it was made of, under the new compensation)


def _phi_jacobian(theta):
    """d phi / d theta (4, 4) at theta: phi = (m, m r)."""
    m, r = theta[0], theta[1:]
    D = np.zeros((4, 4))
    D[0, 0], D[1:, 0], D[1:, 1:] = 1.0, r, m * np.eye(3)
    return D


def _phi_cov(theta, cov):
    """Covariance (4, 4) of phi = (m, m r) from theta's (4, 4) at theta (first order)."""
    D = _phi_jacobian(theta)
    return D @ np.asarray(cov) @ D.T


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
