"""Streaming mismatch detector (Appendix A, Algorithm 1): a rapid change of ||tau_ext||^2 over the last 500 samples,
then stabilisation, with a vertical external force. Ring buffers of running sums make every window mean O(1),
so each 1 kHz update costs the same whatever the window length."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import lapack

import checks
from dynamics import pseudo_wrench

ALGORITHM_1_CHECKS = ((431, 450), (351, 370), (271, 290))   # Alg. 1's stabilisation checks: the last 230 ms
MAX_TORQUE = 1e4    # Nm: no joint torque sensor reads more; larger samples are refused (their squares would overflow
                    #   the running sums long before 1e154 Nm, and they are faults, not loads)


@dataclass(frozen=True)
class DetectorSettings:
    """Algorithm 1's constants. Sample indices are 1-based within the window, 1 = the oldest, `window` = the newest."""
    window: int = 500                                   # samples, 500 ms at 1 kHz: Alg. 1
    activation_threshold: float = 0.7                   # Nm^2 (Alg. 1 compares ||tau_ext||^2): App. A, 0.7-1.1;
                                                        #   the lowest: 0.2 kg at the ready pose gives 1.25 Nm^2
    stabilisation_threshold: float = 0.2                # Nm^2: App. A ("within 0.2"), compared as Alg. 1 does
    check_windows: tuple = ALGORITHM_1_CHECKS           # Alg. 1's "stabilization checks"
    end_window: tuple = (491, 500)                      # Alg. 1 "end stabilization"
    force_window: tuple = (451, 500)                    # Alg. 1 mean external force
    side_force_limit: float = 2.5                       # N, |F_x| and |F_y| below it: App. A
    refractory: int = 350                               # ours: samples after a detection before the next one;
                                                        #   then the window starts after the earliest check that
                                                        #   found the change settled (Alg. 1 does not say)
    lam: float = 0.01                                   # pseudo-wrench damping, authors' public code (paper_notes)

    def __post_init__(self):
        """Every field checked (checks.py); upper bounds far beyond use keep the running sums finite: a 100 s window,
        thresholds of 1e12 Nm^2 (never fires: 7 joints at MAX_TORQUE give 7e8), a side force of 10^4 N, damping 10."""
        c, N = checks, checks.number("window", self.window, "2..100000", "samples")
        if not isinstance(self.check_windows, tuple) or not self.check_windows:
            raise ValueError(f"check_windows: expected a tuple of at least one window, found {self.check_windows!r}")
        named = [("end_window", self.end_window), ("force_window", self.force_window)]
        for name, w in named + [(f"check_windows[{i}]", w) for i, w in enumerate(self.check_windows)]:
            if not (c.array(name, w, (2,), f"1..{N}", "(first, last) samples")[0] <= w[1]):
                raise ValueError(f"{name}: expected (first, last) with first <= last, found {w}")
        c.number("activation_threshold", self.activation_threshold, "(0, 1e12]", "Nm^2")
        c.number("stabilisation_threshold", self.stabilisation_threshold, "(0, 1e12]", "Nm^2")
        c.number("side_force_limit", self.side_force_limit, "(0, 1e4]", "N")
        c.number("refractory", self.refractory, "0..1000000", "samples")
        c.number("lam", self.lam, "[0, 10]")


def pseudo_force(J, tau_ext, lam=DetectorSettings.lam, check=True):
    """Force part (3,) of the pseudo-wrench W = (J J^T + lam I)^-1 J tau_ext (dynamics.pseudo_wrench, Sec. 4.1),
    J (6, n) world frame, linear rows first; lam defaults to the detector's damping."""
    return pseudo_wrench(J, tau_ext, lam, check)[:3]


