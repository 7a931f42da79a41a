"""A calibrated map of the robot's own load-free torque over poses (effect "pose_bias": the sensor's pose-dependent
bias and the static torques the nominal gravity misses), fitted on a load-free hold log and given to RME
(`RME(correction=model)`, subtracted from tau_ext as in Eq. 1); and the exploration benchmark with it."""
from __future__ import annotations

import dataclasses

import numpy as np

from diagnosis.effect_model import Model
from diagnosis.effects import EffectConfig
from diagnosis.excite import ExciteConfig, HoldsConfig, Tracker, hold_poses, hold_reference
from diagnosis.logs import prepare
from dynamics import Q_READY
from experiments.episodes import measure
from sim import Plant, PlantConfig


def trial_plant(seed: int, preset: str = "realistic") -> Plant:
    """The plant explore_trial(theta, seed) runs on (the same draws: link errors, sensor bias), a fresh copy."""
    rng = np.random.default_rng(seed)
    return Plant(PlantConfig.preset(preset, rng), rng=rng)


def record_holds(plant: Plant, center=Q_READY, config: HoldsConfig = HoldsConfig(),
                 rng: np.random.Generator | None = None):
    """A load-free calibration log: the plant (its payload removed) tracks hold_reference through hold_poses around
    center (n,) under computed torque (diagnosis.excite.Tracker). Returns (raw log dict t, q, dq, tau_J, tau_ext,
    the times (K,) [s] of the samples to fit: the still end of every hold)."""
    if not isinstance(plant, Plant):
        raise ValueError(f"plant: expected a sim.Plant, found {type(plant).__name__}")
    rng = np.random.default_rng(0) if rng is None else rng
    poses = hold_poses(center, config, rng)
    lo, hi = plant.model.jnt_range.T
    if np.any(poses < lo + 0.05) or np.any(poses > hi - 0.05):
        raise ValueError(f"center, config.spans: expected poses 0.05 rad inside the joint limits, found some outside "
                         f"(center {np.round(center, 3).tolist()}, spans {config.spans})")
    t, q_d, dq_d, ddq_d, still = hold_reference(poses, config, plant.dt)
    plant.set_payload(0.0)
    first = plant.reset(q_d[0])
    tracker = Tracker(plant.robot, t, q_d, dq_d, ddq_d, ExciteConfig())
    log = measure(plant, tracker, t[-1] + plant.dt, first)
    return {k: log[k] for k in ("t", "q", "dq", "tau_J", "tau_ext")}, log["t"][still[:len(log["t"])]]


def fit_bias_map(raw: dict, still_times, robot, every: int = 5, friction: bool = False) -> tuple:
    """Model.static(robot, EffectConfig(bias_joints=n)) + "pose_bias" fitted on every `every`-th of the raw log's samples
    at still_times (a real robot's log goes the same way, through logs.load_log). friction: Model.nominal + "pose_bias"
    + "sigmoid" (Gaz joint friction) + "rotor", fitted on every sample from the first still one on, moves included
    (the moves of the holds sweep the joints' speed through zero). Returns (model, info of Model.fit)."""
    log = prepare(raw, source="load-free holds")
    rows = np.isin(np.round(log.t / log.info["dt"]), np.round(np.asarray(still_times) / log.info["dt"]))
    if rows.sum() < 100:
        raise ValueError(f"still_times: expected at least 100 still samples in the log, found {int(rows.sum())}")
    if friction:                 # the filtered torques and M ddq pass the same filter (logs.prepare): moves fit too
        model = Model.nominal(robot, EffectConfig(bias_joints=robot.n)).add("pose_bias").add("sigmoid").add("rotor")
        rows = log.t >= log.t[rows][0]
        return model, model.fit(log, rows=np.flatnonzero(rows)[::every])
    model = Model.static(robot, EffectConfig(bias_joints=robot.n)).add("pose_bias")        # static effects, unfiltered: the still rows alone suffice,
    return model, model.fit(log.rows(np.flatnonzero(rows)[::every]))   # every k-th (the filter correlates them)


def calibrate(plant: Plant, center=Q_READY, config: HoldsConfig = HoldsConfig(), rng=None, friction=True) -> Model:
    """record_holds then fit_bias_map: the map of the plant's load-free torque around center (with its joint friction
    unless friction=False), ready for RME."""
    raw, still = record_holds(plant, center, config, rng)
    return fit_bias_map(raw, still, plant.robot, friction=friction)[0]


def map_error(plant: Plant, model: Model, q) -> np.ndarray:
    """Per pose q (P, n): what the map misses of the plant's load-free level, correction(q) + the sensor's
    pose_bias(q) + offset + the links' gravity error (tau_ext sign: the level tau_ext reads at rest without load)."""
    import mujoco
    q = np.atleast_2d(np.asarray(q, dtype=float))
    d, out = mujoco.MjData(plant.model), []
    for qi in q:
        d.qpos[:], d.qvel[:] = qi, 0.0
        mujoco.mj_forward(plant.model, d)
        level = plant.robot.gravity(qi) - (d.qfrc_bias + plant.pose_bias(qi) + np.asarray(plant.config.torque_offset))
        out.append(level)
    return np.asarray(model.correction(q)) - np.array(out)


def add_map_column(res: dict, trial, settings, holds: HoldsConfig = HoldsConfig()) -> dict:
    """explore_demo.explore_table's result res for Table 5's six payloads, each trial run again by trial(theta, seed,
    settings=, preset=, correction=) (explore_demo.explore_trial) with RME(correction=the plant's map), the map calibrated
    first on a load-free hold log of the same plant seed; settings: the table's ExploreSettings (its offset prior
    replaced by RME's own). Adds rows[i]["map"] {before, after, status} and map_{before,after}_mean_abs_error."""
    mapped = dataclasses.replace(settings, offset_std=None)      # the map leaves RME's own offset prior
    for i, row in enumerate(res["rows"]):
        s, theta = 1000 * (i + 1) + res["seed"], np.array(row["truth"])
        model = calibrate(trial_plant(s, res["preset"]), config=holds, rng=np.random.default_rng(s + 2))
        rec, _ = trial(theta, s, settings=mapped, preset=res["preset"], correction=model)
        x = rec.exploration[0] if rec.exploration else None
        row["map"] = dict(status="no estimate at rest" if x is None else x.status,
                          before=None if x is None else x.before.mean.tolist(),
                          after=None if x is None or x.after is None else x.after.mean.tolist())
    for key in ("before", "after"):
        err = [[abs(a - b) for a, b in zip(r["map"][key], r["truth"])] for r in res["rows"] if r["map"][key]]
        res[f"map_{key}_mean_abs_error"] = np.mean(err, axis=0).tolist() if err else [None] * 4
    res["holds"] = dataclasses.asdict(holds)
    return res
