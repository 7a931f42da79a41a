"""The mismatch network f_NN of Sec. 4.1 / Appendix F (Table 6) in NumPy with hand-written backprop, its
pseudo-wrench input (Sec. 4.1, W = (J J^T + lambda I)^-1 J tau_ext), training data from the simulated plant,
an Adam trainer and the weights file. Retrain: python nn_numpy.py train; time it: python nn_numpy.py bench."""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import asdict, dataclass, replace

import numpy as np

WEIGHTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "weights.npz")


@dataclass(frozen=True)
class NetConfig:
    M: int = 20               # input tokens sampled from the window, Table 6
    d_in: int = 6             # pseudo-wrench channels (F, torque), Sec. 4.1
    d: int = 64               # convolution output / model width, Table 6
    kernel: int = 5           # convolution kernel, Table 6 ('same' padding keeps length M)
    heads: int = 8            # attention heads, Table 6
    d_hidden: int = 256       # MLP hidden width, Table 6
    blocks: int = 3           # sequential MLP blocks, Table 6; ONE block applied 3 times (53,252 parameters)
    dropout: float = 0.1      # after each MLP block, Sec. 4.1 / Table 6
    d_out: int = 4            # theta = (m, rx, ry, rz)
    lam: float = 1e-4         # pseudo-wrench damping; deviation: the authors' code uses 0.01, which shrinks W by
                              # a pose-dependent 9-23 % at our random poses and costs ~10x in mass error (README)


# ----------------------------------------------------------------------------------------------------
# Layers: y, cache = f(x, p); dx, grads = f_backward(dy, cache). x is (B, L, D) unless stated.
# ----------------------------------------------------------------------------------------------------
def conv1d(x, p):
    """'same' 1-D convolution: x (B, L, C), W (K, C, D), b (D,) -> (B, L, D)."""
    K, C, D = p["W"].shape
    L, pad = x.shape[1], K // 2
    xp = np.pad(x, ((0, 0), (pad, pad), (0, 0)))
    cols = np.concatenate([xp[:, k:k + L] for k in range(K)], axis=-1)       # (B, L, K*C)
    return cols @ p["W"].reshape(K * C, D) + p["b"], (cols, p["W"])


