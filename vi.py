"""Mean-field Gaussian variational inference of the payload theta = (m, rx, ry, rz) (Sec. 4.2, Eqs. 9-10, 14-18):
-ELBO by the reparameterisation trick with hand-written gradients through tau_mm = Y(q) phi(theta),
phi = (m, m rx, m ry, m rz); Adam with global-norm clipping, stopped when mu and sigma settle."""
from __future__ import annotations

import functools
import time
from dataclasses import dataclass

import numpy as np
from scipy import special

import checks
from dynamics import phi_of, theta_of   # noqa: F401  (vi.phi_of, vi.theta_of: the estimate's parameters)

LOG_2PI = float(np.log(2.0 * np.pi))
ADAM = (0.9, 0.999, 1e-8)   # Adam's moment decays and epsilon: Kingma and Ba 2015's defaults


@dataclass(frozen=True)
class VISettings:
    """Settings of fit(). mu and sigma are optimised in units of the starting q (see fit)."""
    sigma_prior: tuple = (0.5, 0.02, 0.02, 0.05)   # kg, m, m, m: Sec. 5 ("empirically tuned")
    lr: float = 0.025                  # Adam learning rate, Sec. 4.2
    clip_norm: float = 1.0             # global gradient-norm clip, authors' public code (paper_notes)
    samples: int = 16                  # Monte Carlo samples per step; ours (authors' code: 1; `python sim.py vi-bench`)
    max_iterations: int = 2500         # authors' public code
    min_iterations: int = 10           # ours: first convergence check (against the start)
    check_every: int = 10              # ours: iterations between convergence checks
    average: float = 0.9               # ours: decay of the running (exponential) average of the iterates
    tol: float = 0.05                  # ours: largest move of the running average between checks (mu / sigma0, log sigma)
    warm_start: bool = True            # ours: start at the MAP with the Laplace mean-field sigma (False: q = prior)
    map_steps: int = 20                # ours: most Gauss-Newton steps of the warm start
    noise_rule: str = "residual"       # ours: "residual" (noise_from_window) or "range" (authors' code)
    noise_scale: float = 1.0           # multiplies the rule's per-joint white-noise value
    noise_floor: float = 0.0058        # Nm, lowest white-noise std: resolution 0.02 Nm / sqrt(12) (authors': 0.1)
    offset_std: float = 0.005          # Nm, std of an offset constant over the window (ours: realistic preset)
    load_share: float = 0.01           # ours: constant error per unit of load torque (bias moves as the arm sags)
    slow_gain: float = 1.0             # ours: constant error per unit of the residual's slow part (settling,
                                       #   friction), both calibrated with `python sim.py calibration`
    motion_gain: float = 0.3           # Nm s/rad, ours: constant error per unit of |dq| (friction, off-pose model
    motion_max: float = 1.3            #   error; 0.3 beats 1.0 on Table 1, calibration, limit cycle); Nm, at most
    reference_samples: int = 30        # samples of the level a window is referred to (the paper's tables' 30
                                       #   before the change; the stream's own is 2 changes.short, 80: less noise)
    swing_frequencies: tuple = tuple(np.arange(1.0, 10.01, 0.1))   # Hz, where swing_share looks for a swing: a
                                       #   flexible load a hand carries, 1-10 Hz (the steel beam of docs/real_logs.md:
                                       #   1.8-4.3 Hz); below 1 Hz a 0.2 s window holds a drift, not a swing
    observed_ratio: float = 0.5        # ours: a parameter counts as observed if its posterior std < this x prior std
    conflict: float = 5.0              # ln Bayes factor of a broad prior over the network's beyond which the window
                                       #   conflicts with the network (fit's alternative): "very strong" evidence,
                                       #   2 ln B > 10 (Kass and Raftery 1995)

    def __post_init__(self):
        """Upper bounds keep the solver finite, far beyond any use: lr 1 (a step of the prior's width), 10 Nm of noise
        (the Panda's: 0.005-0.09 Nm), 10^4 iterations x 256 samples (about 10 s); prior stds of 1e3 (flat)."""
        c = checks
        c.array("sigma_prior", self.sigma_prior, (4,), "(0, 1e3]", "kg, m, m, m")
        for name, interval in (("lr", "(0, 1]"), ("clip_norm", "(0, 1e3]"), ("average", "[0, 1)"),
                               ("tol", "(0, 10]"), ("noise_scale", "(0, 1e3]"), ("noise_floor", "[0, 10]"),
                               ("offset_std", "[0, 10]"), ("load_share", "[0, 1]"), ("slow_gain", "[0, 10]"),
                               ("motion_gain", "[0, 100]"), ("motion_max", "[0, 100]"), ("observed_ratio", "(0, 1]"), ("conflict", "(0, 1e3]"),
                               ("samples", "1..256"), ("max_iterations", "1..10000"), ("check_every", "1..10000"),
                               ("map_steps", "0..1000"), ("reference_samples", "1..10000")):
            c.number(name, getattr(self, name), interval, "Nm" if name in ("noise_floor", "offset_std") else "")
        c.number("min_iterations", self.min_iterations, f"0..{self.max_iterations}", "(max_iterations)")
        c.array("swing_frequencies", self.swing_frequencies, (None,), "(0, 500]", "Hz")
        c.flag("warm_start", self.warm_start)
        if self.samples % 2:
            raise ValueError(f"samples: expected an even number (antithetic pairs), found {self.samples}")
        c.choice("noise_rule", self.noise_rule, ("residual", "range"))


