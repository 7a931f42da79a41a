"""One window's payload posterior (Sec. 4.1-4.2): the network's prior and variational inference on a window of
tau_ext, absolute or referred to the level before a change, with the robot's error model (error_model.py). The
streaming pipeline (rme.py) is built on it."""
from __future__ import annotations

import os
import time
from dataclasses import dataclass

import numpy as np

import checks
import vi
from dynamics import Robot, as_states
from error_model import as_error_model
from motion.tool_forms import load_tool, phi_of_tool
from nn_numpy import WEIGHTS, MismatchNet
from rme_settings import RMESettings


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
    accepted: bool = True            # False: the change did not look like a payload and was not compensated
    kind: str = "window"             # "detection" (the model found a new payload), "at rest" (the same change
                                     #   again on the full window, motion's share of its error small), "back" (the
                                     #   level returned to what an earlier payload leaves: that payload again, no
                                     #   window estimated), "correction" (nothing changed, and the level corrects the
                                     #   payload held: the noise hypothesis' posterior, no window estimated) or
                                     #   "window"
    applied: float = float("nan")    # stream time the compensation started using it (update only)
    reason: str = ""                 # why it was not applied, or applied only later (update only)
    prior_source: str = "network"    # the prior VI started from: "network" (Sec. 4.1; zeros without weights), or
                                     #   "broad" (every plausible payload): for an absolute window, or where a
                                     #   referred window's evidence says the network's prior conflicts with it