def conv1d_backward(dy, cache):
    cols, W = cache
    K, C, D = W.shape
    B, L, _ = dy.shape
    dW = (cols.reshape(-1, K * C).T @ dy.reshape(-1, D)).reshape(K, C, D)
    dcols = (dy @ W.reshape(K * C, D).T).reshape(B, L, K, C)
    dxp = np.zeros((B, L + K - 1, C), dtype=dy.dtype)
    for k in range(K):
        dxp[:, k:k + L] += dcols[:, :, k]
    return dxp[:, K // 2:K // 2 + L], {"W": dW, "b": dy.sum((0, 1))}


def pos_embed(x, p):
    """x (B, L, D) + P (L, D)."""
    return x + p["P"], None


def pos_embed_backward(dy, cache):
    return dy, {"P": dy.sum(0)}


def attention(x, p, heads):
    """Multi-head self-attention with biased q/k/v/out projections (W (D, D), b (D,)): (B, L, D) -> (B, L, D)."""
    B, L, D = x.shape
    dh = D // heads
    split = lambda z: z.reshape(B, L, heads, dh).transpose(0, 2, 1, 3)     # (B, L, D) -> (B, h, L, dh)
    q, k, v = (split(x @ p["W" + s] + p["b" + s]) for s in "qkv")
    s = q @ k.transpose(0, 1, 3, 2) / np.sqrt(dh)                            # (B, h, L, L)
    a = np.exp(s - s.max(-1, keepdims=True))
    a /= a.sum(-1, keepdims=True)                                            # softmax over keys
    o = (a @ v).transpose(0, 2, 1, 3).reshape(B, L, D)                       # heads merged
    return o @ p["Wo"] + p["bo"], (x, p, heads, q, k, v, a, o)


def attention_backward(dy, cache):
    x, p, heads, q, k, v, a, o = cache
    B, L, D = x.shape
    dh = D // heads
    g = {"Wo": o.reshape(-1, D).T @ dy.reshape(-1, D), "bo": dy.sum((0, 1))}
    do = (dy @ p["Wo"].T).reshape(B, L, heads, dh).transpose(0, 2, 1, 3)    # (B, h, L, dh)
    da = do @ v.transpose(0, 1, 3, 2)
    dv = a.transpose(0, 1, 3, 2) @ do
    ds = a * (da - (da * a).sum(-1, keepdims=True)) / np.sqrt(dh)           # softmax Jacobian
    dq, dk = ds @ k, ds.transpose(0, 1, 3, 2) @ q
    dx = 0.0
    for s, dz in zip("qkv", (dq, dk, dv)):
        dz = dz.transpose(0, 2, 1, 3).reshape(B * L, D)
        g["W" + s], g["b" + s] = x.reshape(-1, D).T @ dz, dz.sum(0)
        dx = dx + dz @ p["W" + s].T
    return dx.reshape(B, L, D), g


def mean_pool(x):
    """(B, L, D) -> (B, D): mean over tokens."""
    return x.mean(1), x.shape[1]


def mean_pool_backward(dy, L):
    return np.repeat(dy[:, None, :] / L, L, axis=1)


def linear(x, p):
    """x (B, D_in) @ W (D_in, D_out) + b (D_out,)."""
    return x @ p["W"] + p["b"], (x, p["W"])


def linear_backward(dy, cache):
    x, W = cache
    return dy @ W.T, {"W": x.T @ dy, "b": dy.sum(0)}


def mlp_block(x, p, rate=0.0, rng=None):
    """Linear D->H, ReLU, Linear H->D, dropout (inverted; only when rng is given): (B, D) -> (B, D)."""
    h = np.maximum(x @ p["W1"] + p["b1"], 0.0)                                # (B, H)
    y = h @ p["W2"] + p["b2"]
    mask = None
    if rng is not None and rate > 0.0:
        mask = (rng.random(y.shape) >= rate) / (1.0 - rate)
        y = y * mask
    return y, (x, p, h, mask)


def mlp_block_backward(dy, cache):
    x, p, h, mask = cache
    if mask is not None:
        dy = dy * mask
    dh = (dy @ p["W2"].T) * (h > 0)
    return dh @ p["W1"].T, {"W1": x.T @ dh, "b1": dh.sum(0), "W2": h.T @ dy, "b2": dy.sum(0)}


# ----------------------------------------------------------------------------------------------------
# The network: conv -> + position -> attention -> mean -> MLP block x3 (shared) -> head (Fig. 2, Table 6)
# ----------------------------------------------------------------------------------------------------
def param_shapes(cfg=NetConfig()):
    """{'conv.W': (K, C, D), ...}: the names and shapes of every parameter tensor (also the file's names)."""
    D, H = cfg.d, cfg.d_hidden
    s = {"conv.W": (cfg.kernel, cfg.d_in, D), "conv.b": (D,), "pos.P": (cfg.M, D)}
    for n in "qkvo":
        s[f"attn.W{n}"], s[f"attn.b{n}"] = (D, D), (D,)
    s.update({"mlp.W1": (D, H), "mlp.b1": (H,), "mlp.W2": (H, D), "mlp.b2": (D,),
              "head.W": (D, cfg.d_out), "head.b": (cfg.d_out,)})
    return s


def nest(flat):
    """{'conv.W': a} -> {'conv': {'W': a}}."""
    out = {}
    for name, a in flat.items():
        layer, key = name.split(".")
        out.setdefault(layer, {})[key] = a
    return out


def flatten(params):
    return {f"{layer}.{key}": a for layer, p in params.items() for key, a in p.items()}


def n_params(params):
    return sum(a.size for a in flatten(params).values())


def init_params(rng, cfg=NetConfig()):
    """Weights ~ N(0, gain / fan_in) (He for the ReLU input, 1 otherwise), biases 0, positions N(0, 0.02^2)."""
    flat = {}
    for name, shape in param_shapes(cfg).items():
        key = name.split(".")[1]
        if key.startswith("b"):
            flat[name] = np.zeros(shape)
        elif key == "P":
            flat[name] = 0.02 * rng.standard_normal(shape)
        else:
            fan_in = int(np.prod(shape[:-1]))
            gain = 2.0 if name == "mlp.W1" else 1.0
            flat[name] = rng.standard_normal(shape) * np.sqrt(gain / fan_in)
    return nest(flat)


def forward(x, params, cfg=NetConfig(), rng=None):
    """x (B, M, 6) normalised pseudo-wrenches -> y (B, 4) scaled theta; dropout only when rng is given."""
    h, c_conv = conv1d(x, params["conv"])
    h, _ = pos_embed(h, params["pos"])
    h, c_attn = attention(h, params["attn"], cfg.heads)
    h, L = mean_pool(h)                                                        # (B, D)
    c_mlp = []
    for _ in range(cfg.blocks):                                               # the same block, applied again
        h, c = mlp_block(h, params["mlp"], cfg.dropout, rng)
        c_mlp.append(c)
    y, c_head = linear(h, params["head"])
    return y, (c_conv, c_attn, L, c_mlp, c_head)


def backward(dy, cache):
    """dL/dy (B, 4) -> dL/dx (B, M, 6) and grads nested like params (the shared block's grads summed)."""
    c_conv, c_attn, L, c_mlp, c_head = cache
    g = {}
    dh, g["head"] = linear_backward(dy, c_head)
    g["mlp"] = None
    for c in reversed(c_mlp):
        dh, gb = mlp_block_backward(dh, c)
        g["mlp"] = gb if g["mlp"] is None else {k: g["mlp"][k] + gb[k] for k in gb}
    dh = mean_pool_backward(dh, L)
    dh, g["attn"] = attention_backward(dh, c_attn)
    dh, g["pos"] = pos_embed_backward(dh, None)
    dx, g["conv"] = conv1d_backward(dh, c_conv)
    return dx, g


# ----------------------------------------------------------------------------------------------------
# Input pipeline (Sec. 4.1): 20 pseudo-wrenches from a 200-sample window
# ----------------------------------------------------------------------------------------------------
def pseudo_wrench(J, tau_ext, lam=0.01):
    """W = (J J^T + lam I)^-1 J tau_ext (paper_notes: the paper's formula lacks the inverse).

    J (T, 6, n), tau_ext (T, n) -> W (T, 6) = [F; torque], in the frame J's rows are expressed in."""
    J, tau_ext = np.asarray(J, dtype=float), np.asarray(tau_ext, dtype=float)
    if J.ndim != 3 or J.shape[1] != 6:
        raise ValueError(f"J: expected shape (T, 6, n), found {J.shape}")
    if tau_ext.shape != (J.shape[0], J.shape[2]):
        raise ValueError(f"tau_ext: expected shape {(J.shape[0], J.shape[2])}, found {tau_ext.shape}")
    if not (np.all(np.isfinite(J)) and np.all(np.isfinite(tau_ext))):
        raise ValueError("J, tau_ext: expected finite values, found NaN or inf")
    if not (np.isfinite(lam) and lam >= 0):
        raise ValueError(f"lam: expected a finite damping >= 0, found {lam}")
    A = J @ J.transpose(0, 2, 1) + lam * np.eye(6)                          # (T, 6, 6)
    return np.linalg.solve(A, (J @ tau_ext[..., None]))[..., 0]


def features(robot, q, tau_ext, cfg=NetConfig()):
    """Network input x (M, 6) from a window q (T, n), tau_ext (T, n) with T >= M (T = 200 at 1 kHz).

    tau_ext must already be REFERRED to the torque just before the load change (tau_ext - its mean over the
    ~50 ms before it), which removes the pose-dependent bias a real Panda shows. M samples are taken evenly
    spaced from the window (Appendix F); W is expressed in the ee frame, W_ee = diag(R^T, R^T) W_world, because
    theta's CoM is in the ee frame and the network is not told the pose otherwise (our choice, README)."""
    q, tau_ext = np.asarray(q, dtype=float), np.asarray(tau_ext, dtype=float)
    n = robot.n
    if q.ndim != 2 or q.shape[1] != n:
        raise ValueError(f"q: expected shape (T, {n}), found {q.shape}")
    if tau_ext.shape != q.shape:
        raise ValueError(f"tau_ext: expected shape {q.shape} (like q), found {tau_ext.shape}")
    if q.shape[0] < cfg.M:
        raise ValueError(f"q: expected a window of at least {cfg.M} samples, found {q.shape[0]}")
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(tau_ext))):
        raise ValueError("q, tau_ext: expected finite values, found NaN or inf")
    idx = token_indices(q.shape[0], cfg.M)
    return pseudo_wrench(ee_jacobian(robot, q[idx]), tau_ext[idx], cfg.lam)


