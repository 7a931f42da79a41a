"""The mismatch network f_NN of Sec. 4.1 / Appendix F (Table 6) in NumPy with hand-written backprop, its
pseudo-wrench input (Sec. 4.1, W = (J J^T + lambda I)^-1 J tau_ext) and the weights file; the trainer is nn_train.py,
the data experiments/training.py. Retrain: python nn_numpy.py train; time it: python nn_numpy.py bench."""
from __future__ import annotations

import json
import os
import sys
from dataclasses import asdict, dataclass

import numpy as np

import checks
from dynamics import pseudo_wrench

WEIGHTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "weights.npz")
MAX_ABS_WEIGHT = 1e6          # larger stored values overflow the forward pass: a corrupt or foreign file


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
    xp = np.zeros((x.shape[0], L + 2 * pad, C), dtype=x.dtype)               # zero padding (np.pad is slow)
    xp[:, pad:pad + L] = x
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
def features(robot, q, tau_ext, cfg=NetConfig(), kinematics=None):
    """Network input x (M, 6) from a window q (T, n), tau_ext (T, n) with T >= M (T = 200 at 1 kHz).

    tau_ext must already be REFERRED to the torque just before the load change (tau_ext - its mean over the
    ~50 ms before it), which removes the pose-dependent bias a real Panda shows. M samples are taken evenly
    spaced from the window (Appendix F); W is expressed in the ee frame, W_ee = diag(R^T, R^T) W_world, because
    theta's CoM is in the ee frame and the network is not told the pose otherwise (our choice, README)."""
    q, tau_ext, n = checks.real("q", q), checks.real("tau_ext", tau_ext), robot.n   # (bool, complex: refused)
    if q.ndim != 2 or q.shape[1] != n:
        raise ValueError(f"q: expected shape (T, {n}), found {q.shape}")
    if tau_ext.shape != q.shape:
        raise ValueError(f"tau_ext: expected shape {q.shape} (like q), found {tau_ext.shape}")
    if q.shape[0] < cfg.M:
        raise ValueError(f"q: expected a window of at least {cfg.M} samples, found {q.shape[0]}")
    if not (np.all(np.isfinite(q)) and np.all(np.isfinite(tau_ext))):
        raise ValueError("q, tau_ext: expected finite values, found NaN or inf")
    idx = token_indices(q.shape[0], cfg.M)
    if kinematics is not None:                     # (R (T, 3, 3), J (T, 6, n)) of the whole window, already known
        R, J = kinematics[0][idx], kinematics[1][idx]
        Rt = R.transpose(0, 2, 1)
        return pseudo_wrench(np.concatenate([Rt @ J[:, :3], Rt @ J[:, 3:]], axis=1), tau_ext[idx], cfg.lam)
    return pseudo_wrench(ee_jacobian(robot, q[idx]), tau_ext[idx], cfg.lam)


def token_indices(T, M=20):
    """M indices spread evenly over a window of T samples (first and last included)."""
    return np.round(np.linspace(0, T - 1, M)).astype(int)


def ee_jacobian(robot, q):
    """J (T, 6, n) with its rows in the ee frame: diag(R^T, R^T) J_world, for q (T, n); one kinematics pass."""
    _, R, J = robot.kinematics(q)                                             # R (T, 3, 3), J (T, 6, n) world
    Rt = R.transpose(0, 2, 1)
    return np.concatenate([Rt @ J[:, :3], Rt @ J[:, 3:]], axis=1)


def feature_regressor(robot, q, cfg=NetConfig()):
    """A (M, 6, 4) with features(robot, q, Y(q) phi) = A @ phi for a window q (T, n): how a static payload
    phi = (m, m r) enters the input, since W is linear in tau_ext and tau_mm = Y phi (used for augmentation)."""
    idx = token_indices(len(q), cfg.M)
    J = ee_jacobian(robot, q[idx])
    A = J @ J.transpose(0, 2, 1) + cfg.lam * np.eye(6)
    return np.linalg.solve(A, J @ robot.payload_regressor(q[idx]))


# ----------------------------------------------------------------------------------------------------
# Weights file: parameters under their code names, normalisation stats, metadata (JSON)
# ----------------------------------------------------------------------------------------------------
STAT_SHAPES = {"norm.x_mean": (6,), "norm.x_std": (6,), "norm.theta_mean": (4,), "norm.theta_std": (4,)}
RANGE_SHAPES = {"range.theta_low": (4,), "range.theta_high": (4,)}      # optional: the training range of theta
DEFAULT_RANGE = ((0.1, -0.1, -0.1, 0.0), (2.0, 0.1, 0.1, 0.2))    # kg, m: nn_train.DataConfig's, for files without it


def training_range(meta):
    """(low (4,), high (4,)) of the payloads in meta["data"] (m_range, r_low, r_high), else DEFAULT_RANGE."""
    data = meta.get("data", {}) if isinstance(meta, dict) else {}
    if not all(k in data for k in ("m_range", "r_low", "r_high")):
        return tuple(np.array(v, dtype=float) for v in DEFAULT_RANGE)
    return (np.array([data["m_range"][0], *data["r_low"]], float), np.array([data["m_range"][1], *data["r_high"]], float))


def save_weights(path, params, stats, meta, theta_range=None):
    """Write the weights file; theta_range (low (4,), high (4,)): the training range, default training_range(meta)."""
    arrays = dict(flatten(params))
    arrays.update({f"norm.{k}": np.asarray(v) for k, v in stats.items()})
    low, high = training_range(meta) if theta_range is None else theta_range
    arrays.update({"range.theta_low": np.asarray(low, float), "range.theta_high": np.asarray(high, float)})
    np.savez(path, meta=np.array(json.dumps(meta)), **arrays)