@dataclass(frozen=True)
class Window:
    """-log p(D | theta) = 1/2 phi^T A phi - b^T phi + c/2 + log_norm, a window's likelihood in phi (4,)."""
    A: np.ndarray            # (4, 4)
    b: np.ndarray            # (4,)
    c: float
    log_norm: float          # 1/2 log det(2 pi Sigma) of the window's covariance
    noise_std: np.ndarray    # (n,) per-joint white-noise std s_j [Nm]
    T: int
    offset_std: np.ndarray   # (n, 3) per-joint std D_j of the error's constant, linear, parabolic parts [Nm]


@dataclass
class Posterior:
    """q(theta) = N(mean, diag(std^2)) and how the solver got there. std, the mean-field sigma, understates the
    spread of correlated components (m, r trade off); cov is the Laplace covariance H^-1 at the mean, whose diagonal
    (marginal_std) gives honest intervals (coverage: `python sim.py calibration`)."""
    mean: np.ndarray         # (4,) m [kg], rx, ry, rz [m] in the ee frame
    std: np.ndarray          # (4,)
    cov: np.ndarray          # (4, 4)
    iterations: int
    seconds: float
    converged: bool
    status: str              # "converged" or "max_iterations"
    neg_elbo: float          # -ELBO at (mean, std), Monte Carlo with 64 samples
    noise_std: np.ndarray    # (n,) the likelihood's per-joint noise std
    observed: np.ndarray     # (4,) bool: marginal_std < observed_ratio x the prior's std (the data informed it)
    prior: str = "network"   # the prior q started from: "network", or "broad" where the window conflicts with it
    prior_mean: np.ndarray | None = None   # (4,) that prior's mean

    marginal_std = property(lambda self: np.sqrt(np.diag(self.cov)), doc="(4,) sqrt(diag(cov))")


# --- input checks ------------------------------------------------------------------------------------
def _array(name, x, shape_text, ndim):
    if (a := checks.real_array(x)) is None:                  # bool, complex, text: refused, not cast
        raise ValueError(f"{name}: expected a real array of shape {shape_text}, found {checks.kind(x)}")
    a = a.astype(float)
    if a.ndim != ndim:
        raise ValueError(f"{name}: expected shape {shape_text}, found {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: expected finite values, found NaN or inf")
    return a


def joint_speed(q, dt, lag=20):
    """(n,) rms speed [rad/s] of each joint over the window q (T, n) sampled every dt s (differences lag apart)."""
    lag = max(1, min(lag, len(q) - 1))
    return np.sqrt(np.mean(((q[lag:] - q[:-lag]) / (lag * dt)) ** 2, axis=0))


def check_window(Y, tau):
    """Checked Y (T, n, 4) and tau (T, n)."""
    Y, tau = _array("Y", Y, "(T, n, 4)", 3), tau
    if Y.shape[2] != 4 or Y.shape[0] < 1:
        raise ValueError(f"Y: expected shape (T, n, 4) with T >= 1, found {Y.shape}")
    if (tau := _array("tau", tau, f"(T, n) = {Y.shape[:2]}", 2)).shape != Y.shape[:2]:
        raise ValueError(f"tau: expected shape {Y.shape[:2]} to match Y, found {tau.shape}")
    return Y, tau