def token_indices(T, M=20):
    """M indices spread evenly over a window of T samples (first and last included)."""
    return np.round(np.linspace(0, T - 1, M)).astype(int)


def ee_jacobian(robot, q):
    """J (T, 6, n) with its rows in the ee frame: diag(R^T, R^T) J_world, for q (T, n)."""
    J = robot.jacobian(q)
    Rt = robot.ee_pose(q)[1].transpose(0, 2, 1)
    return np.concatenate([Rt @ J[:, :3], Rt @ J[:, 3:]], axis=1)


def feature_regressor(robot, q, cfg=NetConfig()):
    """A (M, 6, 4) with features(robot, q, Y(q) phi) = A @ phi for a window q (T, n): how a static payload
    phi = (m, m r) enters the input, since W is linear in tau_ext and tau_mm = Y phi (used for augmentation)."""
    idx = token_indices(len(q), cfg.M)
    J = ee_jacobian(robot, q[idx])
    A = J @ J.transpose(0, 2, 1) + cfg.lam * np.eye(6)
    return np.linalg.solve(A, J @ robot.payload_regressor(q[idx]))


# ----------------------------------------------------------------------------------------------------
# Training data from the simulated plant (Appendix F: 350 simulations, 3 windows each, 80/20)
# ----------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DataConfig:
    m_range: tuple = (0.1, 2.0)              # kg, payload mass (issue 4)
    r_low: tuple = (-0.1, -0.1, 0.0)         # m, CoM box in the ee frame: objects held below the flange
    r_high: tuple = (0.1, 0.1, 0.2)          # m (Table 5 payloads: |rx|, |ry| <= 0.06, rz = 0.13)
    q_spread: tuple = (1.5, 0.5, 0.8, 0.6, 1.0, 0.6, 1.5)   # rad, uniform half-width around the ready pose
    tilt_max: float = 1.05                   # rad (60 deg), largest angle between the ee z axis and straight down
    z_min: float = 0.25                      # m, lowest ee height above the floor
    sv_min: float = 0.1                      # smallest singular value of J's linear rows (away from singular)
    t_change: float = 0.15                   # s, payload attached (observer and holding settled before)
    t_ref: float = 0.05                      # s, tau_ext reference: mean over [t_change - t_ref, t_change)
    window: int = 200                        # samples, the 200 ms window at 1 kHz (Sec. 4)
    windows_per_episode: int = 3             # 350 -> 1,050 inputs (Appendix F)
    delay_max: float = 0.4                   # s, window starts uniform in [0, delay_max] after the change
    hold_kp: tuple = (300.0,) * 4 + (50.0, 50.0, 20.0)      # Nm/rad, holding controller (our choice)
    hold_kd: tuple = (30.0,) * 4 + (5.0, 5.0, 2.0)          # Nm s/rad


