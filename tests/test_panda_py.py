"""franka.py's panda-python backend (a Panda through libfranka 0.9) against the real panda-python package, without a
robot: no simulator speaks its protocol (v5), so the package's own types (RobotState, Duration, Torques) and its
connection refusal are checked, and the hand-off between libfranka's control callback (its own thread) and the
loop is driven by a stand-in for Robot.control that calls the callback once per millisecond as libfranka does.
Each check runs in a process of its own (panda-python bundles its own libfranka) and is bounded in time."""
import importlib.util
import json
import subprocess
import sys

import pytest

from tests.helpers import ROOT

pytestmark = pytest.mark.skipif(importlib.util.find_spec("panda_py") is None,
                                reason="panda-python is not installed (pip install -r requirements-robot.txt)")


def run_python(code: str, timeout: float = 60.0) -> dict:
    """Run code in a fresh interpreter in the repository; it prints one JSON line last."""
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=timeout)
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_the_fields_read_exist_in_panda_pythons_robot_state_and_its_types_behave():
    res = run_python("""
import json
from panda_py import libfranka
t = libfranka.Torques([0.5 * i for i in range(7)])
t.motion_finished = True
print(json.dumps({"fields": [f for f in ("q", "dq", "tau_J", "tau_ext_hat_filtered")
                             if not hasattr(libfranka.RobotState, f)],
                  "dt": libfranka.Duration(1).to_sec(), "tau": list(t.tau_J), "done": t.motion_finished}))
""")
    assert res["fields"] == []                       # the backend reads exactly these (robot.backends._state_of)
    assert res["dt"] == 1e-3 and res["tau"] == [0.5 * i for i in range(7)] and res["done"] is True


def test_panda_py_backend_and_cli_refuse_to_start_without_a_robot():
    """Nothing answers libfranka on 127.0.0.1: the backend says which library found no robot, and franka.py exits
    with 2 without starting a loop."""
    res = run_python("""
import io, json, contextlib
from robot.backends import PandaPyBackend
import franka
try:
    PandaPyBackend("127.0.0.1")
    msg = None
except RuntimeError as err:
    msg = str(err)
err = io.StringIO()
with contextlib.redirect_stderr(err):
    code = franka.main(["--robot-ip", "127.0.0.1", "--lib", "panda-py", "--seconds", "0.1"])
print(json.dumps({"msg": msg, "code": code, "cli": err.getvalue()}))
""")
    assert res["msg"] is not None and res["msg"].startswith("--robot-ip 127.0.0.1: no robot answered through "
                                                            "panda-python (RuntimeError: libfranka"), res
    assert res["code"] == 2 and "not started" in res["cli"] and "panda-python" in res["cli"], res


HAND_OFF = """
import json, sys, time, types
import numpy as np
from panda_py import libfranka
from robot.backends import PandaPyBackend

CYCLES, FAIL, LATE, BY, AFTER = {cycles}, {fail}, {late}, {by}, {after}   # cycles; the one whose callback
                       # raises; every LATE-th read answered BY s late; AFTER s of work after each write (a log)

def state(i):               # the fields the backend reads, marked with the cycle
    return types.SimpleNamespace(q=[i * 1e-3] * 7, dq=[0.0] * 7, tau_J=[float(i)] * 7,
                                 tau_ext_hat_filtered=[-1.0 * i] * 7)

class StandIn:              # panda_py.Panda's get_robot / get_state, libfranka.Robot.control at 1 kHz
    def __init__(self):
        self.out = []
    def get_robot(self):
        return self
    def get_state(self):
        return state(0)
    def control(self, callback):
        t0 = time.perf_counter()
        for i in range(1, CYCLES + 1):
            time.sleep(max(0.0, t0 + i * 1e-3 - time.perf_counter()))   # (libfranka waits in C++, GIL released)
            if i == FAIL:
                raise RuntimeError("libfranka: Move command aborted: motion aborted by reflex!")
            t1 = time.perf_counter()
            t = callback(state(i), libfranka.Duration(1))
            self.out.append((i, list(t.tau_J), t.motion_finished, time.perf_counter() - t1))
            if t.motion_finished:
                return
        raise RuntimeError("the loop never stopped the motion")

sys.setswitchinterval(1e-4)                      # as franka.main sets it
stand = StandIn()
b = PandaPyBackend("stand-in", panda=stand)
read, error, t_end = [], None, time.perf_counter() + 5.0
try:
    for _ in range(CYCLES):
        if time.perf_counter() > t_end:
            break
        s = b.read()
        read.append((round(s.q[0] * 1e3), s.tau_ext_hat_filtered[0], s.duration_s))
        if LATE and len(read) % LATE == 0:
            time.sleep(BY)                       # the loop misses its deadline
        b.write(np.full(7, s.tau_J[0]))          # the command answering cycle i: i Nm on every joint
        if AFTER:
            time.sleep(AFTER)
        if len(read) == 200 and FAIL == 0:
            break
except RuntimeError as err:
    error = str(err)
b.stop()
print(json.dumps({{"read": read, "out": stand.out, "error": error, "alive": b._thread.is_alive(),
                   "dry": PandaPyBackend("stand-in", control=False, panda=stand).read().q[0]}}))
"""


