"""Randomised reliability benchmark of an estimator in closed loop (`python sim.py reliability`): CPIC holds random
poses while loads are attached, swapped and removed and people push the arm, on a realistic or a harsh plant; episodes
drawn from separate tuning and test seed streams, scored from the Record alone (theta_hat against theta)."""
from __future__ import annotations

import importlib
import json
import time
from dataclasses import dataclass

import numpy as np

from cpic import CPIC, Attractor
from error_model import as_error_model
from experiments.runner import PayloadChange, Push, run
from nn_train import DataConfig, random_pose
from sim import PRESETS, Plant, PlantConfig

TAU_MAX = np.array([87.0] * 4 + [12.0] * 3)        # Nm, Panda torque limits (panda_facts.md)
ENTROPY = 0x5EED_2026_AB1E                          # fixed root of every episode's seed (any constant will do)
SPLITS = ("tuning", "test")                         # the test split is for judging a finished estimator only
PLANTS = PRESETS
KINDS = ("load", "push")                            # load episodes (changes and pushes) and push-only episodes
FLANGE = (0.0, 0.0, 0.107)                          # m, the flange in link7's frame: where pushes are applied


@dataclass(frozen=True)
class ReliabilityConfig:
    """What an episode draws (a person handing the arm loads and pushing it) and how it is scored."""
    seconds: float = 8.0                 # s per episode
    first_change: tuple = (1.0, 2.5)     # s, the first load change is uniform in this range
    gap: tuple = (0.6, 2.5)              # s between changes
    max_changes: int = 3                 # 1..max_changes changes per load episode
    rest_after_last: float = 3.0         # s at least between the last change or push and the end
    mass: tuple = (0.1, 3.0)             # kg (the Panda's rated payload is 3 kg)
    com: float = 0.15                    # m, |rx|, |ry| <= com, rz in [0, com] (ee frame)
    centred_prob: float = 0.3            # a load centred below the flange (a basket, a grasped object) ...
    centred: float = 0.01                # m ... with |rx|, |ry| <= centred
    removal_prob: float = 0.5            # a change while a load is held removes it (otherwise swaps it) ...
    last_removal_prob: float = 0.5       # ... and so does the last change of an episode
    pushes: tuple = (0, 3)               # pushes per load episode (inclusive); push-only episodes have 1..pushes[1]
    push_force: tuple = (8.0, 50.0)      # N
    push_duration: tuple = (0.1, 2.0)    # s
    push_from: float = 0.5               # s, the earliest push (the arm has settled from its start)
    vertical_prob: float = 1 / 3         # a push straight up or down (a press looks like a centred load)
    near_change_prob: float = 0.3        # a push that starts within near_change of a load change
    near_change: float = 0.3             # s
    mass_tolerance: tuple = (0.10, 0.05)  # right: |m_hat - m| <= max(10 %, 50 g)
    calm_speed: float = 0.02             # rad/s: the arm is calm when every joint is slower
    rest_for: float = 0.3                # s of calm, no push, before "compensated once calm" is read
    pushed_within: float = 0.5           # s: a change with a push within this is scored apart
    after_push: float = 0.3              # s after a push's end still counted as the push's
    side_force: float = 3.0              # N: a push with more horizontal force is sideways, else vertical
    withdraw_s: float = 0.2              # s: target, a press's compensation withdrawn after its release
    release_window: float = 0.5          # s after a press's release whose rise above the target is measured
    rise_mm: float = 10.0                # mm: target, rise above the target after a press's release
    ignored_s: float = 1.5               # s: target, the longest calm stretch with a held load uncompensated
    kept_s: float = 1.0                  # s: target, an old load's compensation kept after it has gone
    outlive_s: float = 0.3               # s: target, compensation outliving its push in push-only episodes
    right_p90_s: float = 1.5             # s: target, p90 time to the right mass of a change without a push (a load
                                         #   ignored longer on a calm arm fails ignored_s anyway)
    error_mm: float = 10.0               # mm: target, the final end-effector error

    def __post_init__(self):
        if self.seconds < self.first_change[1] + self.rest_after_last:
            raise ValueError(f"seconds: expected at least first_change[1] + rest_after_last = "
                             f"{self.first_change[1] + self.rest_after_last} s, found {self.seconds}")
        if self.seconds < self.push_from + self.push_duration[1] + self.rest_after_last:
            raise ValueError(f"seconds: expected at least push_from + push_duration[1] + rest_after_last = "
                             f"{self.push_from + self.push_duration[1] + self.rest_after_last} s, found {self.seconds}")


