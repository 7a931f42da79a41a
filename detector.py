"""Streaming mismatch detector (Appendix A, Algorithm 1): a rapid change of ||tau_ext||^2 over the last 500 samples,
then stabilisation, with a vertical external force. Ring buffers of running sums make every window mean O(1),
so each 1 kHz update costs the same whatever the window length."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

import checks
from dynamics import pseudo_wrench

ALGORITHM_1_CHECKS = ((431, 450), (351, 370), (271, 290))   # Alg. 1's stabilisation checks: the last 230 ms
MAX_TORQUE = 1e4    # Nm: no joint torque sensor reads more; larger samples are refused (their squares would overflow
                    #   the running sums long before 1e154 Nm, and they are faults, not loads)


@dataclass(frozen=True)
class DetectorSettings:
    """Sample indices are 1-based within the window, 1 = the oldest, `window` = the newest (Alg. 1)."""
    window: int = 500                                   # samples, 500 ms at 1 kHz: Alg. 1
    activation_threshold: float = 0.7                   # Nm^2 (Alg. 1 compares ||tau_ext||^2): App. A, 0.7-1.1;
                                                        #   the lowest: 0.2 kg at the ready pose gives 1.25 Nm^2
    stabilisation_threshold: float = 0.2                # App. A ("within 0.2 Nm"); Nm^2 for "as_printed"
    stabilisation_relative: float = 0.03                # ours ("referred"): plus this share of the change's size
                                                        #   (a compliant arm settles slowly under a heavy load: its
                                                        #   drift stays above 0.2 Nm for seconds after 2.5 kg)
    stabilisation_quadratic: float = 0.0016             # 1/Nm, ours ("referred"): plus this times the size squared
                                                        #   (a heavier load sags the arm further: 2.5-3 kg far out,
                                                        #   a 20-30 Nm change, creeps for 0.4 s; 4 % more of a
                                                        #   25 Nm change, 0.16 % more of 1 Nm)
    check_windows: tuple = ((431, 450), (391, 410), (351, 370))   # ours: Alg. 1's "stabilization checks"
                                                        #   (ALGORITHM_1_CHECKS) over the last 150 ms, not 230
                                                        #   (App. A: tuned to the task): loads compensated sooner
    end_window: tuple = (491, 500)                      # Alg. 1 "end stabilization"
    force_window: tuple = (451, 500)                    # Alg. 1 mean external force
    side_force_limit: float = 2.5                       # N, |F_x| and |F_y| below it: App. A
    algorithm: str = "referred"                         # ours (see Detector); "as_printed" with
                                                        #   check_windows=ALGORITHM_1_CHECKS: Alg. 1 verbatim
    reference_window: tuple = (1, 10)                   # ours ("referred"): the torque and force before the change
    settled_window: tuple = (11, 30)                    # ours ("referred"): must agree with reference_window
    refractory: int = 350                               # ours: samples after a detection before the next one:
                                                        #   then the window starts at the detection's earliest
                                                        #   check (every sample held lies after the change), not
                                                        #   a whole window later (see Detector)
    lam: float = 0.01                                   # pseudo-wrench damping, authors' public code (paper_notes)

    def __post_init__(self):
        """Every field checked (checks.py); upper bounds far beyond use keep the running sums finite: a 100 s window,
        thresholds of 1e12 Nm^2 (never fires: 7 joints at MAX_TORQUE give 7e8), a side force of 10^4 N, damping 10."""
        c, N = checks, checks.number("window", self.window, "2..100000", "samples")
        if not isinstance(self.check_windows, tuple) or not self.check_windows:
            raise ValueError(f"check_windows: expected a tuple of at least one window, found {self.check_windows!r}")
        named = [("end_window", self.end_window), ("force_window", self.force_window),
                 ("reference_window", self.reference_window), ("settled_window", self.settled_window)]
        for name, w in named + [(f"check_windows[{i}]", w) for i, w in enumerate(self.check_windows)]:
            if not (c.array(name, w, (2,), f"1..{N}", "(first, last) samples")[0] <= w[1]):
                raise ValueError(f"{name}: expected (first, last) with first <= last, found {w}")
        c.number("activation_threshold", self.activation_threshold, "(0, 1e12]", "Nm^2")
        c.number("stabilisation_threshold", self.stabilisation_threshold, "(0, 1e12]", "Nm (Nm^2 for as_printed)")
        c.number("stabilisation_relative", self.stabilisation_relative, "[0, 1)", "(a share)")
        c.number("stabilisation_quadratic", self.stabilisation_quadratic, "[0, 1]", "1/Nm")
        c.number("side_force_limit", self.side_force_limit, "(0, 1e4]", "N")
        c.choice("algorithm", self.algorithm, ("referred", "as_printed"))
        c.number("refractory", self.refractory, "0..1000000", "samples")
        c.number("lam", self.lam, "[0, 10]")


def pseudo_force(J, tau_ext, lam=DetectorSettings.lam, check=True):
    """Force part (3,) of the pseudo-wrench W = (J J^T + lam I)^-1 J tau_ext (dynamics.pseudo_wrench, Sec. 4.1),
    J (6, n) world frame, linear rows first; lam defaults to the detector's damping."""
    return pseudo_wrench(J, tau_ext, lam, check)[:3]


