"""One model of what changed at the flange (docs/streaming.md): the residual r = tau_ext - Y(q) phi_hat is
r = b(q) + Y(q) dphi + J(q)^T w + e, and over {noise, payload, wrench, back to an earlier payload} the model keeps
closed-form Gaussian posterior probabilities from which the streaming estimator decides. No MuJoCo in here."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.linalg.lapack import dpotrf, dpotrs
from scipy.special import log_ndtr

import checks

HYPOTHESES = ("noise", "payload", "wrench", "back", "back+wrench")
EXPECTED = math.log(10.0)   # the payload's log prior odds while the task says a load change is coming
                            #   (RME.expect_change)
COMPOUND = math.log(0.25)   # a return under a wrench is two events at once: its prior, the product of two of the four
                            #   single hypotheses' equal priors, is a quarter of one's


@dataclass(frozen=True)
class ChangeSettings:
    """What the residual holds besides a change, and what a change may be. Sources in docs/streaming.md."""
    short: int = 40                 # samples (40 ms) of the level compared with the reference
    rest_noise: tuple = (0.015,) * 4 + (0.004,) * 3   # Nm: std of a `short`-sample mean of tau_ext at rest per joint
                                    #   (realistic plant: 1.5-16 mNm); the start value of what the stream learns
                                    #   from its own calm stretches
    friction: tuple = (0.55, 0.87, 0.64, 1.28, 0.84, 0.30, 0.56)   # Nm: the most friction a moving joint leaves
                                    #   in tau_ext, not averaging down (Gaz et al. 2019's sigmoid amplitudes p1)
    friction_slope: tuple = (0.70, 1.98, 1.62, 1.79, 1.75, 1.30, 1.46)   # Nm s/rad: its growth from rest (Gaz's
                                    #   p1 p2 / 4; measured on the realistic plant in motion: 0.5-1.6)
    model_error: float = 0.1        # share of the links' gravity torque the robot model misses (link masses within
                                    #   8 %, CoMs within 2 cm on the realistic preset): the level moves with the pose
    bias_length: float = 2.0        # rad: the distance in joint space over which the torque sensors' pose-dependent
                                    #   offset (its size: the error model's `absolute`) decorrelates (load-free rest
                                    #   levels at 250 poses of each simulated plant, docs/streaming.md)
    push_force: float = 30.0        # N: std of each component of a person's push (pushes of 5-60 N)
    push_arm: float = 0.1           # m: lever of a push about the flange (a hand on the gripper or the tool)
    detect: float = 24.3            # chi^2 of the level's departure from the reference that opens a judgement
                                    #   (chi2.isf(1e-3, 7): one false start a second at rest)
    confidence: float = 0.99        # posterior probability of the best hypothesis to act on at once; below it, wait
                                    #   (a change of the compensation: its expected loss at most (1 - c) / c of
                                    #   keeping's, the same bar where the other hypotheses keep it; Verdict.loss)
    patience: float = 0.3           # s: then, once the level no longer moves, act on the most probable hypothesis (a
                                    #   phantom and a missed load cost alike): the level of a compliant arm settles
                                    #   within 0.2-0.4 s of a load change (CPIC on the realistic plant), after which
                                    #   waiting adds no evidence

    def __post_init__(self):
        c = checks
        c.number("changes.short", self.short, "10..250", "samples (2 short: at least the 20 the network reads)")
        for name in ("rest_noise", "friction", "friction_slope"):
            c.array(f"changes.{name}", getattr(self, name), (len(getattr(self, name)),), "(0, 100]", "Nm")
        c.number("changes.model_error", self.model_error, "[0, 1]", "(a share)")
        c.number("changes.bias_length", self.bias_length, "(0, 100]", "rad")
        c.number("changes.push_force", self.push_force, "(0, 1e4]", "N")
        c.number("changes.push_arm", self.push_arm, "(0, 10]", "m")
        c.number("changes.detect", self.detect, "(0, 1e6]", "(chi^2)")
        c.number("changes.confidence", self.confidence, "(0.5, 1)", "(a probability)")
        c.number("changes.patience", self.patience, "[0, 60]", "s")


@dataclass
class Reference:
    """The level the compensation is judged against: the residual (n,) left when it was right (the robot's bias b
    there), at pose q (n,), with the joints' friction std (n,) then and the gravity torque's gradient (n, n)."""
    level: np.ndarray
    q: np.ndarray
    friction: np.ndarray
    gradient: np.ndarray
    k: int = 0                     # samples seen when it was taken (the mean of the 2 short before)
    held: np.ndarray = field(default_factory=lambda: np.zeros((4, 4)))   # the covariance (4, 4) of the compensated
    #                                payload's error e then (ChangeModel.error): the level holds -Y(q) e of it
    moving: np.ndarray | None = None   # the joints' friction (n,) [Nm] the level holds (ChangeModel.friction_in, its
    #                                    mean over the level's samples; zeros for a level taken at rest)


@dataclass
class Verdict:
    """A judgement of the level d (n,) [Nm] away from the reference: each hypothesis' posterior probability, the
    best, and for "back" the earlier payload phi (4,) it returns to; payload: the posterior mean of the new phi."""
    d: np.ndarray
    posterior: dict
    best: str
    phi: np.ndarray | None = None
    mass_std: float = np.inf       # the payload hypothesis' posterior std of the new mass [kg]
    cov: np.ndarray | None = None  # for "back": the covariance (4, 4) of the earlier phi
    under: np.ndarray | None = None   # back, payload: the held wrench's level (n,) it is a step from (None: from
    #                                   the reference)
    kept: np.ndarray | None = None    # noise: the posterior mean (4,) of the payload compensated (nothing
    kept_cov: np.ndarray | None = None  #   changed: the same payload, its estimate N(phi, cov) updated by d) and cov
    means: dict = field(default_factory=dict)   # each hypothesis' posterior mean of the payload on the flange (4,)

    @property
    def sure(self) -> float:
        return self.posterior[self.best]

    def loss(self, Y, phi) -> float:
        """The expected squared torque error [Nm^2] at the pose (payload regressor Y (n, 4)) of compensating phi (4,):
        the sum over the hypotheses of its posterior times |Y (phi - its mean)|^2 (the parts of the truth's spread
        that every compensation pays alike left out)."""
        return float(sum(p * np.sum((Y @ (np.asarray(phi) - self.means[h])) ** 2)
                         for h, p in self.posterior.items() if p > 0.0))


@dataclass
class Payloads:
    """Payload priors in phi = (m, m r) [kg, kg m] (ee frame): a new payload ~ N(mean, diag(std^2)) inside the box
    0 <= m <= max_mass; earlier: the payloads compensated before (phi (4,) each, newest last), each a hypothesis."""
    mean: np.ndarray
    std: np.ndarray
    max_mass: float
    max_com: float
    earlier: list = field(default_factory=list)
    covs: list = field(default_factory=list)      # their covariances (4, 4)
    owed: list = field(default_factory=list)      # the level (n,) each one's estimate at rest is owed against (None:
    #                                               made): a return to it owes that estimate again

    @staticmethod
    def plausible(max_mass: float, max_com: float) -> "Payloads":
        m = max_mass / 2                 # every payload the arm carries: m about half the rating, CoM to max_com
        return Payloads(np.array([m, 0, 0, 0]), np.array([m, m * max_com, m * max_com, m * max_com]), max_mass,
                        max_com)

    def forget(self, phi):
        """Drop phi (4,) from the earlier payloads (it is compensated again now): the level (n,) its estimate at rest
        was owed against, if it was (else None)."""
        same = [np.abs(p - np.asarray(phi)).max() <= 1e-9 for p in self.earlier]
        owed = next((o for o, s in zip(self.owed, same) if s), None)
        self.earlier, self.covs, self.owed = ([x for x, s in zip(xs, same) if not s]
                                              for xs in (self.earlier, self.covs, self.owed))
        return owed

    def remember(self, phi, cov, owed=None, keep: int = 3):
        """Keep phi (4,) with its covariance (4, 4) as an earlier payload (the newest `keep`), and the level (n,) its
        estimate at rest is owed against (None: made)."""
        self.forget(phi)
        self.earlier, self.covs, self.owed = (self.earlier[-(keep - 1):] + [np.array(phi, dtype=float)],
                                              self.covs[-(keep - 1):] + [np.array(cov, dtype=float)],
                                              self.owed[-(keep - 1):] + [owed])


def cholesky(C):
    """The lower Cholesky factor (n, n) of C (n, n), symmetric positive semi-definite (LAPACK's dpotrf, called
    directly: the judgement factors a dozen 7 x 7 matrices, where SciPy's checking wrappers cost more than the
    arithmetic), with a jitter of 1e-12 of its trace where rounding (a wrench's variance 1e8 times the noise's)
    leaves it indefinite, so that the 1 kHz loop never raises for rounding (a matrix the jitter does not make
    positive definite either raises LinAlgError)."""
    L, info = dpotrf(C, lower=1, clean=1)
    if info != 0:
        L, info = dpotrf(C + (1e-12 * np.trace(C) + 1e-300) * np.eye(len(C)), lower=1, clean=1)
        if info != 0:
            raise np.linalg.LinAlgError(f"covariance not positive definite even with a jitter (dpotrf info {info})")
    return L


def solve(L, b):
    """C^-1 b for b (n,) or (n, k), L C's `cholesky` factor (LAPACK's dpotrs; its only failure, a malformed argument,
    cannot arise from `cholesky`'s factor)."""
    return dpotrs(L, b, lower=1)[0]


