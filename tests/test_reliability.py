"""The reliability benchmark (experiments/reliability.py): the harsh and stressed plants as stated, disjoint and
reproducible seed streams, worker processes that change nothing, and each score on hand-made traces whose answer is
known."""
import dataclasses
import json
from types import SimpleNamespace

import numpy as np
import pytest

from cpic import CPIC, Attractor
from dynamics import Q_READY, Robot
from experiments.reliability import (ReliabilityConfig, draw_episode, episode_seed, reliability, score, summarise)
from experiments.runner import run
from sim import GAZ_P1, PRESETS, Plant, PlantConfig


def test_the_harsh_plant_differs_from_the_realistic_one_as_stated_and_runs():
    real, harsh = (getattr(PlantConfig, name)(np.random.default_rng(11)) for name in ("realistic", "harsh"))
    assert np.allclose(harsh.tau_noise, 2 * np.array(real.tau_noise))
    assert np.allclose(harsh.bias_amp, 2 * np.array(real.bias_amp))
    assert np.allclose(harsh.friction_sigmoid[0], 1.5 * np.array(GAZ_P1))
    assert np.allclose(harsh.friction_sigmoid[1:], real.friction_sigmoid[1:])
    assert (real.observer_gain, harsh.observer_gain) == (100.0, 50.0)
    # the same draws, stretched: masses +-12 % instead of +-8 %, CoM shifts 5-30 mm instead of 5-20 mm
    assert np.allclose(np.array(harsh.mass_scale) - 1, 1.5 * (np.array(real.mass_scale) - 1))
    assert np.all(np.abs(np.array(harsh.mass_scale) - 1) <= 0.12)
    r, h = (np.linalg.norm(c.com_shift, axis=1) for c in (real, harsh))
    assert np.allclose(h - 0.005, (r - 0.005) * 0.025 / 0.015) and np.all((h >= 0.005) & (h <= 0.03))
    assert np.allclose(np.array(harsh.com_shift) / h[:, None], np.array(real.com_shift) / r[:, None])
    for name in ("tau_step", "q_noise", "dq_noise", "stale_prob", "torque_offset", "armature", "observer"):
        assert getattr(harsh, name) == getattr(real, name), name
    assert PlantConfig.preset("harsh", np.random.default_rng(11)) == harsh
    rng = np.random.default_rng(11)
    plant = Plant(PlantConfig.harsh(rng), rng=rng)
    dq = np.full(7, 0.3)
    assert np.allclose(plant._friction(dq) - plant._friction(-dq),
                       1.5 * (Plant(real, rng=np.random.default_rng(1))._friction(dq)
                              - Plant(real, rng=np.random.default_rng(1))._friction(-dq)))
    rec = run(plant, CPIC(plant.robot, Attractor(*plant.robot.ee_pose(Q_READY))), 0.5, q0=Q_READY)
    assert np.all(np.isfinite(rec.tau_ext)) and rec.ee_error.max() < 0.02   # CPIC holds it within 2 cm


def test_each_stressed_plant_is_the_realistic_one_with_one_part_changed_as_stated():
    rng = lambda: np.random.default_rng(12)
    real = PlantConfig.realistic(rng())
    changed = {"noisy": ("tau_noise", "bias_amp"), "sticky": ("friction_sigmoid",), "slow-sensor": ("observer_gain",)}
    for name, fields in changed.items():
        c = PlantConfig.preset(name, rng())
        for f in dataclasses.fields(PlantConfig):
            if f.name not in fields:
                assert getattr(c, f.name) == getattr(real, f.name), (name, f.name)
    noisy, sticky = PlantConfig.preset("noisy", rng()), PlantConfig.preset("sticky", rng())
    assert np.allclose(noisy.tau_noise, 3 * np.array(real.tau_noise))
    assert np.allclose(noisy.bias_amp, 2 * np.array(real.bias_amp))
    assert np.allclose(sticky.friction_sigmoid[0], 2 * np.array(GAZ_P1))
    assert sticky.friction_sigmoid[1:] == real.friction_sigmoid[1:]
    assert PlantConfig.preset("slow-sensor", rng()).observer_gain == 25.0
    with pytest.raises(ValueError, match="preset: expected one of"):
        PlantConfig.preset("rough", rng())


