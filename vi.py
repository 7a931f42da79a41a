"""Mean-field Gaussian variational inference of the payload theta = (m, rx, ry, rz) (Sec. 4.2, Eqs. 9-10, 14-18):
-ELBO by the reparameterisation trick with hand-written gradients through tau_mm = Y(q) phi(theta),
phi = (m, m rx, m ry, m rz); Adam with global-norm clipping, stopped when mu and sigma settle."""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from dynamics import phi_of, theta_of   # noqa: F401  (vi.phi_of, vi.theta_of: the estimate's parameters)

LOG_2PI = float(np.log(2.0 * np.pi))


@dataclass(frozen=True)
class VISettings:
    """Settings of fit(). mu and sigma are optimised in units of the starting q (see fit)."""
    sigma_prior: tuple = (0.5, 0.02, 0.02, 0.05)   # kg, m, m, m: Sec. 5 ("empirically tuned")
    lr: float = 0.025                  # Adam learning rate, Sec. 4.2
    betas: tuple = (0.9, 0.999)        # Adam moment decays, Kingma and Ba 2015 defaults
    adam_eps: float = 1e-8             # Kingma and Ba 2015
    clip_norm: float = 1.0             # global gradient-norm clip, authors' public code (paper_notes)
    samples: int = 16                  # Monte Carlo samples per step; ours (authors' code: 1; `python sim.py vi-bench`)
    antithetic: bool = True            # ours: samples in pairs (eps, -eps) (variance reduction; samples even)
    control_variate: bool = True       # ours: quadratic control variate for the sigma gradient (Miller et al. 2017)
    max_iterations: int = 2500         # authors' public code
    min_iterations: int = 10           # ours: first convergence check (against the start)
    check_every: int = 10              # ours: iterations between convergence checks
    average: float = 0.9               # ours: decay of the running (exponential) average of the iterates
    tol: float = 0.05                  # ours: largest change of the running average between two checks,
                                       #   mu in units of the starting sigma, log sigma absolute
    warm_start: bool = True            # ours: start at the MAP with the Laplace mean-field sigma (False: q = prior)
    map_steps: int = 20                # ours: most Gauss-Newton steps of the warm start
    noise_rule: str = "residual"       # ours: "residual" (rms of the window's least-squares residual per joint)
                                       #   or "range" (authors' code: 0.25 x the range of the joint's torque)
    noise_scale: float = 1.0           # multiplies the rule's per-joint value
    noise_floor: float = 0.1           # Nm, lowest per-joint noise std, authors' public code
    offset_std: float = 0.05           # Nm, std of a torque offset constant over the window, marginalised
                                       #   (ours; Panda torque repeatability 0.05 Nm, panda_facts.md)
    keep_history: bool = False         # record mu, sigma and the -ELBO estimate at every iteration

    def __post_init__(self):
        sp = np.asarray(self.sigma_prior, dtype=float)
        if sp.shape != (4,) or not np.all(np.isfinite(sp)) or np.any(sp <= 0):
            raise ValueError(f"sigma_prior: expected 4 finite values > 0, found {self.sigma_prior}")
        for name in ("lr", "clip_norm", "tol", "noise_scale"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"{name}: expected a finite value > 0, found {v}")
        for name in ("noise_floor", "offset_std", "adam_eps"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v >= 0):
                raise ValueError(f"{name}: expected a finite value >= 0, found {v}")
        for name in ("samples", "max_iterations", "check_every", "map_steps"):
            v = getattr(self, name)
            if not (isinstance(v, (int, np.integer)) and v >= (0 if name == "map_steps" else 1)):
                raise ValueError(f"{name}: expected a positive integer, found {v!r}")
        if not (0 <= self.min_iterations <= self.max_iterations):
            raise ValueError(f"min_iterations: expected 0..max_iterations, found {self.min_iterations}")
        if len(self.betas) != 2 or not all(0 <= b < 1 for b in self.betas):
            raise ValueError(f"betas: expected two values in [0, 1), found {self.betas}")
        if not 0 <= self.average < 1:
            raise ValueError(f"average: expected a value in [0, 1), found {self.average}")
        if self.antithetic and self.samples % 2:
            raise ValueError(f"samples: expected an even number with antithetic pairs, found {self.samples}")
        if self.noise_rule not in ("residual", "range"):
            raise ValueError(f"noise_rule: expected 'residual' or 'range', found {self.noise_rule!r}")


