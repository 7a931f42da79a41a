"""Where RME's streamed estimates (network prior + VI, Sec. 4) run beside the 1 kHz loop: a thread of this process
(ThreadWorker) or a worker process that owns its own estimator, rebuilt from picklable parts (ProcessWorker). Both
fit RME's executor protocol: submit(RME._estimate, q, tau) -> a future with done() / result() -> (Estimate, Y)."""
from __future__ import annotations

import os
import socket
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from multiprocessing.connection import Connection

import numpy as np

from dynamics import PANDA_XML
from nn_numpy import WEIGHTS
from rme import RMESettings

WORKERS = ("thread", "process")
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))   # the project's modules, for the worker process


@dataclass(frozen=True)
class EstimatorSpec:
    """What a worker process needs to rebuild the loop's estimator: the arm's MJCF path and ee site, the network
    weights (None: zero prior mean), the settings, the seed of its Generator (the VI's sampling) and an optional
    correction model file (diagnosis.effect_model.Model.save). build() gives the RME; same spec, same estimates."""
    xml_path: str = PANDA_XML
    ee: str = "ee"
    weights: str | None = WEIGHTS
    settings: RMESettings = RMESettings()
    seed: int = 0
    correction: str | None = None

    def __post_init__(self):
        for name in ("xml_path", "weights", "correction"):
            path = getattr(self, name)
            if path is not None and not os.path.isfile(path):
                raise ValueError(f"{name}: expected a file, found no file at {path!r}")
        if not isinstance(self.settings, RMESettings):
            raise ValueError(f"settings: expected an RMESettings, found {type(self.settings).__name__}")
        if not isinstance(self.seed, (int, np.integer)) or self.seed < 0:
            raise ValueError(f"seed: expected an integer >= 0, found {self.seed!r}")

    def build(self, executor=None):
        """The RME this spec describes (executor: where its streamed estimates run; None: within update)."""
        from dynamics import Robot
        from rme import RME
        robot = Robot.from_xml(self.xml_path, ee=self.ee)
        correction = None
        if self.correction is not None:
            from diagnosis.effect_model import Model
            correction = Model.load(self.correction, robot)
        return RME(robot, weights=self.weights, settings=self.settings, rng=np.random.default_rng(self.seed),
                   correction=correction, executor=executor)


class ThreadWorker:
    """One worker thread of this process (concurrent.futures); busy() while the last job is not done. The loop keeps
    the GIL between its cycles only as far as sys.setswitchinterval lets it (franka.py sets 0.1 ms)."""

    def __init__(self):
        self._pool, self._last = ThreadPoolExecutor(1), None

    def submit(self, fn, *args):
        self._last = self._pool.submit(fn, *args)
        return self._last

    def busy(self) -> bool:
        return self._last is not None and not self._last.done()

    def shutdown(self):
        self._pool.shutdown(cancel_futures=True)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.shutdown()


class _Job:
    """A job of a ProcessWorker: done() polls the worker's pipe (never waits), result() waits for it."""

    def __init__(self, worker, index):
        self._worker, self._index = worker, index

    def done(self) -> bool:
        return self._worker._collect(self._index, wait=False)

    def result(self):
        self._worker._collect(self._index, wait=True)
        out = self._worker._results.pop(self._index)
        if isinstance(out, BaseException):
            raise out
        return out


