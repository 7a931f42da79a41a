"""Randomised reliability benchmark of streaming RME in closed loop (`python sim.py reliability`): CPIC holds random
poses on the realistic plant while loads are attached, changed and removed at random times, people push the arm in
every direction, and RME runs in the loop. Counts every change that is detected and compensated, and every push."""
from __future__ import annotations

import json
import time
from dataclasses import dataclass

import numpy as np

from cpic import CPIC, Attractor
from experiments.runner import PayloadChange, Push, run
from nn_train import DataConfig, random_pose
from rme import RME
from sim import Plant, PlantConfig

TAU_MAX = np.array([87.0] * 4 + [12.0] * 3)        # Nm, Panda torque limits (panda_facts.md)


@dataclass(frozen=True)
class ReliabilityConfig:
    seconds: float = 7.0                 # s per episode
    first_change: tuple = (1.0, 2.5)     # s, the first load change is uniform in this range
    gap: tuple = (0.2, 2.0)              # s between changes
    rest_after_last: float = 3.0         # s at least between the last change or push and the end
    mass: tuple = (0.1, 3.0)             # kg (the Panda's rated payload is 3 kg)
    com: float = 0.15                    # m, |rx|, |ry| <= com, rz in [0, com] (ee frame)
    removal_prob: float = 0.5            # the last change removes the load
    max_changes: int = 3
    pushes: tuple = (0, 3)               # pushes per load episode (inclusive)
    push_force: tuple = (5.0, 60.0)      # N
    push_duration: tuple = (0.1, 2.0)    # s
    vertical_prob: float = 0.25          # a push straight up or down (the hardest case: it looks like a load)
    near_change_prob: float = 0.3        # a push that starts within 0.3 s of a load change
    mass_tolerance: tuple = (0.10, 0.05)  # compensated: |m_hat - m| <= max(10 %, 50 g) once the arm rests
    error_mm: float = 10.0               # final end-effector error target
    rest_speed: float = 0.02             # rad/s: the arm rests when every joint is slower for the last 1 s


def draw_episode(rng: np.random.Generator, cfg: ReliabilityConfig, loads: bool = True) -> dict:
    """Random events of one episode: payload changes [(t, m, r)] and pushes [(t, force (3,), duration)]."""
    changes, t, m = [], rng.uniform(*cfg.first_change), 0.0
    if loads:
        for i in range(rng.integers(1, cfg.max_changes + 1)):
            last = t + cfg.rest_after_last > cfg.seconds - cfg.gap[0]
            remove = m > 0 and (last or rng.random() < cfg.removal_prob)
            if remove:
                changes.append((t, 0.0, np.zeros(3)))
                m = 0.0
            else:
                m = rng.uniform(*cfg.mass)
                changes.append((t, m, np.array([*rng.uniform(-cfg.com, cfg.com, 2), rng.uniform(0.0, cfg.com)])))
            t += rng.uniform(*cfg.gap)
            if t > cfg.seconds - cfg.rest_after_last:
                break
    pushes = []
    n_push = rng.integers(cfg.pushes[0], cfg.pushes[1] + 1) if loads else rng.integers(1, cfg.pushes[1] + 1)
    for _ in range(n_push):
        if rng.random() < cfg.vertical_prob:
            direction = np.array([0.0, 0.0, rng.choice([-1.0, 1.0])])
        else:
            direction = rng.normal(size=3)
            direction /= np.linalg.norm(direction)
        duration = rng.uniform(*cfg.push_duration)
        if changes and rng.random() < cfg.near_change_prob:
            start = changes[rng.integers(len(changes))][0] + rng.uniform(-0.3, 0.3)
        else:
            start = rng.uniform(0.5, cfg.seconds - 1.0)
        start = float(np.clip(start, 0.5, cfg.seconds - cfg.rest_after_last - duration))
        pushes.append((start, rng.uniform(*cfg.push_force) * direction, duration))
    return {"changes": changes, "pushes": sorted(pushes, key=lambda p: p[0])}


def run_episode(seed: int, cfg: ReliabilityConfig, loads: bool = True, rme_settings=None) -> dict:
    """One episode: draw it, run CPIC + RME on the realistic plant, score every change and push."""
    rng = np.random.default_rng(seed)
    plant = Plant(PlantConfig.realistic(rng), rng=rng)
    robot = plant.robot
    q0 = random_pose(robot, rng, DataConfig())
    ep = draw_episode(rng, cfg, loads)
    est = RME(robot, rng=np.random.default_rng(seed + 1), **({} if rme_settings is None else
                                                              {"settings": rme_settings}))
    events = [PayloadChange(t, m, r) for t, m, r in ep["changes"]]
    events += [Push(t, f, d, body="link7", offset=(0.0, 0.0, 0.107)) for t, f, d in ep["pushes"]]   # at the flange
    rec = run(plant, CPIC(robot, Attractor(*robot.ee_pose(q0))), cfg.seconds, estimator=est, events=events, q0=q0)
    return dict(score(rec, ep, cfg, robot), not_payload=est.changes_not_payload, held=est.changes_held)