@dataclass(frozen=True)
class Window:
    """The Gaussian log-likelihood of a window as a quadratic form in phi (4,):
    -log p(D | theta) = 1/2 phi^T A phi - b^T phi + c/2 + log_norm."""
    A: np.ndarray            # (4, 4)
    b: np.ndarray            # (4,)
    c: float
    log_norm: float          # 1/2 log det(2 pi Sigma) of the window's covariance
    noise_std: np.ndarray    # (n,) per-joint white-noise std s_j [Nm]
    T: int


@dataclass
class Posterior:
    """q(theta) = N(mean, diag(std^2)) and how the solver got there.

    std is the mean-field sigma, which ignores the posterior's correlations and so understates the marginal
    spread of correlated components (from one pose, r along gravity is unobservable and m, r trade off);
    cov is the Laplace covariance H^-1 at the mean (Gauss-Newton Hessian of the log joint), whose diagonal
    (marginal_std) gives honest intervals. Measured coverage: test_vi.py and `python sim.py vi-bench`."""
    mean: np.ndarray         # (4,) m [kg], rx, ry, rz [m] in the ee frame
    std: np.ndarray          # (4,)
    cov: np.ndarray          # (4, 4)
    iterations: int
    seconds: float
    converged: bool
    status: str              # "converged" or "max_iterations"
    neg_elbo: float          # -ELBO at (mean, std), Monte Carlo with 64 samples
    noise_std: np.ndarray    # (n,) the likelihood's per-joint noise std
    history: np.ndarray | None = field(default=None, repr=False)   # (iterations, 9): mu, sigma, -ELBO

    @property
    def marginal_std(self):
        """(4,) sqrt(diag(cov))."""
        return np.sqrt(np.diag(self.cov))


# --- input checks ------------------------------------------------------------------------------------
def _array(name, x, shape_text, ndim):
    try:
        a = np.asarray(x, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a numeric array of shape {shape_text}, "
                         f"found {type(x).__name__}") from None
    if a.ndim != ndim:
        raise ValueError(f"{name}: expected shape {shape_text}, found {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name}: expected finite values, found NaN or inf")
    return a


def check_window(Y, tau):
    """Checked Y (T, n, 4) and tau (T, n)."""
    Y = _array("Y", Y, "(T, n, 4)", 3)
    if Y.shape[2] != 4 or Y.shape[0] < 1:
        raise ValueError(f"Y: expected shape (T, n, 4) with T >= 1, found {Y.shape}")
    tau = _array("tau", tau, f"(T, n) = {Y.shape[:2]}", 2)
    if tau.shape != Y.shape[:2]:
        raise ValueError(f"tau: expected shape {Y.shape[:2]} to match Y, found {tau.shape}")
    return Y, tau


# ------------------------------------------------------------------------------------------------------
# Likelihood: the window's quadratic form in phi (computed once, O(T n))
# ------------------------------------------------------------------------------------------------------
def noise_from_window(Y, tau, settings=VISettings()):
    """Per-joint likelihood noise s (n,) [Nm] from the window Y (T, n, 4), tau (T, n).

    "residual": s_j = rms over t of the least-squares residual tau_tj - y_tj phi - beta_j (phi shared by the
    joints, beta_j a per-joint constant), i.e. what the model cannot explain; unlike the range or the std of
    tau it does not count the payload's own pose-dependent torque (a moving window) as noise.
    "range": s_j = 0.25 (max_t tau_tj - min_t tau_tj), the authors' code. Both: max(noise_scale s_j, noise_floor).
    """
    T = Y.shape[0]
    if settings.noise_rule == "range":
        s = 0.25 * (tau.max(axis=0) - tau.min(axis=0))
    elif T < 2:
        raise ValueError(f"tau: the residual noise rule needs T >= 2 samples, found T = {T}")
    else:
        Yc = Y - Y.mean(axis=0)                              # (T, n, 4): per-joint constants removed
        tc = tau - tau.mean(axis=0)                          # (T, n)
        Z = Yc.reshape(-1, 4)                                # (T n, 4)
        G = Z.T @ Z
        ridge = 1e-9 * (np.trace(G) + np.sum(Y * Y)) + 1e-300   # keeps phi finite when Yc is ~0 (static)
        phi = np.linalg.solve(G + ridge * np.eye(4), Z.T @ tc.reshape(-1))
        res = tc - Yc @ phi                                  # (T, n)
        s = np.sqrt(np.sum(res * res, axis=0) / (T - 1))
    return np.maximum(settings.noise_scale * s, settings.noise_floor)