# --- Likelihood: the window's quadratic form in phi (computed once, O(T n)) --------------------------
def noise_from_window(Y, tau, settings=VISettings(), speed=None, bias_std=None):
    """Per-joint error model of the window Y (T, n, 4), tau (T, n), speed (n,) [rad/s] (joint_speed; None: at rest):
    s (n,) [Nm] the std of the error that averages down over the T samples, D (n, 3) [Nm] the std of its slow parts
    (constant, P1(t), P2(t)), marginalised by precompute.

    "residual": res (T, n), the least-squares residual of tau_tj = y_tj phi + beta_j (phi shared, beta_j per joint),
    splits into a slow part (line and parabola in t per joint: settling, friction, a drifting bias) and the rest e.
    s_j = max(noise_scale rms(e_j) sqrt((1 + rho_j) / (1 - rho_j)), noise_floor), rho_j the lag-1 autocorrelation of
    e_j (the variance of the mean of AR(1) noise); d_j^2 = offset_std^2 + (load_share |mean_t tau_tj|)^2 +
    (slow_gain rms(slow_j))^2 + s_j^2 / reference_samples + min(motion_gain |speed|, motion_max)^2: the sensor's
    bias, its change as the arm sags under the load, what settling leaves in the window's mean, the noise of the
    reference the window is referred to, what a moving arm adds on every joint (friction, and the model's error as
    the pose leaves the reference's: steady over a window of steady motion, no residual shows it); the P1 and
    P2 parts: slow_gain x the fitted coefficient's rms (with offset_std): a drift that shadows the arm's motion.
    "range": s_j = max(noise_scale 0.25 (max_t tau_tj - min_t tau_tj), noise_floor) (authors' code), D_j = (offset_std, 0, 0).
    bias_std (n,) [Nm] (error_model.ErrorModel: absolute or referred): replaces offset_std as the constant's std
    ("residual" only: the range rule is the authors' as it is).
    """
    T, n, _ = Y.shape
    offset = np.full(n, settings.offset_std) if bias_std is None else np.asarray(bias_std, dtype=float)
    if settings.noise_rule == "range":
        s = settings.noise_scale * 0.25 * (tau.max(axis=0) - tau.min(axis=0))
        return np.maximum(s, settings.noise_floor), np.outer(np.full(n, settings.offset_std), [1.0, 0.0, 0.0])
    if T < 4:
        raise ValueError(f"tau: the residual noise rule needs T >= 4 samples, found T = {T}")
    Yc, tc = Y - Y.mean(axis=0), tau - tau.mean(axis=0)      # (T, n, 4), (T, n): per-joint constants removed
    Z = Yc.reshape(-1, 4)                                    # (T n, 4)
    G = Z.T @ Z
    ridge = 1e-9 * (np.trace(G) + np.sum(Y * Y)) + 1e-300   # keeps phi finite when Yc is ~0 (static)
    res = tc - Yc @ np.linalg.solve(G + ridge * np.eye(4), Z.T @ tc.reshape(-1))   # (T, n)
    slow, coef, s = _slow_and_white(res, settings)
    d2 = (offset**2 + (settings.load_share * tau.mean(axis=0))**2
          + settings.slow_gain**2 * np.mean(slow * slow, axis=0) + s**2 / settings.reference_samples
          + np.minimum(settings.motion_gain * np.linalg.norm(0.0 if speed is None else speed), settings.motion_max)**2)
    v = np.sqrt(settings.offset_std**2 + settings.slow_gain**2 * np.mean(coef * coef, axis=0))
    return s, np.stack([np.sqrt(d2), v, v], axis=1)


def _slow_and_white(res, settings):
    """res (T, n) -> slow (T, n) its line and parabola in t per joint (Legendre P1, P2: drift, settling, a swing),
    coef (2, n) their coefficients, s (n,) the std of the rest e, inflated for its lag-1 autocorrelation rho_j
    (the variance of the mean of AR(1) noise): max(noise_scale rms(e_j) sqrt((1 + rho_j) / (1 - rho_j)), noise_floor)."""
    T = res.shape[0]
    t = np.linspace(-1.0, 1.0, T)
    B = np.stack([t, 1.5 * t * t - 0.5], axis=1)             # (T, 2) Legendre P1, P2: slow drift
    coef = np.linalg.lstsq(B, res, rcond=None)[0]            # (2, n)
    slow, e = B @ coef, res - B @ coef                       # (T, n) each
    rho = np.clip(np.sum(e[1:] * e[:-1], axis=0) / np.maximum(np.sum(e * e, axis=0), 1e-300), 0.0, 0.9)
    s = np.maximum(settings.noise_scale * np.sqrt(np.sum(e * e, axis=0) / (T - 3) * (1 + rho) / (1 - rho)),
                   settings.noise_floor)
    return slow, coef, s


def swing_share(x, dt, freqs):
    """A swing's share of its slow part in a window's mean: x (T, n) a window less its mean, sampled every dt s.
    Its swing x_j(t) = a_j cos(w t + psi) + e shares one frequency f = w / 2 pi over the joints: the f of `freqs` [Hz]
    whose per-joint fit (1, cos wt, sin wt) leaves the least. For a uniform phase psi, with c, s = cos wt, sin wt
    (T,), C the centring and P the projector on the window's P1, P2 (_slow_and_white):
      E[mean_t x^2] / E[rms(slow)^2] = ((1^T c)^2 + (1^T s)^2) / T^2 / ((|P C c|^2 + |P C s|^2) / T).
    Returns (share, f)."""
    Q, shares = _swing_bases(x.shape[0], float(dt), tuple(float(f) for f in freqs))
    k = int(np.argmax(np.sum(np.einsum("ftk,tj->fkj", Q, x) ** 2, axis=(1, 2))))   # the most held: the least left
    return float(shares[k]), float(freqs[k])


