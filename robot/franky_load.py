"""franky-sim (a simulated Franka FCI server on MuJoCo) with a load that can be added to the simulated hand while a
client runs (`python -m robot.franky_load --mass 1 --com 0.03 -0.02 0.05`; SIGUSR1 adds it at the next 1 ms tick), or a
tool fused into the hand from the start (`--tool M CX CY CZ` and its inertia); the physics only, not the server's model."""
from __future__ import annotations

import argparse
import contextlib
import copy
import gc
import os
import signal
import subprocess
import sys
import threading
import time

import mujoco
import numpy as np


SETTLE_TICKS = 1000     # 1 ms ticks after the tool is fused before a client is let in: the server's own hold (kp/kv
#                         = 10 /s on every joint, franky-sim's MuJoCo gains) has the arm at rest again within 1 s


def add_point_mass(model: mujoco.MjModel, body: int, m: float, r, inertia=None) -> None:
    """Fuse a point mass m [kg] at r (3,) [m] (body frame), or a body of that mass and CoM with `inertia` (3, 3)
    [kg m^2] about its CoM (body frame), into the body's inertial: new mass, CoM and inertia about the new CoM
    (parallel-axis theorem), principal axes in body_iquat; then mj_setConst for the derived values (on a scratch
    MjData: it moves its data to qpos0)."""
    m0, c0 = float(model.body_mass[body]), model.body_ipos[body].copy()
    R0 = np.empty(9)
    mujoco.mju_quat2Mat(R0, model.body_iquat[body])
    R0 = R0.reshape(3, 3)
    I0 = R0 @ np.diag(model.body_inertia[body]) @ R0.T      # about c0, body frame
    m1 = m0 + m
    c1 = (m0 * c0 + m * np.asarray(r, float)) / m1
    shift = lambda mass, d: mass * (d @ d * np.eye(3) - np.outer(d, d))
    I1 = I0 + shift(m0, c0 - c1) + shift(m, np.asarray(r, float) - c1) + (0.0 if inertia is None else
                                                                          np.asarray(inertia, float))
    w, V = np.linalg.eigh(I1)
    if np.linalg.det(V) < 0:
        V[:, 0] = -V[:, 0]
    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, V.ravel())
    model.body_mass[body], model.body_ipos[body], model.body_inertia[body], model.body_iquat[body] = m1, c1, w, quat
    mujoco.mj_setConst(model, mujoco.MjData(model))


def prepared_load(model: mujoco.MjModel, body: int, m: float, r, inertia=None):
    """What add_point_mass changes, worked out on a copy of the model: [(field, values)] of the arrays that differ
    and the copy's statistics. apply_load then makes the change within one 1 ms tick (12 us), while working it out
    takes 1.5-2 ms (a fresh MjData and mj_setConst), which stalls the simulated robot's clock."""
    loaded = copy.deepcopy(model)
    add_point_mass(loaded, body, m, r, inertia)
    arrays = [f for f in dir(model) if not f.startswith("_") and isinstance(getattr(model, f, None), np.ndarray)]
    changed = [(f, getattr(loaded, f).copy()) for f in arrays
               if getattr(loaded, f).shape == getattr(model, f).shape and not np.array_equal(getattr(loaded, f),
                                                                                          getattr(model, f))]
    stat = {k: copy.copy(getattr(loaded.stat, k)) for k in ("meaninertia", "meanmass", "meansize", "extent", "center")}
    return changed, stat


def apply_load(model: mujoco.MjModel, prepared) -> None:
    """Write what prepared_load worked out into the model."""
    changed, stat = prepared
    for f, values in changed:
        getattr(model, f)[...] = values
    for k, v in stat.items():
        setattr(model.stat, k, v)


def _frictionless(sim):
    """Before the first step (the model exists once the server started the simulation): no joint friction."""
    if sim.model.dof_frictionloss.any():
        sim.model.dof_frictionloss[:] = 0.0


class _LoadAt:
    """A backend that asks the server (SIGUSR1, by its pid) to add its load when the loop reads tick `at`."""

    def __init__(self, inner, server, at):
        self.inner, self.server, self.at, self.k, self.initial = inner, server, at, 0, inner.initial

    def read(self):
        self.k += 1
        if self.k == self.at:
            os.kill(self.server.pid, signal.SIGUSR1)
        return self.inner.read()

    def write(self, cmd):
        self.inner.write(cmd)

    def stop(self):
        self.inner.stop()