def precompute(Y, tau, noise_std=None, settings=VISettings()):
    """Window quadratic form from Y (T, n, 4) and tau (T, n).

    Per joint j: tau_tj = y_tj^T phi + beta_j + e_tj with e_tj ~ N(0, s_j^2) white and beta_j ~ N(0, d^2)
    (d = settings.offset_std) constant over the window, marginalised: the joint's covariance over the window is
    s_j^2 I + d^2 11^T, whose inverse is (I - k_j 11^T) / s_j^2 with k_j = d^2 / (s_j^2 + T d^2). So
      A = sum_j (G_j - k_j yb_j yb_j^T) / s_j^2,  b = sum_j (h_j - k_j yb_j taub_j) / s_j^2,
    with G_j = sum_t y y^T, h_j = sum_t y tau, yb_j = sum_t y, taub_j = sum_t tau. d = 0: independent samples.
    noise_std (n,) overrides the settings' noise rule.
    """
    Y, tau = check_window(Y, tau)
    T, n, _ = Y.shape
    if noise_std is None:
        s = noise_from_window(Y, tau, settings)
    else:
        s = _array("noise_std", noise_std, f"({n},)", 1)
        if s.shape != (n,) or np.any(s <= 0):
            raise ValueError(f"noise_std: expected shape ({n},) with values > 0, found {s}")
    w = 1.0 / s**2                                           # (n,)
    d2 = settings.offset_std**2
    k = d2 / (s**2 + T * d2)                                 # (n,)
    Zw = (Y * np.sqrt(w)[:, None]).reshape(-1, 4)            # (T n, 4) whitened regressor
    tw = (tau * np.sqrt(w)).reshape(-1)
    yb, tb = Y.sum(axis=0), tau.sum(axis=0)                  # (n, 4), (n,)
    wk = w * k
    A = Zw.T @ Zw - (yb * wk[:, None]).T @ yb
    b = Zw.T @ tw - (yb * wk[:, None]).T @ tb
    c = float(tw @ tw - wk @ tb**2)
    log_norm = 0.5 * float(np.sum(T * (LOG_2PI + np.log(s**2)) + np.log1p(T * d2 / s**2)))
    return Window(0.5 * (A + A.T), b, c, log_norm, s, T)


def combine(windows):
    """One Window from several windows of the same payload (e.g. at other poses): each with its own offset
    (precompute), independent of the others, so their quadratic forms in phi add (evidence accumulates)."""
    if len(windows) < 1:
        raise ValueError("windows: expected at least one Window, found none")
    total = lambda key: sum(getattr(w, key) for w in windows)
    return Window(total("A"), total("b"), total("c"), total("log_norm"),
                  np.sqrt(np.mean([w.noise_std ** 2 for w in windows], axis=0)), total("T"))


# ------------------------------------------------------------------------------------------------------
# -ELBO and its gradient (reparameterised, eps held fixed)
# ------------------------------------------------------------------------------------------------------
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
    mu, log_sigma, eps = (np.asarray(a, dtype=float) for a in (mu, log_sigma, eps))
    sigma_prior = np.asarray(sigma_prior, dtype=float)
    sigma = np.exp(log_sigma)
    nll, dtheta = likelihood_grad(mu + sigma * eps, window.A, window.b)
    P = 1.0 / sigma_prior**2
    diff = mu - mu_prior
    value = (nll.mean() + 0.5 * window.c + window.log_norm
             + 0.5 * np.sum((diff**2 + sigma**2) * P) + np.sum(np.log(sigma_prior)) + 2.0 * LOG_2PI
             - np.sum(log_sigma) - 2.0 * (1.0 + LOG_2PI))
    d_mu = dtheta.mean(axis=0) + diff * P
    d_log_sigma = (dtheta * eps).mean(axis=0) * sigma + sigma**2 * P - 1.0
    return float(value), d_mu, d_log_sigma