def episode_seed(split: str, plant: str, kind: str, index: int) -> int:
    """The seed of episode `index` of `kind` ('load', 'push') on `plant` in `split`: SeedSequence children of one
    fixed root, keyed (split, plant, kind, index), so the splits' streams are disjoint and each episode reproducible."""
    for name, value, options in (("split", split, SPLITS), ("plant", plant, PLANTS), ("kind", kind, KINDS)):
        if value not in options:
            raise ValueError(f"{name}: expected one of {options}, found {value!r}")
    key = (SPLITS.index(split), PLANTS.index(plant), KINDS.index(kind), int(index))
    return int(np.random.SeedSequence(ENTROPY, spawn_key=key).generate_state(1, np.uint64)[0])


def draw_episode(rng: np.random.Generator, cfg: ReliabilityConfig, loads: bool = True) -> dict:
    """Random events of one episode: payload changes [dict(t, m, r (3,), kind)] (kind 'attach', 'swap', 'removal')
    and pushes [(t, force (3,), duration)], sorted by time."""
    changes = _draw_changes(rng, cfg) if loads else []
    last = cfg.seconds - cfg.rest_after_last
    pushes = []
    for _ in range(rng.integers(cfg.pushes[0] if loads else 1, cfg.pushes[1] + 1)):
        if rng.random() < cfg.vertical_prob:
            direction = np.array([0.0, 0.0, rng.choice([-1.0, 1.0])])
        else:
            direction = rng.normal(size=3)
            direction /= np.linalg.norm(direction)
        duration = rng.uniform(*cfg.push_duration)
        if changes and rng.random() < cfg.near_change_prob:
            start = changes[rng.integers(len(changes))]["t"] + rng.uniform(-cfg.near_change, cfg.near_change)
            start = min(start, last - cfg.push_duration[0])
            duration = min(duration, last - start)
        else:
            start = rng.uniform(cfg.push_from, last - duration)
        pushes.append((float(start), rng.uniform(*cfg.push_force) * direction, float(duration)))
    return {"changes": changes, "pushes": sorted(pushes, key=lambda p: p[0])}


def _draw_changes(rng, cfg):
    times = [rng.uniform(*cfg.first_change)]
    for _ in range(rng.integers(1, cfg.max_changes + 1) - 1):
        times.append(times[-1] + rng.uniform(*cfg.gap))
    times = [t for t in times if t <= cfg.seconds - cfg.rest_after_last]
    changes, held = [], False
    for i, t in enumerate(times):
        if held and (rng.random() < (cfg.last_removal_prob if i == len(times) - 1 else cfg.removal_prob)):
            changes.append(dict(t=float(t), m=0.0, r=np.zeros(3), kind="removal"))
            held = False
            continue
        side = cfg.centred if rng.random() < cfg.centred_prob else cfg.com
        r = np.array([*rng.uniform(-side, side, 2), rng.uniform(0.0, cfg.com)])
        changes.append(dict(t=float(t), m=float(rng.uniform(*cfg.mass)), r=r, kind="swap" if held else "attach"))
        held = True
    return changes


def estimator_class(spec: str):
    """'module:Class' -> the class; it is built as Class(robot, rng=...) and has update(q, dq, tau_ext), theta."""
    module, _, name = spec.partition(":")
    if not module or not name:
        raise ValueError(f"estimator: expected MODULE:CLASS (e.g. rme:RME), found {spec!r}")
    try:
        return getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError) as err:
        raise ValueError(f"estimator: {spec!r} cannot be loaded ({err})") from err


