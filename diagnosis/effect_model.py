"""A robot model as a sum of effects (Eq. 1 plus the effects of effects.py), fitted by least squares under each
effect's physical constraints (physical.py), and the correction it offers RME: the fitted torques beyond the nominal
model in the paper's tau_ext sign (Eq. 1)."""
from __future__ import annotations

import copy
import dataclasses
import json
import os

import numpy as np

from diagnosis.batch_dynamics import BatchDynamics
from diagnosis.effects import Effect, EffectConfig, Signals, library, segments
from diagnosis.identify import IdentifyConfig, conditional, information, weights
from diagnosis.logs import Log
from diagnosis.physical import solve, solve_physical
from dynamics import PANDA_XML, Robot, as_states

__all__ = ["Model", "solve", "solve_physical"]


class Model:
    """tau_J (T, n) = sum over effects of regressor @ p. Fixed effects keep their parameters (the nominal gravity and
    motion terms, scale 1); free ones are fitted by fit(log). The residual tau_J - model is, for the nominal model,
    -tau_ext in the paper's sign (= libfranka's tau_ext_hat_filtered)."""

    def __init__(self, robot: Robot, config: EffectConfig = EffectConfig(),
                 identify: IdentifyConfig | None = IdentifyConfig()):
        if np.ndim(config.offset_max) and len(config.offset_max) != robot.n:     # the Panda's bounds, another arm
            config = dataclasses.replace(config, offset_max=float(np.max(config.offset_max)),
                                         offset_source=f"the largest of {len(config.offset_max)} joints': "
                                                       f"{config.offset_source}")
        self.robot, self.config, self.identify = robot, config, identify
        self.library = library(config)
        self.effects, self.params, self.nl, self.fixed = [], {}, {}, set()
        self.fitted, self._batch = False, None
        self.violations = {}                 # effect -> [(label, value)] the unconstrained fit asked for (last fit)
        self.at_bounds = {}                  # effect -> [(label, value)] parameters the last fit left at a bound
        self.held = {}                       # effect -> {directions, params, info}: what the log could not identify
        #                                      (held at the nominal value; identify.py), last fit

    @classmethod
    def nominal(cls, robot: Robot, config: EffectConfig = EffectConfig()) -> "Model":
        """The nominal rigid-body model of Eq. 1: gravity + motion, both fixed at scale 1."""
        return cls(robot, config).add("gravity", fixed=[1.0]).add("motion", fixed=[1.0])

    @classmethod
    def static(cls, robot: Robot, config: EffectConfig = EffectConfig()) -> "Model":
        """RME's model: the nominal gravity only (the paper's static windows, Sec. 4)."""
        return cls(robot, config).add("gravity", fixed=[1.0])

    def copy(self) -> "Model":
        new = copy.copy(self)
        new.effects, new.params, new.nl = list(self.effects), dict(self.params), dict(self.nl)
        new.fixed, new.violations, new.held = set(self.fixed), dict(self.violations), dict(self.held)
        new.at_bounds = dict(self.at_bounds)
        return new

    def effect(self, e) -> Effect:
        if isinstance(e, Effect):
            return e
        if e not in self.library:
            raise ValueError(f"effect: expected an Effect or one of {sorted(self.library)}, found {e!r}")
        return self.library[e]

    def add(self, effect, fixed=None) -> "Model":
        """Add an effect (an Effect or a library name), free unless `fixed` parameters are given; returns self."""
        e = self.effect(effect)
        if e.name in self.names:
            raise ValueError(f"effect: {e.name!r} is already in the model ({self.names})")
        p = None if fixed is None else \
            e.check("fixed", np.ravel(fixed) if isinstance(fixed, np.ndarray) else fixed, self.robot.n)
        self.effects.append(e)
        n = self.robot.n
        if p is not None:
            self.params[e.name], self.fixed = p, self.fixed | {e.name}
        else:
            self.params[e.name] = np.full(e.size(n), e.nominal)
            self.fitted = False
        if e.nonlinear:
            self.nl[e.name] = np.tile(np.asarray(e.nonlinear[2], dtype=float), (n, 1))
        return self

    @property
    def names(self) -> list:
        return [e.name for e in self.effects]

    @property
    def free(self) -> list:
        return [e for e in self.effects if e.name not in self.fixed]

    def signals(self, log) -> Signals:
        """The Signals of a Log (pass Signals around to compute the rigid-body terms of a log only once)."""
        if isinstance(log, Signals):
            return log
        if self._batch is None:
            self._batch = BatchDynamics(self.robot)
        return Signals(log, self.robot, self._batch)

    def torque(self, s: Signals, effects=None) -> np.ndarray:
        """Sum of the effects' torques (T, n) with the current parameters."""
        out = np.zeros((len(s), s.n))
        for e in (self.effects if effects is None else effects):
            out += e.block(s, self.nl.get(e.name)) @ e.coef(self.params[e.name], self.robot.g)
        return out

    def fit(self, log, rows=None, iterations: int = 3) -> dict:
        """Fit the free parameters to tau_J on the log, or on its samples `rows` (an index or mask; regressors are
        computed on the whole log first, so filters never bridge the gaps); nonlinear parameters alternate with the
        linear solve, which keeps every effect inside its physical constraints (physical.solve_physical; what the
        unconstrained fit asked for beyond them is left in self.violations). Returns info {status, rank, K,
        iterations, constrained, violations}."""
        s = self.signals(log)
        try:
            idx = np.arange(len(s)) if rows is None else np.arange(len(s))[rows]
        except IndexError as err:
            raise ValueError(f"rows: expected a slice, boolean mask or indices into the {len(s)} samples, found "
                             f"{err}") from None
        free = self.free
        k = sum(e.size(self.robot.n) for e in free)
        if free and len(idx) * self.robot.n < max(k, 1) or free and len(idx) < 2:
            raise ValueError(f"rows: expected enough samples to fit {k} parameters of {[e.name for e in free]}, "
                             f"found {len(idx)} rows")
        y = (s.measured() - self.torque(s, [e for e in self.effects if e.name in self.fixed]))[idx]
        nonlinear = [e for e in free if e.nonlinear]
        info = self._fit_linear(s, y, free, idx)
        for _ in range(iterations if nonlinear else 0):
            for e in nonlinear:
                z = y - self.torque(s, [f for f in free if f is not e])[idx]
                self.nl[e.name] = e.fit_nonlinear(s, idx, z, self.nl[e.name])
            info = self._fit_linear(s, y, free, idx)
        info["iterations"] = iterations if nonlinear else 1
        self.fitted = True
        return info

    def _fit_linear(self, s, y, free, idx):
        blocks = [e.block(s, self.nl.get(e.name))[idx] for e in free]
        self.violations = {}
        if not blocks:
            return {"status": "ok", "rank": 0, "K": 0, "constrained": False, "violations": {}}
        A = np.concatenate(blocks, axis=2).reshape(-1, sum(Y.shape[2] for Y in blocks))
        G, b = A.T @ A, A.T @ y.reshape(-1)
        if self.identify is not None:
            G, b, self.held = self._hold_unidentified(G, b, blocks, free, s.t[idx], s.q[idx], s.dq[idx])
        _, info = solve_physical(G, b, segments(free, self.robot.n, self.robot.g))
        for e, p in zip(free, info.pop("params")):
            self.params[e.name] = p
        self.violations = info["violations"]
        self.at_bounds = {e.name: v for e in free if (v := at_bounds(e, self.params[e.name], self.robot.n))}
        info["status"] = "ok" if info["rank"] == info["K"] else \
            f"rank deficient: {info['K'] - info['rank']} parameter combinations not identifiable (set to 0)"
        return info

    def _hold_unidentified(self, G, b, blocks, free, t, q, dq):
        """G, b (K, K), (K,) with every direction the log cannot identify held at the nominal value (identify.py):
        effect by effect in the model's order, the directions of its parameters (at their plausible scales) whose
        information, once the effects before it are fitted too, is below min_info; held by a penalty 1e4 times the
        largest information. Returns (G, b, held {effect: {directions, of, params, info}})."""
        n, g = self.robot.n, self.robot.g
        scales = [e.column_scales(n, g) for e in free]
        M = information(blocks, scales, weights(t, q, dq, self.identify))
        S = np.nan_to_num(np.concatenate(scales), nan=1.0)
        mu = 1e4 * max(np.linalg.eigvalsh(G * np.outer(S, S)).max(), 1e-300)
        off = np.cumsum([0] + [len(c) for c in scales])
        P, nominal, held = np.zeros_like(G), np.zeros(len(b)), {}
        for i, e in enumerate(free):
            nominal[off[i]:off[i + 1]] = 0.0 if e.physical == "tilt" else e.nominal
            if np.all(np.isnan(scales[i])):
                continue                                 # no plausible scale (a custom effect): fitted as it is
            lam, V = conditional(M[:off[i + 1], :off[i + 1]], slice(off[i], off[i + 1]))
            U = V[:, lam < self.identify.min_info]
            if U.shape[1]:
                Q = U / S[off[i]:off[i + 1], None]                      # directions in the effect's own units
                P[off[i]:off[i + 1], off[i]:off[i + 1]] += Q @ Q.T
                labels = e.labels(n) if e.physical != "tilt" else ("dg_x", "dg_y", "dg_z")
                main = sorted({labels[j] for u in U.T for j in np.flatnonzero(np.abs(u) >= 0.3 * np.abs(u).max())})
                held[e.name] = {"directions": int(U.shape[1]), "of": int(len(lam)), "params": main,
                                "info": float(lam[lam < self.identify.min_info].max())}
        return G + mu * P, b + mu * P @ nominal, held

    def predict(self, log) -> np.ndarray:
        """Model torque tau_J (T, n) for a log."""
        self._check_fitted()
        return self.torque(self.signals(log))

    def residual(self, log) -> np.ndarray:
        """tau_J - model (T, n); for the nominal model this is -tau_ext in the paper's sign."""
        s = self.signals(log)
        return s.measured() - self.predict(s)

    def correction(self, q, dq=None, ddq=None) -> np.ndarray:
        """The fitted torques beyond the nominal model, in the paper's tau_ext sign: (T, n) or (n,) for one state.
        RME subtracts it, tau_ext - correction, to remove what the nominal model misses (friction, offsets, ...).
        dq, ddq default to zero (a static window). Fit the model on a log without the payload to be estimated:
        every fitted effect, a payload-shaped one absorbing wrist mass errors included, then belongs to the robot."""
        self._check_fitted()
        qa, batched = as_states("q", q, self.robot.n)
        z = np.zeros_like(qa)
        dqa = z if dq is None else as_states("dq", dq, self.robot.n)[0]
        ddqa = z if ddq is None else as_states("ddq", ddq, self.robot.n)[0]
        if not (len(qa) == len(dqa) == len(ddqa)):
            raise ValueError(f"dq, ddq: expected {len(qa)} rows like q, found {len(dqa)} and {len(ddqa)}")
        T = len(qa)
        s = self.signals(Log(t=np.arange(T, dtype=float), q=qa, dq=dqa, ddq=ddqa, tau_J=None, tau_ext=z))
        out = np.zeros((T, self.robot.n))
        for e in self.effects:
            p = self.params[e.name]
            if np.any(p != e.nominal):
                delta = e.coef(p, self.robot.g) - e.coef(np.full(p.shape, e.nominal), self.robot.g)
                out -= e.block(s, self.nl.get(e.name)) @ delta
        return out if batched else out[0]

    def report(self) -> str:
        """One line per effect: name, fixed or fitted, parameters with units."""
        lines = []
        for e in self.effects:
            tag = "fixed" if e.name in self.fixed else ("fitted" if self.fitted else "not fitted")
            text = e.describe(self.params[e.name], self.nl.get(e.name), self.robot.n)
            lines.append(f"  {e.name:14s} ({tag}): {text}")
            if self.held.get(e.name):
                h = self.held[e.name]
                lines.append(f"  {'':14s} not identifiable from this log, held at the nominal value: {h['directions']} "
                             f"of {h['of']} parameter directions (mainly {', '.join(h['params'])})")
            if self.violations.get(e.name):
                lines.append(f"  {'':14s} held to its physical constraints; unconstrained it asked for: "
                             f"{held_text(e, self.violations[e.name], self.robot.n)}")
            if self.at_bounds.get(e.name):
                edge = ", ".join(f"{k} {v:.4g}" for k, v in self.at_bounds[e.name])
                lines.append(f"  {'':14s} at its bounds: {edge}"
                             + (f" (bounds: {e.source})" if e.source and not self.violations.get(e.name) else ""))
        return "\n".join(lines)

    def save(self, path) -> None:
        """Write the model as JSON: every effect with its parameters (nonlinear ones included), fixed or fitted, the
        arm by name ("panda") or by its MJCF path relative to the model file, and its ee site. Only library effects
        can be saved (a custom one is code: rebuild it)."""
        unknown = [e.name for e in self.effects if e.name not in self.library or self.library[e.name] is not e]
        if unknown:
            raise ValueError(f"model: custom effects {unknown} cannot be saved (only library effects can)")
        xml = getattr(self.robot, "xml_path", None)
        if xml and os.path.abspath(xml) == os.path.abspath(PANDA_XML) and self.robot.ee == "ee":
            arm = {"name": "panda"}
        elif xml:
            arm = {"xml": os.path.relpath(os.path.abspath(xml), os.path.dirname(os.path.abspath(path)))}
        else:
            raise ValueError("model: the robot has no MJCF file (Robot.from_xml) to name in the saved model")
        doc = {"format": FORMAT, "version": 1, "robot": {**arm, "ee": self.robot.ee, "n": self.robot.n},
               "fitted": self.fitted, "config": dataclasses.asdict(self.config),
               "effects": [{"name": e.name, "fixed": e.name in self.fixed, "params": self.params[e.name].tolist(),
                            "nonlinear": self.nl[e.name].tolist() if e.name in self.nl else None}
                           for e in self.effects]}
        with open(path, "w") as f:
            json.dump(doc, f, indent=1)

    @classmethod
    def load(cls, path, robot: Robot | None = None, config: EffectConfig | None = None) -> "Model":
        """The model `save` wrote, with every parameter as saved; robot: the arm (default: the saved one, an MJCF path
        relative to the model file); config: the effects' shapes (default: as saved, e.g. pose_bias's joints).
        Every field is checked (types, shapes, finite values within each effect's bounds): ValueError naming the
        file, the field, what was found and what was expected."""
        try:
            with open(path, encoding="utf-8-sig") as f:             # -sig: an editor's byte-order mark
                doc = json.load(f)
        except (OSError, ValueError, TypeError) as err:
            raise ValueError(f"path: could not read a model from {path!r}: {err}") from None
        where = f"{path}: "
        if not isinstance(doc, dict) or doc.get("format") != FORMAT:
            raise ValueError(f"{where}format: expected {FORMAT!r} (a file Model.save wrote), found "
                             f"{doc.get('format') if isinstance(doc, dict) else type(doc).__name__!r}")
        _field(doc, "version", int, where, lambda v: v == 1, "1")
        robot = robot or _saved_robot(_field(doc, "robot", dict, where), path, where)
        config = config or _saved_config(_field(doc, "config", dict, where), where)
        fitted = _field(doc, "fitted", bool, where)
        items = _field(doc, "effects", list, where, lambda v: len(v) > 0, "a non-empty list of effects")
        model = cls(robot, config)
        for i, item in enumerate(items):
            _load_effect(model, item, f"{where}effects[{i}].")
        model.fitted = fitted
        return model

    def _check_fitted(self):
        if self.free and not self.fitted:
            raise ValueError(f"model: free effects {[e.name for e in self.free]} have no fitted parameters; "
                             "call model.fit(log) first")


