"""Held-out forward selection of the effects a model misses (Eq. 1 plus the effects of effects.py): rank, add the
best while it is significant and the log can tell it from the others (identify.py)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from diagnosis.effect_model import Model
from diagnosis.findings import collect
from diagnosis.heldout import Selection, blocks_of, rank
from diagnosis.identify import IdentifyConfig, Separability, describe_excitation


@dataclass(frozen=True)
class DiagnoseConfig:
    """Held-out forward selection (see diagnose)."""
    block: float = 0.5          # s, interleaved hold-out blocks: >> the 0.05 s filter window, << the motion's periods
    min_drop: float = 0.10      # an effect must cut the held-out RMS of some joint by >= 10 % ...
    t_min: float = 3.0          # ... with t >= 3 for the per-block log error ratios (one-sided p < 0.01) ...
    min_torque: float = 0.01    # Nm, ... explaining >= 0.01 Nm RMS there: half the Panda's 0.02 Nm torque resolution
    min_total_drop: float = 0.01  # and cut the RMS of the summed held-out error by >= 1 % with t >= t_min (not 10 %:
                                  # an effect of a wrist joint is small beside the shoulders' error in the sum) ...
    max_rise: float = 0.05      # ... and raise no joint's held-out RMS by >= 5 % with t >= t_min
    max_add: int = 6            # forward-selection steps at most
    min_blocks: int = 6         # fewer hold-out blocks: the log is too short to diagnose


@dataclass
class Diagnosis:
    """diagnose() output. rms (n,): held-out RMS of the input model; ranking: the first round's candidates, best first,
    each {effect, k, explained, explained_joints, joints (improved), worse (joints made worse), significant, rms_after,
    rms_change (n,) = rms_after / rms_before - 1, total_change, total_t, drop, t, params}; steps: the forward
    selection, each {effect, rms_before, rms_after, rms_change, explained, joints, params}; selected: effect names;
    model: the input model plus the selected effects, fitted on the whole log; stop: why selection ended; findings:
    what the data asked of an effect beyond its physical constraints, [{effect, text, joints, violations}]."""
    rms: np.ndarray
    ranking: list
    steps: list
    selected: list
    model: Model
    stop: str
    samples: int = 0
    info: dict = field(default_factory=dict)
    findings: list = field(default_factory=list)


def diagnose(model: Model, log, candidates=None, config: DiagnoseConfig = DiagnoseConfig()) -> Diagnosis:
    """Rank the candidate effects (default: the library's effects not in the model) by how much of the model's
    residual each explains on held-out data, then add the best and repeat while the gain is significant.

    Hold-out: the log is cut into interleaved blocks of config.block seconds; each effect set is fitted on the even
    blocks and scored on the odd ones, and vice versa (2-fold), so both halves see the same motions and an effect
    cannot win by fitting noise. Significant (heldout.verdict), all three of: (a) the held-out error falls overall: the
    RMS of the summed SSE over all joints drops by >= min_total_drop with t >= t_min for the per-block log ratios of the
    totals; (b) no joint gets worse: no joint's held-out RMS rises by >= max_rise with t >= t_min for its per-block
    log ratios log(sse_after / sse_before); (c) on at least one joint the held-out RMS drops by >= min_drop AND the
    per-block log error ratios log(sse_before / sse_after) have t >= t_min AND the torque explained there is
    >= min_torque RMS. So the selection cannot trade one joint's error for another's. Parsimony: a significant
    candidate with fewer parameters is preferred unless the better-scoring one is significantly better than it on some
    joint by rule (c) (e.g. coulomb over sigmoid, payload over rigid_payload on a quasi-static log). Every fit keeps
    to the effects' physical constraints; where the unconstrained fit of a candidate breaks them and scores
    significantly better for it, that is a finding (findings.py). Candidates: Effect objects or library names."""
    s = model.signals(log)
    y = s.measured() - model.torque(s, [e for e in model.effects if e.name in model.fixed])
    block = blocks_of(s.t, config.block)
    if block.max() + 1 < config.min_blocks:
        raise ValueError(f"log: too short to diagnose: {block.max() + 1} hold-out blocks of {config.block} s, "
                         f"expected at least {config.min_blocks} ({config.min_blocks * config.block} s)")
    cands = [model.effect(c) for c in candidates] if candidates is not None else \
        [e for e in model.library.values() if e.name not in model.names]
    clash = [c.name for c in cands if c.name in model.names]
    if clash:
        raise ValueError(f"candidates: expected effects not yet in the model, found {clash} (in {model.names})")
    sel = Selection(s, y, block, config)
    for e in model.free:
        sel.extend(e)
    rms0 = np.sqrt(sel.sse.sum(axis=0) / len(s))
    sep = Separability(s, model.identify or IdentifyConfig())
    ranking, steps, stop, asked, notes = _forward_selection(sel, cands, config, sep, list(model.free))
    final = model.copy()
    for st in steps:
        final.add(st["obj"])
    if final.free:
        final.fit(s)
    selected = [st["effect"] for st in steps]
    supported = {n for n in ("motion", "gravity") if n not in final.names
                 and sep.dims(model.effect(n), list(final.free)) != 0}
    findings = notes + collect(asked, selected, supported, describe_excitation(sep.excitation),
                               {c.name: c for c in cands}, s.n)
    return Diagnosis(rms0, ranking, steps, selected, final, stop, len(s),
                     {"blocks": int(block.max() + 1), "block_s": config.block, "excitation": sep.excitation},
                     findings)


def _forward_selection(sel: Selection, cands: list, config: DiagnoseConfig, sep: Separability, base: list):
    """Add the top-ranked significant candidate while there is one the log can tell from the others: (first round's
    ranking, steps, stop reason, what the data asked of each effect beyond its constraints when it was last tried
    {effect: asked}, findings on what the log cannot identify or tell apart)."""
    N, ranking, steps, asked, notes = len(sel.s), None, [], {}, []
    for _ in range(config.max_add):
        cands, dropped = _identifiable(cands, base, sep)
        notes += dropped
        if not cands:
            return ranking or [], steps, "no candidate effects left the log can identify", asked, notes
        order = rank([sel.try_effect(c) for c in cands], config, N)
        for r in order:
            asked.pop(r["effect"], None)
            if r["asked"]:
                asked[r["effect"]] = r["asked"]
        ranking = order if ranking is None else ranking
        top = order[0]
        clash = _ambiguity(top, order, base, sep) if top["significant"] else None
        if clash:
            notes.append(clash)
            return ranking, steps, f"{top['effect']} cannot be told apart from {clash['effect'].split('/')[1]} by " \
                "this log (findings)", asked, notes
        if not top["significant"]:
            j = int(np.argmax(top["drop"]))
            stop = (f"no remaining effect is significant (best: {top['effect']}, held-out RMS drop "
                    f"{100 * top['drop'][j]:.1f} % on J{j + 1}, t = {top['t'][j]:.1f}; total "
                    f"{100 * top['total_change']:+.1f} %, t = {top['total_t']:.1f}; "
                    f"worse on joints {top['worse'] or '-'})")
            return ranking, steps, stop, asked, notes
        steps.append(dict(effect=top["effect"], obj=top["obj"], rms_before=np.sqrt(sel.sse.sum(axis=0) / N),
                          rms_after=top["rms_after"], rms_change=top["rms_change"], explained=top["explained"],
                          joints=top["joints"], params=top["params"]))
        sel.accept(top)
        base = base + [top["obj"]]
        cands = [c for c in cands if c.name != top["effect"]]
    return ranking, steps, f"stopped after max_add = {config.max_add} steps", asked, notes


def _identifiable(cands, base, sep: Separability):
    """(the candidates with a direction the log identifies beside the effects `base`, a finding for each other)."""
    keep, notes = [], []
    for c in cands:
        dims = sep.dims(c, base)
        if dims is None or dims > 0:
            keep.append(c)
            continue
        alone = sep.dims(c) if base else 0
        why = (f"what it would explain, {', '.join(e.name for e in base)} explain as well at this log's states"
               if alone else "a plausible size of it moves the torque by less than the model's error (0.15 Nm) "
               "at the states this log visits")
        notes.append(dict(effect=c.name, joints=[], violations=[], kind="not identifiable",
                          text=f"{c.name} is not identifiable from this log ({describe_excitation(sep.excitation)}): "
                               f"{why}; not fitted"))
    return keep, notes


def _ambiguity(top, order, base, sep: Separability):
    """A finding if top and an effect of the other kind (a load against the robot's own) explain the same torque: a
    direction of the load the log identifies beside `base` is lost once the robot's effect is fitted too
    (Separability.dims), and the other effect helps on its own or is lost entirely (whatever it is, top could be
    it), so the log cannot say which of the two is there; else None. The text gives the
    share of the fitted load's torque the robot's effect makes as well (Separability.shared)."""
    for r in order[1:]:
        e = r["obj"]
        if e.payload == top["obj"].payload:
            continue
        load, robot = (r, top) if e.payload else (top, r)
        alone, given = sep.dims(load["obj"], base), sep.dims(load["obj"], base + [robot["obj"]])
        if alone is None or given is None or given >= alone or (not r["joints"] and given > 0):
            continue                    # told apart, or a partly mimicked effect that does not help on its own
        L, R = load["effect"], robot["effect"]
        share = sep.shared(load["obj"], load["p"], robot["obj"], base)
        lost = f"{alone - given} of the {alone} directions of {L} it identifies alone " + \
            ("is a torque" if alone - given == 1 else "are torques")
        text = (f"the log cannot tell {L} from {R} ({describe_excitation(sep.excitation)}): {lost} {R} makes as "
                f"well" + (f" ({100 * share:.0f} % of the fitted {L}'s torque is)" if share is not None else "")
                + f", so a load and the robot's own {R} explain the same torque; neither is added. To separate them, "
                f"hold the load at three or more poses that turn the hand differently against gravity, or fit the "
                f"robot's {R} on a log without the load first")
        return dict(effect=f"{top['effect']}/{e.name}", joints=[], violations=[], kind="ambiguity", text=text,
                    shared=share)
    return None


def heldout_rms(model: Model, log, config: DiagnoseConfig = DiagnoseConfig()) -> np.ndarray:
    """Per-joint RMS (n,) of the model's residual on held-out blocks (its free effects refitted per fold)."""
    s = model.signals(log)
    y = s.measured() - model.torque(s, [e for e in model.effects if e.name in model.fixed])
    sel = Selection(s, y, blocks_of(s.t, config.block), config)
    for e in model.free:
        sel.extend(e)
    return np.sqrt(sel.sse.sum(axis=0) / len(s))