def score(rec, ep, cfg: ReliabilityConfig, robot) -> dict:
    times = [c[0] for c in ep["changes"]] + [cfg.seconds]
    changes = []
    for (t, m, _), t_next in zip(ep["changes"], times[1:]):
        before = rec.theta[rec.at(t) - 1, 0]
        hits = [e for e in rec.history if t <= e.t < t_next]
        applied = [e for e in hits if e.accepted and e.applied is not None]
        busy = [p[0] + p[2] for p in ep["pushes"] if p[0] < t_next and p[0] + p[2] > t]   # pushes in the interval
        calm = (rec.t >= t_next - 1.0) & (rec.t < t_next)
        settled = bool(t_next - max([t] + busy) >= 1.0 and np.abs(rec.dq[calm]).max() < cfg.rest_speed)
        m_hat = rec.theta_hat[rec.at(t_next) - 1, 0]
        tol = max(cfg.mass_tolerance[0] * m, cfg.mass_tolerance[1])
        ok = abs(m_hat - m) <= tol
        right = np.flatnonzero((rec.t >= t) & (rec.t < t_next) & (np.abs(rec.theta_hat[:, 0] - m) <= tol))
        m_hat_before = float(rec.theta_hat[rec.at(t) - 1, 0])      # compensated just before the change
        t_applied = applied[0].applied if applied else None        # the pushes over the change (from 0.5 s before
        free = max([t] + [p[0] + p[2] for p in ep["pushes"] if p[0] < t_applied and t - 0.5 < p[0] + p[2] <= t_applied]
                   ) if applied else t             # it) that ended before its compensation: the load can be told apart
                                                   # from then on
        changes.append(dict(t=t, m=m, before=before, m_hat_before=m_hat_before,
                            kind="removal" if m == 0 else "attachment", detected=bool(hits), settled=settled,
                            compensated=bool(ok), m_hat=float(m_hat),
                            latency_ms=(1e3 * (t_applied - t) if applied else None),
                            after_push_ms=(1e3 * (t_applied - free) if applied and free > t else None),
                            right_ms=(1e3 * (rec.t[right[0]] - t) if len(right) else None),
                            pushed=any(abs(p[0] - t) < 0.5 or p[0] <= t <= p[0] + p[2] for p in ep["pushes"])))
    err_mm = 1e3 * rec.ee_error
    lo, hi = robot.model.jnt_range.T
    return dict(changes=changes, pushes=len(ep["pushes"]),
                detections=len(rec.history), applied=sum(e.accepted for e in rec.history),
                final_error_mm=float(err_mm[-1]), nan=bool(not np.all(np.isfinite(rec.tau))),
                over_limit=bool(np.any(np.abs(rec.tau) > TAU_MAX + 1e-9)),
                joint_limit=bool(np.any(rec.q < lo - 1e-3) or np.any(rec.q > hi + 1e-3)))


def summarise(load_eps: list, push_eps: list, cfg: ReliabilityConfig) -> dict:
    ch = [c for e in load_eps for c in e["changes"]]
    counted = [c for c in ch if c["settled"]]

    def share(kind, key, which=lambda c: True):
        sel = [c for c in counted if c["kind"] == kind and which(c)]
        return {"count": len(sel), key: sum(c[key] for c in sel), "share": (sum(c[key] for c in sel) / len(sel)
                                                                             if sel else None)}
    pick = lambda key, push_ok=True: [c[key] for c in ch if c[key] is not None and c["kind"] == "attachment"
                                      and (push_ok or not c["pushed"])]
    lat, quiet, right, right_quiet = pick("latency_ms"), pick("latency_ms", False), pick("right_ms"), pick("right_ms", False)
    after = pick("after_push_ms")
    errs = np.array([e["final_error_mm"] for e in load_eps])
    return {
        "attachments_detected": share("attachment", "detected"),
        "attachments_compensated": share("attachment", "compensated"),
        "removals_detected": share("removal", "detected", lambda c: c["m_hat_before"] > cfg.mass_tolerance[1]),
        "removals_compensated": share("removal", "compensated"),
        "compensated_with_a_push_nearby": sum(c["compensated"] for c in counted if c["pushed"]),
        "with_a_push_nearby": sum(1 for c in counted if c["pushed"]),
        "latency_ms_median": float(np.median(lat)) if lat else None,
        "latency_ms_p90": float(np.percentile(lat, 90)) if lat else None,
        "latency_ms_median_no_push": float(np.median(quiet)) if quiet else None,
        "after_push_ms_median": float(np.median(after)) if after else None,
        "right_ms_median": float(np.median(right)) if right else None,
        "right_ms_median_no_push": float(np.median(right_quiet)) if right_quiet else None,
        "final_error_mm_median": float(np.median(errs)) if len(errs) else None,
        "final_error_below_target": int(np.sum(errs < cfg.error_mm)), "load_episodes": len(load_eps),
        "push_episodes": len(push_eps),
        "push_episodes_detected": sum(e["detections"] > 0 for e in push_eps),
        "push_episodes_applied": sum(e["applied"] > 0 for e in push_eps),
        "push_episodes_not_payload": sum(e.get("not_payload", 0) > 0 for e in push_eps),
        "push_episodes_held": sum(e.get("held", 0) > 0 for e in push_eps),
        "load_episodes_held": sum(e.get("held", 0) > 0 for e in load_eps),
        "nan": sum(e["nan"] for e in load_eps + push_eps),
        "torque_over_limit": sum(e["over_limit"] for e in load_eps + push_eps),
        "joint_limit_violations": sum(e["joint_limit"] for e in load_eps + push_eps),
    }