def load_weights(path, net=NetConfig()):
    """(params, stats, meta, theta_range) from a weights file (theta_range (2, 4): low, high; DEFAULT_RANGE if the
    file has none); ValueError naming any missing, unexpected, misshaped or non-finite array, a network
    configuration unlike net, or a file that is not a readable .npz."""
    try:
        with np.load(path, allow_pickle=False) as f:
            arrays = {k: f[k] for k in f.files}
    except Exception as err:                      # missing file, truncated zip, bad header, pickled object...
        raise ValueError(f"path: could not read weights file {str(path)!r}: {type(err).__name__}: {err}") from None
    expected = {**param_shapes(net), **STAT_SHAPES, "meta": (), **RANGE_SHAPES}
    for name, shape in expected.items():
        if name not in arrays and name in RANGE_SHAPES:
            continue
        if name not in arrays:
            raise ValueError(f"{path}: array {name!r} missing (expected shape {shape})")
        a = arrays[name]
        if name != "meta" and (a.shape != shape or a.dtype.kind != "f" or not np.all(np.isfinite(a))):
            raise ValueError(f"{path}: array {name!r} expected finite floats of shape {shape}, "
                             f"found {a.dtype} {a.shape}")
        if name.endswith("_std") and np.any(a <= 0):
            raise ValueError(f"{path}: array {name!r} expected positive values, found {a.tolist()}")
        if name != "meta" and np.abs(a).max(initial=0.0) > MAX_ABS_WEIGHT:
            raise ValueError(f"{path}: array {name!r} expected values within +-{MAX_ABS_WEIGHT:g} (a trained network's "
                             f"are of order 1), found {np.abs(a).max():.3g}")
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
    theta_range = np.array([arrays[k] if k in arrays else v for k, v in zip(RANGE_SHAPES, DEFAULT_RANGE)], float)
    if np.any(theta_range[0] >= theta_range[1]):
        raise ValueError(f"{path}: arrays 'range.theta_low' < 'range.theta_high' expected, found {theta_range.tolist()}")
    return params, stats, meta, theta_range


class MismatchNet:
    """The trained f_NN: raw pseudo-wrenches or a referred window -> theta = (m, rx, ry, rz) in kg and m."""

    def __init__(self, params, stats, meta=None, theta_range=DEFAULT_RANGE, net=NetConfig()):
        self.params, self.stats, self.meta, self.net = params, stats, meta or {}, net
        self.theta_range = np.array(theta_range, dtype=float)             # (2, 4): low, high of the training set

    @classmethod
    def load(cls, path=WEIGHTS, net=NetConfig()):
        """The network stored at path; ValueError naming the file and the array if it cannot be used, including a
        network whose prediction for a typical input is not finite."""
        model = cls(*load_weights(path, net), net=net)
        probe = model.stats["x_mean"] + model.stats["x_std"] * np.ones((net.M, net.d_in))
        if not np.all(np.isfinite(model.predict(probe))):
            raise ValueError(f"{path}: the stored network predicts non-finite values for a typical input")
        return model

    def predict(self, x):
        """x (B, M, 6) or (M, 6) raw pseudo-wrenches (from `features`) -> theta (B, 4) or (4,)."""
        a = checks.real("x", x)                       # (bool, complex: refused, never cast)
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

    def predict_window(self, robot, q, tau_ext, kinematics=None):
        """theta (4,) from a window q (T, n), tau_ext (T, n) already referred to the pre-change torque;
        kinematics: (R (T, 3, 3), J (T, 6, n)) of the window when the caller has them."""
        return self.predict(features(robot, q, tau_ext, self.net, kinematics))

    def prior_std(self, theta, sigma_prior, R=None, margin=0.1):
        """The prior's std (4,) for the prediction theta (4,). sigma_prior (4,) holds at the ready pose, where the ee z
        axis is vertical: across gravity the network reads r to sp_perp = (sp_rx, sp_ry, max of the two), along
        gravity (which no torque shows) only to sp_rz. R (3, 3), the ee orientation, gives g = R^T e_z in the ee frame;
        r_i's variance sp_perp_i^2 (1 - g_i^2) + sp_rz^2 |g_i| sum_k |g_k| keeps the diagonal prior's std along g at
        least sp_rz (sum_i g_i^2 / var_i <= 1 / sp_rz^2), which the plain diagonal of the turned covariance would not.
        Each component within margin x the training range's half-width of the range's edge, or beyond it, is widened
        to that half-width: there the network extrapolates (a saturated output looks like the edge)."""
        sp = np.array(sigma_prior, dtype=float)
        if R is not None:
            g, perp = np.abs(np.asarray(R, dtype=float)[2]), np.r_[sp[1:3], sp[1:3].max()]
            sp[1:] = np.sqrt(perp**2 * (1.0 - g**2) + sp[3] ** 2 * g * g.sum())
        low, high = self.theta_range
        half = 0.5 * (high - low)
        near = (theta < low + margin * half) | (theta > high - margin * half) | ~np.isfinite(theta)
        return np.where(near, np.maximum(sp, half), sp)


if __name__ == "__main__":          # python nn_numpy.py train|bench: the script's entry, not part of the module
    from experiments.training import main
    sys.exit(main())