@functools.lru_cache(maxsize=8)
def _swing_bases(T, dt, freqs):
    """Q (F, T, 3) orthonormal bases of (1, cos wt, sin wt) and each frequency's share (swing_share), (F,)."""
    t, u = np.arange(T) * dt, np.linspace(-1.0, 1.0, T)
    B = np.stack([u, 1.5 * u * u - 0.5], axis=1)                   # (T, 2) as in _slow_and_white
    Q, shares = np.empty((len(freqs), T, 3)), np.empty(len(freqs))
    for i, f in enumerate(freqs):
        cs = np.stack([np.cos(2 * np.pi * f * t), np.sin(2 * np.pi * f * t)], axis=1)      # (T, 2)
        Q[i] = np.linalg.qr(np.column_stack([np.ones(T), cs]))[0]
        slow = B @ np.linalg.lstsq(B, cs - cs.mean(axis=0), rcond=None)[0]                 # (T, 2) P C c, P C s
        shares[i] = (np.sum(cs.sum(axis=0) ** 2) / T**2) / max(np.sum(slow**2) / T, 1e-300)
    return Q, shares


def level_variance(tau, settings=VISettings(), dt=1e-3):
    """(n,) [Nm^2] what the mean of a window tau (T, n) at rest with nothing changing (a baseline), sampled every dt
    s, holds besides its level: its swing's share of its slow part (swing_share) x rms(slow_j)^2, and its noise
    s_j^2 / T (_slow_and_white)."""
    tau = _array("baseline", tau, "(T, n)", 2)
    if tau.shape[0] < 4:
        raise ValueError(f"baseline: expected a window of T >= 4 samples, found T = {tau.shape[0]}")
    x = tau - tau.mean(axis=0)
    slow, _, s = _slow_and_white(x, settings)
    share = swing_share(x, dt, settings.swing_frequencies)[0]
    return share * np.mean(slow * slow, axis=0) + s**2 / tau.shape[0]


def precompute(Y, tau, noise_std=None, settings=VISettings(), speed=None, bias_std=None):
    """Window quadratic form from Y (T, n, 4) and tau (T, n) (speed (n,): the joints' speed, noise_from_window).

    Per joint j: tau_j = Y_j phi + B g_j + e_j, e_j ~ N(0, s_j^2 I) white, B (T, 3) = (1, P1(t), P2(t)) and
    g_j ~ N(0, diag(D_j^2)) a slow error (an offset, a drift), marginalised: the joint's covariance over the window is
    S_j = s_j^2 I + B diag(D_j^2) B^T, and by Woodbury S_j^-1 = (I - B K_j B^T) / s_j^2 with
    K_j = R (s_j^2 I + R B^T B R)^-1 R, R = diag(D_j). So, with Yb_j = B^T Y_j, taub_j = B^T tau_j:
      A = sum_j (Y_j^T Y_j - Yb_j^T K_j Yb_j) / s_j^2,  b = sum_j (Y_j^T tau_j - Yb_j^T K_j taub_j) / s_j^2.
    s, D from noise_from_window (bias_std (n,): the constant's std there); noise_std (n,) overrides s, with
    D_j = (bias_std or settings.offset_std, 0, 0).
    bias_std (n, n): a covariance C of a constant c (n,) shared by the joints (a robot model's error is correlated
    across them; error_model.ErrorModel.covariance), marginalised too: with u_j = 1^T S_j^-1 1, F_j = 1^T S_j^-1 Y_j
    and f_j = 1^T S_j^-1 tau_j, Woodbury over c removes F^T W F from A, F^T W f from b, f^T W f from c, with
    W = (C^-1 + diag(u))^-1, and adds 1/2 log det(I + C diag(u)) to log_norm.
    """
    Y, tau = check_window(Y, tau)
    T, n, _ = Y.shape
    if speed is not None and ((speed := _array("speed", speed, f"({n},)", 1)).shape != (n,) or np.any(speed < 0)):
        raise ValueError(f"speed: expected shape ({n},) with values >= 0, found {speed}")
    C = None
    if bias_std is not None:
        b_in, bias_std = bias_std, _array("bias_std", bias_std, f"({n},) or ({n}, {n})", np.ndim(bias_std))
        if bias_std.shape not in ((n,), (n, n)) or np.any(np.diag(np.atleast_2d(bias_std)) < 0) or (
                bias_std.ndim == 2 and (not np.allclose(bias_std, bias_std.T)
                                        or np.linalg.eigvalsh(bias_std)[0] <= 0)):
            raise ValueError(f"bias_std: expected ({n},) stds >= 0 or an ({n}, {n}) positive definite covariance, "
                             f"found {np.shape(b_in)} {np.asarray(b_in).ravel()[:4]}")
    if bias_std is not None and bias_std.ndim == 2:                 # a shared constant: the diagonal part is 0
        C, bias_std = bias_std, np.zeros(n)
    if noise_std is None:
        s, D = noise_from_window(Y, tau, settings, speed, bias_std)
    else:
        s = _array("noise_std", noise_std, f"({n},)", 1)
        D = np.outer(np.full(n, settings.offset_std) if bias_std is None else bias_std, [1.0, 0, 0])
        if s.shape != (n,) or np.any(s <= 0):
            raise ValueError(f"noise_std: expected shape ({n},) with values > 0, found {s}")
    t = np.linspace(-1.0, 1.0, T)
    B = np.stack([np.ones(T), t, 1.5 * t * t - 0.5], axis=1)          # (T, 3)
    M = s[:, None, None] ** 2 * np.eye(3) + D[:, :, None] * (B.T @ B) * D[:, None, :]   # (n, 3, 3)
    K = D[:, :, None] * np.linalg.inv(M) * D[:, None, :] / s[:, None, None] ** 2          # (n, 3, 3), / s_j^2
    Zw, tw = (Y / s[:, None]).reshape(-1, 4), (tau / s).reshape(-1)   # (T n, 4), (T n,) whitened
    Yb, tb = np.einsum("tk,tjp->jkp", B, Y), B.T @ tau       # (n, 3, 4), (3, n)
    A = Zw.T @ Zw - np.einsum("jkp,jkq->pq", Yb, KYb := K @ Yb)                   # K Yb (n, 3, 4)
    b = Zw.T @ tw - np.einsum("jkp,kj->p", KYb, tb)
    c = float(tw @ tw - np.einsum("kj,jkl,lj->", tb, K, tb))
    log_norm = 0.5 * float(T * np.sum(LOG_2PI + np.log(s**2)) + np.sum(np.linalg.slogdet(M)[1] - 3 * np.log(s**2)))
    if C is not None:
        g = (B.T @ B)[0]                                             # 1^T B (3,)
        gK = np.einsum("k,jkl->jl", g, K)                            # (n, 3): g^T K_j
        u = T / s**2 - gK @ g                                        # (n,) 1^T S_j^-1 1, S_j^-1 = I / s_j^2 - B K_j B^T
        F = Yb[:, 0, :] / s[:, None] ** 2 - np.einsum("jl,jlp->jp", gK, Yb)   # (n, 4)
        f = tb[0] / s**2 - np.einsum("jl,lj->j", gK, tb)             # (n,)
        Mc = np.linalg.inv(C) + np.diag(u)
        W = np.linalg.inv(Mc)
        A, b, c = A - F.T @ W @ F, b - F.T @ W @ f, c - float(f @ W @ f)
        log_norm += 0.5 * float(np.linalg.slogdet(C)[1] + np.linalg.slogdet(Mc)[1])
    return Window(0.5 * (A + A.T), b, c, log_norm, s, T, D)