def at_bounds(e, p, n: int, tol: float = 1e-6) -> list:
    """[(label, value)] of the parameters p (size(n),) of effect e at one of its finite bounds, a bound that is not
    the nominal value (friction, a rotor or a mass at 0 is the nominal model, not a fit held back)."""
    lo, hi = e.bounds(n)
    p = np.asarray(p, dtype=float)
    near = lambda b: np.isfinite(b) & (np.abs(p - b) <= tol * (1 + np.abs(np.where(np.isfinite(b), b, 0)))) & \
        (np.abs(b - e.nominal) > tol)
    return [(lbl, float(v)) for lbl, v, hit in zip(e.labels(n), p, near(lo) | near(hi)) if hit]


def held_text(e, violations, n: int) -> str:
    """What the unconstrained fit asked for, each value beside the bound it was held to, and the bounds' source:
    'tau_0 J2 -1.6 (bound -1.14), ... (bounds: SOURCE)'."""
    lo, hi = e.bounds(n)
    bound = {lbl: (a, b) for lbl, a, b in zip(e.labels(n), lo, hi)}
    parts = []
    for lbl, v in violations:
        a, b = bound.get(lbl, (-np.inf, np.inf))
        edge = a if v < a else b if v > b else None
        parts.append(f"{lbl} {v:.4g}" + (f" (bound {edge:.4g})" if edge is not None and np.isfinite(edge) else ""))
    return ", ".join(parts) + (f" (bounds: {e.source})" if e.source else "")