def run_client(seconds: float = 5.0, at: int = 1500, mass: float = 1.0, com=(0.03, -0.02, 0.05), seed: int = 4,
               hostname: str = "127.0.0.1", start_timeout: float = 60.0, realtime: bool = False):
    """The bridge's loop (robot.loop.run_loop: CPIC hold, RME with its estimates in a worker process) through
    pylibfranka against this module's server, started frictionless on `hostname` in its own process and stopped by
    its own pid at the end; the server adds `mass` at `com` to the hand when the loop reads tick `at`. realtime: the
    loop's thread at SCHED_FIFO when permitted (realtime_priority; the server and the worker keep their own), as
    libfranka runs it on a robot, on a CPU the server and the worker keep off (own_cpu); summary["realtime"] says
    whether it was at SCHED_FIFO. Returns run_loop's (summary, log) and the estimator. Needs pylibfranka and
    franky-sim (requirements-robot.txt)."""
    from dynamics import Robot
    from robot.backends import FrankySimBackend
    from robot.loop import make_controller, own_cpu, realtime_priority, run_loop
    from robot.worker import EstimatorSpec, ProcessWorker
    spec, robot = EstimatorSpec(seed=seed), Robot.panda()
    with ProcessWorker(spec) as worker, _server(["--mass", str(mass), "--com", *map(str, com)], hostname,
                                                seconds * 10 + start_timeout, start_timeout) as server:
        backend = FrankySimBackend(hostname, realtime=False)
        est = spec.build(executor=worker)
        with realtime_priority() if realtime else contextlib.nullcontext(False) as fifo, \
                own_cpu([worker.pid, server.pid]) if realtime else contextlib.nullcontext():
            summary, log = run_loop(_LoadAt(backend, server, at), robot,
                                    make_controller(robot, backend.initial.q, "hold"), est, seconds)
        summary["realtime"] = fifo
    return summary, log, est


