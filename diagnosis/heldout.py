"""Held-out (2-fold, interleaved blocks) least-squares fits of sets of effects for model diagnosis: per-block,
per-joint normal equations computed once, so every candidate set is scored by small solves, never by refitting; each
fold's fit keeps to the effects' physical constraints (physical.solve_physical), as the whole-log fit does."""
from __future__ import annotations

import numpy as np

from diagnosis.effects import Signals, segments
from diagnosis.physical import solve, solve_physical, violations


class BlockGrams:
    """Sums for least squares on any subset of column groups: per block b and joint j, G[b, j] = A_bj^T A_bj,
    g[b, j] = A_bj^T y_bj, yy[b, j] = y_bj^T y_bj, where A_bj are the rows of block b, joint j.

    y (T, n) is the target; block (T,) the block index of each row (0 .. nb-1, contiguous in time). Groups are
    regressor blocks (T, n, k) added under a key and stored per joint with only their non-zero columns (a per-joint
    effect keeps one column per joint); pair products are computed on first use and cached. A group added with its
    Effect is fitted under that effect's constraints (g (3,): the gravity a tilt rotates)."""

    def __init__(self, y: np.ndarray, block: np.ndarray, g=(0.0, 0.0, -9.81)):
        self.nb, self.L = int(block.max()) + 1, int(np.bincount(block).max())
        self.block, self.pos = block, np.arange(len(block)) - np.searchsorted(block, block)   # row within its block
        self.T, self.n = y.shape
        self.y = self._pad(y)                                      # (nb, L, n)
        self.yy = np.einsum("blj,blj->bj", self.y, self.y)         # (nb, n)
        self.groups, self._pair, self._gy, self.effects, self.g = {}, {}, {}, {}, np.asarray(g, dtype=float)

    def _pad(self, A):
        """(T, ...) rows -> (nb, L, ...), zero rows where a block is shorter than L."""
        out = np.zeros((self.nb, self.L) + A.shape[1:])
        out[self.block, self.pos] = A
        return out

    def add(self, key, A: np.ndarray, effect=None):
        if effect is not None:
            self.effects[key] = effect
        if key not in self.groups:
            cols = [np.flatnonzero(np.any(A[:, j, :] != 0, axis=0)) for j in range(self.n)]
            self.groups[key] = (A.shape[2], [(c, self._pad(A[:, j][:, c])) for j, c in enumerate(cols)])

    def size(self, key) -> int:
        return self.groups[key][0]

    def pair(self, a, b):
        """(nb, n, ka, kb) cross products of groups a and b."""
        if (a, b) not in self._pair:
            (ka, Xa), (kb, Xb) = self.groups[a], self.groups[b]
            out = np.zeros((self.nb, self.n, ka, kb))
            for j, ((ca, xa), (cb, xb)) in enumerate(zip(Xa, Xb)):
                if len(ca) and len(cb):
                    out[:, j][:, ca[:, None], cb[None, :]] = xa.transpose(0, 2, 1) @ xb     # (nb, ka', kb')
            self._pair[(a, b)], self._pair[(b, a)] = out, out.transpose(0, 1, 3, 2)
        return self._pair[(a, b)]

    def cross_y(self, a):
        """(nb, n, k) products of group a with the target."""
        if a not in self._gy:
            k, X = self.groups[a]
            out = np.zeros((self.nb, self.n, k))
            for j, (c, x) in enumerate(X):
                out[:, j][:, c] = np.einsum("bl,blk->bk", self.y[:, :, j], x)
            self._gy[a] = out
        return self._gy[a]

    def assemble(self, keys):
        """G (nb, n, K, K), g (nb, n, K) for the concatenated groups `keys`."""
        off = np.cumsum([0] + [self.size(k) for k in keys])
        G, g = np.zeros((self.nb, self.n, off[-1], off[-1])), np.zeros((self.nb, self.n, off[-1]))
        for i, a in enumerate(keys):
            g[:, :, off[i]:off[i + 1]] = self.cross_y(a)
            for j, b in enumerate(keys[i:], start=i):
                P = self.pair(a, b)
                G[:, :, off[i]:off[i + 1], off[j]:off[j + 1]] = P
                G[:, :, off[j]:off[j + 1], off[i]:off[i + 1]] = P.transpose(0, 1, 3, 2)
        return G, g

    def heldout(self, keys_per_fold, physical: bool = True, relax=()):
        """2-fold cross-validation: fold f fits on blocks b % 2 == f with groups keys_per_fold[f] and predicts the other
        blocks; physical: under the constraints of the groups' effects (groups added without one are free), except
        those of the effects named in relax. Returns
        (sse (nb, n): held-out squared error per block and joint, params [p_0, p_1] (columns), infos [info_0, info_1]
        of the solves (rank, constrained, params per group, violations))."""
        sse, params, infos = np.zeros((self.nb, self.n)), [], []
        for f in (0, 1):
            keys = keys_per_fold[f]
            G, g = self.assemble(keys)
            train, test = np.arange(f, self.nb, 2), np.arange(1 - f, self.nb, 2)
            Gt, gt = G[train].sum(axis=(0, 1)), g[train].sum(axis=(0, 1))
            if physical and all(k in self.effects for k in keys):
                p, info = solve_physical(Gt, gt, segments([self.effects[k] for k in keys], self.n, self.g, relax))
            else:
                p, info = solve(Gt, gt)
                k0 = np.cumsum([0] + [self.size(k) for k in keys])
                info.update(constrained=False, violations={}, params=[p[a:b] for a, b in zip(k0[:-1], k0[1:])])
            params.append(p)
            infos.append(info)
            sse[test] = self.yy[test] - 2 * g[test] @ p + np.einsum("bjk,k->bj", G[test] @ p, p)
        return np.maximum(sse, 0.0), params, infos

    def predict(self, keys, p) -> np.ndarray:
        """A p (T, n) for groups `keys` and parameters p."""
        out, k0 = np.zeros((self.nb, self.L, self.n)), 0
        for key in keys:
            k, X = self.groups[key]
            for j, (c, x) in enumerate(X):
                out[:, :, j] += x @ p[k0 + c]
            k0 += k
        return out[self.block, self.pos]