def simulate(split: str, plant: str, kind: str, index: int, cfg: ReliabilityConfig, estimator: str = "rme:RME",
             calibration=None):
    """One episode: draw it from its seed, run CPIC + the estimator on the plant. (Record, episode). calibration:
    the estimator's error model, passed as its `calibration` (None: not passed)."""
    seed = episode_seed(split, plant, kind, index)
    rng = np.random.default_rng(seed)
    sim = Plant(PlantConfig.preset(plant, rng), rng=rng)
    robot = sim.robot
    q0 = random_pose(robot, rng, DataConfig())
    ep = draw_episode(rng, cfg, loads=kind == "load")
    extra = {} if calibration is None else dict(calibration=calibration)
    est = estimator_class(estimator)(robot, rng=np.random.default_rng(seed + 1), **extra)
    events = [PayloadChange(c["t"], c["m"], c["r"]) for c in ep["changes"]]
    events += [Push(t, f, d, body="link7", offset=FLANGE) for t, f, d in ep["pushes"]]
    rec = run(sim, CPIC(robot, Attractor(*robot.ee_pose(q0))), cfg.seconds, estimator=est, events=events, q0=q0)
    return rec, dict(ep, seed=seed, q0=q0)


def run_episode(task) -> dict:
    """task = (split, plant, kind, index, cfg, estimator[, calibration]): the episode's scores (JSON-ready)."""
    split, plant, kind, index, cfg, estimator, *calibration = task
    rec, ep = simulate(split, plant, kind, index, cfg, estimator, *calibration)
    return dict(score(rec, ep, cfg), split=split, plant=plant, kind=kind, index=index, seed=ep["seed"])


# --- scores: from the Record's arrays (t, q, dq, tau, theta, theta_hat, p, target) and the episode's events --------
def tolerance(m, cfg: ReliabilityConfig):
    """The mass tolerance [kg] around a true mass m: max(10 % of m, 50 g)."""
    return np.maximum(cfg.mass_tolerance[0] * np.asarray(m), cfg.mass_tolerance[1])


def _index(t: np.ndarray, when: float) -> int:
    """The first row at or after `when` (len(t) past the end)."""
    return int(np.searchsorted(t, when - 1e-9))


def _longest_run(mask: np.ndarray) -> int:
    """The length of the longest run of True in mask."""
    if not mask.any():
        return 0
    edges = np.diff(np.concatenate(([0], mask.astype(np.int8), [0])))
    return int((np.flatnonzero(edges == -1) - np.flatnonzero(edges == 1)).max())


def _run_length(mask: np.ndarray) -> np.ndarray:
    """For each sample, the length of the run of True ending there (0 where False)."""
    idx = np.arange(len(mask))
    last_false = np.maximum.accumulate(np.where(mask, -1, idx))
    return np.where(mask, idx - last_false, 0)


def _pushes_over(pushes, t: float, pad: float) -> list:
    """The ends of the pushes active within pad of t."""
    return [s + d for s, _, d in pushes if s < t + pad and s + d > t - pad]


def score(rec, ep: dict, cfg: ReliabilityConfig) -> dict:
    """Every change and push of one episode scored from rec (a Record or anything with its arrays) and the episode's
    events ep (draw_episode's); the safety flags and the final end-effector error."""
    t, dt = rec.t, (rec.t[1] - rec.t[0] if len(rec.t) > 1 else 1e-3)
    m, m_hat = rec.theta[:, 0], rec.theta_hat[:, 0]
    right = np.abs(m_hat - m) <= tolerance(m, cfg)
    calm = np.all(np.abs(rec.dq) < cfg.calm_speed, axis=1)
    free = np.ones(len(t), dtype=bool)                         # no push now nor within after_push
    for s, _, d in ep["pushes"]:
        free[_index(t, s):_index(t, s + d + cfg.after_push)] = False
    ctx = dict(t=t, dt=dt, m_hat=m_hat, right=right, calm=calm, quiet=calm & free)
    ends = [c["t"] for c in ep["changes"][1:]] + [t[-1] + dt]
    before = [0.0] + [c["m"] for c in ep["changes"][:-1]]
    changes = [_score_change(c, m0, t_end, ep["pushes"], ctx, cfg) for c, m0, t_end in zip(ep["changes"], before, ends)]
    pushes = [_score_push(p, ep, rec, ctx, cfg) for p in ep["pushes"]]
    lo, hi = rec.robot.model.jnt_range.T
    return dict(changes=changes, pushes=pushes, final_error_mm=float(1e3 * rec.ee_error[-1]),
                nan=bool(not (np.all(np.isfinite(rec.tau)) and np.all(np.isfinite(rec.theta_hat)))),
                over_limit=bool(np.any(np.abs(rec.tau) > TAU_MAX + 1e-9)),
                joint_limit=bool(np.any(rec.q < lo - 1e-3) or np.any(rec.q > hi + 1e-3)),
                estimates=len(getattr(rec, "history", ())))