def combine(windows):
    """One Window from several windows of the same payload (e.g. at other poses): each with its own offset
    (precompute), independent of the others, so their quadratic forms in phi add (evidence accumulates)."""
    if len(windows) < 1:
        raise ValueError("windows: expected at least one Window, found none")
    total = lambda key: sum(getattr(w, key) for w in windows)
    rms = lambda key: np.sqrt(np.mean([getattr(w, key) ** 2 for w in windows], axis=0))
    return Window(total("A"), total("b"), total("c"), total("log_norm"), rms("noise_std"), total("T"), rms("offset_std"))


# --- -ELBO and its gradient (reparameterised, eps held fixed) ----------------------------------------
def likelihood_grad(theta, A, b, value=True):
    """NLL(phi(theta_k)) without its constants and dNLL/dtheta_k for samples theta (K, 4) -> (K,), (K, 4).

    NLL = 1/2 phi^T A phi - b^T phi; dNLL/dphi = A phi - b = g; dphi/dm = (1, r) = u, dphi/dr = m I
    => dNLL/dtheta = (u . g, m g_r). value=False skips the NLL (returns None for it)."""
    m = theta[:, :1]                                          # (K, 1)
    u = theta.copy()
    u[:, 0] = 1.0                                             # (K, 4) = (1, r)
    phi = m * u                                               # (K, 4)
    phiA = phi @ A                                            # (K, 4), A symmetric
    g = phiA - b                                              # (K, 4)
    dtheta = m * g
    dtheta[:, 0] = (u * g).sum(axis=1)
    return (0.5 * (phi * phiA).sum(axis=1) - phi @ b) if value else None, dtheta


def neg_elbo_grad(mu, log_sigma, window, mu_prior, sigma_prior, eps):
    """-ELBO(mu, sigma) estimated with samples theta_k = mu + sigma eps_k, eps (K, 4), and its exact gradient.

    -ELBO = 1/K sum_k NLL(phi(theta_k)) + E_q[-log p(theta)] - H[q]; the last two in closed form:
      E_q[-log p(theta)] = sum_i ((mu_i - mp_i)^2 + sigma_i^2) / (2 sp_i^2) + log sp_i + log(2 pi)/2,
      H[q] = sum_i log sigma_i + (1 + log(2 pi))/2.
    Reparameterisation: d/dmu = mean_k dNLL/dtheta_k, d/dlog_sigma = mean_k (dNLL/dtheta_k * eps_k) * sigma.
    Returns (value, d_mu (4,), d_log_sigma (4,)).
    """
    mu, log_sigma, eps, sigma_prior = (np.asarray(a, dtype=float) for a in (mu, log_sigma, eps, sigma_prior))
    sigma = np.exp(log_sigma)
    nll, dtheta = likelihood_grad(mu + sigma * eps, window.A, window.b)
    P, diff = 1.0 / sigma_prior**2, mu - mu_prior
    value = (nll.mean() + 0.5 * window.c + window.log_norm
             + 0.5 * np.sum((diff**2 + sigma**2) * P) + np.sum(np.log(sigma_prior)) + 2.0 * LOG_2PI
             - np.sum(log_sigma) - 2.0 * (1.0 + LOG_2PI))
    d_mu = dtheta.mean(axis=0) + diff * P
    d_log_sigma = (dtheta * eps).mean(axis=0) * sigma + sigma**2 * P - 1.0
    return float(value), d_mu, d_log_sigma