def blocks_of(t: np.ndarray, seconds: float) -> np.ndarray:
    """Block index (T,) of each time stamp: consecutive blocks of `seconds`; a short last block joins the previous."""
    b = np.floor((t - t[0]) / seconds).astype(int)
    nb = b.max() + 1
    if nb > 1 and np.sum(b == nb - 1) < 0.5 * np.sum(b == 0):
        b[b == nb - 1] = nb - 2
    return b


def _tstat(d):
    """t statistic (k,) of the per-block values d (nb, k): mean / standard error, blocks as independent replicates."""
    sd = d.std(axis=0, ddof=1) / np.sqrt(d.shape[0])
    return np.where(sd > 0, d.mean(axis=0) / np.maximum(sd, 1e-300), np.where(d.mean(axis=0) > 0, np.inf, 0.0))


def significance(sse_old, sse_new, config, samples: int):
    """Per joint (n,): the held-out RMS drop 1 - rms_new / rms_old; the t statistic of the per-block log error ratios
    d_b = log(sse_old_b / sse_new_b) (blocks as independent replicates, so correlated samples do not inflate it;
    scale-free, so a few blocks with large errors do not dominate); the RMS torque explained
    sqrt(rms_old^2 - rms_new^2); and whether all three pass config's min_drop, t_min and min_torque."""
    old, new = sse_old.sum(axis=0), sse_new.sum(axis=0)
    drop = 1 - np.sqrt(new / np.maximum(old, 1e-300))
    tstat = _tstat(np.log(np.maximum(sse_old, 1e-300) / np.maximum(sse_new, 1e-300)))
    torque = np.sqrt(np.maximum(old - new, 0.0) / samples)
    return drop, tstat, (drop >= config.min_drop) & (tstat >= config.t_min) & (torque >= config.min_torque)


def verdict(sse_old, sse_new, config, samples: int) -> dict:
    """The selection rule for held-out errors sse_old -> sse_new (nb, n). An effect is significant only if
    (a) the total falls: the summed held-out SSE over all joints drops, RMS by >= min_total_drop, with t >= t_min for
        the per-block log ratios of the totals;
    (b) no joint gets worse: no joint has an RMS rise >= max_rise with t >= t_min for the per-block log ratios
        log(sse_new_b / sse_old_b);
    (c) some joint improves by significance(): RMS drop >= min_drop, t >= t_min, >= min_torque RMS explained.
    Returns {drop, t, better, worse (n,), total_drop, total_t, significant}."""
    drop, tstat, better = significance(sse_old, sse_new, config, samples)
    worse = (-drop >= config.max_rise) & (-tstat >= config.t_min)
    total_drop, total_t, _ = significance(sse_old.sum(axis=1, keepdims=True), sse_new.sum(axis=1, keepdims=True),
                                          config, samples)
    total_drop, total_t = float(total_drop[0]), float(total_t[0])
    overall = total_drop >= config.min_total_drop and total_t >= config.t_min
    return dict(drop=drop, t=tstat, better=better, worse=worse, total_drop=total_drop, total_t=total_t,
                significant=bool(overall and better.any() and not worse.any()))