def gaussian_log_pdf(x, C, L=None) -> float:
    """log N(x; 0, C) for x (n,), C (n, n) positive definite (L: its `cholesky` factor, if already factored)."""
    L = cholesky(C) if L is None else L
    return float(-0.5 * x @ solve(L, x) - np.log(np.diag(L)).sum() - 0.5 * len(x) * math.log(2 * math.pi))


class ChangeModel:
    """The level of the residual r (n,) over the last `short` samples against the reference, its noise, and the
    posterior over what moved it. push(r, dq) each sample; judge(...) when departure() > settings.detect.
    pose_bias (n,) [Nm]: the std over the workspace of the torque sensors' pose-dependent offset (the robot's error
    model's `absolute`; None: none)."""

    def __init__(self, settings: ChangeSettings, n: int, keep: int = 500, pose_bias=None):
        self.s, self.n = settings, n
        self.pose_bias = np.zeros(n) if pose_bias is None else np.asarray(pose_bias, dtype=float)[:n]
        self._r, self._dq, self._k = np.zeros((keep, n)), np.zeros((keep, n)), 0   # rings of r, dq; samples
        self._top, self._slope = np.array(settings.friction[:n]), np.array(settings.friction_slope[:n])
        self._half, self._gain = self._top / 2, 2 * self._slope / self._top   # (the signed friction: friction_in)
        self.noise = np.array(settings.rest_noise, dtype=float)[:n] ** 2          # learned at rest (Nm^2)
        self.reference: Reference | None = None
        self.compensated = np.zeros((4, 4))       # the covariance of phi_hat's error that the level's departure
        #                                           from the reference shows (against the error the reference holds)
        self.error = np.zeros((4, 4))             # the covariance of phi_hat's error against the true payload
        self.inertial = np.zeros(n)        # the variance (n,) [Nm^2] of the compensated payload's inertial force now

    # --- the stream ------------------------------------------------------------------------------
    def push(self, r, dq):
        i = self._k % len(self._r)
        self._r[i], self._dq[i] = r, dq
        self._k += 1

    def _rows(self, L: int, back: int = 0, of=None):
        """The L samples (L, n) ending `back` samples ago (of: the ring, default r)."""
        x, N = self._r if of is None else of, len(self._r)
        start = (self._k - back - L) % N
        if start + L <= N:                                          # (the 1 kHz path: a slice, no index array)
            return x[start:start + L]
        return x[np.arange(start, start + L) % N]

    def mean(self, L: int, back: int = 0) -> np.ndarray:
        """Mean (n,) of r over the L samples ending `back` samples ago."""
        return self._rows(L, back).mean(axis=0)

    def speed(self, L: int) -> np.ndarray:
        """Each joint's mean speed |dq| (n,) [rad/s] over the last L samples."""
        return np.abs(self._rows(L, of=self._dq)).mean(axis=0)

    def shift(self, d):
        """The compensation changed by d (n,): every sample held is re-expressed as its residual under it."""
        self._r -= d

    def friction(self, speed) -> np.ndarray:
        """Each joint's friction std (n,) [Nm] at mean joint speeds (n,) [rad/s]: 0 at rest, up to `friction`."""
        return self._top * np.tanh(self._slope * np.asarray(speed) / self._top)

    def learn_noise(self):
        """At rest with nothing changing: the spread of consecutive short means updates the noise (Nm^2, n), and the
        reference level follows the bias's slow drift (the level of the last 2 short samples, the pose kept)."""
        S = self.s.short
        self.reference.level, self.reference.k, self.reference.held = self.mean(2 * S), self._k, self.error.copy()
        self.reference.friction, self.reference.moving = self.friction(self.speed(S)), self._friction_held()
        u = self.mean(S) - self.mean(S, S)
        floor = np.array(self.s.rest_noise[:self.n]) ** 2 / 4
        self.noise = np.maximum(0.99 * self.noise + 0.01 * u * u / 2, floor)

    def set_reference(self, q, gradient):
        """The level of the last 2 short samples, at pose q (n,), becomes the reference (gradient (n, n): dG/dq)."""
        S = self.s.short
        self.reference = Reference(self.mean(2 * S), np.array(q, dtype=float), self.friction(self.speed(S)),
                                   np.array(gradient, dtype=float), self._k, self.error.copy(), self._friction_held())

    def friction_in(self, dq) -> np.ndarray:
        """The joints' friction tau_ext holds at velocities dq (n,) or (T, n) [rad/s], its expected value [Nm]:
        Gaz et al. 2019's sigmoid against the motion, -(friction / 2) tanh(2 friction_slope dq / friction) (the
        amplitude and slope `friction` uses; Gaz's identified p1 / 2 tanh(p2 dq / 2), its small offset p3 left out;
        paper sign, as an external torque that resists the motion)."""
        return -self._half * np.tanh(self._gain * np.asarray(dq))

    def _friction_held(self) -> np.ndarray:
        """friction_in's mean (n,) over the last 2 short samples: what the level taken of them holds."""
        return self.friction_in(self._rows(2 * self.s.short, of=self._dq)).mean(axis=0)

    def covariance(self, q, Y=None, moving=True, friction=True, look=None) -> np.ndarray:
        """Covariance (n, n) of the level's departure d from the reference with nothing changed: the short mean's
        noise and the reference's, friction in motion now and then, the level still moving, the robot model's error
        carried along the pose change since the reference (model_error of the gravity torque's change), the
        sensors' pose-dependent offset carried along it (a Gaussian process of std pose_bias and length bias_length
        in joint space: 2 pose_bias^2 (1 - exp(-|q - q_ref|^2 / (2 bias_length^2))) per joint), and with the payload
        regressor Y (n, 4) at q, the compensated payload's own uncertainty Y cov Y^T. look: the level's samples
        (default `short`)."""
        own, g = self._parts(q, moving, friction, look)
        C = np.outer(g, g)
        C.flat[::self.n + 1] += own
        return C if Y is None else C + Y @ self.compensated @ Y.T

    def variance(self, q, Y=None, moving=True, friction=True, look=None) -> np.ndarray:
        """The diagonal (n,) of `covariance`, without forming it (the tests of every 5th sample)."""
        own, g = self._parts(q, moving, friction, look)
        v = own + g * g
        return v if Y is None else v + np.einsum("ij,jk,ik->i", Y, self.compensated, Y)

    def _parts(self, q, moving, friction, look=None):
        """covariance's per-joint variances (n,) and the pose error's direction g (n,) (its rank-one part g g^T),
        for a level of `look` samples (default `short`: a shorter one's noise grows as short / look)."""
        s, ref, S = self.s, self.reference, self.s.short
        L = look or S
        fric = self.friction(self.speed(S)) ** 2 + ref.friction ** 2 if friction else 0.0
        moving = (self.mean(L) - self.mean(L, L)) if moving else 0.0  # how far the level moved over the last L
        g, bias = self.carried(q)
        return (1 + S / L) * self.noise + fric + moving * moving + bias + self.inertial, g

    def carried(self, q):
        """What the pose's change since the reference, to q (n,), carries into the level: the robot model's error of
        the gravity torque's change g (n,) [Nm] (a rank-one direction) and the variance (n,) [Nm^2] of the sensors'
        pose-dependent offset's change, a Gaussian process of std pose_bias and length bias_length in joint space."""
        s, ref = self.s, self.reference
        moved = np.asarray(q) - ref.q                                  # (n,) the pose's change since the reference
        bias = self.pose_bias ** 2 * (2.0 * -math.expm1(-0.5 * (moved @ moved) / s.bias_length ** 2))
        return s.model_error * ref.gradient @ moved, bias

    def sees_better_here(self, q, Y, prior_std) -> bool:
        """Whether a reference taken now would show a new payload's mass better than the one held: the posterior
        variance [kg^2] of its mass seen through the level's departure at q (n,) (Y (n, 4) the payload regressor
        there, prior_std (4,) the payload prior's) is smaller with the pose's carried error and the reference's
        friction replaced by the friction now."""
        own, g = self._parts(q, moving=False, friction=True)
        f = self.friction(self.speed(self.s.short)) ** 2
        comp, P = np.einsum("ij,jk,ik->i", Y, self.compensated, Y), np.diag(1.0 / np.asarray(prior_std) ** 2)
        held, fresh = (float(np.linalg.inv(Y.T @ (Y / (v + comp)[:, None]) + P)[0, 0])
                       for v in (own + g * g, 2 * self.noise + 2 * f))
        return fresh < held

    def settling(self, friction: bool = True) -> float:
        """chi^2 of the level's move over the last `short` samples under the noise alone (of two short means, with
        friction unless told not): above settings.detect, the level is still on its way (a change, the arm
        swinging); without friction's allowance, also while the arm's speed changes (friction and inertia with it)."""
        S = self.s.short
        u = self.mean(S) - self.mean(S, S)
        f = self.friction(self.speed(2 * S)) if friction else 0.0
        return float(u @ (u / (2 * self.noise + 2 * f * f)))

    def arriving(self) -> float:
        """chi^2 of the level's move over the last `short` samples (of two short means) under the noise and the
        change of the joints' friction between them (Gaz et al.'s sigmoid, signed: (friction / 2) tanh(2
        friction_slope dq / friction) per sample, its mean over each): above settings.detect, the level may still be
        on its way, on an arm moving steadily as well (where the friction's size, `settling`'s allowance, hides it)."""
        S = self.s.short
        u = self.mean(S) - self.mean(S, S)
        f = self.friction_in(self._rows(2 * S, of=self._dq))
        f = f[S:].mean(axis=0) - f[:S].mean(axis=0)
        return float(u @ (u / (2 * self.noise + f * f)))

    def departure(self, q, Y=None, look=None) -> float:
        """chi^2 of the level's departure from the reference under `covariance` (diagonal part); look: the level's
        samples (default `short`)."""
        d = self.mean(look or self.s.short) - self.reference.level
        return float(d @ (d / self.variance(q, Y, look=look)))

    # --- the judgement -----------------------------------------------------------------------------
    def explains(self, prediction, q, Y, look=None) -> bool:
        """Whether the level's departure is `prediction` (n,) within the noise, friction and pose error alone (not
        the allowance for a level still moving): chi^2 <= detect."""
        u = self.mean(look or self.s.short) - self.reference.level - prediction
        return bool(u @ (u / self.variance(q, Y, moving=False, look=look)) <= self.s.detect)

    def same(self, d, e, q, Y=None) -> bool:
        """Whether two departures d, e (n,) differ by less than the sensor's noise and the pose error say a change
        does (chi^2 <= detect; friction left out: a level that moves with the arm's speed is not the same level)."""
        u = np.asarray(d) - np.asarray(e)
        return bool(u @ (u / self.variance(q, Y, moving=False, friction=False)) <= self.s.detect)

    def judge(self, Y, J, phi, q, payloads: Payloads, expected: bool = False, held=None, still=True,
              look=None) -> Verdict:
        """Posterior over the hypotheses for the level now (equal prior odds, a compound one's the product): noise (and
        bias), a new payload (phi_new ~ payloads, inside its box), an external wrench at the flange (force ~ N(0,
        push_force^2), moment ~ N(0, (push_force push_arm)^2) per axis), back to an earlier payload (no free
        parameter; the best of them), and back to one under a wrench.
        Y (n, 4): the payload regressor at q; J (6, n): the flange's world Jacobian; phi (4,): compensated now;
        expected: the task announced a load change (the payload's prior odds EXPECTED); held (n,): the level of a
        wrench judged before this one and still acting, if any: a return or a new payload may be a step from it (one
        event: the wrench stays), as well as a step from the reference (the wrench gone with it; for a new payload
        two events at once, COMPOUND); still: the arm was still when that level was held (else a new payload is
        judged from the reference alone); look: the level's samples (default `short`)."""
        s = self.s
        d = self.mean(look or s.short) - self.reference.level
        V = self.covariance(q, Y, look=look)
        fV = cholesky(V)
        logs = {"noise": gaussian_log_pdf(d, V, fV)}
        K = self.compensated @ Y.T                                 # nothing changed: the compensated payload,
        kept = phi + K @ solve(fV, d)                              #   phi ~ N(phi_hat, cov), seen through d
        kept_cov = self.compensated - K @ solve(fV, K.T)
        held = None if held is None else np.asarray(held, dtype=float)
        steps = [(d, 0.0, None)] if held is None or not still else [(d, COMPOUND, None), (d - held, 0.0, held)]
        log, new, cov, odds, under = max((self._payload(x, Y, V, phi, payloads) + (o, u) for x, o, u in steps),
                                         key=lambda c: c[0] + c[3])
        logs["payload"] = log + odds               # under a held wrench: a step from its level (it goes on), or
        #                                            from the reference (the wrench gone at once: two events)
        W = np.diag([s.push_force ** 2] * 3 + [(s.push_force * s.push_arm) ** 2] * 3)
        logs["wrench"] = gaussian_log_pdf(d, J.T @ W @ J + V)        # a new wrench, or the held one unchanged
        if held is not None:
            logs["wrench"] = max(logs["wrench"], gaussian_log_pdf(d - held, V))
        C0 = V - Y @ self.compensated @ Y.T                            # each earlier payload with its own error
        own = self.reference.held                                      #   and the one the reference holds
        states = [(p, c) for p, c in zip(payloads.earlier + [np.zeros(4)], payloads.covs + [np.zeros((4, 4))])
                  if np.abs(p - phi).max() > 1e-6]
        backs = []                                                     # from the reference, and from a held wrench
        for p, c in states:
            Cb = C0 + Y @ (c + own) @ Y.T
            f, e = cholesky(Cb), d - Y @ (p - phi)
            backs += [(gaussian_log_pdf(e, Cb, f), p, c, None)]
            backs += [] if held is None else [(gaussian_log_pdf(e - held, Cb, f), p, c, held)]
        back = max(backs, key=lambda b: b[0]) if backs else (-np.inf, None, None, None)
        logs["back"] = back[0]
        Cw = J.T @ W @ J + C0                                          # an earlier payload back under a new wrench
        mixed = [(gaussian_log_pdf(d - Y @ (p - phi), Cw + Y @ (c + own) @ Y.T), p, c, None)   # (a press
                 for p, c in states]
        mixed = max(mixed, key=lambda b: b[0]) if mixed else (-np.inf, None, None, None)           # let go in a push)
        logs["back+wrench"] = mixed[0] + COMPOUND
        logs["payload"] += EXPECTED if expected else 0.0
        top = max(logs.values())
        w = {h: math.exp(v - top) for h, v in logs.items()}
        total = sum(w.values())
        post = {h: w[h] / total for h in HYPOTHESES}
        best = max(post, key=post.get)
        earlier = back if best == "back" else mixed
        returned = best.startswith("back")
        means = {"noise": kept, "payload": new, "wrench": np.asarray(phi, dtype=float)}
        means.update({h: phi if b[1] is None else b[1] for h, b in (("back", back), ("back+wrench", mixed))})
        return Verdict(d, post, best, earlier[1] if returned else new if best == "payload" else None,
                       math.sqrt(max(cov[0, 0], 0.0)), earlier[2] if returned else None,
                       earlier[3] if returned else under if best == "payload" else None, kept, kept_cov, means)

    def _payload(self, e, Y, V, phi, payloads: Payloads) -> tuple:
        """(log evidence, posterior mean (4,), covariance (4, 4)) of a new payload phi_new ~ payloads, inside its
        box, for the departure e (n,) from the level it replaces (phi compensated; V the level's covariance)."""
        P = np.diag(payloads.std ** 2)
        f = cholesky(Y @ P @ Y.T + V)
        e = e - Y @ (payloads.mean - phi)
        K = P @ Y.T
        z = solve(f, e)
        new = payloads.mean + K @ z                                              # posterior of phi_new
        cov = P - K @ solve(f, K.T)
        log = float(-0.5 * e @ z - np.log(np.diag(f)).sum()
                    - 0.5 * self.n * math.log(2 * math.pi)) + self._box(new[0], cov[0, 0], payloads) \
            - self._box(payloads.mean[0], P[0, 0], payloads)
        if new[0] >= 0.1 and np.abs(new[1:]).max() > payloads.max_com * new[0]:
            log = -np.inf                                              # a CoM beyond any hand's reach: no payload
        return log, new, cov

    @staticmethod
    def _box(mean, var, p: Payloads) -> float:
        """log of the Gaussian's mass (mean, var) of the mass inside [0, max_mass] (from the nearer tail)."""
        sd = math.sqrt(max(var, 1e-18))
        a, b = (0.0 - mean) / sd, (p.max_mass - mean) / sd
        if a > 0:
            a, b = -b, -a
        hi, lo = float(log_ndtr(b)), float(log_ndtr(a))
        return hi + float(np.log(-np.expm1(min(lo - hi, 0.0)))) if lo < hi else -np.inf
