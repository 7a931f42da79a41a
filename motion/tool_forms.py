"""The tool on the flange as a rigid body (mass, CoM, inertia about the CoM, in libfranka's flange frame F) and the
forms users type it in: Desk's end-effector settings, libfranka's setLoad, franka_ros2's SetLoad; tool.json; the
project's pi (ee frame = F rotated -45 deg about z, README Conventions)."""
from __future__ import annotations

import json
import math
from dataclasses import dataclass

import numpy as np

from motion.inertia import inertia_of, rigid_body

EE_IN_F = np.array([[math.cos(-math.pi / 4), -math.sin(-math.pi / 4), 0.0],      # R_F_ee (3, 3): the ee frame's
                    [math.sin(-math.pi / 4), math.cos(-math.pi / 4), 0.0],       #   axes in F (panda.xml's ee site:
                    [0.0, 0.0, 1.0]])                                            #   axisangle 0 0 1 -45 deg)
MAX_COM = 0.5          # m: a CoM farther from the flange is no tool the Panda carries (its reach is 0.855 m)
MAX_MASS = 5.0         # kg: above the Panda's 3 kg payload with margin (datasheet); more is refused as input


@dataclass(frozen=True)
class Tool:
    """A rigid tool: mass [kg], com (3,) [m] from the flange origin and inertia (3, 3) [kg m^2] about the CoM,
    both in the flange frame F. Built by make_tool (checked)."""
    mass: float
    com: np.ndarray
    inertia: np.ndarray

    def as_dict(self) -> dict:
        return {"mass": float(self.mass), "com": self.com.tolist(), "inertia": self.inertia.tolist()}


def make_tool(mass, com, inertia, name: str = "tool") -> Tool:
    """A checked Tool: ValueError naming `name`.field, what was found and what was expected."""
    try:
        m, c, I = float(mass), np.asarray(com, dtype=float), np.asarray(inertia, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected numbers for mass, com (3,), inertia (3, 3), found {mass!r}, {com!r}, "
                         f"{inertia!r}") from None
    if not (math.isfinite(m) and 0.0 <= m <= MAX_MASS):
        raise ValueError(f"{name}.mass: expected a mass in [0, {MAX_MASS}] kg, found {m!r}")
    if c.shape != (3,) or not np.all(np.isfinite(c)) or np.linalg.norm(c) > MAX_COM:
        raise ValueError(f"{name}.com: expected a finite (3,) CoM within {MAX_COM} m of the flange, found {c.tolist()}")
    if I.shape != (3, 3) or not np.all(np.isfinite(I)) or not np.allclose(I, I.T, atol=1e-12):
        raise ValueError(f"{name}.inertia: expected a finite symmetric (3, 3) in kg m^2, found {I.tolist()}")
    w = np.linalg.eigvalsh(I)
    tol = 1e-9 * max(abs(w).max(), 1e-12)
    if w.min() < -tol or w.sum() - 2 * w.max() < -tol:
        raise ValueError(f"{name}.inertia: expected a physical inertia (principal moments >= 0 and each at most the "
                         f"sum of the other two), found principal moments {w.tolist()}")
    return Tool(m, c, 0.5 * (I + I.T))


# --- the project's pi (ee frame, inertia about the ee origin) --------------------------------------------------
def params_of_tool(tool: Tool) -> np.ndarray:
    """pi (10,) = (m, m c, Ixx, Ixy, Iyy, Ixz, Iyz, Izz) in the ee frame about its origin (= the flange origin):
    c_ee = R^T c_F, I_ee = R^T I_F R with R = EE_IN_F, then Steiner (motion.inertia.rigid_body)."""
    R = EE_IN_F
    return rigid_body(tool.mass, R.T @ tool.com, R.T @ tool.inertia @ R)


def tool_of_params(pi) -> Tool:
    """The Tool of a physical pi (10,) (ee frame): c = h / m, I_c = I_o - m (|c|^2 E - c c^T), rotated to F.
    A pi of mass <= 0 gives a zero tool (no CoM can be formed)."""
    pi = np.asarray(pi, dtype=float)
    m = float(pi[0])
    if m <= 0:
        return Tool(0.0, np.zeros(3), np.zeros((3, 3)))
    c = pi[1:4] / m
    Ic = inertia_of(pi) - m * ((c @ c) * np.eye(3) - np.outer(c, c))
    R = EE_IN_F
    return Tool(m, R @ c, R @ Ic @ R.T)


def phi_of_tool(tool: Tool) -> np.ndarray:
    """phi (4,) = (m, m c_ee): what the tool's weight adds to tau_ext through robot.payload_regressor."""
    return params_of_tool(tool)[:4]