FORMAT = "rme effect model"                     # the "format" field of a saved model


def _field(doc: dict, key: str, kind, where: str, ok=None, expected: str = ""):
    """doc[key], ValueError naming it unless present, of type kind (bool is not an int) and ok(value)."""
    if key not in doc:
        raise ValueError(f"{where}{key}: expected a field {key!r}, found none")
    v = doc[key]
    if not isinstance(v, kind) or (kind is int and isinstance(v, bool)) or (ok is not None and not ok(v)):
        raise ValueError(f"{where}{key}: expected {expected or kind.__name__}, found {v!r}")
    return v


def _saved_robot(saved: dict, path, where: str) -> Robot:
    """The arm a saved model names: {"name": "panda"} or {"xml": path relative to the model file}, with its ee and n."""
    ee = _field(saved, "ee", str, where + "robot.") if "ee" in saved else "ee"
    if saved.get("name") == "panda":
        robot = Robot.panda()
    elif isinstance(saved.get("xml"), str):
        xml = os.path.join(os.path.dirname(os.path.abspath(path)), saved["xml"])
        robot = Robot.from_xml(xml, ee=ee)
    else:
        raise ValueError(f"{where}robot: expected {{'name': 'panda'}} or {{'xml': MJCF path}}, found {saved!r}")
    if "n" in saved:
        _field(saved, "n", int, where + "robot.", lambda v: v == robot.n, f"{robot.n} joints like the arm")
    return robot


