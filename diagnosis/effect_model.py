"""A robot model as a sum of effects (Eq. 1 plus the effects of effects.py), fitted by least squares under each
effect's physical constraints (physical.py), and the correction it offers RME: the fitted torques beyond the nominal
model in the paper's tau_ext sign (Eq. 1)."""
from __future__ import annotations

import copy
import dataclasses
import json

import numpy as np

from diagnosis.batch_dynamics import BatchDynamics
from diagnosis.effects import Effect, EffectConfig, Signals, library, segments
from diagnosis.logs import Log
from diagnosis.physical import solve, solve_physical
from dynamics import Robot, as_states

__all__ = ["Model", "solve", "solve_physical"]


class Model:
    """tau_J (T, n) = sum over effects of regressor @ p. Fixed effects keep their parameters (the nominal gravity and
    motion terms, scale 1); free ones are fitted by fit(log). The residual tau_J - model is, for the nominal model,
    -tau_ext in the paper's sign (= libfranka's tau_ext_hat_filtered)."""

    def __init__(self, robot: Robot, config: EffectConfig = EffectConfig()):
        self.robot, self.config = robot, config
        self.library = library(config)
        self.effects, self.params, self.nl, self.fixed = [], {}, {}, set()
        self.fitted, self._batch = False, None
        self.violations = {}                 # effect -> [(label, value)] the unconstrained fit asked for (last fit)

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
        new.fixed, new.violations = set(self.fixed), dict(self.violations)
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
        self.effects.append(e)
        n = self.robot.n
        if fixed is not None:
            p = np.asarray(fixed, dtype=float).reshape(-1)
            if p.shape != (e.size(n),):
                raise ValueError(f"fixed: expected {e.size(n)} parameters for {e.name!r}, found {p.shape[0]}")
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
        idx = np.arange(len(s)) if rows is None else np.arange(len(s))[rows]
        free = self.free
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
        _, info = solve_physical(A.T @ A, A.T @ y.reshape(-1), segments(free, self.robot.n, self.robot.g))
        for e, p in zip(free, info.pop("params")):
            self.params[e.name] = p
        self.violations = info["violations"]
        info["status"] = "ok" if info["rank"] == info["K"] else \
            f"rank deficient: {info['K'] - info['rank']} parameter combinations not identifiable (set to 0)"
        return info

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
            if self.violations.get(e.name):
                asked = ", ".join(f"{k} {v:.4g}" for k, v in self.violations[e.name])
                lines.append(f"  {'':14s} held to its physical constraints; unconstrained it asked for: {asked}")
        return "\n".join(lines)

    def save(self, path) -> None:
        """Write the model as JSON: every effect with its parameters (nonlinear ones included), fixed or fitted, the
        arm's MJCF path and ee site. Only library effects can be saved (a custom one is code: rebuild it)."""
        unknown = [e.name for e in self.effects if e.name not in self.library or self.library[e.name] is not e]
        if unknown:
            raise ValueError(f"model: custom effects {unknown} cannot be saved (only library effects can)")
        doc = {"format": "rme effect model", "version": 1,
               "robot": {"xml": getattr(self.robot, "xml_path", None), "ee": self.robot.ee, "n": self.robot.n},
               "fitted": self.fitted, "config": dataclasses.asdict(self.config),
               "effects": [{"name": e.name, "fixed": e.name in self.fixed, "params": self.params[e.name].tolist(),
                            "nonlinear": self.nl[e.name].tolist() if e.name in self.nl else None}
                           for e in self.effects]}
        with open(path, "w") as f:
            json.dump(doc, f, indent=1)

    @classmethod
    def load(cls, path, robot: Robot | None = None, config: EffectConfig | None = None) -> "Model":
        """The model `save` wrote, with every parameter as saved; robot: the arm (default: the saved MJCF and site,
        else the Panda); config: the effects' shapes (default: as saved, e.g. pose_bias's joints). ValueError naming
        the file and what is wrong."""
        try:
            with open(path) as f:
                doc = json.load(f)
        except (OSError, ValueError, TypeError) as err:
            raise ValueError(f"path: could not read a model from {path!r}: {err}") from None
        if not isinstance(doc, dict) or doc.get("format") != "rme effect model":
            raise ValueError(f"{path}: expected a model written by Model.save, found no 'rme effect model' format")
        saved = doc.get("robot") or {}
        if robot is None:
            robot = Robot.from_xml(saved["xml"], ee=saved.get("ee", "ee")) if saved.get("xml") else Robot.panda()
        if saved.get("n") not in (None, robot.n):
            raise ValueError(f"{path}: the model is for an arm of {saved['n']} joints, the robot has {robot.n}")
        if config is None:
            try:
                config = EffectConfig(**{k: tuple(v) if isinstance(v, list) else v
                                         for k, v in (doc.get("config") or {}).items()})
            except TypeError as err:
                raise ValueError(f"{path}: the saved effect config does not fit EffectConfig: {err}") from None
        model = cls(robot, config)
        for item in doc.get("effects", []):
            name = item.get("name")
            if name not in model.library:
                raise ValueError(f"{path}: unknown effect {name!r}; expected one of {sorted(model.library)}")
            params = np.asarray(item["params"], dtype=float)
            e = model.library[name]
            if params.shape != (e.size(robot.n),) or not np.all(np.isfinite(params)):
                raise ValueError(f"{path}: effect {name!r} expected {e.size(robot.n)} finite parameters, found "
                                 f"{params.shape}")
            model.add(name, fixed=params if item.get("fixed") else None)
            model.params[name] = params
            if item.get("nonlinear") is not None:
                nl = np.asarray(item["nonlinear"], dtype=float)
                want = (robot.n, len(e.nonlinear[0])) if e.nonlinear else None
                if nl.shape != want or not np.all(np.isfinite(nl)):
                    raise ValueError(f"{path}: effect {name!r} expected nonlinear parameters of shape {want}, "
                                     f"found {nl.shape}")
                model.nl[name] = nl
        model.fitted = bool(doc.get("fitted", False))
        return model

    def _check_fitted(self):
        if self.free and not self.fitted:
            raise ValueError(f"model: free effects {[e.name for e in self.free]} have no fitted parameters; "
                             "call model.fit(log) first")