class ProcessWorker:
    """A worker process (a fresh interpreter, scheduled below the loop) that owns RME(spec.build()) and runs its _estimate
    on the windows each submit sends: the same (Estimate, Y) as the loop's own estimator with the same spec and the
    same sequence of windows. submit accepts only the bound method RME._estimate (its estimator is the worker's own).
    The constructor waits until the worker is ready (at most `start_timeout` s; ValueError if the spec cannot be
    built there, RuntimeError if it does not answer). shutdown() ends it (killed by its own pid if it hangs)."""

    def __init__(self, spec: EstimatorSpec, nice: int = 19, start_timeout: float = 60.0):
        if not isinstance(spec, EstimatorSpec):
            raise ValueError(f"spec: expected an EstimatorSpec, found {type(spec).__name__}")
        ours, theirs = socket.socketpair()
        code = f"import sys; sys.path.insert(0, {ROOT!r}); from robot.worker import _serve; _serve({theirs.fileno()})"
        self._proc = subprocess.Popen([sys.executable, "-c", code], pass_fds=(theirs.fileno(),))
        theirs.close()
        self._conn = Connection(ours.detach())
        self._sent, self._received, self._results = 0, 0, {}
        try:
            self._conn.send((spec, int(nice)))
            ready = self._conn.recv() if self._conn.poll(start_timeout) else "no answer"
        except (EOFError, OSError) as err:
            ready = f"it ended ({type(err).__name__})"
        if ready != "ready":
            self.shutdown()
            cls = ValueError if ready.startswith("spec") else RuntimeError
            raise cls(f"the estimate worker did not start: {ready}")

    @property
    def pid(self) -> int:
        return self._proc.pid

    def submit(self, fn, *args):
        if getattr(fn, "__name__", None) != "_estimate":
            raise ValueError(f"fn: expected the bound method RME._estimate, found {fn!r}")
        if self._proc.poll() is not None:
            raise RuntimeError(f"the estimate worker has ended (exit status {self._proc.returncode})")
        self._conn.send(("estimate", args))
        self._sent += 1
        return _Job(self, self._sent - 1)

    def busy(self) -> bool:
        self._collect(self._sent - 1, wait=False)
        return self._received < self._sent

    def _collect(self, index, wait):
        """Receive the results that have arrived (all of them up to `index` if wait); True once `index`'s is in."""
        while self._received <= index:
            if not wait and not self._conn.poll():
                return False
            if wait and not self._conn.poll(1.0):
                if self._proc.poll() is not None:
                    self._results[self._received] = RuntimeError("the estimate worker ended during a job")
                    self._received += 1
                continue
            try:
                self._results[self._received] = self._conn.recv()
            except (EOFError, OSError):
                self._results[self._received] = RuntimeError("the estimate worker ended during a job")
            self._received += 1
        return True

    def shutdown(self, timeout: float = 5.0):
        if self._proc.poll() is None:
            try:
                self._conn.send(("stop", ()))
            except OSError:
                pass
            try:
                self._proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self._proc.kill()                      # this worker's own process, by its pid
                self._proc.wait(timeout)
        self._conn.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.shutdown()


def _serve(fd: int):
    """The worker process: receive (spec, nice), build the estimator, say "ready", then answer each ("estimate",
    (q, tau)) with est._estimate(q, tau) until ("stop", ()) or the loop's end of the socket closes."""
    conn = Connection(fd)
    try:
        spec, nice = conn.recv()
        _yield_to_the_loop(nice)
        est = spec.build()
    except (EOFError, OSError):
        return
    except Exception as err:
        conn.send(f"spec: {type(err).__name__}: {err}")
        return
    conn.send("ready")
    while True:
        try:
            kind, args = conn.recv()
        except (EOFError, OSError):
            return
        if kind != "estimate":
            return
        try:
            out = est._estimate(*args)
        except Exception as err:                       # handed to result() in the loop's process
            out = RuntimeError(f"the estimate failed in the worker: {type(err).__name__}: {err}")
        conn.send(out)


def _yield_to_the_loop(nice):
    """Linux SCHED_IDLE (the worker runs only on a core nothing else wants, and never preempts the loop when its
    job arrives), else the niceness `nice`."""
    try:
        os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
    except (AttributeError, OSError):
        os.nice(nice)


def make_worker(kind: str, spec: EstimatorSpec):
    """ThreadWorker() or ProcessWorker(spec) by name ("thread" | "process")."""
    if kind not in WORKERS:
        raise ValueError(f"worker: expected one of {WORKERS}, found {kind!r}")
    return ThreadWorker() if kind == "thread" else ProcessWorker(spec)