def neg_elbo(mu, log_sigma, window, mu_prior, sigma_prior, eps):         # the Monte Carlo -ELBO alone
    return neg_elbo_grad(mu, log_sigma, window, mu_prior, sigma_prior, eps)[0]


# --- Warm start: MAP by Gauss-Newton, sigma from the diagonal of its Hessian -------------------------
def gauss_newton(theta, window, mu_prior, sigma_prior):
    """-log p(D, theta) up to constants, E = 1/2 phi^T A phi - b^T phi + 1/2 sum_i P_i (theta_i - mp_i)^2, its gradient
    (4,) and Gauss-Newton Hessian H (4, 4), P = 1/sp^2: with J = dphi/dtheta = [(1, r), m I],
    grad = J^T (A phi - b) + P (theta - mp), H = J^T A J + diag(P)."""
    P = 1.0 / sigma_prior**2
    m, u = theta[0], np.concatenate([[1.0], theta[1:]])
    phi = m * u
    Aphi, d = window.A @ phi, theta - mu_prior
    E = 0.5 * phi @ Aphi - window.b @ phi + 0.5 * (P * d) @ d
    J = np.diag(np.full(4, m))
    J[:, 0] = u                                               # dphi/dm = (1, r); dphi/dr = m I
    return E, J.T @ (Aphi - window.b) + P * d, J.T @ window.A @ J + np.diag(P)


def map_estimate(window, mu_prior, sigma_prior, steps=20, tol=1e-3):
    """MAP of theta with m >= 0 by Gauss-Newton (gauss_newton) with backtracking, until no step is larger than
    tol times the Laplace mean-field sigma 1 / sqrt(H_ii).

    Starts at m = the least-squares mass of the window (phi_0 of argmin over phi: the weight's force, whatever
    r), r = the prior mean: from m = 0 Gauss-Newton could not move r (dphi/dr = m I = 0).
    Returns (theta (4,), H (4, 4) at theta). For a Gaussian target the best mean-field q has 1/sigma_i^2 = H_ii.
    """
    A = window.A
    phi_ls = np.linalg.solve(A + 1e-9 * np.trace(A) * np.eye(4), window.b)   # ridge: rz may be unobservable
    theta = mu_prior.copy()
    theta[0] = phi_ls[0] if phi_ls[0] > 0 else max(theta[0], 0.0)
    E, grad, H = gauss_newton(theta, window, mu_prior, sigma_prior)
    for _ in range(steps):
        delta = np.linalg.solve(H, grad)
        if np.max(np.abs(delta) * np.sqrt(np.diag(H))) < tol:       # step in Laplace sigmas
            break
        for t in 0.5 ** np.arange(12):                        # backtracking on E
            trial = theta - t * delta
            trial[0] = max(trial[0], 0.0)
            terms = gauss_newton(trial, window, mu_prior, sigma_prior)
            if terms[0] < E:
                theta, (E, grad, H) = trial, terms
                break
        else:
            break
    return theta, H