def _score_change(c: dict, m0: float, t_end: float, pushes, ctx: dict, cfg: ReliabilityConfig) -> dict:
    """One change over its interval [t, t_end): compensated once rested (None: never rested), the time to the right
    mass for good (None: wrong at the interval's end), the longest calm stretch with the held load uncompensated, how
    long the compensation of the load before it was kept after it had gone (removals and swaps), and for a change
    with a push over it, after the end of the pushes over it (a removal inside a push is a wrench's change until the
    push ends: its torques cannot tell them apart). A push that begins `pushed_within` or more after the change, when
    the compensation was right (for the time to the right mass) or had left the load before (for how long that was
    kept), owns the compensation from its start to after_push past its end: a reading then (a press read as a load)
    is scored as the push's, not the change's; the samples after it count again."""
    t, dt, m_hat = ctx["t"], ctx["dt"], ctx["m_hat"]
    i0, i1 = _index(t, c["t"]), _index(t, t_end)
    right = ctx["right"][i0:i1]
    rested = np.flatnonzero(_run_length(ctx["quiet"][i0:i1]) * dt >= cfg.rest_for - 1e-9)   # calm since the change
    spans = [(_index(t, s) - i0, _index(t, s + d + cfg.after_push) - i0)       # the later pushes, with their lag
             for s, _, d in pushes if c["t"] + cfg.pushed_within <= s < t_end]

    def owned(ok):
        """The samples (bool, over the interval) of a later push that began with ok true at the sample before."""
        x = np.zeros(len(ok), dtype=bool)
        for a, b in spans:
            x[a:b] |= bool(ok[a - 1])
        return x
    skip = owned(right)
    wrong = np.flatnonzero(~right & ~skip)
    if right[np.flatnonzero(~skip)[-1]]:          # (the first sample is never a later push's)
        to_right = 0.0 if not len(wrong) else float(t[i0 + wrong[-1] + 1] - c["t"])
    else:
        to_right = None
    ignored = float(_longest_run(ctx["calm"][i0:i1] & ~right) * dt) if c["m"] > 0 else None
    kept = None
    ends = _pushes_over(pushes, c["t"], cfg.pushed_within)
    if c["kind"] != "attach":
        old = np.abs(m_hat[i0:i1] - m0) <= tolerance(m0, cfg)
        new = np.abs(m_hat[i0:i1] - c["m"]) <= tolerance(c["m"], cfg)
        gone = np.flatnonzero(old & ~new & ~owned(~old))
        kept = float(t[i0 + gone[-1]] + dt - c["t"]) if len(gone) else 0.0
    pushed, over = bool(ends), max(ends, default=c["t"])   # (the end of the pushes over the change)
    return dict(t=c["t"], m=c["m"], m_before=m0, kind=c["kind"], pushed=pushed,
                compensated=None if not len(rested) else bool(right[rested[-1]]),
                m_hat_end=float(m_hat[i1 - 1]), to_right_s=to_right, ignored_s=ignored, kept_s=kept,
                kept_after_push_s=None if kept is None or not pushed else max(0.0, kept - (over - c["t"])))