def _saved_config(saved: dict, where: str) -> EffectConfig:
    """EffectConfig from its saved fields: each a finite real number or a list of them (a string where EffectConfig
    has one), names EffectConfig has."""
    names = {f.name: f for f in dataclasses.fields(EffectConfig)}
    out = {}
    for k, v in saved.items():
        if k not in names:
            raise ValueError(f"{where}config.{k}: expected one of the fields {sorted(names)}, found {k!r}")
        if isinstance(names[k].default, str):
            if not isinstance(v, str):
                raise ValueError(f"{where}config.{k}: expected a string, found {v!r}")
            out[k] = v
            continue
        vals = v if isinstance(v, list) else [v]
        if not all(isinstance(x, (int, float)) and not isinstance(x, bool) and np.isfinite(x) for x in vals):
            raise ValueError(f"{where}config.{k}: expected finite real numbers, found {v!r}")
        if isinstance(names[k].default, int) and not isinstance(names[k].default, bool) and \
                not (isinstance(v, int) and v >= 0):
            raise ValueError(f"{where}config.{k}: expected a whole number >= 0, found {v!r}")
        out[k] = tuple(v) if isinstance(v, list) else v
    return EffectConfig(**out)


def _load_effect(model: "Model", item, where: str):
    """Add one saved effect {name, fixed, params, nonlinear} to the model, every field checked."""
    if not isinstance(item, dict):
        raise ValueError(f"{where[:-1]}: expected an object {{name, fixed, params, nonlinear}}, found {item!r}")
    name = _field(item, "name", str, where, lambda v: v in model.library, f"one of {sorted(model.library)}")
    if name in model.names:
        raise ValueError(f"{where}name: expected each effect once, found {name!r} again")
    e, n = model.library[name], model.robot.n
    params = e.check(where + "params", _field(item, "params", list, where), n)
    fixed = _field(item, "fixed", bool, where) if "fixed" in item else False
    model.add(name, fixed=params if fixed else None)
    model.params[name] = params
    if item.get("nonlinear") is not None:
        if not e.nonlinear:
            raise ValueError(f"{where}nonlinear: expected null for {name!r} (linear), found {item['nonlinear']!r}")
        model.nl[name] = e.check(where + "nonlinear", item["nonlinear"], n, nonlinear=True)