class Detector:
    """update(tau_ext, force) once per sample -> True when a load change is detected (Algorithm 1 as printed);
    watch(tau_ext, q, J) with the pseudo-force map kept per pose, shift_watched(d) after a compensation changes by d.

    With s_i = ||tau_ext,i||^2 over the last `window` samples: rapid = |s_500 - s_1| > activation_threshold; each
    check window's mean of s within stabilisation_threshold of the end window's; the mean force F over force_window
    has |F_z| > |F_x|, |F_z| > |F_y| and |F_x|, |F_y| < side_force_limit. After firing it stays quiet for
    `refractory` samples. shift() re-expresses the samples held after the
    compensation changes (RME feeds it the residual tau_ext - tau_mm(q, theta_hat)). `active`: whether the last
    evaluation found rapid > activation_threshold. Work per update: O(n) whatever the window length (prefix sums
    over a ring of window + 1 entries).
    """

    def __init__(self, settings: DetectorSettings = DetectorSettings(), n: int = 7):
        if not isinstance(settings, DetectorSettings):
            raise ValueError(f"settings: expected a DetectorSettings, found {type(settings).__name__}")
        if not (isinstance(n, (int, np.integer)) and n >= 1):
            raise ValueError(f"n: expected a positive number of joints, found {n!r}")
        self.settings, self.n = settings, n
        N, D = settings.window, 1 + n + 3                       # x_i = (||tau_i||^2, tau_i (n), F_i (3))
        self._raw = np.zeros((N, D))                            # the last N samples x_i
        self._prefix = np.zeros((N + 1, D))                     # P_k = x_1 + ... + x_k at k % (N + 1)
        windows = [*settings.check_windows, settings.end_window, settings.force_window]   # rows of the window means
        lo, hi = np.array([w[0] - 1 for w in windows]), np.array([w[1] for w in windows])
        self._lo, self._hi, self._len = lo, hi, (hi - lo).astype(float)[:, None]
        self._counts = np.arange(N + 1)                         # ring positions of the prefix sums (shift)
        self.count, self._quiet, self.active = 0, 0, False
        self._status, self._evaluated = None, 0  # the last evaluation (see status) and its sample count
        self._frozen = None                      # (raw, prefix) as at that evaluation, if shifted since
        self._pose, self._map = np.full(n, np.inf), None   # the pose and pseudo-force map P (3, n) of `watch`

    def reset(self):
        """Forget the history (the next detection needs a full window again)."""
        self.__init__(self.settings, self.n)

    def shift(self, d_tau, d_force):
        """Re-express the buffered samples as if d_tau (n,) [Nm] and d_force (3,) [N] had been subtracted from each:
        after the compensation changes by d_tau, the detector keeps watching the residual without a blind window.
        The sums change linearly (P_j by its count c_j of samples: the square column by -2 d.P_j[tau] + c_j |d|^2,
        the others by -c_j d), so no sum is rebuilt: O(window) in a few vector operations."""
        N, n, k = self.settings.window, self.n, self.count
        if self._status is None and self._evaluated and self._frozen is None:
            self._frozen = (self._raw.copy(), self._prefix.copy())              # for status
        d = np.concatenate([np.asarray(d_tau, dtype=float).ravel(), np.asarray(d_force, dtype=float).ravel()])
        dd = float(d[:n] @ d[:n])
        held = (self._counts - (k - min(k, N))) % (N + 1)        # samples summed in each prefix entry since the
        for x, c in ((self._prefix, held), (self._raw, np.ones(N))):   # oldest held (entries outside: unused)
            x[:, 0] += c * dd - 2.0 * (x[:, 1:1 + n] @ d[:n])
            x[:, 1:] -= np.multiply.outer(c, d)

    def update(self, tau_ext, force=None, J=None) -> bool:
        """Add one sample: tau_ext (n,) [Nm, paper sign] and either the world-frame pseudo-force (3,) [N] or the
        Jacobian J (6, n) to compute it from. Returns True when a load change is detected at this sample."""
        tau = checks.array("tau_ext", tau_ext, (self.n,), f"[-{MAX_TORQUE:g}, {MAX_TORQUE:g}]", "Nm")
        if (force is None) == (J is None):
            raise ValueError("force, J: expected exactly one of them, found "
                             f"{'both' if force is not None else 'neither'}")
        if force is None:
            J = checks.array("J", J, (6, self.n))
            force = pseudo_force(J, tau, self.settings.lam)
        force = checks.array("force", force, (3,), f"[-{1e3 * MAX_TORQUE:g}, {1e3 * MAX_TORQUE:g}]", "N")
        return self.push(tau, force)

    def watch(self, tau, q, J) -> bool:
        """push() of a residual tau (n,) checked by the caller, its pseudo-force P tau from the flange's world Jacobian
        J (6, n) at pose q (n,): P = ((J J^T + lam I)^-1 J)[:3], formed again only when the pose moves by 1e-3 rad
        (by Cholesky, LAPACK's dposv: a third of np.linalg.solve's time at 1 kHz)."""
        if np.abs(q - self._pose).max() > 1e-3:
            A = J @ J.T
            A.flat[::7] += self.settings.lam
            _, PJ, bad = lapack.dposv(A, J)
            self._pose, self._map = q.copy(), (PJ if not bad else np.linalg.lstsq(A, J, rcond=None)[0])[:3]
        return self.push(tau, self._map @ tau)

    def shift_watched(self, d_tau):
        """shift() for samples fed by watch(): d_tau (n,) [Nm] and its pseudo-force at the last pose watched (none
        watched yet: the force is not shifted)."""
        self.shift(d_tau, np.zeros(3) if self._map is None else self._map @ d_tau)

    def push(self, tau, force):
        """update() without the input checks, for a caller that checked tau (n,) and force (3,) itself."""
        N = self.settings.window
        k = self.count = self.count + 1
        x = self._raw[(k - 1) % N]
        x[0], x[1:1 + self.n], x[1 + self.n:] = tau @ tau, tau, force
        self._prefix[k % (N + 1)] = self._prefix[(k - 1) % (N + 1)] + x
        if k % (N + 1) == N:                                   # re-base (amortised O(1)): keeps the sums small
            self._prefix -= self._prefix[(k - N) % (N + 1)].copy()
        if self._quiet > 0:
            self._quiet -= 1
            return False
        if k < N:
            return False
        self._status, self._evaluated, self._frozen = None, k, None
        fired = self._evaluate(k)
        if fired:
            self._quiet = self.settings.refractory
        return fired

    @property
    def status(self):
        """dict of the last evaluation: rapid, stabilisation (per check: |its mean s - the end's|), force (the mean
        force), fired (None before the first); computed on demand (the 1 kHz path stops at the activation test when
        nothing changed)."""
        if self._status is None and self._evaluated:
            now = (self._raw, self._prefix)                                   # as the samples were then
            self._raw, self._prefix = self._frozen or now
            try:
                self._status = self._evaluate(self._evaluated, full=True)
            finally:
                self._raw, self._prefix = now
        return self._status

    def _evaluate(self, k, full=False):
        """Algorithm 1 on the window of samples k - N + 1 .. k (its sample i is at raw[(k - N + i - 1) % N]):
        whether it fires (full: the status dict instead)."""
        s, N, n, P = self.settings, self.settings.window, self.n, self._prefix
        rapid = abs(self._raw[(k - 1) % N, 0] - self._raw[k % N, 0])           # |s_N - s_1|
        if not full:
            self.active = bool(rapid > s.activation_threshold)   # a change in the window (it may yet settle)
            if not self.active:
                return False                                   # the common case at 1 kHz: nothing changed
        means = (P[(k - N + self._hi) % (N + 1)] - P[(k - N + self._lo) % (N + 1)]) / self._len   # (W, D)
        drift, F = np.abs(means[:-2, 0] - means[-2, 0]), means[-1, 1 + n:]
        vertical = abs(F[2]) > abs(F[0]) and abs(F[2]) > abs(F[1])
        side = abs(F[0]) < s.side_force_limit and abs(F[1]) < s.side_force_limit
        fired = bool(rapid > s.activation_threshold and drift.max() < s.stabilisation_threshold and vertical and side)
        status = dict(rapid=rapid, stabilisation=drift, force=F, fired=fired)
        if not full:
            self._status = status
        return status if full else fired


def safe_theta(new, old, max_mass):
    """The estimate to compensate: finite, mass in [0, max_mass], CoM within 1 m; otherwise keep the current one."""
    new = np.asarray(new, dtype=float)
    if new.shape != (4,) or not all(map(math.isfinite, new.tolist())):
        return old
    m, *r = new.tolist()                                  # plain floats: this runs inside the 1 kHz loop
    return np.array([min(max(m, 0.0), max_mass)] + [min(max(x, -1.0), 1.0) for x in r])