def _push_class(force, cfg: ReliabilityConfig) -> str:
    """'sideways' (horizontal part > side_force), 'press' (vertical, down at the flange) or 'up'."""
    f = np.asarray(force)
    if np.hypot(f[0], f[1]) > cfg.side_force:
        return "sideways"
    return "press" if f[2] < 0 else "up"


def _score_push(push, ep: dict, rec, ctx: dict, cfg: ReliabilityConfig) -> dict:
    """One push [s, e): a sample is the push's compensation if the compensated mass has moved from the one before
    the push by more than the tolerance, is off the true mass by more than the tolerance, and further off it than
    the one before (no load change warrants it). Compensated: such a sample in [s, e), or in [e, e + after_push)
    with no other push acting or let go since e (a detection's or a withdrawal's lag: the push acting, or the one
    let go last, owns it), up to the next change (from s on: a change's compensation is scored as its own) or push;
    outlived: the last such sample, less the end of the pushes acting at e (its own or a longer one under which it
    began or ended: until then the compensation may be theirs); rise (presses alone: no other push or change from s
    to the end of the release window, else None): the end effector's height above its target after e."""
    s, force, d = push
    e = s + d
    t, m_hat, right = ctx["t"], ctx["m_hat"], ctx["right"]
    k_s = _index(t, s)
    ref = m_hat[k_s - 1] if k_s > 0 else 0.0
    last = e                                 # the end of the pushes still acting when it ends (a compensation
    for p in sorted(ep["pushes"], key=lambda p: p[0]):   # until then may be theirs: a press under it)
        last = max(last, p[0] + p[2]) if p[0] <= last else last
    nxt = [c["t"] for c in ep["changes"] if c["t"] > s] + [p[0] for p in ep["pushes"] if p[0] > last]
    k_end = _index(t, min(nxt, default=t[-1] + ctx["dt"]))
    m = rec.theta[k_s:k_end, 0]
    h = m_hat[k_s:k_end]
    own = (np.abs(h - ref) > tolerance(ref, cfg)) & ~right[k_s:k_end] & (np.abs(h - m) > np.abs(ref - m))
    hit = np.flatnonzero(own)
    th = t[k_s + hit]
    other = np.zeros(len(th), dtype=bool)                  # another push acting at the sample, or let go after
    for q in ep["pushes"]:                                 #   this one and within after_push of it (its lag)
        other |= (q is not push) & (th >= q[0]) & (th < q[0] + q[2] + (cfg.after_push if q[0] + q[2] > e else 0.0))
    during = bool(np.any(th < e) or np.any((th < e + cfg.after_push) & ~other))
    outlived = max(0.0, float(t[k_s + hit[-1]] + ctx["dt"] - last)) if len(hit) else 0.0
    kind, until = _push_class(force, cfg), e + cfg.release_window
    alone = not any(c["t"] >= s and c["t"] < until for c in ep["changes"]) and not any(
        q is not push and q[0] < until and q[0] + q[2] > s for q in ep["pushes"])
    w = slice(_index(t, e), _index(t, until))
    rise = float(1e3 * max(0.0, np.max(rec.p[w, 2] - rec.target[w, 2]))) if (
        kind == "press" and alone and w.stop > w.start) else None
    return dict(t=s, duration=d, force=np.asarray(force).tolist(), kind=kind,
                compensated=during, outlived_s=outlived, rise_mm=rise)


# --- summary ---------------------------------------------------------------------------------------------------
CHANGE_KINDS = ("attach", "swap", "removal")


def _times(values) -> dict:
    """Count, reached, median and p90 [s] of times where None is never (counted as infinite in the percentiles)."""
    x = np.sort(np.array([np.inf if v is None else v for v in values], dtype=float))

    def pct(q):                                              # linear between neighbours; None: next to a never
        if not len(x):
            return None
        pos = q / 100 * (len(x) - 1)
        lo, hi, w = int(np.floor(pos)), int(np.ceil(pos)), pos - np.floor(pos)
        v = x[lo] if w == 0 else np.inf if np.isinf(x[hi]) else x[lo] + w * (x[hi] - x[lo])
        return float(v) if np.isfinite(v) else None
    return dict(count=len(x), reached=int(np.isfinite(x).sum()), median=pct(50), p90=pct(90))