def test_the_splits_seed_streams_are_disjoint_and_each_episode_is_reproducible():
    cfg = ReliabilityConfig()
    seeds = {split: [episode_seed(split, plant, kind, i) for plant in PRESETS
                     for kind in ("load", "push") for i in range(2000)] for split in ("tuning", "test")}
    assert len(set(seeds["tuning"])) == len(seeds["tuning"]) == len(set(seeds["test"]))
    assert not set(seeds["tuning"]) & set(seeds["test"])
    draw = lambda *key: draw_episode(np.random.default_rng(episode_seed(*key)), cfg)
    a, b, c = draw("tuning", "harsh", "load", 7), draw("tuning", "harsh", "load", 7), draw("test", "harsh", "load", 7)
    assert json.dumps(a, default=np.ndarray.tolist) == json.dumps(b, default=np.ndarray.tolist)
    assert json.dumps(a, default=np.ndarray.tolist) != json.dumps(c, default=np.ndarray.tolist)
    with pytest.raises(ValueError, match="split"):
        episode_seed("validation", "realistic", "load", 0)


def test_the_drawn_episodes_follow_the_stated_distribution():
    """3000 draws: each stated share within 3 standard errors, every bound held."""
    cfg = ReliabilityConfig()
    eps = [draw_episode(np.random.default_rng(episode_seed("tuning", "realistic", "load", i)), cfg) for i in range(3000)]
    loads = [c for e in eps for c in e["changes"] if c["m"] > 0]
    pushes = [p for e in eps for p in e["pushes"]]
    centred = np.mean([np.abs(c["r"][:2]).max() <= cfg.centred for c in loads])
    vertical = np.mean([np.hypot(*p[1][:2]) == 0 for p in pushes])
    expected = 0.3 + 0.7 * (cfg.centred / cfg.com) ** 2            # off-centre loads may fall inside 1 cm too
    assert abs(centred - expected) < 3 * np.sqrt(expected * (1 - expected) / len(loads))
    assert abs(vertical - 1 / 3) < 3 * np.sqrt(2 / 9 / len(pushes))
    for e in eps:
        times = [c["t"] for c in e["changes"]]
        assert 1 <= len(times) <= 3 and 1.0 <= times[0] <= 2.5 and np.all(np.diff(times) >= 0.6 - 1e-12)
        assert np.all(np.diff(times) <= 2.5) and len(e["pushes"]) <= 3
        assert max(times + [s + d for s, _, d in e["pushes"]]) <= 8.0 - 3.0 + 1e-9
        held = 0.0
        for c in e["changes"]:
            assert c["kind"] == ("removal" if c["m"] == 0 else "swap" if held else "attach")
            assert c["m"] == 0 or (0.1 <= c["m"] <= 3.0 and np.abs(c["r"][:2]).max() <= 0.15 and 0 <= c["r"][2] <= 0.15)
            assert held > 0 or c["m"] > 0                          # nothing is removed that is not held
            held = c["m"]
        for s, f, d in e["pushes"]:
            assert 8.0 <= np.linalg.norm(f) <= 50.0 and 0.1 - 1e-12 <= d <= 2.0 and s >= 0.5


def test_worker_processes_give_the_same_results_as_one():
    cfg = ReliabilityConfig(seconds=1.2, first_change=(0.3, 0.5), gap=(0.2, 0.3), rest_after_last=0.6,
                            push_duration=(0.1, 0.2), push_from=0.2)
    runs = [reliability(1, "tuning", "harsh", "tests.helpers:SyncRME", jobs, cfg, log=lambda *a: None)
            for jobs in (1, 2)]
    same = [json.dumps({k: r[k] for k in ("summary", "episodes", "push_episodes")}, default=float) for r in runs]
    assert same[0] == same[1]
    assert runs[0]["episodes"][0]["seed"] == episode_seed("tuning", "harsh", "load", 0)
    with pytest.raises(ValueError, match="estimator"):
        reliability(1, estimator="rme", cfg=cfg)


