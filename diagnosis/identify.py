"""What a log can tell apart: the information of each effect's parameters at their plausible scale, against the error
a robot model keeps at a state (the identifiability of Eq. 1's effects); the poses and motion behind it, in words."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class IdentifyConfig:
    """When a direction of an effect's parameters is identifiable from a log.

    Hypotheses for a direction v of the parameters, each scaled by its plausible size (Effect.scale): (H1) the log
    sees it: a change of v by one plausible size moves the torque, beyond what the other effects can mimic, by more
    than the error a model keeps; (H0) it does not: the fitted value along v is that error projected onto v (a CoM
    metres away, an offset that is the load's weight). A real arm's model error is a function of its state (pose-
    dependent model and sensor error), so it does not average down over samples of one state: each distinct state
    counts once, a rest pose (on a pose_grid lattice) or a block of motion, I(v) = sum over states of the state's mean
    of sum_j (A_tj v)^2 / sigma^2. v is identifiable when I(v) >= min_info = 1: the log at least halves the
    uncertainty the plausible size leaves (a Gaussian prior of that size against one of data). Cost: fitting an
    unidentifiable v hands RME a wrong correction and a wrong load; holding an identifiable one at its nominal
    value leaves a residual the report shows, so the rule leans to holding."""
    error: float = 0.15                # Nm, model error one state keeps: the Panda torque sensor's relative
    #                                    accuracy (datasheet, panda_facts.md)
    v_rest: float = 0.02               # rad/s, every |dq| below: at rest (CompareConfig.v_rest)
    pose_grid: float = 0.05            # rad, rest poses closer than this on every joint are one state
    block: float = 0.5                 # s, a block of motion is one state (DiagnoseConfig.block)
    min_info: float = 1.0              # the log at least halves the plausible size's uncertainty


def weights(t, q, dq, config: IdentifyConfig = IdentifyConfig()) -> np.ndarray:
    """1 / (sigma^2 size of its state) (T,) per sample: t (T,), q, dq (T, n); states are rest poses (on the pose
    grid) and blocks of motion, so each state weighs as one sample of mean information."""
    still = np.all(np.abs(dq) < config.v_rest, axis=1)
    key = np.zeros((len(t), q.shape[1] + 1), np.int64)
    key[still, 1:] = np.round(q[still] / config.pose_grid)
    key[~still, 0] = 1 + np.floor((t[~still] - t[0]) / config.block).astype(np.int64)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return 1.0 / (config.error ** 2 * counts[inverse.ravel()])


def information(blocks, scales, w) -> np.ndarray:
    """M (K, K) = sum_t w_t sum_j (A_tj S)^T (A_tj S) for the blocks (T, n, k_i) concatenated, S = diag(scales, (k_i,)
    each; columns without a plausible scale, NaN, get scale 1), w (T,) from weights()."""
    A = np.concatenate(blocks, axis=2) * np.nan_to_num(np.concatenate([np.ravel(c) for c in scales]), nan=1.0)
    return np.einsum("tjk,t,tjl->kl", A, w, A, optimize=True)


def conditional(M, own: slice):
    """Eigenvalues (k,) ascending and eigenvectors (k, k) of the information of the columns `own` of M once every
    other column is fitted too (the Schur complement: what no other column can mimic)."""
    idx = np.arange(M.shape[0])
    a, b = idx[own], np.setdiff1d(idx, idx[own])
    S = M[np.ix_(a, a)]
    if len(b):
        Mbb = M[np.ix_(b, b)]
        S = S - M[np.ix_(a, b)] @ np.linalg.pinv(Mbb, rcond=1e-12, hermitian=True) @ M[np.ix_(b, a)]
    lam, V = np.linalg.eigh(0.5 * (S + S.T))
    return np.maximum(lam, 0.0), V


def excitation(q, dq, config: IdentifyConfig = IdentifyConfig()) -> dict:
    """What the log visits: {moving: share of samples with some |dq| >= v_rest, poses: distinct rest poses (on a
    pose_grid lattice), top_pose: share of the rest samples at the most visited pose}. q, dq (T, n)."""
    still = np.all(np.abs(dq) < config.v_rest, axis=1)
    cells = np.round(q[still] / config.pose_grid).astype(np.int64)
    if len(cells):
        _, counts = np.unique(cells, axis=0, return_counts=True)
        counts = counts[counts >= max(1, 0.01 * len(cells))]       # a pose held for < 1 % of the rest: passing by
    else:
        counts = np.zeros(0)
    return {"moving": float(1 - still.mean()), "poses": int(len(counts)),
            "top_pose": float(counts.max() / max(counts.sum(), 1)) if len(counts) else 0.0}


def describe_excitation(x: dict) -> str:
    """The excitation in words, e.g. '98 % of the samples at rest, at 2 poses (one holds 99 % of the rest)'."""
    rest = 100 * (1 - x["moving"])
    if x["poses"] == 0:
        return f"{100 * x['moving']:.0f} % of the samples moving, never at rest"
    where = "at one pose" if x["poses"] == 1 else \
        f"at {x['poses']} poses (one holds {100 * x['top_pose']:.0f} % of the rest)"
    return f"{rest:.0f} % of the samples at rest, {where}, {100 * x['moving']:.0f} % moving"


class Separability:
    """Which effects a log can tell apart: the information (identify.information) of any set of effects on the log's
    signals s, their blocks at the effects' initial nonlinear parameters, weights from weights()."""

    def __init__(self, s, config: IdentifyConfig = IdentifyConfig()):
        self.s, self.config = s, config
        self.w = weights(s.t, s.q, s.dq, config)
        self.excitation = excitation(s.q, s.dq, config)
        self._blocks = {}

    def _block(self, e):
        if e.name not in self._blocks:
            nl = np.tile(np.asarray(e.nonlinear[2], float), (self.s.n, 1)) if e.nonlinear else None
            self._blocks[e.name] = (e.block(self.s, nl), e.column_scales(self.s.n, self.s.robot.g))
        return self._blocks[e.name]

    def dims(self, effect, given=()) -> int | None:
        """How many directions of `effect`'s parameters the log identifies once the effects `given` are fitted too;
        None for an effect without plausible scales (a custom one: not judged)."""
        parts = [self._block(e) for e in list(given) + [effect]]
        if np.all(np.isnan(parts[-1][1])):
            return None
        M = information([b for b, _ in parts], [c for _, c in parts], self.w)
        k = len(parts[-1][1])
        lam, _ = conditional(M, slice(M.shape[0] - k, M.shape[0]))
        return int(np.sum(lam >= self.config.min_info))

    def shared(self, effect, p, other, given=()) -> float | None:
        """The share of the torque of `effect` with parameters p (its fitted values) that `other` can make as well at
        this log's states: 1 - x^T C_other x / x^T C x with x = p / scale, C the information of the effect beside
        `given`, C_other beside `given` and `other` (0: nothing shared, 1: all). None without plausible scales."""
        parts = [self._block(e) for e in list(given) + [other, effect]]
        if np.all(np.isnan(parts[-1][1])):
            return None
        M = information([b for b, _ in parts], [c for _, c in parts], self.w)
        k, k0 = len(parts[-1][1]), len(parts[-2][1])
        x = np.asarray(p, float) / np.nan_to_num(parts[-1][1], nan=1.0)
        K = M.shape[0]
        keep = np.r_[0:K - k - k0, K - k:K]                               # without `other`
        lam_o, V_o = conditional(M, slice(K - k, K))
        lam_a, V_a = conditional(M[np.ix_(keep, keep)], slice(len(keep) - k, len(keep)))
        alone = float(np.sum(lam_a * (V_a.T @ x) ** 2))
        return 1.0 - float(np.sum(lam_o * (V_o.T @ x) ** 2)) / alone if alone > 0 else None
