"""Where a model fails on a log: per-joint RMS and fit share, the error by regime (at rest, moving, by the sign of dq)
and the worst time segments (the nominal Eq. 1 model against the log's torques)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from diagnosis.effect_model import Model
from diagnosis.heldout import blocks_of


@dataclass(frozen=True)
class CompareConfig:
    """Regimes and segments in which compare() splits the error."""
    v_rest: float = 0.02        # rad/s, |dq| below: at rest (20x the 1e-3 rad/s velocity noise of realistic())
    v_sign: float = 0.1         # rad/s, |dq| above: a clear sign of dq (the 0.05 s filter x 2 rad/s^2 smears 0.1 rad/s)
    v_fast: float = 0.5         # rad/s, |dq| above: fast (a quarter of the Panda's 2.2-2.6 rad/s limits)
    a_acc: float = 2.0          # rad/s^2, |ddq| above: accelerating (10-25 % of the 7.5-20 rad/s^2 limits)
    segment: float = 0.5        # s, length of the time segments ranked by error
    worst: int = 3              # how many worst segments to report



@dataclass
class Comparison:
    """compare() output: per joint (n,) rms [Nm], fit [%] (100 (1 - NRMSE) of tau_J; NaN where undefined, fit_note
    says why), mean [Nm]; regimes: name -> {rms, mean, share} (n,) each (NaN where a joint has no sample in the
    regime); worst: [{t0, t1, rms, joint}]; residual (T, n) = tau_J - model; t (T,)."""
    rms: np.ndarray
    fit: np.ndarray
    mean: np.ndarray
    regimes: dict
    worst: list
    residual: np.ndarray
    t: np.ndarray
    fit_note: dict = field(default_factory=dict)


def fit_percent(y, r):
    """Per joint (n,): 100 (1 - RMS(r) / std(y)), the share of the torque's variation y (T, n) the model explains
    given its residual r (T, n), and {joint: why} where it is no share: tau_J varies by less than the model's error
    (a static log), so 1 - NRMSE would be a large negative number that says nothing (NaN there)."""
    rms, spread = np.sqrt(np.mean(r ** 2, axis=0)), y.std(axis=0)
    fit, notes = np.full(len(rms), np.nan), {}
    for j in range(len(rms)):
        if spread[j] > rms[j]:
            fit[j] = 100 * (1 - rms[j] / spread[j])
        else:
            notes[f"J{j + 1}"] = (f"tau_J varies by {spread[j]:.3f} Nm RMS, less than the {rms[j]:.3f} Nm error: "
                                  "nothing for a share to explain")
    return fit, notes


def compare(model: Model, log, config: CompareConfig = CompareConfig()) -> Comparison:
    """Where the model fails on the log: per-joint RMS and fit, the worst time segments, the error by regime."""
    s = model.signals(log)
    y = s.measured()
    r = y - model.predict(s)
    rms = np.sqrt(np.mean(r ** 2, axis=0))
    fit, notes = fit_percent(y, r)
    adq, addq = np.abs(s.dq), np.abs(s.ddq)
    masks = {"at rest": adq < config.v_rest, "moving": adq >= config.v_rest, "fast": adq >= config.v_fast,
             "accelerating": addq >= config.a_acc, "dq > 0": s.dq >= config.v_sign, "dq < 0": s.dq <= -config.v_sign}
    regimes = {}
    for name, m in masks.items():
        cnt = m.sum(axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            regimes[name] = {"rms": np.sqrt((r ** 2 * m).sum(axis=0) / cnt), "mean": (r * m).sum(axis=0) / cnt,
                             "share": cnt / len(r)}
    seg = blocks_of(s.t, config.segment)
    seg_rms = np.sqrt(np.stack([np.mean(r[seg == b] ** 2, axis=0) for b in range(seg.max() + 1)]))   # (S, n)
    score = (seg_rms / np.maximum(rms, 1e-12)).mean(axis=1)          # each joint relative to its own RMS
    worst = []
    for b in np.argsort(-score)[:config.worst]:
        rows = np.flatnonzero(seg == b)
        j = int(np.argmax(seg_rms[b] / np.maximum(rms, 1e-12)))
        worst.append({"t0": float(s.t[rows[0]]), "t1": float(s.t[rows[-1]]), "joint": j + 1,
                      "rms": float(seg_rms[b, j]), "ratio": float(score[b])})
    return Comparison(rms, fit, r.mean(axis=0), regimes, worst, r, s.t, notes)