def random_pose(robot, rng, cfg=DataConfig()):
    """A static pose q (7,) near the ready pose, inside the joint limits (5 % margin), high enough, not
    singular, and with the ee pointing no more than tilt_max from straight down."""
    from sim import Q_READY
    lo, hi = robot.model.jnt_range[:, 0], robot.model.jnt_range[:, 1]
    margin = 0.05 * (hi - lo)
    for _ in range(1000):
        q = np.clip(Q_READY + rng.uniform(-1, 1, 7) * np.asarray(cfg.q_spread), lo + margin, hi - margin)
        p, R = robot.ee_pose(q)
        tilt = np.arccos(np.clip(-R[2, 2], -1.0, 1.0))
        sv = np.linalg.svd(robot.jacobian(q)[:3], compute_uv=False)[-1]
        if p[2] >= cfg.z_min and tilt <= cfg.tilt_max and sv >= cfg.sv_min:
            return q
    raise RuntimeError("random_pose: no pose met the constraints in 1000 draws")


def simulate_episode(q0, theta, delays, rng, cfg=DataConfig()):
    """Hold q0 on a realistic plant, attach theta at t_change, return the referred windows.

    Returns q (k, window, 7) and tau_ext (k, window, 7) - mean(tau_ext over t_ref before the change),
    one per delay (s after the change). Simulates only up to the end of the last window."""
    from sim import Plant, PlantConfig
    plant = Plant(PlantConfig.realistic(rng), rng=rng)
    robot, dt = plant.robot, plant.dt
    kp, kd = np.asarray(cfg.hold_kp), np.asarray(cfg.hold_kd)
    i_change = int(round(cfg.t_change / dt))
    starts = i_change + np.round(np.asarray(delays) / dt).astype(int)
    n_steps = int(starts.max()) + cfg.window
    plant.schedule_payload(cfg.t_change, theta[0], theta[1:])
    s = plant.reset(q0)
    Q, T = np.empty((n_steps, 7)), np.empty((n_steps, 7))
    for i in range(n_steps):                     # sample i is at time (i + 1) dt
        s = plant.step(robot.gravity(s.q) + kp * (q0 - s.q) - kd * s.dq)    # gravity + PD hold
        Q[i], T[i] = s.q, s.tau_ext
    i_ref = i_change - int(round(cfg.t_ref / dt))
    ref = T[i_ref - 1:i_change - 1].mean(0)      # samples at times in [t_change - t_ref, t_change)
    k = np.arange(cfg.window)
    return Q[starts[:, None] + k], T[starts[:, None] + k] - ref