def neg_elbo(mu, log_sigma, window, mu_prior, sigma_prior, eps):
    """The Monte Carlo -ELBO of neg_elbo_grad, value only."""
    return neg_elbo_grad(mu, log_sigma, window, mu_prior, sigma_prior, eps)[0]


# ------------------------------------------------------------------------------------------------------
# Warm start: MAP by Gauss-Newton, sigma from the diagonal of its Hessian
# ------------------------------------------------------------------------------------------------------
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
def fit(Y, tau, mu_prior, settings=VISettings(), rng=None, noise_std=None):
    """q(theta) = N(mean, diag(std^2)) for the window Y (T, n, 4) = payload_regressor(q), tau (T, n) = tau_ext
    (referred to the torque before the change; or lists of windows: combine), prior N(mu_prior, diag(sigma_prior^2)).

    Adam minimises the Monte Carlo -ELBO over x = (z, w): mu = mu0 + C z, log sigma = log sigma0 + w, from the
    starting q (mu0, sigma0). warm_start: mu0 = MAP, sigma0 = the Laplace mean-field sigma (1 / sqrt(H_ii)),
    C = chol(H^-1) (lower triangular), so that Adam's steps are fractions of the posterior's width along its own
    axes, correlated (m, r) included; otherwise q starts at the prior and C = diag(sigma_prior).
    m >= 0: after each step mu_m = mu0_m + C_00 z_0 is projected onto mu_m >= 0 (projected Adam; the objective
    and its gradient are unchanged; samples of m may be < 0, where the likelihood is still defined).
    Convergence: every check_every iterations the running average of x must have moved by less than tol;
    the running average is what is returned (it smooths the Monte Carlo jitter of the last iterates).
    """
    t0 = time.perf_counter()
    mu_prior = _array("mu_prior", mu_prior, "(4,)", 1)
    if mu_prior.shape != (4,):
        raise ValueError(f"mu_prior: expected shape (4,), found {mu_prior.shape}")
    if not isinstance(rng, np.random.Generator):
        raise ValueError(f"rng: expected a np.random.Generator, found {type(rng).__name__}")
    if not isinstance(settings, VISettings):
        raise ValueError(f"settings: expected a VISettings, found {type(settings).__name__}")
    many = isinstance(Y, (list, tuple))
    if many != isinstance(tau, (list, tuple)) or (many and len(Y) != len(tau)):
        raise ValueError(f"Y, tau: expected a window each or equal-length lists, found {type(Y)}, {type(tau)}")
    window = combine([precompute(Yi, ti, noise_std, settings) for Yi, ti in zip(Y, tau)]) if many else \
        precompute(Y, tau, noise_std, settings)
    sp = np.asarray(settings.sigma_prior, dtype=float)
    if settings.warm_start:
        mu0, H = map_estimate(window, mu_prior, sp, settings.map_steps)
        sigma0 = 1.0 / np.sqrt(np.diag(H))
        C = np.linalg.cholesky(np.linalg.inv(H))                     # C C^T = H^-1, C[0, 1:] = 0
    else:
        mu0, sigma0, C = mu_prior.copy(), sp.copy(), np.diag(sp)
        mu0[0] = max(mu0[0], 0.0)
    x, it, converged, history = _adam(window, mu_prior, sp, mu0, sigma0, C, settings, rng)
    mean, std = mu0 + C @ x[:4], sigma0 * np.exp(x[4:])
    cov = np.linalg.inv(gauss_newton(mean, window, mu_prior, sp)[2])      # Laplace covariance at the mean
    eps = rng.standard_normal((64, 4))                               # a final, less noisy -ELBO estimate
    value = neg_elbo_grad(mean, np.log(std), window, mu_prior, sp, eps)[0]
    return Posterior(mean, std, cov, it, time.perf_counter() - t0, converged,
                     "converged" if converged else "max_iterations", value, window.noise_std, history)