@contextlib.contextmanager
def _server(options, hostname: str, max_seconds: float, start_timeout: float,
            ready_line: str = "Connect to the server"):
    """This module's server (frictionless, `options` added) on `hostname` in its own process, until it prints
    `ready_line` (clients may connect; with a tool: the arm has come to rest holding it) (RuntimeError if not within
    start_timeout or 200 lines); stopped by its own pid on leaving."""
    server = subprocess.Popen([sys.executable, "-m", "robot.franky_load", "--hostname", hostname, *options,
                               "--frictionless", "--max-seconds", str(max_seconds)],
                              cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        t0, ready = time.monotonic(), False
        for _ in range(200):                                  # bounded: 200 lines or start_timeout
            line = server.stdout.readline()
            if ready_line in line:
                ready = True
                break
            if not line or time.monotonic() - t0 > start_timeout:
                break
        if not ready:
            raise RuntimeError("franky-sim did not start")
        yield server
    finally:
        server.terminate()                                    # the server's own process
        try:
            server.wait(timeout=10)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait(timeout=10)


def identify_client(tool=None, seconds=None, hostname: str = "127.0.0.1", start_timeout: float = 60.0,
                    center=None):
    """The tool identification's motion (robot.identify.run_motion, about `center`: the reference run's start)
    through pylibfranka against this module's server, started frictionless with the Tool `tool` (flange frame F,
    motion.tool_forms) fused into the simulated hand (none: the flange as it is, the reference run). Returns
    run_motion's (log, summary, controller) and the server's own joint limits (7, 2) [rad] (franky-sim simulates an
    FR3, whose limits are not the Panda's)."""
    from dynamics import Robot
    from motion.tool_forms import EE_IN_F
    from robot.backends import FrankySimBackend
    from robot.identify import run_motion
    from robot.loop import run_loop
    options = []
    if tool is not None:                                     # the hand's frame is F turned -45 deg about z: ee
        R = EE_IN_F
        I = R.T @ tool.inertia @ R
        options = ["--tool", str(tool.mass), *map(str, R.T @ tool.com), *map(str, I[np.triu_indices(3)])]
    robot = Robot.panda()
    ready = "Connect to the server" if tool is None else "tool settled"     # with a tool: the arm at rest holding it
    with _server(options, hostname, 600.0, start_timeout, ready):
        backend = FrankySimBackend(hostname, realtime=False)
        limits = backend.joint_limits()
        log, summary, controller = run_motion(backend, robot, run_loop, seconds=seconds, center=center)
    return log, summary, controller, limits


def _prepare(model, hand, tool, args, fused, ready):
    """Beside the ticks: the tool's change (into fused) and the load's, on the model with the tool (into ready)."""
    if tool is not None:
        change = prepared_load(model, hand, tool.mass, tool.com, tool.inertia)
        model = copy.deepcopy(model)
        apply_load(model, change)
        fused.append(change)
    ready.append(prepared_load(model, hand, args.mass, args.com))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hostname", default="127.0.0.1")
    ap.add_argument("--mass", type=float, default=1.0, help="kg added to the hand on SIGUSR1")
    ap.add_argument("--com", type=float, nargs=3, default=(0.03, -0.02, 0.05), help="m, in the hand frame")
    ap.add_argument("--frictionless", action="store_true",
                    help="no joint friction (franky-sim's joints have frictionloss 1.1 Nm, which at rest holds up "
                         "to that much of a load's torque: about 0.2 kg of 1 kg at the ready pose)")
    ap.add_argument("--tool", type=float, nargs=10, default=None,
                    metavar=("M", "CX", "CY", "CZ", "IXX", "IXY", "IXZ", "IYY", "IYZ", "IZZ"),
                    help="a tool fused into the hand from the first ticks: kg, its CoM [m] and its inertia about the "
                         "CoM [kg m^2] (upper triangle), in the hand's frame")
    ap.add_argument("--max-seconds", type=float, default=120.0, help="the server stops by itself after this")
    args = ap.parse_args(argv)
    if not (np.isfinite(args.mass) and 0 < args.mass <= 3):
        raise ValueError(f"--mass: expected 0..3 kg, found {args.mass!r}")
    tool = None
    if args.tool is not None:
        from motion.tool_forms import make_tool
        I = np.zeros((3, 3))
        I[np.triu_indices(3)] = args.tool[4:]
        tool = make_tool(args.tool[0], args.tool[1:4], I + np.triu(I, 1).T, "--tool")   # checked: physical
    import franky_sim
    from franky_sim.mujoco_simulator import MujocoSimulator
    asked, ticks, ready, fused, fused_at = [False], [0], [], [], [-SETTLE_TICKS - 1]
    signal.signal(signal.SIGUSR1, lambda *_: asked.__setitem__(0, True))
    with MujocoSimulator() as sim:
        sim.add_robot()
        if args.frictionless:
            sim.register_pre_step_callback(_frictionless)

        def tick(s):
            ticks[0] += 1
            if ticks[0] == 1:                 # worked out once, beside the ticks (MuJoCo's calls release the GIL)
                gc.freeze()                   # and the server's heap as it is now is never walked again by a
                #                               collection between two ticks (a full one took milliseconds)
                hand = mujoco.mj_name2id(s.model, mujoco.mjtObj.mjOBJ_BODY, "robot0_hand")
                threading.Thread(target=_prepare, args=(s.model, hand, tool, args, fused, ready), daemon=True).start()
            if fused and fused[0] is not None:
                apply_load(s.model, fused[0])
                print(f"tool fused: {args.tool} (hand frame), tick {ticks[0]}", flush=True)
                fused[0], fused_at[0] = None, ticks[0]
            if ticks[0] == fused_at[0] + SETTLE_TICKS:
                print(f"tool settled: the arm held it for {SETTLE_TICKS} ticks, tick {ticks[0]}", flush=True)
            if asked[0] and ready:
                asked[0] = False
                apply_load(s.model, ready[0])
                print(f"load added: {args.mass} kg at {list(args.com)} m, tick {ticks[0]}", flush=True)
            if ticks[0] >= args.max_seconds * 1000:
                server.running = False
        sim.register_pre_step_callback(tick)
        with franky_sim.SimulationServer(sim, hostname_candidates=[args.hostname]) as server:
            print(f"Connect to the server using '{args.hostname}'", flush=True)
            server.run_forever()
    return 0


if __name__ == "__main__":
    sys.exit(main())