def make_dataset(n_episodes, rng, cfg=DataConfig(), net=NetConfig()):
    """Simulated windows: {'x' (N, M, 6) raw pseudo-wrenches, 'theta' (N, 4), 'A' (N, M, 6, 4) the
    feature_regressor, 'episode' (N,), 'delay' (N,)}."""
    from dynamics import Robot
    if int(n_episodes) < 1:
        raise ValueError(f"n_episodes: expected >= 1, found {n_episodes}")
    robot = Robot.panda()
    lo, hi = np.array([cfg.m_range[0], *cfg.r_low]), np.array([cfg.m_range[1], *cfg.r_high])
    xs, As, thetas, eps, delays = [], [], [], [], []
    for e in range(int(n_episodes)):
        q0 = random_pose(robot, rng, cfg)
        theta = rng.uniform(lo, hi)
        d = rng.uniform(0.0, cfg.delay_max, cfg.windows_per_episode)
        Qw, Tw = simulate_episode(q0, theta, d, rng, cfg)
        for j in range(len(d)):
            xs.append(features(robot, Qw[j], Tw[j], net)), As.append(feature_regressor(robot, Qw[j], net))
            thetas.append(theta), eps.append(e), delays.append(d[j])
    return {"x": np.array(xs), "theta": np.array(thetas), "A": np.array(As), "episode": np.array(eps),
            "delay": np.array(delays)}


def split_by_episode(data, rng, val_fraction=0.2):
    """80/20 split (Table 6) by episode, so no episode has windows on both sides: (train, val) dicts."""
    ep = np.unique(data["episode"])
    val_ep = rng.choice(ep, size=max(1, int(round(val_fraction * len(ep)))), replace=False)
    is_val = np.isin(data["episode"], val_ep)
    return ({k: v[~is_val] for k, v in data.items()}, {k: v[is_val] for k, v in data.items()})


# ----------------------------------------------------------------------------------------------------
# Training: inputs normalised per channel, targets scaled per output, Adam on the MSE, early stopping
# ----------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TrainConfig:
    episodes: int = 350           # simulations, Appendix F
    val_fraction: float = 0.2     # Table 6
    lr: float = 1e-3              # Adam; deviation: Table 6 uses 1e-4 for 50,000 iterations (README)
    lr_decay: float = 0.3         # lr *= lr_decay when val loss has not improved for `plateau` epochs
    plateau: int = 50             # epochs
    patience: int = 150           # epochs without val improvement before stopping
    batch: int = 64
    max_epochs: int = 3000
    max_minutes: float = 14.0     # wall-clock cap for training (the 15 min target)
    swap_prob: float = 1.0        # share of training windows whose payload CoM is redrawn each step (our choice)
    swap_mass: bool = False       # redraw the mass too (its sag transient would then not match it)
    calib_epochs: int = 60        # phase 2, dropout off (our choice: removes dropout's shrink of the output)
    lr_calib: float = 1e-4        # phase 2 learning rate (Table 6's rate)
    betas: tuple = (0.9, 0.999)   # Adam defaults (Kingma and Ba 2015)


def norm_stats(train):
    """Per-channel input stats and per-output target stats from the TRAINING set only."""
    x, th = train["x"], train["theta"]
    return {"x_mean": x.mean((0, 1)), "x_std": x.std((0, 1)) + 1e-12,
            "theta_mean": th.mean(0), "theta_std": th.std(0) + 1e-12}


def mse_loss(y, t):
    """Mean over batch and outputs of (y - t)^2 and its gradient dL/dy. With targets scaled to unit variance
    per output, 1.0 is what always predicting the training mean scores, for mass and each CoM part alike."""
    d = y - t
    return float(np.mean(d * d)), 2.0 * d / d.size


def to_phi(theta):
    """theta (..., 4) = (m, r) -> phi (..., 4) = (m, m r)."""
    return np.concatenate([theta[..., :1], theta[..., :1] * theta[..., 1:]], axis=-1)