def test_panda_py_callback_hands_each_state_to_the_loop_and_sends_its_command():
    """Each state libfranka passes to the callback reaches read() in order, converted (tau_ext_hat_filtered kept in
    libfranka's sign); the command write() gives back for it is what the callback returns as libfranka.Torques, or,
    when the loop is late (0.9 ms), the last command again; stop() ends the motion (motion_finished) and the thread.
    A loop the OS holds back for over a millisecond (a loaded machine) loses the states that came meanwhile: only
    order, never completeness, is asserted; on a quiet machine none is lost and every command is on time."""
    res = run_python(HAND_OFF.format(cycles=1000, fail=0, late=0, by=0, after=0))
    read, out = res["read"], res["out"]
    assert res["error"] is None and not res["alive"] and len(read) == 200
    cycles = [r[0] for r in read]
    assert cycles == sorted(set(cycles)) and cycles[0] >= 1            # in order, none repeated
    assert all(r[1] == -r[0] and r[2] == 1e-3 for r in read)
    last, on_time, written = 0.0, 0, set(map(float, cycles))
    for i, tau, done, _ in out[:-1]:
        assert not done and tau == [tau[0]] * 7
        assert tau[0] in (float(i), last) or (tau[0] in written and last <= tau[0] < i), (i, tau[0], last)
        on_time += tau[0] == float(i)                                  # its own command, else the last one again
        last = tau[0]                                                  # (or one the loop wrote late)
    assert out[-1][2] is True                                          # stop(): motion_finished on the next cycle
    assert on_time >= 0.5 * (len(out) - 1), on_time                    # the loop answers within 0.9 ms
    waits = sorted(dt for i, tau, _, dt in out[:-1] if tau[0] == i)    # and the callback returns once it has its
    assert waits[len(waits) // 2] < 0.45e-3, waits[len(waits) // 2]   # answer, not at its deadline
    assert res["dry"] == 0.0                                           # control=False: Panda.get_state()


def test_panda_py_control_error_reaches_the_loop():
    """libfranka ends control with an exception (a reflex): the next read() raises it, naming it."""
    res = run_python(HAND_OFF.format(cycles=1000, fail=50, late=0, by=0, after=0))
    assert res["error"] is not None and "panda-python control ended" in res["error"] and "reflex" in res["error"]
    assert 0 < len(res["read"]) <= 49 and res["read"][-1][0] <= 49 and not res["alive"]


def test_panda_py_callback_never_waits_for_a_late_loop():
    """A loop that misses its deadline by 50 ms every 50th state: the callback does not wait for it (0.9 ms), it
    sends the last command again (the late one goes out only if no newer answer replaced it first), and no command
    is ever one the loop did not write, nor older than one already sent. Then the loop answers the newest state, on time again: a command
    for an older state found waiting is not taken for the answer (else it would stay a cycle behind for good)."""
    res = run_python(HAND_OFF.format(cycles=1000, fail=0, late=50, by=0.05, after=0))
    read, out = res["read"], res["out"]
    assert res["error"] is None and not res["alive"] and len(read) == 200
    written = {float(r[0]) for r in read}
    sent = [tau[0] for _, tau, _, _ in out]
    assert set(sent) <= written | {0.0} and sent == sorted(sent)
    assert max(dt for *_, dt in out) < 25e-3                           # never the 50 ms the loop took
    for r in read[49::50]:                                             # the late ones: not sent on their own cycle
        own = [tau[0] for i, tau, _, _ in out if i == r[0]]
        assert own and own[0] < r[0], (r[0], own)
    answered = {r[0] for r in read} - {r[0] for r in read[49::50]}       # the states the loop answered in time:
    after = [tau[0] == i for i, tau, _, _ in out[:-1] if i in answered and i > read[49][0]]   # their own answers
    assert sum(after) >= 0.5 * len(after), (sum(after), len(after))       # went out, after the first late one too


def test_panda_py_loop_answering_a_little_late_once_is_on_time_again_at_once():
    """Every 50th answer comes 1.4 ms late: after the callback's 0.9 ms, before the next state is due; and the loop
    works 0.3 ms after each write (its log) before it reads again. The next callback meets that stale answer; it
    must still wait for the answer to its own state, which the loop gives 0.3 ms later (taking the stale one would
    leave every later command a cycle late, as the loop's answer would then always come after the callback left)."""
    res = run_python(HAND_OFF.format(cycles=1000, fail=0, late=50, by=0.0014, after=3e-4))
    read, out = res["read"], res["out"]
    assert res["error"] is None and not res["alive"] and len(read) == 200
    answered = {r[0] for r in read} - {r[0] for r in read[49::50]}
    after = [tau[0] == i for i, tau, _, _ in out[:-1] if i in answered and i > read[49][0]]
    assert sum(after) >= 0.9 * len(after), (sum(after), len(after))