def _trace(seconds, pieces, moving=()):
    """A Record-like object at 1 kHz at the ready pose: theta_hat's mass set piecewise [(t0, t1, m)], the arm
    moving at 0.05 rad/s over each (t0, t1) in moving, ee at its target."""
    t = np.arange(int(seconds * 1000)) * 1e-3
    theta, theta_hat, dq = np.zeros((len(t), 4)), np.zeros((len(t), 4)), np.zeros((len(t), 7))
    for t0, t1, m in pieces:
        theta_hat[(t >= t0 - 1e-9) & (t < t1 - 1e-9), 0] = m
    for t0, t1 in moving:
        dq[(t >= t0 - 1e-9) & (t < t1 - 1e-9)] = 0.05
    zeros = np.zeros((len(t), 3))
    return SimpleNamespace(t=t, q=np.tile(Q_READY, (len(t), 1)), dq=dq, tau=np.zeros((len(t), 7)), theta=theta,
                           theta_hat=theta_hat, p=zeros.copy(), target=zeros, ee_error=np.zeros(len(t)),
                           robot=Robot.panda())


def test_the_scores_of_hand_made_traces_are_the_known_ones():
    cfg = ReliabilityConfig()
    # 1 kg at 1 s (read 0.8 kg from 1.4 s, 1 kg from 1.6 s), 2 kg at 3 s (1 kg kept until 4.7 s), removed at 5.5 s
    # (withdrawn at 5.6 s); a sideways push 6.1-6.6 s, read as 0.5 kg from 6.2 s to 7.0 s, the arm moving 6.1-7.2 s
    # (the removal right from 5.6 s until the push began; its reading outlives the push's 0.3 s lag: the removal's too)
    changes = [dict(t=1.0, m=1.0, r=np.zeros(3), kind="attach"), dict(t=3.0, m=2.0, r=np.zeros(3), kind="swap"),
               dict(t=5.5, m=0.0, r=np.zeros(3), kind="removal")]
    rec = _trace(8.0, [(1.4, 1.6, 0.8), (1.6, 4.7, 1.0), (4.7, 5.6, 2.0), (6.2, 7.0, 0.5)], moving=[(6.1, 7.2)])
    for c, t1 in zip(changes, (3.0, 5.5, 8.0)):
        rec.theta[(rec.t >= c["t"] - 1e-9) & (rec.t < t1 - 1e-9), 0] = c["m"]
    ep = dict(changes=changes, pushes=[(6.1, np.array([20.0, 0.0, 0.0]), 0.5)])
    s = score(rec, ep, cfg)
    attach, swap, removal = s["changes"]
    assert [c["compensated"] for c in s["changes"]] == [True, True, True]
    assert [c["to_right_s"] for c in s["changes"]] == pytest.approx([0.6, 1.7, 1.5], abs=1e-9)
    assert [c["ignored_s"] for c in s["changes"]] == pytest.approx([0.6, 1.7, None], abs=1e-9)
    assert (attach["kept_s"], swap["kept_s"], removal["kept_s"]) == (None, pytest.approx(1.7), pytest.approx(0.1))
    assert [c["kept_after_push_s"] for c in s["changes"]] == [None, None, None]   # no push over them
    (push,) = s["pushes"]
    assert push["kind"] == "sideways" and push["compensated"] and push["outlived_s"] == pytest.approx(0.4)
    # push-only: a press 2-3 s read as 1.5 kg from 2.3 s to 3.15 s, the hand 12 mm above its target at 3.1 s
    press = _trace(5.0, [(2.3, 3.15, 1.5)])
    press.p[3100, 2] = 0.012
    p = score(press, dict(changes=[], pushes=[(2.0, np.array([0.0, 1.0, -20.0]), 1.0)]), cfg)
    assert p["pushes"][0]["kind"] == "press" and p["pushes"][0]["outlived_s"] == pytest.approx(0.15)
    assert p["pushes"][0]["rise_mm"] == pytest.approx(12.0)
    with_another = dict(changes=[], pushes=[(2.0, np.array([0.0, 1.0, -20.0]), 1.0), (3.4, np.array([0.0, 0.0, 20.0]), 0.2)])
    assert [x["rise_mm"] for x in score(press, with_another, cfg)["pushes"]] == [None, None]   # not alone; not a press
    # a sideways push 1.0-1.5 s under a press 1.2-2.5 s, read as 1.5 kg from 1.7 s: after the sideways one's end, with
    # the press acting, the press's; the same reading without the press: the sideways push's (a detection's lag)
    late = _trace(4.0, [(1.7, 2.6, 1.5)])
    side, down = (1.0, np.array([15.0, 0.0, 0.0]), 0.5), (1.2, np.array([0.0, 0.0, -20.0]), 1.3)
    pushes = score(late, dict(changes=[], pushes=[side, down]), cfg)["pushes"]
    assert [x["compensated"] for x in pushes] == [False, True]
    assert score(late, dict(changes=[], pushes=[side]), cfg)["pushes"][0]["compensated"]
    # a load swapped under a sideways push: 1 kg held and compensated, the push 1.0-2.0 s, 2 kg from 1.5 s, read as
    # none 1.6-1.9 s, then 2 kg: the swap's reading (off the new load), not the push's
    swapped = _trace(3.0, [(0.6, 1.6, 1.0), (1.9, 3.0, 2.0)])
    swapped.theta[(swapped.t >= 0.5 - 1e-9), 0] = 1.0
    swapped.theta[(swapped.t >= 1.5 - 1e-9), 0] = 2.0
    ep2 = dict(changes=[dict(t=0.5, m=1.0, r=np.zeros(3), kind="attach"),
                        dict(t=1.5, m=2.0, r=np.zeros(3), kind="swap")],
               pushes=[(1.0, np.array([15.0, 0.0, 0.0]), 1.0)])
    s2 = score(swapped, ep2, cfg)
    assert not s2["pushes"][0]["compensated"] and s2["changes"][1]["to_right_s"] == pytest.approx(0.4)
    swapped.theta_hat[(swapped.t >= 1.2 - 1e-9) & (swapped.t < 1.4 - 1e-9), 0] = 0.3   # read before the swap: its own
    assert score(swapped, ep2, cfg)["pushes"][0]["compensated"]
    sm = summarise([s], [p], cfg)
    assert sm["compensated"]["all"]["yes"] == 3 and sm["to_right_s"]["no_push"]["attach"]["median"] == pytest.approx(0.6)
    assert sm["ignored_load"]["over_target"] == 1 and sm["kept_after_gone"]["over_target"] == 1
    assert sm["pushes"]["sideways"]["yes"] == 1 and sm["presses_withdrawn"]["yes"] == 1
    assert sm["press_rise_mm"]["over_target"] == 1 and sm["push_only_outlived"]["over_target"] == 0
    # a removal never withdrawn: never right, the load before it kept to the end; then one never rested
    rec = _trace(4.0, [(1.2, 4.0, 1.0)])
    rec.theta[(rec.t >= 1.0 - 1e-9) & (rec.t < 2.0 - 1e-9), 0] = 1.0
    ep = dict(changes=[dict(t=1.0, m=1.0, r=np.zeros(3), kind="attach"),
                       dict(t=2.0, m=0.0, r=np.zeros(3), kind="removal")], pushes=[])
    attach, removal = score(rec, ep, cfg)["changes"]
    assert removal["to_right_s"] is None and removal["compensated"] is False and removal["kept_s"] == pytest.approx(2.0)
    # the same under a push 1.8-3.0 s: kept 1.0 s after the push's end, counted there, not without a push
    pushed = score(rec, dict(ep, pushes=[(1.8, np.array([20.0, 0.0, 0.0]), 1.2)]), cfg)["changes"][1]
    assert pushed["pushed"] and pushed["kept_after_push_s"] == pytest.approx(1.0)
    km = summarise([score(rec, ep, cfg)], [], cfg)["kept_after_gone"]
    assert (km["no_push"], km["pushed"], km["after_push"]) == (1, 0, 0)
    km = summarise([score(rec, dict(ep, pushes=[(1.8, np.array([20.0, 0.0, 0.0]), 1.2)]), cfg)], [], cfg)
    assert [km["kept_after_gone"][k] for k in ("over_target", "no_push", "pushed", "after_push")] == [1, 0, 1, 0]
    assert attach["to_right_s"] == pytest.approx(0.2)
    rec.dq[(rec.t >= 2.0 - 1e-9) & (rec.t < 3.75 - 1e-9)] = 0.05   # calm only 0.25 s after the removal: never rested
    assert score(rec, ep, cfg)["changes"][1]["compensated"] is None