# --- the forms users type in --------------------------------------------------------------------------------
def desk(tool: Tool) -> dict:
    """Desk's end-effector settings (Settings > End effector): mass [kg], centre of mass [m] in the flange frame,
    inertia tensor [kg m^2] about the CoM in the flange frame (Franka's Desk manual). Use this or set_load, not both."""
    I = tool.inertia
    return {"frame": "flange F (libfranka), origin on the flange, inertia about the CoM",
            "mass": round(float(tool.mass), 4), "center_of_mass": [round(float(v), 5) for v in tool.com],
            "inertia": {k: round(float(I[i, j]), 6) for k, (i, j) in
                        (("Ixx", (0, 0)), ("Iyy", (1, 1)), ("Izz", (2, 2)), ("Ixy", (0, 1)), ("Ixz", (0, 2)),
                         ("Iyz", (1, 2)))}}


def set_load(tool: Tool) -> dict:
    """libfranka Robot::setLoad(load_mass, F_x_Cload, load_inertia): F_x_Cload the flange-to-CoM translation in F
    [m], load_inertia the inertia about the CoM [kg m^2], 9 values column-major (libfranka's robot.h). It adds to
    what Desk has; it is refused while a controller runs."""
    col = tool.inertia.ravel(order="F")
    return {"frame": "flange F", "load_mass": float(tool.mass), "F_x_Cload": tool.com.tolist(),
            "load_inertia": col.tolist(),
            "call": f"robot.setLoad({tool.mass:.4f}, {{{', '.join(f'{v:.5f}' for v in tool.com)}}}, "
                    f"{{{', '.join(f'{v:.6g}' for v in col)}}});"}


def ros2_set_load(tool: Tool) -> dict:
    """franka_ros2's franka_msgs/srv/SetLoad request: mass [kg], center_of_mass (3,) [m] in F, load_inertia (9,)
    column-major [kg m^2] about the CoM (franka_msgs SetLoad.srv), and the `ros2 service call` that sends it."""
    col = tool.inertia.ravel(order="F")
    body = (f"{{mass: {tool.mass:.4f}, center_of_mass: [{', '.join(f'{v:.5f}' for v in tool.com)}], "
            f"load_inertia: [{', '.join(f'{v:.6g}' for v in col)}]}}")
    return {"frame": "flange F", "mass": float(tool.mass), "center_of_mass": tool.com.tolist(),
            "load_inertia": col.tolist(),
            "command": f"ros2 service call /service_server/set_load franka_msgs/srv/SetLoad \"{body}\""}


def tool_of_desk(d: dict) -> Tool:
    I = d["inertia"]
    M = [[I["Ixx"], I["Ixy"], I["Ixz"]], [I["Ixy"], I["Iyy"], I["Iyz"]], [I["Ixz"], I["Iyz"], I["Izz"]]]
    return make_tool(d["mass"], d["center_of_mass"], M, "desk")


def tool_of_set_load(d: dict) -> Tool:
    return make_tool(d["load_mass"], d["F_x_Cload"], np.reshape(d["load_inertia"], (3, 3), order="F"), "set_load")


def tool_of_ros2(d: dict) -> Tool:
    return make_tool(d["mass"], d["center_of_mass"], np.reshape(d["load_inertia"], (3, 3), order="F"), "ros2")


def forms(tool: Tool) -> dict:
    """Every form at once: mass, com, inertia (F) beside desk, libfranka_set_load and franka_ros2_set_load."""
    return {**tool.as_dict(), "frame": "flange F (libfranka); the project's ee frame is F rotated -45 deg about z",
            "desk": desk(tool), "libfranka_set_load": set_load(tool), "franka_ros2_set_load": ros2_set_load(tool)}


# --- tool.json ------------------------------------------------------------------------------------------------
def save_tool(path, tool: Tool, extra: dict | None = None) -> None:
    """Write tool.json: forms(tool) and, under "identification", what the fit reported (extra)."""
    with open(path, "w") as f:
        json.dump({**forms(tool), **({"identification": extra} if extra else {})}, f, indent=1)


def load_tool(source) -> Tool:
    """A Tool from a tool.json path, a dict with mass, com, inertia (F), or a Tool (checked); ValueError otherwise."""
    if isinstance(source, Tool):
        return make_tool(source.mass, source.com, source.inertia)
    if isinstance(source, dict):
        missing = [k for k in ("mass", "com", "inertia") if k not in source]
        if missing:
            raise ValueError(f"tool: expected the keys mass, com, inertia (flange frame F), missing {missing}")
        return make_tool(source["mass"], source["com"], source["inertia"])
    if not isinstance(source, (str, bytes)) and not hasattr(source, "__fspath__"):
        raise ValueError(f"tool: expected a Tool, a dict or a tool.json path, found {type(source).__name__}")
    try:
        with open(source) as f:
            d = json.load(f)
    except (OSError, json.JSONDecodeError) as err:
        raise ValueError(f"tool: could not read {source!r} as tool.json: {type(err).__name__}: {err}") from None
    if not isinstance(d, dict):
        raise ValueError(f"tool: expected a JSON object in {source!r}, found {type(d).__name__}")
    return load_tool(d)