class Selection:
    """The state of forward selection: the accepted groups per fold and their held-out errors."""

    def __init__(self, s: Signals, y, block, config):
        self.s, self.y, self.block, self.config = s, y, block, config
        self.grams = BlockGrams(y, block, s.robot.g)
        self.keys, self.nl, self.tag = [[], []], {}, 0
        self.sse, self.params = self.grams.heldout(self.keys)[:2]

    def _group(self, e, fold):
        """Key of the effect's columns for a fold; nonlinear effects are fitted on that fold's training rows."""
        if not e.nonlinear:
            if e.name not in self.grams.groups:
                self.grams.add(e.name, e.block(self.s), e)
            return e.name
        rows = np.flatnonzero(self.block % 2 == fold)
        z = (self.y - self.grams.predict(self.keys[fold], self.params[fold]))[rows]
        nl0 = self.nl.get((e.name, fold), np.tile(np.asarray(e.nonlinear[2], dtype=float), (self.s.n, 1)))
        nl = self.nl[(e.name, fold)] = e.fit_nonlinear(self.s, rows, z, nl0)     # warm start from the last round
        self.tag += 1
        key = (e.name, fold, self.tag)
        self.grams.add(key, e.block(self.s, nl), e)
        return key

    def extend(self, e):
        self.keys = [self.keys[f] + [self._group(e, f)] for f in (0, 1)]
        self.sse, self.params = self.grams.heldout(self.keys)[:2]

    def try_effect(self, e):
        keys = [self._group(e, f) for f in (0, 1)]
        trial = [self.keys[f] + [keys[f]] for f in (0, 1)]
        sse, params, infos = self.grams.heldout(trial)
        v = verdict(self.sse, sse, self.config, len(self.s))
        n = self.s.n
        k = e.size(n) + (len(e.nonlinear[0]) * n if e.nonlinear else 0)
        explained = 1 - sse.sum(axis=0) / np.maximum(self.sse.sum(axis=0), 1e-300)
        p = 0.5 * (infos[0]["params"][-1] + infos[1]["params"][-1])        # the two folds' fits, averaged
        nl = 0.5 * (self.nl[(e.name, 0)] + self.nl[(e.name, 1)]) if e.nonlinear else None
        return dict(effect=e.name, obj=e, keys=keys, sse=sse, fold_params=params, k=k, p=p,
                    explained=float(explained.mean()), explained_joints=explained,
                    joints=[int(j) + 1 for j in np.flatnonzero(v["better"])], significant=v["significant"],
                    worse=[int(j) + 1 for j in np.flatnonzero(v["worse"])], rms_change=-v["drop"],
                    total_change=-v["total_drop"], total_t=v["total_t"],
                    rms_after=np.sqrt(sse.sum(axis=0) / len(self.s)), drop=v["drop"], t=v["t"],
                    params=e.describe(p, nl, n), asked=self._asked(e, trial, sse, infos))

    def _asked(self, e, trial, sse, infos):
        """What the data ask of e beyond its physical constraints, or None: refit with e's constraints dropped (the
        accepted effects keep theirs); if that beats the constrained fit significantly (significance()) on some joint,
        the violations [(label, value)] found in both folds (values averaged) and the joints (1-based) it helps."""
        if not any(info["constrained"] for info in infos):
            return None
        sse_free, _, free = self.grams.heldout(trial, relax={e.name})
        better = significance(sse, sse_free, self.config, len(self.s))[2]
        if not better.any():
            return None
        seg = segments([e], self.s.n, self.s.robot.g)[0]
        folds = [dict(violations(seg, free[f]["params"][-1])) for f in (0, 1)]
        viol = [(k, 0.5 * (v + folds[1][k])) for k, v in folds[0].items() if k in folds[1]]
        if not viol:
            return None
        return dict(effect=e.name, violations=viol, joints=[int(j) + 1 for j in np.flatnonzero(better)],
                    rms_gain=1 - np.sqrt(sse_free.sum(axis=0) / np.maximum(sse.sum(axis=0), 1e-300)))

    def accept(self, row):
        self.keys = [self.keys[f] + [row["keys"][f]] for f in (0, 1)]
        self.sse, self.params = row["sse"], row["fold_params"]


def rank(rows, config, samples: int):
    """Best first by mean explained held-out variance, except that the best significant candidate (verdict(): the
    total falls, no joint worse, some joint better) goes first; parsimony among the significant ones: one with fewer
    parameters replaces it unless it improves on that one significantly on some joint (significance())."""
    order = sorted(rows, key=lambda r: -r["explained"])
    sig = [r for r in order if r["significant"]]
    if sig:
        choice = sig[0]
        for r in sig[1:]:
            if r["k"] < choice["k"] and not significance(r["sse"], choice["sse"], config, samples)[2].any():
                choice = r
        order.remove(choice)
        order.insert(0, choice)
    return order