class Detector:
    """update(tau_ext, force) once per sample -> True when a load change is detected (Algorithm 1).

    "as_printed" (Alg. 1): s_i = ||tau_ext,i||^2; rapid = |s_500 - s_1| > activation_threshold; each check window's
    mean of s within stabilisation_threshold of the end window's; the mean force F over force_window has
    |F_z| > |F_x|, |F_z| > |F_y| and |F_x|, |F_y| < side_force_limit (magnitudes, as the paper intends).
    "referred" (default) keeps the structure but measures every signal against the torque and force BEFORE the
    change, tau_ref and F_ref = their means over reference_window (samples 1-10):
      rapid = |mean_end ||tau - tau_ref||^2 - mean_ref ||tau - tau_ref||^2| > activation_threshold [Nm^2] (within a
        window of the last detection, at most ||mean_end(tau) - the end window's mean at that detection||^2);
      settled before: ||mean_settled(tau) - tau_ref|| < stabilisation_threshold [Nm] (samples 11-30);
      stable after: ||mean_check(tau) - mean_end(tau)|| < stabilisation_threshold + (stabilisation_relative +
        stabilisation_quadratic x D) x D [Nm] for every check window, D = ||mean_end(tau) - tau_ref||;
      force: the same tests on the force CHANGE dF = mean_force(F) - F_ref.
    Why: a real Panda's tau_ext carries a pose-dependent bias b of a few tenths of a Nm, so ||b + tau_mm||^2 -
    ||b||^2 = 2 b.tau_mm + ||tau_mm||^2 can hide a load or a removal, the absolute force after a removal is the
    bias's own (pointing anywhere), and single samples of ||b + noise||^2 jump by > 0.7 Nm^2 at rest on the
    realistic plant (as_printed fires repeatedly at rest there: `python sim.py detector-bench`). Window means instead of
    samples 1 and 500, and the settled-before test, stop it firing on the first samples of a new change or on a
    window that starts mid-change; the vector stabilisation test does not grow with the load, as
    |mean s - mean s'| ~ 2 ||tau_mm|| noise does (Alg. 1 delayed a 1.2 kg detection past 500 ms in simulation).
    After firing it stays quiet for `refractory` samples (the buffer then holds only samples from the detection's
    earliest check on, after the change) and then fires again for the next change, a removal included. While the
    window still reaches back to that detection, rapid is also measured against the level it settled at (the mean of
    its end window, re-expressed by shift): the rest of a change that still crept within the allowance at its
    detection does not fire again. The cost: a small second change inside that detection's end window (within about
    0.1 s of a heavy first one) is not detected. `active`: whether the last evaluation
    found rapid > activation_threshold (a change in the window that may yet settle and fire).
    Work per update: O(n) whatever the window length (prefix sums over a ring of window + 1 entries).
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
        windows = [settings.reference_window, settings.settled_window, *settings.check_windows,
                   settings.end_window, settings.force_window]  # rows of the window means, in this order
        lo, hi = np.array([w[0] - 1 for w in windows]), np.array([w[1] for w in windows])
        self._lo, self._hi, self._len = lo, hi, (hi - lo).astype(float)[:, None]
        self._counts = np.arange(N + 1)                         # ring positions of the prefix sums (shift)
        self.count, self._quiet, self.active = 0, 0, False
        self.reference_torque = np.zeros(n)   # (n,) tau_ref at the last detection (the torque before the change)
        self._status, self._evaluated = None, 0  # the last evaluation (see status) and its sample count
        self._frozen = None                      # (raw, prefix, settled) as at that evaluation, if shifted since
        self._detected_level = None              # (sample count, mean torque of the end window) at the last detection

    def reset(self):
        """Forget the history (the next detection needs a full window again)."""
        self.__init__(self.settings, self.n)

    def shift(self, d_tau, d_force):
        """Re-express the buffered samples as if d_tau (n,) [Nm] and d_force (3,) [N] had been subtracted from each:
        after the compensation changes by d_tau, the detector keeps watching the residual without a blind window.
        The prefix sums change linearly (P_j by its count c_j of samples: the square column by -2 d.P_j[tau] +
        c_j |d|^2, the others by -c_j d), so no sum is rebuilt: O(window) in a few vector operations."""
        N, n, k = self.settings.window, self.n, self.count
        if self._status is None and self._evaluated and self._frozen is None:
            self._frozen = (self._raw.copy(), self._prefix.copy(), self._detected_level)     # for status
        d = np.concatenate([np.asarray(d_tau, dtype=float).ravel(), np.asarray(d_force, dtype=float).ravel()])
        dd = float(d[:n] @ d[:n])
        held = (self._counts - (k - min(k, N))) % (N + 1)        # samples summed in each prefix entry since the
        shifted = [(self._prefix, held)]                         #   oldest held (entries outside: unused)
        if self.settings.algorithm == "as_printed":              # the only reader of single samples (raw)
            shifted.append((self._raw, np.ones(N)))
        for x, c in shifted:
            x[:, 0] += c * dd - 2.0 * (x[:, 1:1 + n] @ d[:n])
            x[:, 1:] -= np.multiply.outer(c, d)
        if self._detected_level is not None:
            self._detected_level = (self._detected_level[0], self._detected_level[1] - d[:n])

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

    def recent_mean(self, L):
        """Mean tau_ext (n,) of the last L samples pushed (1 <= L <= window; samples before the first count as 0), in
        O(n) from the running sums, as shift() re-expressed them."""
        N, k = self.settings.window, self.count
        if not 1 <= L <= N:
            raise ValueError(f"L: expected 1..{N} samples (the window), found {L}")
        if k < L:                                              # fewer samples than asked: the zeros before them
            return self._prefix[k % (N + 1), 1:1 + self.n] / L if k else np.zeros(self.n)
        return (self._prefix[k % (N + 1), 1:1 + self.n] - self._prefix[(k - L) % (N + 1), 1:1 + self.n]) / L

    @property
    def status(self):
        """dict of the last evaluation: rapid, settled, stabilisation, force_change, fired (None before the first);
        computed on demand (the 1 kHz path stops at the activation test when nothing changed)."""
        if self._status is None and self._evaluated:
            now = (self._raw, self._prefix, self._detected_level)            # as the samples were then
            self._raw, self._prefix, self._detected_level = self._frozen or now
            try:
                self._status = self._evaluate(self._evaluated, full=True)
            finally:
                self._raw, self._prefix, self._detected_level = now
        return self._status

    def _evaluate(self, k, full=False):
        """Algorithm 1 on the window of samples k - N + 1 .. k (its sample i is at raw[(k - N + i - 1) % N]):
        whether it fires (full: the status dict instead)."""
        s, N, n = self.settings, self.settings.window, self.n
        P = self._prefix
        T = slice(1, 1 + n)                                                   # the torque columns
        if s.algorithm == "as_printed":
            first, last = self._raw[k % N, 0], self._raw[(k - 1) % N, 0]
            rapid = abs(last - first)
        else:
            ref, end = ((P[(k - N + self._hi[i]) % (N + 1)] - P[(k - N + self._lo[i]) % (N + 1)]) / self._len[i]
                        for i in (0, -2))
            tau_ref = ref[T]
            # mean over a window of ||tau - tau_ref||^2 = mean ||tau||^2 - 2 tau_ref . mean tau + ||tau_ref||^2
            s_end, s_ref = (w[0] - 2.0 * w[T] @ tau_ref + tau_ref @ tau_ref for w in (end, ref))
            rapid = abs(s_end - s_ref)
            last = self._detected_level
            if last is not None and k - last[0] < N:       # the window reaches back to the last detection: a new
                gap = end[T] - last[1]                      #   change also moves the level that detection settled at
                rapid = min(rapid, float(gap @ gap))
        if not full:
            self.active = bool(rapid > s.activation_threshold)   # a change in the window (it may yet settle)
        if not full and rapid <= s.activation_threshold:
            return False                                   # the common case at 1 kHz: nothing changed
        means = (P[(k - N + self._hi) % (N + 1)] - P[(k - N + self._lo) % (N + 1)]) / self._len   # (W, D)
        ref, settled, checks, end, frc = means[0], means[1], means[2:-2], means[-2], means[-1]
        if s.algorithm == "as_printed":
            drift, dF = np.abs(checks[:, 0] - end[0]), frc[1 + n:]
            settled_ok, tau_ref = True, np.zeros(n)
        else:
            tau_ref = ref[T]
            d = checks[:, T] - end[T]
            size = end[T] - tau_ref
            big = math.sqrt(size @ size)
            allowed = (s.stabilisation_relative + s.stabilisation_quadratic * big) * big
            drift = np.sqrt(np.einsum("ij,ij->i", d, d)) - allowed
            d = settled[T] - tau_ref
            settled_ok = d @ d < s.stabilisation_threshold**2
            dF = frc[1 + n:] - ref[1 + n:]
        vertical = abs(dF[2]) > abs(dF[0]) and abs(dF[2]) > abs(dF[1])
        side = abs(dF[0]) < s.side_force_limit and abs(dF[1]) < s.side_force_limit
        fired = bool(rapid > s.activation_threshold and settled_ok and drift.max() < s.stabilisation_threshold
                     and vertical and side)
        status = dict(rapid=rapid, settled=settled_ok, stabilisation=drift, force_change=dF, fired=fired)
        if full:
            return status
        self._status = status
        if fired:
            self.reference_torque = tau_ref.copy()
            self._detected_level = (k, end[T].copy())
        return fired


def safe_theta(new, old, max_mass):
    """The estimate to compensate: finite, mass in [0, max_mass], CoM within 1 m; otherwise keep the current one."""
    new = np.asarray(new, dtype=float)
    if new.shape != (4,) or not all(map(math.isfinite, new.tolist())):
        return old
    m, *r = new.tolist()                                  # plain floats: this runs inside the 1 kHz loop
    return np.array([min(max(m, 0.0), max_mass)] + [min(max(x, -1.0), 1.0) for x in r])