def swap_payload(x, theta, A, rng, prob, low, high, mass=False):
    """Augmentation: with probability prob per window, replace the static payload part of its raw input,
    A @ phi, by that of a fresh theta ~ U(low, high) (its CoM only unless mass); sensor noise, bias residue
    and the sag transient of the simulation stay. x (B, M, 6), theta (B, 4), A (B, M, 6, 4) -> (x, theta)."""
    swap = rng.random(len(x)) < prob
    new = np.where(swap[:, None], rng.uniform(low, high, theta.shape), theta)
    if not mass:
        new[:, 0] = theta[:, 0]
    return x + (A @ (to_phi(new) - to_phi(theta))[:, None, :, None])[..., 0], new


def adam_step(params, grads, state, lr, betas=(0.9, 0.999), eps=1e-8):
    """One Adam update in place; state holds the moments and the step count."""
    state["t"] = state.get("t", 0) + 1
    b1, b2 = betas
    for layer, g in grads.items():
        for key, gk in g.items():
            m = state.setdefault(("m", layer, key), np.zeros_like(gk))
            v = state.setdefault(("v", layer, key), np.zeros_like(gk))
            m += (1 - b1) * (gk - m)
            v += (1 - b2) * (gk * gk - v)
            mh, vh = m / (1 - b1 ** state["t"]), v / (1 - b2 ** state["t"])
            params[layer][key] -= lr * mh / (np.sqrt(vh) + eps)


def evaluate(params, x, t, net=NetConfig(), batch=512):
    """Scaled MSE per output (4,) on normalised inputs x (N, M, 6) and scaled targets t (N, 4)."""
    y = np.concatenate([forward(x[i:i + batch], params, net)[0] for i in range(0, len(x), batch)])
    return ((y - t) ** 2).mean(0)