# --- the solver ---------------------------------------------------------------------------------------
def fit(Y, tau, mu_prior, settings=VISettings(), rng=None, noise_std=None, sigma_prior=None, speed=None,
        bias_std=None, alternative=None):
    """q(theta) = N(mean, diag(std^2)) for the window Y (T, n, 4) = payload_regressor(q), tau (T, n) = tau_ext
    (referred to the torque before the change; or lists of windows: combine), prior N(mu_prior, diag(sigma_prior^2)),
    sigma_prior (4,) = settings.sigma_prior unless given (e.g. widened where the network extrapolates), speed (n,)
    the joints' speed in the window (joint_speed; a list with lists of windows; None: at rest), bias_std (n,) the
    std of the window's constant error (error_model; a list with lists of windows; None: settings.offset_std).
    alternative: (mean, std, lo, hi) (4,) each, a broad prior over every plausible payload, taken instead of the network's
    where the window's Laplace evidence favours it by more than settings.conflict (prior_conflict); `Posterior.prior`
    names the one used.

    Adam minimises the Monte Carlo -ELBO over x = (z, w): mu = mu0 + C z, log sigma = log sigma0 + w. warm_start:
    mu0 = MAP, sigma0 = the Laplace mean-field sigma (1 / sqrt(H_ii)), C = chol(H^-1), so that Adam's steps are
    fractions of the posterior's width along its own axes; otherwise q starts at the prior and C = diag(sigma_prior).
    m >= 0: mu_m = mu0_m + C_00 z_0 is projected onto mu_m >= 0 after each step (samples of m may be < 0).
    Convergence: every check_every iterations the running average of x (returned) must move by less than tol.
    """
    t0 = time.perf_counter()
    if (mu_prior := _array("mu_prior", mu_prior, "(4,)", 1)).shape != (4,):
        raise ValueError(f"mu_prior: expected shape (4,), found {mu_prior.shape}")
    if not isinstance(rng, np.random.Generator):
        raise ValueError(f"rng: expected a np.random.Generator, found {type(rng).__name__}")
    if not isinstance(settings, VISettings):
        raise ValueError(f"settings: expected a VISettings, found {type(settings).__name__}")
    many = isinstance(Y, (list, tuple))
    if many != isinstance(tau, (list, tuple)) or (many and len(Y) != len(tau)):
        raise ValueError(f"Y, tau: expected a window each or equal-length lists, found {type(Y)}, {type(tau)}")
    if many and len(speed := [None] * len(Y) if speed is None else list(speed)) != len(Y):
        raise ValueError(f"speed: expected one (n,) array per window ({len(Y)}), found {len(speed)}")
    if many and len(bias_std := [None] * len(Y) if bias_std is None else list(bias_std)) != len(Y):
        raise ValueError(f"bias_std: expected one (n,) array per window ({len(Y)}), found {len(bias_std)}")
    window = combine([precompute(Yi, ti, noise_std, settings, v, d) for Yi, ti, v, d in zip(Y, tau, speed, bias_std)]) \
        if many else precompute(Y, tau, noise_std, settings, speed, bias_std)
    sp = np.asarray(settings.sigma_prior if sigma_prior is None else sigma_prior, dtype=float)
    if sp.shape != (4,) or not np.all(np.isfinite(sp)) or np.any(sp <= 0):
        raise ValueError(f"sigma_prior: expected 4 finite values > 0, found {sigma_prior}")
    source, steps = "network", settings.map_steps
    start = map_estimate(window, mu_prior, sp, steps) if settings.warm_start or alternative is not None else None
    if alternative is not None and prior_conflict(window, (mu_prior, sp), alternative, steps, start) > settings.conflict:
        (mu_prior, sp), source = (np.asarray(a, dtype=float) for a in alternative[:2]), "broad"
        start = map_estimate(window, mu_prior, sp, steps) if settings.warm_start else None
    if settings.warm_start:
        mu0, H = start
        sigma0 = 1.0 / np.sqrt(np.diag(H))
        C = np.linalg.cholesky(np.linalg.inv(H))                     # C C^T = H^-1, C[0, 1:] = 0
    else:
        mu0, sigma0, C = np.r_[max(mu_prior[0], 0.0), mu_prior[1:]], sp.copy(), np.diag(sp)
    x, it, converged = _adam(window, mu_prior, sp, mu0, sigma0, C, settings, rng)
    mean, std = mu0 + C @ x[:4], sigma0 * np.exp(x[4:])
    cov = np.linalg.inv(gauss_newton(mean, window, mu_prior, sp)[2])      # Laplace covariance at the mean
    eps = rng.standard_normal((64, 4))                               # a final, less noisy -ELBO estimate
    value = neg_elbo_grad(mean, np.log(std), window, mu_prior, sp, eps)[0]
    return Posterior(mean, std, cov, it, time.perf_counter() - t0, converged, "converged" if converged else
                     "max_iterations", value, window.noise_std, np.sqrt(np.diag(cov)) < settings.observed_ratio * sp,
                     source, mu_prior.copy())


def log_evidence(window, mu_prior, sigma_prior, steps=20, box=None, start=None):
    """Laplace approximation of log p(D) under the prior N(mu_prior, diag(sigma_prior^2)), up to a constant the
    same for every prior: -E(theta*) - sum log sp - 1/2 log det H at the MAP theta* (map_estimate, gauss_newton;
    start: its (theta*, H) when known). box (lo (4,), hi (4,)): the prior truncated to the box (every plausible
    payload) adds log P_post(box) - log P_prior(box), the masses inside of the Laplace posterior N(theta*, H^-1) and
    of the prior, each the product of its marginals'; -inf when the MAP itself lies outside the box (the Laplace
    approximation, centred there, would credit the box with mass the fit never visits: a transient, a push)."""
    theta, H = map_estimate(window, mu_prior, sigma_prior, steps) if start is None else start
    if box is not None and not np.all((box[0] <= theta) & (theta <= box[1])):
        return -np.inf                          # its best payload is implausible: no payload in the box explains D
    E = gauss_newton(theta, window, mu_prior, sigma_prior)[0]
    value = float(-E - np.sum(np.log(sigma_prior)) - 0.5 * np.linalg.slogdet(H)[1])
    if box is not None:
        post_std = np.sqrt(np.diag(np.linalg.inv(H)))
        value += _log_mass(theta, post_std, *box) - _log_mass(np.asarray(mu_prior), np.asarray(sigma_prior), *box)
    return value