class WindowEstimator:
    """estimate(q, tau_ext) for a window (RME adds streaming, rme.py). robot, weights, settings, rng, correction,
    calibration and tool as RME's (its docstring)."""

    def __init__(self, robot: Robot | None = None, weights: str | None = WEIGHTS, settings: RMESettings = RMESettings(),
                 rng: np.random.Generator | None = None, correction=None, calibration=None, tool=None):
        self.robot = Robot.panda() if robot is None else checks.instance("robot", robot, Robot)
        self.error_model = as_error_model(calibration, self.robot.n)
        if len(self.error_model.absolute) != self.robot.n:
            raise ValueError(f"calibration: expected an error model of the robot's {self.robot.n} joints, found one of "
                             f"{len(self.error_model.absolute)} ({self.error_model.source})")
        self.tool = None if tool is None else load_tool(tool)        # ValueError naming what is wrong
        self._tool_phi = np.zeros(4) if tool is None else phi_of_tool(self.tool)   # (m, m c) in the ee frame
        self.settings = s = checks.instance("settings", settings, RMESettings)
        self.correction = None if correction is None else checks.has_methods("correction", correction, "correction")
        self.rng = np.random.default_rng(0) if rng is None else checks.generator("rng", rng)
        if not (weights is None or isinstance(weights, (str, os.PathLike))):
            raise ValueError(f"weights: expected a weights file's path or None, found {weights!r:.60}")
        self.net = MismatchNet.load(weights) if s.use_network and weights is not None else None  # or ValueError
        c, m = s.max_com, s.max_mass                   # every plausible payload: a weak prior (1 sigma to the
        self._broad = (np.array([m / 2, 0, 0, 0]), np.array([m / 2, c, c, c]),   # box's edge) truncated to the box
                       np.array([0.0, -c, -c, -c]), np.array([m, c, c, c]))     # (vi.log_evidence)

    def estimate(self, q, tau_ext, baseline=None, dq=None, referred: bool | None = None) -> Estimate:
        """Posterior of theta from a window q, tau_ext (T, n) (paper sign), T about 200 at 1 kHz; or from lists of
        windows [q_a, q_b], [tau_a, tau_b] of one payload (each (T_i, n); baseline and dq lists too, or None): one
        posterior, their evidence combined (vi.combine), the prior mean the network's mean over them.
        baseline (n,): the tau_ext seen before the change at the same pose, subtracted first. Pass it when you have
        it: the robot model's own error at the pose cancels (ErrorModel.referred, a few mNm); without it the window
        is absolute and carries that error (ErrorModel.absolute, tenths of a Nm; its calibrated offset subtracted).
        A baseline window (T_b, n) is subtracted as its mean, and what its own swing leaves in that mean is counted
        (vi.level_variance, with ErrorModel.drift for the rest when calibrated).
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
            q, tau, level = self._window(q, tau_ext, baseline, dq, ref(baseline))
            return self._estimate(q, tau, referred=ref(baseline), level=level)
        each = lambda v: [None] * len(q) if v is None else list(v) if isinstance(v, (list, tuple)) else []
        if not (q and len(each(tau_ext)) == len(q) == len(each(baseline)) == len(each(dq))):
            raise ValueError(f"q, tau_ext, baseline, dq: expected lists of {len(q)} windows (or None), found other")
        windows = [self._window(*w, ref(w[2])) for w in zip(q, each(tau_ext), each(baseline), each(dq))]
        return self._estimate([w[0] for w in windows], [w[1] for w in windows],
                              referred=[ref(b) for b in each(baseline)], level=[w[2] for w in windows])

    def _absolute_error(self, q):
        """The covariance (n, n) or stds (n,) [Nm] of an absolute window's constant error about the offset at the
        window q's (T, n) mean pose: from the calibrated links' errors (ErrorModel.pose_error_at) when the model has
        them, else at the pose's own gravity torque (ErrorModel.absolute_cov_at)."""
        em, qm = self.error_model, np.mean(q, axis=0)
        if em.links is not None:
            return em.pose_error_at(self.robot.link_gravity_regressor(qm, em.links))[1]
        return em.absolute_cov_at(self.robot.gravity(qm))

    def _window(self, q, tau_ext, baseline, dq, referred):
        """A checked (q, tau) (T, n) window, less the baseline (its mean, for a window) and the correction; and
        level (n,) [Nm^2] what a baseline window's mean holds of its own slow part and noise (vi.level_variance;
        None for a baseline given as its mean, or none)."""
        n, q_in, tau_in = self.robot.n, q, tau_ext
        q, qb = as_states("q", q, n)
        tau, tb = self._torques("tau_ext", tau_ext)
        if not (qb and tb) or q.shape != tau.shape:
            raise ValueError(f"q, tau_ext: expected two windows of the same shape (T, {n}), found "
                             f"{np.shape(q_in)} and {np.shape(tau_in)}")
        if q.shape[0] < 20:
            raise ValueError(f"q: expected a window of at least 20 samples (the network reads 20), found {q.shape[0]}")
        level = None
        if baseline is not None:
            base, window = self._torques("baseline", baseline)
            tau = tau - base.mean(axis=0)
            level = vi.level_variance(base, self.settings.vi) if window else None
        if not referred:                                             # an absolute window: the calibrated mean
            tau = tau - np.asarray(self.error_model.offset)          #   model error, and the known tool's weight
            if self.tool is not None:
                tau = tau - self.robot.payload_regressor(q) @ self._tool_phi
        if self.correction is not None:
            dq = np.zeros_like(q) if dq is None else as_states("dq", dq, n)[0]
            if dq.shape != q.shape:
                raise ValueError(f"dq: expected shape {q.shape} like q, found {dq.shape}")
            tau = tau - self.correction.correction(q, dq)
        return q, tau, level

    def _torques(self, name, x, allow_window=True):
        """as_states, every torque within settings.max_abs_torque (beyond it a sensor fault, not a load)."""
        tau, batched = as_states(name, x, self.robot.n, allow_window)
        if (big := np.argwhere(np.abs(tau) > self.settings.max_abs_torque)).size:
            i = tuple(int(k) for k in big[0])
            raise ValueError(f"{name}: expected torques within settings.max_abs_torque = "
                             f"{self.settings.max_abs_torque:g} Nm, found {tau[i]:g} at index {i if batched else i[1]}")
        return tau, batched

    def _estimate(self, q, tau, referred=True, level=None):
        """Network prior and VI on checked, corrected windows (or lists): the Estimate.
        referred: the window is less the level before the change (else absolute; a list with lists of windows);
        level (n,) [Nm^2]: what that level's own window leaves in its mean (_window; a list; None: a level given as a
        mean), with which a calibrated ErrorModel.drift replaces ErrorModel.referred.
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
        dt = 1 / self.settings.rate
        speed = [vi.joint_speed(qi, dt) for qi in q] if many else vi.joint_speed(q, dt)
        em, s = self.error_model, self.settings
        absolute = self._absolute_error                                                   # at the window's pose
        relative = lambda lv: em.referred if lv is None or em.drift is None else np.sqrt(np.square(em.drift) + lv)
        levels = (level if level is not None else [None] * len(q)) if many else level
        bias = [relative(lv) if r else absolute(qi) for r, qi, lv in zip(referred, q, levels)] if many else \
            (relative(levels) if referred else absolute(q))
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
        return e
