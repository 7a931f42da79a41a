"""The streaming estimator on one model of what changed (changes.py): each sample the residual's level is compared
with the reference; when it departs, the posterior over {noise, payload, wrench, back} decides: estimate the new
payload (network + VI on the window referred to the reference), return to an earlier one, or wait."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

import checks
import vi
from changes import ChangeModel, ChangeSettings, Payloads
from detector import safe_theta
from dynamics import as_states
from rme import RME, Estimate
from rme_settings import faulty


@dataclass
class Due:
    """A decision being carried out: apply `estimate` from sample `at`; `refine`: estimate again once the arm rests
    (the window was taken in motion, friction in it)."""
    at: int
    estimate: Estimate
    refine: bool


class ModelRME(RME):
    """RME whose streaming decisions come from changes.ChangeModel (same construction and outputs as RME)."""

    def __init__(self, *args, changes: ChangeSettings = ChangeSettings(), **kwargs):
        super().__init__(*args, **kwargs)
        self.changes = checks.instance("changes", changes, ChangeSettings)
        self.model = ChangeModel(changes, self.robot.n)
        s = self.settings
        self.payloads = Payloads.plausible(s.max_mass, s.max_com)
        self._due: Due | None = None
        self._since = None               # the sample a departure from the reference was first seen
        self._refine_at = None           # (reference level) an estimate at rest is owed for the change applied
        self._calm_k = 0                 # samples every joint has been slower than rest_speed
        self.verdicts = []               # (t, Verdict) judged, for reading why it decided

    def _gradient(self, q):
        """d G / d q (n, n) at q by central differences of the nominal gravity torque (the model error's direction)."""
        h, n = 1e-4, self.robot.n
        E = np.eye(n) * h
        return np.stack([(self.robot.gravity(q + E[j]) - self.robot.gravity(q - E[j])) / (2 * h)
                         for j in range(n)], axis=1)

    def update(self, q, dq, tau_ext) -> np.ndarray:
        n, s, S = self.robot.n, self.settings, self.changes.short
        q, dq = as_states("q", q, n, allow_window=False)[0][0], as_states("dq", dq, n, allow_window=False)[0][0]
        tau = tau_ext if type(tau_ext) is np.ndarray and tau_ext.dtype == np.float64 else checks.real_array(tau_ext)
        if tau is None or tau.shape != (n,):
            raise ValueError(f"tau_ext: expected real values of shape ({n},), found "
                             f"{checks.kind(tau_ext) if tau is None else tau.shape}")
        if faulty(tau, s.max_abs_torque):
            self.dropped += 1
            return self._last
        keep = len(self._q)
        i = self._k % keep
        _, R, J = self.robot.kinematics(q)
        Y = self.robot.payload_regressor_from(J, R)
        tool = None
        if self.tool is not None:
            tool = Y @ self._tool_phi
            tau = tau - tool
        self._q[i], self._dq[i], self._tau[i] = q, dq, tau
        self._k += 1
        r = tau - Y @ self._phi
        if self.correction is not None:
            c = self.correction.correction(q, dq)
            r = r - c if np.isfinite(c).all() else r
        self.model.push(r, dq)
        self._calm_k = self._calm_k + 1 if np.abs(dq).max() < s.rest_speed else 0
        k, m = self._k, self.model
        if self._due is not None and k >= self._due.at:
            self._apply_due(Y)
        elif m.reference is None:
            if k >= 2 * S and self._calm_k >= 2 * S:
                m.set_reference(m.mean(2 * S), q, self._gradient(q))
        elif self._due is None and k % 5 == 0:
            self._step(q, Y, J, S)
        comp = -(Y @ self._phi) if tool is None else -(Y @ self._phi) - tool
        self._last = np.minimum(np.maximum(comp, -self._limit), self._limit)
        return self._last

    def _step(self, q, Y, J, S):
        """Every 5th sample: judge a departure, learn the noise at rest, or estimate at rest a change owed it."""
        m, s, k = self.model, self.settings, self._k
        if m.departure(q) <= self.changes.detect:
            self._since = None
            if self._refine_at is not None and self._calm_k >= s.window:
                level, self._refine_at = self._refine_at, None
                self._estimate_now(s.window, level, "at rest", refine=False)
            elif self._calm_k >= 2 * S and k % S == 0:
                m.learn_noise()
            return
        self._since = k if self._since is None else self._since
        if k % 10:
            return
        v = m.judge(Y, J, self._phi, q, self.payloads)
        self.verdicts.append((k / s.rate, v))
        if v.sure < self.changes.confidence:
            return
        if v.best == "payload":
            W = int(np.clip(k - self._since + S, S, s.window))
            moving = self._calm_k < W
            self._estimate_now(W, m.reference.level, "detection", refine=moving)
        elif v.best == "back":
            e = Estimate(_theta(v.phi), np.zeros(4),
                         np.zeros((4, 4)), np.zeros(4), np.zeros(4, dtype=bool), 0.0, 0, True)
            e.t, e.kind, e.reason = k / s.rate, "back", "the level returned to what an earlier payload leaves"
            self.history.append(e)
            self._due = Due(k, e, False)
        elif v.best == "noise" and self._calm_k >= 2 * S:
            m.set_reference(m.mean(2 * S), q, self._gradient(q))     # the bias moved with the pose: the new level
            self._since = None

    def _estimate_now(self, W, level, kind, refine):
        """Network + VI on the last W samples referred to `level` (the residual the compensation left before)."""
        s, keep = self.settings, len(self._q)
        idx = np.arange(self._k - W, self._k) % keep
        Qw, Tw = self._q[idx], self._tau[idx] - level
        if self.correction is not None:
            Tw = Tw - self.correction.correction(Qw, self._dq[idx])
        e, _ = self._estimate(Qw, Tw)
        e.t, e.kind = self._k / s.rate, kind
        e.accepted = self._plausible(e.mean)
        if not e.accepted:
            e.reason = "beyond what the arm carries"
        self.history.append(e)
        if e.accepted:
            delay = math.ceil(e.seconds * s.rate) if s.asynchronous else 0
            self._due = Due(self._k + delay, e, refine)

    def _apply_due(self, Y):
        due, self._due = self._due, None
        theta = safe_theta(due.estimate.mean, self.theta, self.settings.max_mass)
        phi = vi.phi_of(theta)
        self.payloads.remember(self._phi)
        d = Y @ (phi - self._phi)
        self.theta, self._phi = theta, phi
        self.model.shift(d)
        self._r -= d
        due.estimate.applied = self._k / self.settings.rate
        self._since = None
        self._refine_at = self.model.reference.level.copy() if due.refine else None


def _theta(phi):
    m = float(phi[0])
    return np.array([m, *(phi[1:] / m if m > 1e-9 else np.zeros(3))])