def _share(flags) -> dict:
    flags = list(flags)
    return dict(count=len(flags), yes=int(sum(flags)), share=(sum(flags) / len(flags) if flags else None))


def summarise(load_eps: list, push_eps: list, cfg: ReliabilityConfig) -> dict:
    """The figures of a run, each beside its target (targets: ReliabilityConfig)."""
    ch = [c for e in load_eps for c in e["changes"]]
    of = lambda kind: [c for c in ch if kind in (c["kind"], "all")]
    rested = lambda cs: [c["compensated"] for c in cs if c["compensated"] is not None]
    pushes = [p for e in load_eps + push_eps for p in e["pushes"]]
    presses = [p for p in pushes if p["kind"] == "press"]
    rises = [p["rise_mm"] for p in presses if p["rise_mm"] is not None]
    kept = [c["kept_s"] for c in ch if c["kept_s"] is not None]
    ignored = [c["ignored_s"] for c in ch if c["ignored_s"] is not None]
    errs = [e["final_error_mm"] for e in load_eps]
    return {
        "compensated": {k: dict(_share(rested(of(k))), never_rested=sum(c["compensated"] is None for c in of(k)))
                        for k in CHANGE_KINDS + ("all",)},
        "to_right_s": {w: {k: _times(c["to_right_s"] for c in of(k) if c["pushed"] == (w == "pushed"))
                           for k in CHANGE_KINDS} for w in ("no_push", "pushed")},
        "ignored_load": dict(changes=len(ignored), over_target=sum(x > cfg.ignored_s for x in ignored),
                             max_s=max(ignored, default=None)),
        "kept_after_gone": dict(changes=len(kept), over_target=sum(x > cfg.kept_s for x in kept),
                                max_s=max(kept, default=None),
                                no_push=sum(c["kept_s"] > cfg.kept_s for c in ch if c["kept_s"] is not None
                                            and not c["pushed"]),
                                after_push=sum((c.get("kept_after_push_s") or 0.0) > cfg.kept_s for c in ch
                                               if c["kept_s"] is not None and c["pushed"]),
                                pushed=sum(c["kept_s"] is not None and c["pushed"] for c in ch)),
        "pushes": {k: _share(p["compensated"] for p in pushes if p["kind"] == k) for k in ("sideways", "press", "up")},
        "presses_withdrawn": _share(p["outlived_s"] <= cfg.withdraw_s for p in presses if p["compensated"]),
        "press_rise_mm": dict(count=len(rises), over_target=sum(x >= cfg.rise_mm for x in rises),
                              max=max(rises, default=None), not_alone=len(presses) - len(rises)),
        "push_only_outlived": dict(pushes=sum(len(e["pushes"]) for e in push_eps),
                                   over_target=sum(p["outlived_s"] > cfg.outlive_s for e in push_eps
                                                   for p in e["pushes"])),
        "nan": sum(e["nan"] for e in load_eps + push_eps),
        "torque_over_limit": sum(e["over_limit"] for e in load_eps + push_eps),
        "joint_limit_violations": sum(e["joint_limit"] for e in load_eps + push_eps),
        "estimates_per_event_max": max((e.get("estimates", 0) / max(1, len(e["changes"]) + len(e["pushes"]))
                                        for e in load_eps + push_eps), default=0.0),
        "final_error_mm_median": float(np.median(errs)) if errs else None,
        "final_error_over_target": sum(x >= cfg.error_mm for x in errs),
        "load_episodes": len(load_eps), "push_episodes": len(push_eps),
    }


