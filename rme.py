"""Rapid Mismatch Estimation, the pipeline (Sec. 4, Fig. 2): detector -> 200 ms window -> network prior ->
variational inference -> compensation tau_comp = -J^T [F_hat; r_hat x F_hat] (Eq. 5). `python rme.py diagnose LOG`
compares the nominal model with a robot log and finds the missing physical effect (diagnosis/)."""
from __future__ import annotations

import math
import sys
import time

import numpy as np
from scipy.linalg import lapack

import vi
from detector import Detector, LevelMap, Levels, payload_like, safe_theta, steady_prefix, through_flange
from dynamics import Robot, as_states
from nn_numpy import WEIGHTS, MismatchNet
from rme_settings import Estimate, RMESettings

__all__ = ["RME", "RMESettings", "Estimate"]


class RME:
    """The estimator. estimate(q, tau_ext) for a window; update(q, dq, tau_ext) once per 1 ms sample for streaming
    use, returning the compensation torque (7,) to add to the controller's torque. executor (ours): runs each streamed
    estimate beside the loop, applied once update finds it done (settings.asynchronous moot); None: within update."""

    def __init__(self, robot: Robot | None = None, weights: str | None = WEIGHTS, settings: RMESettings = RMESettings(),
                 rng: np.random.Generator | None = None, correction=None, executor=None):
        self.robot = Robot.panda() if robot is None else robot
        self.settings, self.correction, self.executor = settings, correction, executor
        self._job, self._queued, self._steps = None, None, None   # (future, request, sample, received) in flight;
                                                       #   a request; (generator, sample): a detection's steps
        self.rng = np.random.default_rng(0) if rng is None else rng
        self.net = MismatchNet.load(weights) if settings.use_network and weights is not None else None  # or ValueError
        if not isinstance(settings, RMESettings):
            raise ValueError(f"settings: expected an RMESettings, found {type(settings).__name__}")
        self.detector = Detector(settings.detector, n=self.robot.n)
        n, keep = self.robot.n, settings.detector.window
        self._q, self._dq, self._tau = np.zeros((keep, n)), np.zeros((keep, n)), np.zeros((keep, n))   # ring buffers
        self._r = np.zeros((keep, n))                  # ring of residuals tau_ext - tau_mm(q, theta) (- correction)
        self._k = 0                                    # samples seen
        self._fq, self._P = np.full(n, np.inf), None   # the pose (1e-3 rad) of the pseudo-force map P (3, n)
        self.dropped = 0                               # samples refused as non-finite or beyond max_abs_torque
        self.changes_not_payload, self.changes_held = 0, 0   # detections no payload explains (not estimated); held
        self._held = None                              # the sample since which a change has been held (_held_back)
        self._evidence = []                            # (q, tau) windows of the compensated payload (accumulate)
        self._lv = Levels(settings.pose_tolerance, settings.monitor_threshold)   # residual levels by pose
        self._last = np.zeros(n)                       # the last compensation returned
        self.theta, self._phi = np.zeros(4), np.zeros(4)   # the estimate compensated; its phi = (m, m r) (1 kHz loop)
        self._pending = None                           # (sample index when it applies, Estimate)
        self._refine, self._still, self._calm = None, 0, 0   # a pending estimate at rest; samples the arm has been
                                                       #   still, and slower than monitor_speed
        self.history: list[Estimate] = []
        self._limit = self.robot.torque_limits()          # the compensation never asks for more than the drives give

    def _payload_like(self, d, gate, YJ, mass=None) -> bool:
        """detector.payload_like for a residual change d (n,) at a pose with payload regressor and Jacobian YJ, from
        the payload mass compensated (now)."""
        return payload_like(YJ[0], d, self.theta[0] if mass is None else mass, gate, YJ[1], 1.2 * self.settings.max_mass)

    # --- one window ----------------------------------------------------------------------------
    def estimate(self, q, tau_ext, baseline=None, dq=None) -> Estimate:
        """Posterior of theta from a window q, tau_ext (T, n) (paper sign), T about 200 at 1 kHz; or from lists of
        windows [q_a, q_b], [tau_a, tau_b] of one payload (each (T_i, n); baseline and dq lists too, or None): one
        posterior, their evidence combined (vi.combine), the prior mean the network's mean over them.
        baseline (n,): the tau_ext seen before the change, subtracted first (default: none).
        dq (T, n): joint velocities, needed only by a velocity-dependent correction (e.g. fitted friction)."""
        if not isinstance(q, (list, tuple)):
            return self._estimate(*self._window(q, tau_ext, baseline, dq))[0]
        each = lambda v: [None] * len(q) if v is None else list(v) if isinstance(v, (list, tuple)) else []
        if not (q and len(each(tau_ext)) == len(q) == len(each(baseline)) == len(each(dq))):
            raise ValueError(f"q, tau_ext, baseline, dq: expected lists of {len(q)} windows (or None), found other")
        windows = [self._window(*w) for w in zip(q, each(tau_ext), each(baseline), each(dq))]
        return self._estimate([w[0] for w in windows], [w[1] for w in windows])[0]

    def _window(self, q, tau_ext, baseline, dq):
        """A checked (q, tau) (T, n) window, less the baseline and the correction."""
        n, q_in, tau_in = self.robot.n, q, tau_ext
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
        return q, tau

    def _estimate(self, q, tau):
        """Network prior and VI on checked, referred, corrected windows (or lists): (Estimate, S) with S (n + 5, 4)
        what judging it needs of the newest window (regressor Y, torques T): mean Y, sum Y^T Y, sum Y^T T (rows)."""
        start, many, Ys, priors = time.perf_counter(), isinstance(q, list), [], []
        for qi, ti in zip(q if many else [q], tau if many else [tau]):
            _, R, J = self.robot.kinematics(qi)                     # one forward-kinematics pass per window
            Ys.append(self.robot.payload_regressor_from(J, R))
            priors.append(self.net.predict_window(self.robot, qi, ti, (R, J)) if self.net is not None else np.zeros(4))
        prior = np.mean(priors, axis=0)
        prior = prior if np.all(np.isfinite(prior)) else np.zeros(4)   # the network overflowed on absurd torques
        speed = [vi.joint_speed(qi, 1 / self.settings.rate) for qi in q] if many else vi.joint_speed(q, 1 / self.settings.rate)
        post = vi.fit(Ys if many else Ys[0], tau, prior, self.settings.vi, self.rng, speed=speed,
                      sigma_prior=None if self.net is None else self.net.prior_std(prior, self.settings.vi.sigma_prior, R[-1]))
        return Estimate(post.mean, post.marginal_std, post.cov, np.asarray(prior, float), post.observed,
                        time.perf_counter() - start, post.iterations, post.converged), np.vstack([
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
        tau = np.asarray(tau_ext, dtype=float)
        if tau.shape != (n,):
            raise ValueError(f"tau_ext: expected shape ({n},), found {tau.shape}")
        if not np.all(np.isfinite(tau)) or np.abs(tau).max() > s.max_abs_torque:
            self.dropped += 1                          # a sensor fault, not a load: never reaches the estimator
            return self._last
        i = self._k % keep
        self._q[i], self._dq[i], self._tau[i] = q, dq, tau
        self._k += 1
        # the detector watches what the current estimate does not explain, r = tau_ext - tau_mm(q, theta_hat):
        # a known load carried to another pose changes tau_ext but not r (ours; Alg. 1 watches tau_ext itself)
        _, R, J = self.robot.kinematics(q)                            # one kinematics pass per sample
        Y = self.robot.payload_regressor_from(J, R)
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
        if self._job is not None and self._job[2] < self._k:           # polled from the next sample on
            if self._job[3]:                           # received on the sample before: judged now
                (future, request, *_), self._job = self._job, None
                self._judge(*request, *future.result())
            elif self._job[0].done():
                self._job = (*self._job[:3], True)
        idle = self._pending is None and self._job is None and self._queued is None and self._steps is None
        if self._refine is not None and idle:
            r = self._refine                           # (a held change is estimated once it has lasted, moving or not)
            if self._still >= s.window or (self._calm >= s.monitor_window and self._k > r["deadline"] - s.rate / 2) \
                    or (r.get("held") and self._k - r["since"] >= s.hold_axial * s.rate):
                self._on_rest(J)
            elif self._k > r["deadline"] + 2 * s.refine_within * s.rate:
                self._refine = self._held = None       # the arm never rested: the monitor checks it when it does
        elif s.monitor and idle and self._calm >= s.monitor_window and self._k % 10 == 0:
            self._check_consistency(Y, J)
        if self._pending is not None and self._k >= self._pending[0]:
            self._apply(*self._pending[1:], Y, J)
            tau_mm = Y @ self._phi
        if self._queued is not None and self._job is None and self._steps is None and self._pending is None:
            asked, self._queued = self._queued, None   # under the compensation just applied
            self._on_detection(asked)
        self._last = np.minimum(np.maximum(-tau_mm, -self._limit), self._limit)
        return self._last

    def _apply(self, e, level, Y, J):
        """Compensate the estimate e from now on; the detector's buffer is re-expressed in the new residual. level:
        (q, residual level) the new compensation should leave at pose q (its reference), or None."""
        self._lv.muted, self._lv.rejected = LevelMap(self.settings.pose_tolerance), None   # judged before it
        if level is not None:
            self._lv.explained.put(*level)
        theta = safe_theta(e.mean, self.theta, self.settings.max_mass)
        d = Y @ (vi.phi_of(theta) - self._phi)                         # the change of tau_mm at this pose
        self.theta, self._phi = theta, vi.phi_of(theta)
        self.detector.shift(d, self._P @ d)                             # the pseudo-force map at this pose
        self._r -= d                                                   # the arm is near this pose over the buffer
        e.applied = self._k / self.settings.rate
        self._pending, self._still, self._calm, self._held = None, 0, 0, None   # the arm answers: wait for rest

    def _buffer(self):
        """The last `detector.window` samples, oldest first: q, tau_ext less any fitted correction, residual."""
        keep = self.settings.detector.window
        order = (np.arange(keep) + self._k) % keep
        Q, TAU = self._q[order], self._tau[order]
        if self.correction is not None:                               # the effects a better model explains
            TAU = TAU - self.correction.correction(Q, self._dq[order])
        return Q, TAU, self._r[order]

    def _on_detection(self, asked=None):
        """Estimate the total payload from the newest window, referred to the torque before the change. An accepted
        change during a pending estimate at rest supersedes it. asked: the sample of a detection made during a job.
        With an executor its steps run one per sample (no cycle of the loop carries them all); else all at once."""
        steps = self._detection(asked)
        if self.executor is not None:              # the first step (the window) now, the next ones from the next sample
            self._steps = (steps, self._k) if next(steps, True) is None else None
        else:
            list(steps)                            # all at once

    def _detection(self, asked):
        """_on_detection's steps (a generator: each yield hands the rest to the next sample)."""
        s = self.settings
        Q, TAU, Rs = self._buffer()
        q_ref, before, asked = Q[:s.reference].mean(axis=0), self.theta.copy(), self._k if asked is None else asked
        held, pending = (self._refine, None) if (self._refine or {}).get("held") else (None, self._refine)
        level = Rs[-s.window:].mean(axis=0)   # (pending: an estimate at rest is due: refer to before its change)
        if self._lv.undone(Q[-1], level):
            self._held, self._refine = None, pending if held is None else self._resumed(held)
            return                         # back to the level before a change that was no payload: its release
        yield                              # (with an executor each step costs 0.05-0.1 ms in a loop's cold caches)
        steady = steady_prefix(Rs, s.reference, len(Rs) - s.window) if pending is None else 0
        yield
        bias = pending["bias"] if pending is not None else self._lv.bias(Rs[:steady], q_ref)   # the level before,
        yield                                                                                   # as long as it holds
        _, R, J = self.robot.kinematics(Q[-1])
        if not self._payload_like(level - bias, s.min_explained, (self.robot.payload_regressor_from(J, R), J), before[0]):
            self.changes_not_payload, self._lv.rejected = self.changes_not_payload + 1, (q_ref, bias)
            return                         # a push, a bias step
        yield
        known = None if np.linalg.norm(bias) > s.monitor_far else (q_ref, bias)    # the level to leave, unless pushed
        if self._held_back(level - bias, J, asked - s.window, int(np.abs(self._dq).max() < s.monitor_speed)):
            self.changes_held, self._lv.rejected = self.changes_held + 1, (q_ref, bias)
            self._refine = dict(bias=bias, known=known, before=before, held=True, since=self._held,   # judged
                                resume=pending if held is None else held["resume"],                     # again at
                                window=(Q[-s.window:], TAU[-s.window:]), level=level,                   # rest
                                deadline=self._k + int(s.refine_within * s.rate))
            return
        yield
        Qw, Tw, prepare = Q[-s.window:], TAU[-s.window:] - bias, getattr(self.executor, "prepare", None)
        if prepare is not None:            # the window into the worker's shared memory now, the job on the next sample
            prepare(Qw, Tw)
            yield
        def then(e, Y):
            self._lv.rejected = None if e.accepted else (q_ref, bias)   # the level before a change that is no payload
            if e.accepted:                 # a rejected detection (the arm answering a compensation) keeps the last
                self._refine = None        #   pending estimate at rest
            if e.accepted and s.refine:
                self._refine = dict(bias=bias, known=known, before=before, deadline=self._k + int(s.refine_within * s.rate))
        self._change(Qw, TAU[-s.window:], bias, before, "detection", then, asked=asked, level=known, Tw=Tw)

    def _on_rest(self, J):
        """Once the arm is still for a window after a detection, estimate again from it (friction no longer holds part
        of the load). A change held at the detection (_held_back, J: update's): released, still held, or estimated."""
        s, r, keep = self.settings, self._refine, len(self._r)
        rest = self._still >= s.window or self._calm >= s.monitor_window
        if r.get("held"):                                              # every 10th sample, from the rings
            if self._k % 10:
                return
            q, level = self._q[(self._k - 1) % keep], self._r[(self._k - s.window + np.arange(s.window)) % keep].mean(0)
            gap = lambda b: np.linalg.norm(level - b)
            if any(gap(b) <= s.monitor_threshold for b in (r["bias"], self._lv.explained.at(q)) if b is not None):
                self._refine, self._held = self._resumed(r), None      # back to the level before it, or to one the
                return                                                 #   compensation explains here: released
            if gap(r["bias"]) < gap(r["level"]):                       # nearer the level before: the press has gone,
                r = self._refine = dict(r, held=False)                 #   what is left is estimated at rest
                if not rest:
                    return
            elif self._k - r["since"] < s.hold_axial * s.rate and through_flange(J, level - r["bias"], s.axial_radius[1]):
                return                                                 # (the monitor stays off meanwhile)
        self._refine, self._held = None, None
        if r.get("held") and not rest:                                 # lasted while the arm moves: the detection's
            again = lambda e, Y: e.accepted and s.refine and setattr(self, "_refine", dict(   # window, then again at
                r, held=False, deadline=self._k + int(s.refine_within * s.rate)))           # rest
            return self._change(*r["window"], r["bias"], r["before"], "detection", again, level=r["known"])
        Q, TAU, _ = self._buffer()
        self._change(Q[-s.window:], TAU[-s.window:], r["bias"], r["before"], "at rest", lambda e, Y: None, level=r["known"])

    def _resumed(self, held):                      # the estimate at rest a held change superseded, due from now
        r, s = held["resume"], self.settings
        return None if r is None else dict(r, deadline=self._k + int(s.refine_within * s.rate))

    def _check_consistency(self, Y, J):
        """The monitor (see update): the residual's level over the last monitor_window samples, if steady, against
        the level explained before at this pose. The very first level is estimated against no payload at all (RME
        assumes it starts unloaded) with the stricter gate first_explained; at a pose never seen, the level is
        taken as explained, unless it is monitor_far from the nearest level known (detector.Levels.judge). Y, J: the
        payload regressor and Jacobian of the current sample (update's), where a payload is tested."""
        s = self.settings
        last = (self._k - s.monitor_window + np.arange(s.monitor_window)) % len(self._r)   # no reorder, no correction
        level, recent = self._r[last].mean(axis=0), self._r[last[-(s.monitor_window // 3):]].mean(axis=0)
        if np.linalg.norm(recent - level) > 0.5 * s.monitor_threshold:
            return                                                     # still changing: not a level yet
        q = self._q[last].mean(axis=0)
        first_gate = s.first_explained if self.theta[0] <= 0 else s.min_explained   # strict only if nothing compensated
        verdict = self._lv.judge(q, level, lambda d, gate: self._payload_like(d, gate, (Y, J)),
                                 (first_gate, s.min_explained), s.monitor_far)
        if verdict == "new" and s.accumulate and self._evidence and self.theta[0] > 0.05 and self._turned(q):
            Q, TAU, _ = self._buffer()           # the same payload seen from a new side: combine the evidence
            same = lambda e, Tw, Y: abs(e.mean[0] - self.theta[0]) <= max(0.1 * self.theta[0], 0.05)
            self._change(Q[-s.window:], TAU[-s.window:], self._evidence[0][2], self.theta, "accumulated",
                         self._leaves(q, level), same, evidence=self._evidence)   # referred like the first window
            self._calm = 0
        if verdict is None:
            self._held = None
        held, before = self._held is not None, self.theta.copy()    # a change held that is let go now: estimated
        if verdict is None or verdict == "new" or self._held_back(level - verdict[0], J, self._k - s.monitor_window,
                                                                  1):   # again at rest (see then)
            return
        (reference, kind), first = verdict, verdict[1] == "first"
        Q, TAU, _ = self._buffer()               # the window to estimate on (correction applied)
        if first:                                # against no payload: only a clear payload counts
            accept = lambda e, Tw, Y: e.explained >= first_gate
        else:                                    # the new estimate must make the level consistent again: within
            gap = np.linalg.norm(level - reference)  # 6 % of a large gap (a heavy load's sag moves the bias); far from
            tol = 0.25 * gap if kind == "far" else min(max(s.monitor_threshold, 0.06 * gap), 0.5 * gap)   # any pose: 3/4
            accept = lambda e, Tw, Ybar: np.linalg.norm(Tw.mean(axis=0) - Ybar @ vi.phi_of(safe_theta(
                e.mean, self.theta, s.max_mass))) <= tol
        def then(e, Y):
            if e.accepted and first:                                   # what the payload leaves is the bias
                self._pending[2] = (q, TAU[-s.window:].mean(axis=0) - Y @ vi.phi_of(e.mean))
            elif first:
                self._lv.explained.put(q, level)                             # no payload: the level is the bias
                self.history.pop()                                     # (establishing it is not an estimate)
            elif kind == "far":
                self._leaves(q, level)(e) if e.accepted else self._lv.muted.put(q, level)
            elif not e.accepted:
                self._lv.muted.put(q, level)
            if e.accepted and held and s.refine:
                self._refine = dict(bias=reference, known=None if kind != "level" else (q, reference), before=before,
                                    deadline=self._k + int(s.refine_within * s.rate))
        self._change(Q[-s.window:], TAU[-s.window:], reference, self.theta, "monitor", then, accept,
                     level=None if kind != "level" else (q, reference))
        self._calm = 0

    def _held_back(self, d, J, since, rest) -> bool:
        """Whether a payload-like change d (n,) waits: it adds a downward force through the flange (through_flange, J
        the flange's Jacobian; rest 0/1: the arm moves/rests, picks axial_radius) and has lasted less than hold_axial
        since self._held (set to `since`, the sample it began by, if None; cleared when such a change goes)."""
        s = self.settings
        if s.hold_axial <= 0 or not through_flange(J, d, s.axial_radius[rest]):
            self._held = None
            return False
        self._held = since if self._held is None else self._held
        return self._k - self._held < s.hold_axial * s.rate

    def _leaves(self, q, level):
        """then(e, Y) for an estimate at pose q, residual level `level` now: once accepted, what it leaves is explained."""
        Yq, phi = self.robot.payload_regressor(q), self._phi.copy()
        return lambda e, Y=None: e.accepted and self._lv.explained.put(q, level - Yq @ (vi.phi_of(safe_theta(
            e.mean, self.theta, self.settings.max_mass)) - phi))

    def _turned(self, q) -> bool:
        """Whether gravity, seen from the ee at pose q, has turned by accumulate_angle from every window kept."""
        g = lambda x: self.robot.ee_pose(x)[1][2]             # the world z axis in the ee frame
        return all(np.arccos(np.clip(g(q) @ g(Q.mean(axis=0)), -1, 1)) > self.settings.accumulate_angle for Q, *_ in
                   self._evidence)

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
        plausible = bool((e.mean[0] < 0.1 or np.all(np.abs(e.mean[1:]) <= s.max_com)) and e.mean[0] <= 1.2 * s.max_mass)
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
            self._pending = [k + delay if self.executor is None else self._k + 1, e, level]
        then(e, Ybar)


if __name__ == "__main__":          # python rme.py diagnose LOG ...: the script's entry, not part of the module
    from diagnosis.diagnose import main
    sys.exit(main(sys.argv[2:], prog="rme.py diagnose") if sys.argv[1:2] == ["diagnose"] else print(
        "usage: python rme.py diagnose LOG [--add EFFECT ...] [--json] [--plot FILE]\n(the estimator itself is a "
        "library: from rme import RME; demos: python sim.py --help)") or 2)
