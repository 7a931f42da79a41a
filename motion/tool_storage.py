"""The storage check of the identification motion's controller (Prop. 4.1's check, for a joint-space spring-damper
about a moving set point): on the ideal plant holding the tool, its weight compensated exactly, S = 1/2 dq^T M dq +
1/2 e^T Kp e never rises by more than the work the set point does on the arm."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import mujoco
import numpy as np

from dynamics import Q_READY, phi_of
from motion.tool_forms import EE_IN_F, Tool
from motion.tool_motion import ExcitationController, MotionSettings, point_mass_inertial


@dataclass(frozen=True)
class StorageCheck:
    """max_rise: the largest rise of S over one 1 ms step beyond the set point's work in it [J] (<= 0 up to rounding
    and the step's discretisation: nothing else feeds energy in); set_point_work: the set point's work over the run,
    dissipated: the dampers' [J]; seconds simulated; passive: max_rise <= tolerance."""
    max_rise: float
    set_point_work: float
    dissipated: float
    seconds: float
    tolerance: float
    passive: bool


def storage_check(tool: Tool, q0=Q_READY, settings: MotionSettings = MotionSettings(), seconds=None,
                  tolerance: float = 1e-6, compensated: Tool | None = None) -> StorageCheck:
    """The motion about q0 on the ideal plant (sim.Plant(), the nominal model) holding `tool` (flange frame F), with
    the weight of `compensated` cancelled instead of the push watch's fit (default `tool` itself: exact, Prop. 4.1's
    premise Delta F_mm = 0; another tool shows what a wrong compensation feeds in). The
    controller's torque (ExcitationController) is
        tau = G + tau_w + [M ddq_d + C dq + tau_f + Kd dq_d] + Kp (q_d - q) - Kd dq,
    tau_f the compensated tool's point mass's inertial torque along the reference (settings.feedforward, as the
    watch's point mass in the motion), the bracket the set point's drive tau_sp, the rest a spring about q_d (stored
    in S) and a damper. With S = 1/2 dq^T M dq + 1/2 (q - q_d)^T Kp (q - q_d) (M: the plant's own, tool included,
    from MuJoCo), over each step k at the set point of step k: rise_k = S(x_k+1) - S(x_k) - (q_k+1 - q_k)^T tau_sp,k;
    moving the set point from q_d,k to q_d,k+1 adds its work on the spring. tolerance [J]: rounding and the 1 ms step (a spring held over a
    step of 0.4 mrad stores 1/2 Kp dq^2 dt^2, 4e-6 J at 50 Nm/rad). seconds: default the whole motion."""
    from sim import Plant                               # the simulator (a heavy import) only when a check runs
    plant = Plant()
    R = EE_IN_F
    plant.set_payload(tool.mass, R.T @ tool.com, R.T @ tool.inertia @ R)
    c = tool if compensated is None else compensated
    robot, theta = plant.robot, np.array([c.mass, *(R.T @ c.com)])
    phi = phi_of(theta)                                 # its point mass's inertial torque fed forward, as the watch's
    ctrl = ExcitationController(robot, q0, dataclasses.replace(settings, compensate=False))
    steps = int(round((ctrl.duration if seconds is None else seconds) * settings.rate))
    kp, kd = ctrl.kp, ctrl.kd
    data, M = mujoco.MjData(plant.model), np.zeros((robot.n, robot.n))

    def S(q, dq, q_d):                                  # storage at the set point q_d [J]
        data.qpos[:] = q
        mujoco.mj_forward(plant.model, data)
        mujoco.mj_fullM(plant.model, data, M)
        e = q - q_d
        return 0.5 * dq @ M @ dq + 0.5 * e @ (kp * e)

    s = plant.reset(q0)
    rise, work, dissipated = -np.inf, 0.0, 0.0
    for k in range(steps):
        i, j = min(k, len(ctrl.q_d) - 1), min(k + 1, len(ctrl.q_d) - 1)
        q, dq = s.q.copy(), s.dq.copy()
        ff = -point_mass_inertial(robot, phi, q, dq, ctrl.ddq_d[i]) if settings.feedforward else 0.0
        tau, _ = ctrl.step(q, dq, -robot.payload_torque(q, theta) + ff)
        tau_sp = robot.inverse_dynamics(q, dq, ctrl.ddq_d[i]) - robot.gravity(q) + kd * ctrl.dq_d[i] + ff
        s = plant.step(tau)
        dq_step = s.q - q
        rise = max(rise, S(s.q, s.dq, ctrl.q_d[i]) - S(q, dq, ctrl.q_d[i]) - dq_step @ tau_sp)
        e0, e1 = s.q - ctrl.q_d[i], s.q - ctrl.q_d[j]
        work += dq_step @ tau_sp + 0.5 * (e1 @ (kp * e1) - e0 @ (kp * e0))
        dissipated += dq_step @ (kd * dq)
    return StorageCheck(float(rise), float(work), float(dissipated), steps / settings.rate, tolerance,
                        bool(rise <= tolerance))