def reliability(episodes: int = 20, split: str = "tuning", plant: str = "realistic", estimator: str = "rme:RME",
                jobs: int = 1, cfg: ReliabilityConfig = ReliabilityConfig(), log=print, first: int = 0,
                calibration=None) -> dict:
    """`episodes` load episodes and as many push-only ones of split/plant, indices first.., in `jobs` worker
    processes (the results do not depend on jobs; an estimator that times itself, as RME's asynchronous setting does,
    may). calibration: the estimator's error model (its `calibration` argument; None: not passed)."""
    estimator_class(estimator)                               # a bad spec fails here, not in a worker
    if calibration is not None:
        as_error_model(calibration)                          # a calibration that cannot be read: here too
    for kind in KINDS:
        episode_seed(split, plant, kind, 0)
    tasks = [(split, plant, kind, i, cfg, estimator, calibration) for kind in KINDS
             for i in range(first, first + episodes)]
    t0 = time.perf_counter()
    if jobs == 1:
        results = []
        for n, task in enumerate(tasks, 1):
            results.append(run_episode(task))
            if n % 10 == 0:
                log(f"  {n}/{len(tasks)} episodes ({time.perf_counter() - t0:.0f} s)")
    else:
        import multiprocessing
        methods = multiprocessing.get_all_start_methods()     # fork: the workers start with the modules loaded
        with multiprocessing.get_context("fork" if "fork" in methods else "spawn").Pool(jobs) as pool:
            results = pool.map(run_episode, tasks, chunksize=1)
    loads, pushes = results[:episodes], results[episodes:]
    return {"summary": summarise(loads, pushes, cfg), "episodes": loads, "push_episodes": pushes,
            "seconds": time.perf_counter() - t0,
            "settings": dict(episodes=episodes, first=first, split=split, plant=plant, estimator=estimator, jobs=jobs,
                             calibration=None if calibration is None else str(calibration))}


def main(args):
    res = reliability(args.episodes, args.split, args.plant, args.estimator, args.jobs,
                      log=(lambda *a: None) if args.json else print, first=args.first, calibration=args.calibration)
    if args.plant == "realistic" and args.estimator == "rme:RME" and args.calibration is None:   # its RME: uncalibrated
        res["limit_cycle"] = limit_cycle_trials(range(20))
    if args.json:
        print(json.dumps(res, default=_jsonable))
        return res
    print_summary(res, ReliabilityConfig())
    if "limit_cycle" in res:
        lc = res["limit_cycle"]
        late = sum(t is not None and t > 1.0 for t in lc["seconds_to_compensation"])
        print(f"  limit cycle with 2 kg (sensor seeds 0..19): compensated {lc['compensated']}/{lc['seeds']}, cycling "
              f"again {lc['cycling_again']}/{lc['seeds']} ({late} only after the arm stalled and rested); load-free "
              f"cycling for {lc['load_free_seconds']:.0f} s: {lc['load_free_applied']} estimates applied")
    return res


def _jsonable(x):
    return x.tolist() if isinstance(x, np.ndarray) else float(x)