def train(train_set, val_set, rng, cfg=TrainConfig(), net=NetConfig(), params=None, log=print):
    """Fit the network; returns (params of the best val epoch, stats, info). Phase 1: dropout on, until val
    stalls for `patience` epochs; phase 2 (`calib_epochs`, lr_calib): from the best params, dropout off, so the
    deterministic network loses the shrink toward the mean that dropout leaves in a regression output."""
    stats = norm_stats(train_set)
    prep = lambda x, th: ((x - stats["x_mean"]) / stats["x_std"], (th - stats["theta_mean"]) / stats["theta_std"])
    (xt, tt), (xv, tv) = prep(train_set["x"], train_set["theta"]), prep(val_set["x"], val_set["theta"])
    low, high = train_set["theta"].min(0), train_set["theta"].max(0)           # the sampling box
    params = init_params(rng, net) if params is None else params
    best = (np.inf, None, 0)
    state, lr, since, t0, hist, phase, end = {}, cfg.lr, 0, time.perf_counter(), [], 1, cfg.max_epochs
    for epoch in range(1, cfg.max_epochs + cfg.calib_epochs + 1):
        order, losses = rng.permutation(len(xt)), []
        for i in range(0, len(xt), cfg.batch):
            b = order[i:i + cfg.batch]
            xb, tb = xt[b], tt[b]
            if cfg.swap_prob > 0:
                xb, tb = prep(*swap_payload(train_set["x"][b], train_set["theta"][b], train_set["A"][b], rng,
                                            cfg.swap_prob, low, high, cfg.swap_mass))
            y, cache = forward(xb, params, net, rng if phase == 1 else None)
            loss, dy = mse_loss(y, tb)
            adam_step(params, backward(dy, cache)[1], state, lr, cfg.betas)
            losses.append(loss)
        val_each = evaluate(params, xv, tv, net)
        val, elapsed = float(val_each.mean()), time.perf_counter() - t0
        hist.append((epoch, float(np.mean(losses)), val))
        if val < best[0]:
            best, since = (val, {k: {kk: a.copy() for kk, a in p.items()} for k, p in params.items()}, epoch), 0
        else:
            since += 1
            if phase == 1 and since % cfg.plateau == 0:
                lr *= cfg.lr_decay
        if epoch == 1 or epoch % 10 == 0:
            log(f"epoch {epoch:4d}  train {hist[-1][1]:.4f}  val {val:.4f} (m, rx, ry, rz "
                f"{' '.join(f'{v:.3f}' for v in val_each)})  best {best[0]:.4f}  lr {lr:.0e}  {elapsed:5.0f} s")
        if phase == 1 and (since >= cfg.patience or epoch >= cfg.max_epochs or elapsed > 60 * cfg.max_minutes):
            phase, end, lr, state = 2, epoch + cfg.calib_epochs, cfg.lr_calib, {}
            params = {k: {kk: a.copy() for kk, a in p.items()} for k, p in best[1].items()}
            log(f"epoch {epoch:4d}  phase 2: dropout off from the best epoch {best[2]}")
        if phase == 2 and (epoch >= end or elapsed > 60 * (cfg.max_minutes + 1)):
            break
    params = best[1]
    info = {"epochs": epoch, "best_epoch": best[2], "iterations": len(hist) * -(-len(xt) // cfg.batch),
            "seconds": elapsed, "val_loss": best[0], "train_loss": float(evaluate(params, xt, tt, net).mean()),
            "val_mse_scaled": evaluate(params, xv, tv, net).tolist(),
            "val_mse": (evaluate(params, xv, tv, net) * stats["theta_std"] ** 2).tolist(), "history": hist}
    return params, stats, info


# ----------------------------------------------------------------------------------------------------
# Weights file: parameters under their code names, normalisation stats, metadata (JSON)
# ----------------------------------------------------------------------------------------------------
STAT_SHAPES = {"norm.x_mean": (6,), "norm.x_std": (6,), "norm.theta_mean": (4,), "norm.theta_std": (4,)}


def save_weights(path, params, stats, meta):
    arrays = dict(flatten(params))
    arrays.update({f"norm.{k}": np.asarray(v) for k, v in stats.items()})
    np.savez(path, meta=np.array(json.dumps(meta)), **arrays)


def load_weights(path, net=NetConfig()):
    """(params, stats, meta) from a weights file; ValueError naming any missing, unexpected, misshaped or
    non-finite array, a network configuration unlike net, or a file that is not a readable .npz."""
    try:
        with np.load(path, allow_pickle=False) as f:
            arrays = {k: f[k] for k in f.files}
    except Exception as err:                      # missing file, truncated zip, bad header, pickled object...
        raise ValueError(f"path: could not read weights file {str(path)!r}: {type(err).__name__}: {err}") from None
    expected = {**param_shapes(net), **STAT_SHAPES, "meta": ()}
    for name, shape in expected.items():
        if name not in arrays:
            raise ValueError(f"{path}: array {name!r} missing (expected shape {shape})")
        a = arrays[name]
        if name != "meta" and (a.shape != shape or a.dtype.kind != "f" or not np.all(np.isfinite(a))):
            raise ValueError(f"{path}: array {name!r} expected finite floats of shape {shape}, "
                             f"found {a.dtype} {a.shape}")
        if name.endswith("_std") and np.any(a <= 0):
            raise ValueError(f"{path}: array {name!r} expected positive values, found {a.tolist()}")
    extra = sorted(set(arrays) - set(expected))
    if extra:
        raise ValueError(f"{path}: unexpected arrays {extra}")
    try:
        meta = json.loads(str(arrays["meta"]))
    except ValueError:
        meta = None
    if not isinstance(meta, dict):
        raise ValueError(f"{path}: array 'meta' expected a JSON object, found {str(arrays['meta'])[:40]!r}")
    stored = {k: v for k, v in meta.get("net", {}).items() if k in asdict(net)}
    if stored != {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(net).items()}:
        raise ValueError(f"{path}: meta 'net' expected {asdict(net)}, found {meta.get('net')}")
    params = nest({k: arrays[k].astype(float) for k in param_shapes(net)})
    stats = {k.split(".")[1]: arrays[k].astype(float) for k in STAT_SHAPES}
    return params, stats, meta


class MismatchNet:
    """The trained f_NN: raw pseudo-wrenches or a referred window -> theta = (m, rx, ry, rz) in kg and m."""

    def __init__(self, params, stats, meta=None, net=NetConfig()):
        self.params, self.stats, self.meta, self.net = params, stats, meta or {}, net

    @classmethod
    def load(cls, path=WEIGHTS, net=NetConfig()):
        return cls(*load_weights(path, net), net=net)

    def predict(self, x):
        """x (B, M, 6) or (M, 6) raw pseudo-wrenches (from `features`) -> theta (B, 4) or (4,)."""
        a = np.asarray(x, dtype=float)
        single = a.ndim == 2
        shape = (self.net.M, self.net.d_in)
        if a.shape[-2:] != shape or a.ndim not in (2, 3):
            raise ValueError(f"x: expected shape {shape} or (B, {shape[0]}, {shape[1]}), found {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError("x: expected finite values, found NaN or inf")
        s = self.stats
        y, _ = forward((a.reshape(-1, *shape) - s["x_mean"]) / s["x_std"], self.params, self.net)
        theta = s["theta_mean"] + s["theta_std"] * y
        return theta[0] if single else theta

    def predict_window(self, robot, q, tau_ext):
        """theta (4,) from a window q (T, n), tau_ext (T, n) already referred to the pre-change torque."""
        return self.predict(features(robot, q, tau_ext, self.net))


# ----------------------------------------------------------------------------------------------------
# Commands: python nn_numpy.py train [--episodes 350] [--seed 0] | bench
# ----------------------------------------------------------------------------------------------------
def train_from_scratch(episodes=350, seed=0, out=WEIGHTS, cfg=TrainConfig(), data_cfg=DataConfig(),
                       net=NetConfig(), log=print):
    """Simulate the data, split 80/20 by episode, train, write the weights file; returns its metadata."""
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    data = make_dataset(episodes, rng, data_cfg, net)
    t_data = time.perf_counter() - t0
    tr, va = split_by_episode(data, rng, cfg.val_fraction)
    log(f"data: {episodes} episodes -> {len(tr['x'])} train / {len(va['x'])} val windows in {t_data:.1f} s")
    cfg = replace(cfg, episodes=episodes)
    params, stats, info = train(tr, va, rng, cfg, net, log=log)
    meta = {"net": asdict(net), "data": asdict(data_cfg), "train": asdict(cfg), "episodes": episodes,
            "seed": seed, "n_train": len(tr["x"]), "n_val": len(va["x"]), "data_seconds": t_data,
            "wrench_frame": "ee", "tau_ext": "referred: minus its mean over t_ref before the load change",
            "target_scaling": "(theta - theta_mean) / theta_std per output, training-set stats",
            "numpy": np.__version__, **info}
    save_weights(out, params, stats, meta)
    log(f"wrote {out}: val MSE m {info['val_mse'][0]:.3e} kg^2, rx {info['val_mse'][1]:.3e}, "
        f"ry {info['val_mse'][2]:.3e}, rz {info['val_mse'][3]:.3e} m^2 ({info['seconds']:.0f} s training)")
    return meta


def held_out_mse(model, n_episodes=40, seed=2024):
    """MSE per parameter (4,) of the model and of the training-set mean on fresh simulated windows."""
    d = make_dataset(n_episodes, np.random.default_rng(seed), net=model.net)
    err = model.predict(d["x"]) - d["theta"]
    return (err ** 2).mean(0), ((model.stats["theta_mean"] - d["theta"]) ** 2).mean(0)


def benchmark(path=WEIGHTS, repeats=2000, held_out_episodes=40):
    """Median forward time for one window, training throughput, and the accuracy figures."""
    from dynamics import Robot
    model, rng = MismatchNet.load(path), np.random.default_rng(0)
    x1 = rng.standard_normal((1, 20, 6)) * model.stats["x_std"] + model.stats["x_mean"]

    def median_s(f, n):
        ts = []
        for _ in range(n):
            t = time.perf_counter()
            f()
            ts.append(time.perf_counter() - t)
        return float(np.median(ts))
    robot = Robot.panda()
    from sim import Q_READY
    q, tau = np.tile(Q_READY, (200, 1)), 0.1 * rng.standard_normal((200, 7))
    xb, tb = rng.standard_normal((32, 20, 6)), rng.standard_normal((32, 4))
    params, state = init_params(rng), {}

    def step():
        y, cache = forward(xb, params, rng=rng)
        adam_step(params, backward(mse_loss(y, tb)[1], cache)[1], state, 1e-4)
    nn_mse, mean_mse = held_out_mse(model, held_out_episodes)
    m = model.meta
    return {"forward_ms_median": 1e3 * median_s(lambda: model.predict(x1), repeats),
            "features_ms_median": 1e3 * median_s(lambda: features(robot, q, tau), repeats // 4),
            "train_samples_per_s": 32 / median_s(step, 200),
            "training_seconds": m.get("seconds"), "data_seconds": m.get("data_seconds"),
            "iterations": m.get("iterations"), "epochs": m.get("epochs"),
            "val_mse": m.get("val_mse"), "held_out_mse": nn_mse.tolist(), "held_out_mean_mse": mean_mse.tolist()}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("command", choices=["train", "bench"])
    ap.add_argument("--episodes", type=int, default=TrainConfig.episodes)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default=WEIGHTS)
    a = ap.parse_args(argv)
    if a.command == "train":
        train_from_scratch(a.episodes, a.seed, a.out, log=lambda s: print(s, flush=True))
    else:
        r = benchmark(a.out)
        for k, v in r.items():
            print(f"{k:22s} {v}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