def _log_mass(mean, std, lo, hi):
    """sum_i log P(lo_i <= x_i <= hi_i) for x_i ~ N(mean_i, std_i^2), in the tail that keeps it finite."""
    a, b = (lo - mean) / std, (hi - mean) / std
    flip = a > 0                                                      # both bounds above the mean: mirror
    a, b = np.where(flip, -b, a), np.where(flip, -a, b)
    la, lb = special.log_ndtr(a), special.log_ndtr(b)                 # log Phi(a) < log Phi(b)
    return float(np.sum(lb + np.log1p(-np.exp(np.minimum(la - lb, 0.0)) + 1e-300)))


def prior_conflict(window, prior, alternative, steps=20, start=None):
    """log p(D | alternative) - log p(D | prior) (Laplace, log_evidence): prior (mean (4,), std (4,)), alternative
    (mean, std, lo, hi) a broad prior over every plausible payload lo <= theta <= hi (a truncated Gaussian); start:
    the narrow prior's (theta*, H) when known. > 0 when the window is better explained by a plausible payload that
    the narrow prior does not expect (one outside the network's training range, a robot unlike the one it was
    trained on); very negative when no plausible payload explains it (a push, a transient). fit takes the broad prior
    beyond VISettings.conflict."""
    mean, std, lo, hi = alternative
    return log_evidence(window, mean, std, steps, (lo, hi)) - log_evidence(window, *prior, steps, start=start)


def _draws(rng, chunk, samples):
    """eps (chunk, samples, 4) in antithetic pairs (eps, -eps), which cancel the odd terms of the estimator."""
    half = rng.standard_normal((chunk, samples // 2, 4))
    return np.concatenate([half, -half], axis=1)


def _adam(window, mu_prior, sp, mu0, sigma0, C, s, rng):
    """Projected Adam on x = (z, w) (8,), ADAM's constants. Returns (running average of x, iterations, converged).

    d/dz = C^T d/dmu, d/dw = d/dlog_sigma; the prior's part of C^T d/dmu is affine in z: q0 + Q z, Q = C^T P C,
    q0 = C^T P (mu0 - mp). Control variate (Miller et al. 2017): the NLL's quadratic model at mu0 (Hessian
    H0 = J^T A J) adds (H0 (sigma eps_k)) * eps_k * sigma to each sample's d/dlog_sigma, of known mean diag(H0)
    sigma^2: swapping one for the other keeps the estimate unbiased without the noise of eps_k^2 (its part in d/dmu
    cancels within antithetic pairs)."""
    b1, b2, adam_eps = ADAM
    A, b, P = window.A, window.b, 1.0 / sp**2
    H0 = gauss_newton(mu0, window, mu_prior, sp)[2] - np.diag(P)
    dH0 = np.diag(H0).copy()
    Q, q0 = C.T @ (P[:, None] * C), C.T @ (P * (mu0 - mu_prior))
    z_min = -mu0[0] / C[0, 0]                                         # mu_m >= 0  <=>  z_0 >= z_min
    x, m1, m2, avg, last, g = (np.zeros(8) for _ in range(6))
    z, w = x[:4], x[4:]                                               # views: updated with x
    mean_k = np.full(s.samples, 1.0 / s.samples)                      # (K,): averages over the samples
    converged, chunk = False, 64
    for t in range(1, s.max_iterations + 1):
        if (t - 1) % chunk == 0:
            E = _draws(rng, chunk, s.samples)
        eps = E[(t - 1) % chunk]                                      # (K, 4)
        mu, sigma = mu0 + C @ z, sigma0 * np.exp(w)
        _, dtheta = likelihood_grad(mu + sigma * eps, A, b, value=False)   # (K, 4)
        g[:4] = (mean_k @ dtheta) @ C + q0 + Q @ z                    # NLL + prior, chain rule to z
        cv = (sigma * eps) @ H0                                       # (K, 4) control variate
        g[4:] = (mean_k @ ((dtheta - cv) * eps) + sigma * (dH0 + P)) * sigma - 1.0   # NLL + prior - entropy
        norm2 = g @ g
        if norm2 > s.clip_norm**2:                                    # global-norm clipping
            g *= s.clip_norm / np.sqrt(norm2)
        m1 += (1 - b1) * (g - m1)                                     # m1 = b1 m1 + (1 - b1) g
        m2 += (1 - b2) * (g * g - m2)
        c1, c2 = 1 - b1**t, np.sqrt(1 - b2**t)                        # Adam's bias corrections
        x -= (s.lr * c2 / c1) * m1 / (np.sqrt(m2) + adam_eps * c2)
        if x[0] < z_min:                                              # projection: mu_m >= 0
            x[0] = z_min
        avg += (1 - s.average) * (x - avg)                            # running average of the iterates
        if t % s.check_every == 0:
            current = avg / (1 - s.average**t)
            if t >= s.min_iterations and np.max(np.abs(current - last)) < s.tol:
                converged = True
                break
            last = current
    return avg / (1 - s.average**t), t, converged
