"""Findings of the diagnosis: what the data ask for beyond an effect's physical and plausible bounds (a negative
rotor inertia, friction or mass, a CoM far from the hand, offsets larger than a sensor drifts, a non-physical rigid
payload) and the likely cause in the nominal model (Eq. 1), as text for the report and as JSON."""
from __future__ import annotations

import re

# effect -> (what a violation of its constraints means, where the cause likely is)
HINTS = {
    "rotor": ("negative rotor inertia", "the nominal link inertias may be too large; try scaling `motion`"),
    "viscous": ("negative viscous friction", "friction cannot drive a joint: the nominal model may already hold "
                "friction, or its motion terms may be off; try scaling `motion`"),
    "coulomb": ("negative Coulomb friction", "friction cannot drive a joint: the nominal model may already hold "
                "friction; check the sign of the logged torques"),
    "sigmoid": ("negative sigmoid friction", "friction cannot drive a joint: the nominal model may already hold "
                "friction; check the sign of the logged torques"),
    "payload": ("a negative payload mass", "the nominal masses of the wrist or hand may be too large; try scaling "
                "`gravity`"),
    "offset": ("offsets larger than the robot's static error at a pose reaches", "a static torque this large "
               "is a load or an error of the nominal model, not a sensor offset"),
    "rigid_payload": ("a non-physical rigid payload", "the nominal inertias of the wrist or hand may be off; try "
                      "scaling `motion`, or the static `payload`"),
    "tilt": ("gravity of another size, which no tilt makes", "the nominal link masses may be off; try scaling "
             "`gravity`"),
    "gravity": ("a negative gravity scale", "check the sign of the logged torques"),
    "motion": ("a negative motion scale", "check the sign of the logged torques and of ddq"),
}


def _joint(label: str):
    m = re.fullmatch(r"(.+) J(\d+)", label)
    return (m.group(1), int(m.group(2))) if m else (label, None)


# violation labels that say more than "beyond its bounds": label -> (phrase with {v}, cause)
BEYOND = {
    "|r| [m]": ("a load whose CoM is {v:.3g} m from the hand, beyond the 0.3 m a held load reaches",
                "the torque is not a load's weight at the hand (an offset, a model error, a force on the arm)"),
    "m": ("a load of {v:.3g} kg, beyond the 4 kg bound (rated 3 kg)", "the torque is more than a load at the hand"),
}


def _support(cause: str, supported, excitation: str) -> str:
    """The cause's advice, without advice to scale an effect the log cannot identify."""
    for name in ("motion", "gravity"):
        tip = f"try scaling `{name}`"
        if tip in cause and supported is not None and name not in supported:
            cause = cause.replace(tip, f"this log cannot identify a scaled `{name}` ({excitation})")
    return cause


def describe(asked: dict, selected: bool, supported=None, excitation: str = "", effect=None, n: int = 7) -> str:
    """One sentence for a finding {effect, violations [(label, value)], joints}: what the fit without the effect's
    constraints asked for (on which joints), the likely cause, and what became of the effect. supported: the effects
    the log could identify (advice to scale another is left out). effect: the Effect (of n joints), whose bounds and
    their source are said beside per-joint values."""
    e = asked["effect"]
    viol = asked["violations"]
    negative = any(lbl == "m" and v < 0 for lbl, v in viol)                   # a negative mass says the most
    special = [] if negative else [(lbl, v) for lbl, v in viol if lbl in BEYOND and (lbl != "m" or v > 0)]
    if special:
        lbl, v = special[0]
        what, cause = BEYOND[lbl][0].format(v=v), BEYOND[lbl][1]
        rest = [(k, x) for k, x in viol if k != lbl]
        values = ", ".join(f"{k} = {x:.3g}" for k, x in rest)
        where = f" (and {values})" if values else ""
    else:
        what, cause = HINTS.get(e, (f"values of {e} outside its bounds", "check the nominal model and the bounds"))
        per_joint = [(name, j, v) for (name, j), v in ((_joint(lbl), v) for lbl, v in viol) if j is not None]
        if per_joint and len(per_joint) == len(viol):
            values = f"{per_joint[0][0]} = " + ", ".join(f"{v:.3g}" for _, _, v in per_joint)
            where = " on " + ", ".join(f"J{j}" for _, j, _ in per_joint) + f" (unconstrained {values}"
            if effect is not None and effect.source:
                lo, hi = (b.reshape(-1, n)[0] for b in effect.bounds(n))   # the first parameter's, per joint
                edges = [lo[j - 1] if v < lo[j - 1] else hi[j - 1] for _, j, v in per_joint]
                where += "; bounds " + ", ".join(f"{x:.3g}" for x in edges) + f" ({effect.source})"
            where += ")"
        else:
            where = " (unconstrained " + ", ".join(f"{lbl} = {v:.3g}" for lbl, v in viol) + ")"
    fate = "selected with its parameters held to the bounds" if selected else "not selected"
    return f"the data ask for {what}{where}: {_support(cause, supported, excitation)}; {e} {fate}"


def collect(asked_by_effect: dict, selected: list, supported=None, excitation: str = "", effects=None,
            n: int = 7) -> list:
    """The findings as JSON-ready dicts {effect, kind, text, joints (where the fit without the constraints is
    significantly better), violations [[label, unconstrained value]], source (of the bounds)}, in the order the
    effects were last tried; effects: name -> Effect (n joints), for the bounds and their source."""
    effects = effects or {}
    return [dict(effect=e, kind="beyond bounds", joints=a["joints"],
                 violations=[[lbl, v] for lbl, v in a["violations"]],
                 text=describe(a, e in selected, supported, excitation, effects.get(e), n),
                 source=getattr(effects.get(e), "source", ""))
            for e, a in asked_by_effect.items()]


def format_findings(findings: list) -> list:
    """Report lines (empty without findings)."""
    return ["  findings:"] + [f"    - {f['text']}" for f in findings] if findings else []