def reliability(episodes: int = 100, push_episodes: int = 100, seed: int = 0, cfg=ReliabilityConfig(),
                log=print) -> dict:
    t0 = time.perf_counter()
    loads = []
    for i in range(episodes):
        loads.append(run_episode(seed * 100_000 + i, cfg))
        if (i + 1) % 10 == 0:
            log(f"  {i + 1}/{episodes} load episodes ({time.perf_counter() - t0:.0f} s)")
    pushes = []
    for i in range(push_episodes):
        pushes.append(run_episode(seed * 100_000 + 50_000 + i, cfg, loads=False))
        if (i + 1) % 10 == 0:
            log(f"  {i + 1}/{push_episodes} push-only episodes ({time.perf_counter() - t0:.0f} s)")
    return {"summary": summarise(loads, pushes, cfg), "episodes": loads, "push_episodes": pushes,
            "seconds": time.perf_counter() - t0, "settings": {"episodes": episodes, "push_episodes": push_episodes,
                                                              "seed": seed, "preset": "realistic"}}


def main(args):
    res = reliability(args.episodes, args.episodes, args.seed, log=(lambda *a: None) if args.json else print)
    res["limit_cycle"] = limit_cycle_trials(range(args.seed, args.seed + 20))
    if args.json:
        print(json.dumps(res, default=float))
        return res
    s = res["summary"]
    pct = lambda d, k: f"{d[k]}/{d['count']}" + (f" ({100 * d['share']:.0f} %)" if d["count"] else "")
    print(f"reliability on the realistic preset, {args.episodes} load episodes + {args.episodes} push-only "
          f"episodes, seed {args.seed} ({res['seconds']:.0f} s)")
    print(f"  attachments detected        {pct(s['attachments_detected'], 'detected')}")
    print(f"  attachments compensated     {pct(s['attachments_compensated'], 'compensated')}   (mass within 10 % or "
          f"50 g once the arm rests)")
    print(f"  removals detected           {pct(s['removals_detected'], 'detected')}   (of loads compensated then)")
    print(f"  removals compensated        {pct(s['removals_compensated'], 'compensated')}")
    print(f"  compensated with a push within 0.5 s   {s['compensated_with_a_push_nearby']}/{s['with_a_push_nearby']}")
    ms = lambda v: "-" if v is None else f"{v:.0f} ms"
    print(f"  load change -> compensation (attachments)  median {ms(s['latency_ms_median'])}, p90 "
          f"{ms(s['latency_ms_p90'])}; without a push within 0.5 s: median {ms(s['latency_ms_median_no_push'])}")
    print(f"  end of the pushes over a change -> its compensation (attachments)  median "
          f"{ms(s['after_push_ms_median'])}")
    print(f"  load change -> mass compensated within 10 % or 50 g (attachments)  median {ms(s['right_ms_median'])}; "
          f"without a push within 0.5 s: median {ms(s['right_ms_median_no_push'])}")
    print(f"  final ee error: median {s['final_error_mm_median']:.1f} mm; below 10 mm in "
          f"{s['final_error_below_target']}/{s['load_episodes']} episodes")
    print(f"  pushes only: estimated in {s['push_episodes_detected']}/{s['push_episodes']} episodes, applied in "
          f"{s['push_episodes_applied']}/{s['push_episodes']}; the detector fired on a change no payload explains "
          f"(not estimated) in {s['push_episodes_not_payload']}; a press through the flange held (never estimated) in "
          f"{s['push_episodes_held']}")
    print(f"  load episodes with a change held as a possible press through the flange: {s['load_episodes_held']}")
    print(f"  safety: NaN {s['nan']}, torque over the limits {s['torque_over_limit']}, joint limits "
          f"{s['joint_limit_violations']}")
    lc = res["limit_cycle"]
    late = sum(t is not None and t > 1.0 for t in lc["seconds_to_compensation"])
    print(f"  limit cycle with 2 kg (sensor seeds {args.seed}..{args.seed + 19}): compensated {lc['compensated']}/"
          f"{lc['seeds']}, cycling again {lc['cycling_again']}/{lc['seeds']} ({late} only after the arm stalled and "
          f"rested); load-free cycling for {lc['load_free_seconds']:.0f} s: {lc['load_free_applied']} estimates applied")
    return res


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