def _draws(rng, chunk, samples, antithetic):
    """eps (chunk, samples, 4); antithetic: pairs (eps, -eps), which cancel the odd terms of the estimator."""
    if not antithetic:
        return rng.standard_normal((chunk, samples, 4))
    half = rng.standard_normal((chunk, samples // 2, 4))
    return np.concatenate([half, -half], axis=1)


def _adam(window, mu_prior, sp, mu0, sigma0, C, s, rng):
    """Projected Adam on x = (z, w) (8,). Returns (running average of x, iterations, converged, history).

    Gradients: d/dz = C^T d/dmu, d/dw = d/dlog_sigma. The prior's part of C^T d/dmu, C^T P (mu0 + C z - mp),
    is affine in z: q0 + Q z with Q = C^T P C, q0 = C^T P (mu0 - mp).
    Control variate (Miller et al. 2017, "Reducing reparameterization gradient variance"): the NLL's quadratic
    model at mu0, with Hessian H0 = J^T A J, contributes (H0 (sigma eps_k)) * eps_k * sigma to each sample's
    d/dlog_sigma, with known mean diag(H0) sigma^2; subtracting the first and adding the second keeps the
    estimate unbiased and removes the noise of eps_k^2 from it (exact for a Gaussian posterior).
    Its part in d/dmu, H0 sigma eps_k, already cancels within antithetic pairs."""
    b1, b2 = s.betas
    A, b, P = window.A, window.b, 1.0 / sp**2
    H0 = gauss_newton(mu0, window, mu_prior, sp)[2] - np.diag(P) if s.control_variate else np.zeros((4, 4))
    dH0 = np.diag(H0).copy()
    Q, q0 = C.T @ (P[:, None] * C), C.T @ (P * (mu0 - mu_prior))
    z_min = -mu0[0] / C[0, 0]                                         # mu_m >= 0  <=>  z_0 >= z_min
    x, m1, m2, avg, last, g = (np.zeros(8) for _ in range(6))
    z, w = x[:4], x[4:]                                               # views: updated with x
    mean_k = np.full(s.samples, 1.0 / s.samples)                      # (K,): averages over the samples
    converged, chunk = False, 64
    history = np.empty((s.max_iterations, 9)) if s.keep_history else None
    for t in range(1, s.max_iterations + 1):
        if (t - 1) % chunk == 0:
            E = _draws(rng, chunk, s.samples, s.antithetic)
        eps = E[(t - 1) % chunk]                                      # (K, 4)
        mu, sigma = mu0 + C @ z, sigma0 * np.exp(w)
        _, dtheta = likelihood_grad(mu + sigma * eps, A, b, value=False)   # (K, 4)
        g[:4] = (mean_k @ dtheta) @ C + q0 + Q @ z                    # NLL + prior, chain rule to z
        cv = (sigma * eps) @ H0                                       # (K, 4) control variate
        g[4:] = (mean_k @ ((dtheta - cv) * eps) + sigma * (dH0 + P)) * sigma - 1.0   # NLL + prior - entropy
        norm2 = g @ g
        if norm2 > s.clip_norm**2:                                    # global-norm clipping
            g *= s.clip_norm / np.sqrt(norm2)
        m1 *= b1
        m1 += (1 - b1) * g
        m2 *= b2
        m2 += (1 - b2) * g * g
        c1, c2 = 1 - b1**t, np.sqrt(1 - b2**t)                        # Adam's bias corrections
        x -= (s.lr * c2 / c1) * m1 / (np.sqrt(m2) + s.adam_eps * c2)
        if x[0] < z_min:                                              # projection: mu_m >= 0
            x[0] = z_min
        avg *= s.average
        avg += (1 - s.average) * x
        if history is not None:
            history[t - 1, :8] = np.concatenate([mu, sigma])
            history[t - 1, 8] = neg_elbo_grad(mu, np.log(sigma), window, mu_prior, sp, eps)[0]
        if t % s.check_every == 0:
            current = avg / (1 - s.average**t)
            if t >= s.min_iterations and np.max(np.abs(current - last)) < s.tol:
                converged = True
                break
            last = current
    return avg / (1 - s.average**t), t, converged, None if history is None else history[:t]