def test_a_reading_under_a_later_push_is_that_push_s_not_the_change_s_nor_one_let_go_before_it_s():
    cfg = ReliabilityConfig()
    # 2 kg swapped for 0.5 kg at 1.0 s, read right from 1.3 s; a press 2.0-2.3 s read as 2.0 kg (like the load before)
    # from 2.05 s until 2.35 s: the press's compensation, withdrawn 50 ms after its release; the swap was right and the
    # old load left 0.7 s before the press began
    swap = _trace(4.0, [(0.0, 1.3, 2.0), (1.3, 2.05, 0.5), (2.05, 2.35, 2.0), (2.35, 4.0, 0.5)])
    swap.theta[:, 0] = 2.0
    swap.theta[swap.t >= 1.0 - 1e-9, 0] = 0.5
    ep = dict(changes=[dict(t=0.0, m=2.0, r=np.zeros(3), kind="attach"),
                       dict(t=1.0, m=0.5, r=np.zeros(3), kind="swap")],
              pushes=[(2.0, np.array([0.0, 0.0, -15.0]), 0.3)])
    s = score(swap, ep, cfg)
    changed, (press,) = s["changes"][1], s["pushes"]
    assert changed["kept_s"] == pytest.approx(0.3) and changed["to_right_s"] == pytest.approx(0.3)
    assert press["compensated"] and press["outlived_s"] == pytest.approx(0.05)
    # the load before never left before the press: kept through it, and the change right only after it
    held = _trace(4.0, [(0.0, 2.35, 2.0), (2.35, 4.0, 0.5)])
    held.theta[:] = swap.theta
    changed = score(held, ep, cfg)["changes"][1]
    assert changed["kept_s"] == pytest.approx(1.35) and changed["to_right_s"] == pytest.approx(1.35)
    # right from 1.2 s after an attach, an upward push 2.0-2.3 s, then 0.3 kg read to the end: wrong after the push's
    # lag, so never right for good (the push owns only its own span and lag)
    up = _trace(4.0, [(1.2, 2.4, 1.0), (2.4, 4.0, 0.3)])
    up.theta[up.t >= 1.0 - 1e-9, 0] = 1.0
    attach = score(up, dict(changes=[dict(t=1.0, m=1.0, r=np.zeros(3), kind="attach")],
                            pushes=[(2.0, np.array([0.0, 0.0, 20.0]), 0.3)]), cfg)["changes"][0]
    assert attach["to_right_s"] is None
    up.theta_hat[up.t >= 2.45 - 1e-9, 0] = 1.0                     # 0.3 kg read 2.4-2.45 s only, within the lag
    up.theta_hat[(up.t >= 2.1 - 1e-9) & (up.t < 2.4 - 1e-9), 0] = 0.3   #   and under the push from 2.1 s: its own
    assert score(up, dict(changes=[dict(t=1.0, m=1.0, r=np.zeros(3), kind="attach")],
                          pushes=[(2.0, np.array([0.0, 0.0, 20.0]), 0.3)]), cfg)["changes"][0]["to_right_s"] == \
        pytest.approx(0.2)
    # a sideways push 1.3-1.8 s inside a press 1.0-2.0 s, the press read as 1.5 kg from 1.2 s and as 2.0 kg from
    # 1.9 s to 2.05 s (50 ms after the press's release): the press's reading and its withdrawal's lag, not the
    # sideways push's (its own window after its end has the press acting, then the press let go later than it)
    both = _trace(3.0, [(1.2, 1.9, 1.5), (1.9, 2.05, 2.0)])
    side, down = (1.3, np.array([15.0, 0.0, 0.0]), 0.5), (1.0, np.array([0.0, 0.0, -15.0]), 1.0)
    scored = score(both, dict(changes=[], pushes=[down, side]), cfg)["pushes"]
    assert [x["compensated"] for x in scored] == [True, False]
    # without the press, the same reading after the sideways push's end is its own (a detection's lag)
    alone = _trace(3.0, [(1.9, 2.05, 2.0)])
    assert score(alone, dict(changes=[], pushes=[side]), cfg)["pushes"][0]["compensated"]