def print_summary(res: dict, cfg: ReliabilityConfig):
    s, st = res["summary"], res["settings"]
    frac = lambda d: f"{d['yes']}/{d['count']}" + (f" ({100 * d['share']:.0f} %)" if d["count"] else "")
    sec = lambda v: "never" if v is None else f"{v:.2f} s"
    print(f"reliability: {st['split']} split, {st['plant']} plant, {st['estimator']}; {st['episodes']} load + "
          f"{st['episodes']} push-only episodes of {cfg.seconds:.0f} s ({res['seconds']:.0f} s wall, {st['jobs']} jobs)")
    rows = [(f"compensated once rested: {k}", frac(s["compensated"][k]) + (f", never rested {n}" if (
        n := s["compensated"][k]["never_rested"]) else ""), "all") for k in CHANGE_KINDS + ("all",)]
    for w, label in (("no_push", f"no push within {cfg.pushed_within} s"), ("pushed", "a push over it")):
        for k in CHANGE_KINDS:
            d = s["to_right_s"][w][k]
            rows.append((f"time to the right mass, {label}: {k}", f"median {sec(d['median'])}, p90 {sec(d['p90'])} "
                         f"(right at the end {d['reached']}/{d['count']})",
                         f"p90 <= {cfg.right_p90_s} s" if w == "no_push" else "-"))
    for key, label, target in (("ignored_load", "held load ignored on a calm arm", cfg.ignored_s),
                               ("kept_after_gone", "old load kept after it has gone", cfg.kept_s)):
        d = s[key]
        rows.append((label, f"> {target} s in {d['over_target']}/{d['changes']} changes, longest "
                            f"{sec(d['max_s'])}", "0"))
        if key == "kept_after_gone":
            rows.append((f"  of those without a push / after the end of a push over it", f"> {target} s in "
                         f"{d['no_push']}/{d['changes'] - d['pushed']} / {d['after_push']}/{d['pushed']}", "0 / 0"))
    rows += [("sideways pushes compensated", frac(s["pushes"]["sideways"]), "0"),
             ("presses compensated (allowed)", frac(s["pushes"]["press"]), "-"),
             (f"  of those withdrawn within {1e3 * cfg.withdraw_s:.0f} ms of the release", frac(s["presses_withdrawn"]),
              "all"),
             (f"  rise above the target within {cfg.release_window} s of the release (alone)",
              f">= {cfg.rise_mm:.0f} mm in {s['press_rise_mm']['over_target']}/{s['press_rise_mm']['count']}, max "
              + ("-" if s["press_rise_mm"]["max"] is None else f"{s['press_rise_mm']['max']:.1f} mm")
              + f"; {s['press_rise_mm']['not_alone']} not alone", "0"),
             ("upward pushes compensated", frac(s["pushes"]["up"]), "-"),
             (f"push-only: compensation outliving its push by > {cfg.outlive_s} s",
              f"{s['push_only_outlived']['over_target']}/{s['push_only_outlived']['pushes']} pushes", "0"),
             ("estimates per change or push, the most in one episode", f"{s['estimates_per_event_max']:.1f}",
              "a few"),
             ("NaN / torque over the limits / joint limits",
              f"{s['nan']} / {s['torque_over_limit']} / {s['joint_limit_violations']}", "0 / 0 / 0"),
             ("final end-effector error", "-" if s["final_error_mm_median"] is None else
              f"median {s['final_error_mm_median']:.1f} mm, >= {cfg.error_mm:.0f} mm in "
              f"{s['final_error_over_target']}/{s['load_episodes']}", f"< {cfg.error_mm:.0f} mm")]
    width = max(len(r[0]) for r in rows)
    value = max(len(r[1]) for r in rows)
    print(f"  {'':{width}}  {'measured':{value}}  target")
    for label, v, target in rows:
        print(f"  {label:{width}}  {v:{value}}  {target}")


def limit_cycle_trials(seeds=range(20), load=(2.0, 0.04, 0.0, 0.10), t_attach=4.0, seconds=12.0,
                       free_seconds=20.0) -> dict:
    """The limit cycle of `python sim.py limit-cycle` on the realistic preset for each sensor seed: is the load
    compensated (mass within 10 %) and does the arm cycle again at the end (>= 0.1 turns/s over the last 2 s)? And
    load-free cycling for free_seconds: how many estimates are applied (none should be)."""
    from experiments.scenarios import Args, run as scenario
    from experiments.scenarios import limit_cycle_policy
    cycle = limit_cycle_policy()
    ok, recovered, detected = [], [], []
    for seed in seeds:
        rec = scenario(Args(seed=seed), seconds, [(t_attach, np.array(load), None)], policies=[(0.0, cycle)])
        ok.append(bool(abs(rec.theta_hat[-1, 0] - load[0]) <= 0.1 * load[0]))
        late = rec.t >= seconds - 2.0
        u = rec.p[late] - cycle.center
        phase = np.unwrap(np.arctan2(u[:, 2], u[:, 1]))
        recovered.append(bool((phase[-1] - phase[0]) / (2 * np.pi * 2.0) >= 0.1))
        hits = [e.applied for e in rec.history if e.accepted and e.t > t_attach and np.isfinite(e.applied)]
        detected.append(hits[0] - t_attach if hits else None)
    free = scenario(Args(seed=0), free_seconds, [], policies=[(0.0, cycle)])
    return {"seeds": len(ok), "compensated": sum(ok), "cycling_again": sum(recovered),
            "seconds_to_compensation": detected,
            "load_free_applied": sum(e.accepted for e in free.history), "load_free_seconds": free_seconds}
