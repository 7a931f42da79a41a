"""Findings of the diagnosis: what the data ask for beyond an effect's physical constraints (a negative rotor
inertia, friction or mass, a non-physical rigid payload, gravity of another size than a tilt keeps) and the likely
cause in the nominal model (Eq. 1), as text for the report and as JSON."""
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


def describe(asked: dict, selected: bool) -> str:
    """One sentence for a finding {effect, violations [(label, value)], joints}: what the fit without the effect's
    constraints asked for (on which joints), the likely cause, and what became of the effect."""
    e = asked["effect"]
    what, cause = HINTS.get(e, (f"values of {e} outside its bounds", "check the nominal model and the bounds"))
    viol = asked["violations"]
    per_joint = [(name, j, v) for (name, j), v in ((_joint(lbl), v) for lbl, v in viol) if j is not None]
    if per_joint and len(per_joint) == len(viol):
        where = " on " + ", ".join(f"J{j}" for _, j, _ in per_joint)
        values = f"{per_joint[0][0]} = " + ", ".join(f"{v:.3g}" for _, _, v in per_joint)
    else:
        where = ""
        values = ", ".join(f"{lbl} = {v:.3g}" for lbl, v in viol)
    fate = ("selected with its parameters held to the constraints" if selected else
            "not selected: within its constraints it does not explain enough")
    return f"the data ask for {what}{where} (unconstrained {values}): {cause}; {e} {fate}"


def collect(asked_by_effect: dict, selected: list) -> list:
    """The findings as JSON-ready dicts {effect, text, joints (where the fit without the constraints is significantly
    better), violations [[label, unconstrained value]]}, in the order the effects were last tried."""
    return [dict(effect=e, text=describe(a, e in selected), joints=a["joints"],
                 violations=[[lbl, v] for lbl, v in a["violations"]]) for e, a in asked_by_effect.items()]


def format_findings(findings: list) -> list:
    """Report lines (empty without findings)."""
    return ["  findings:"] + [f"    - {f['text']}" for f in findings] if findings else []
