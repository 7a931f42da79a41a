"""Where RME's streamed estimates (network prior + VI, Sec. 4) run beside the 1 kHz loop: a thread of this process
(ThreadWorker) or a worker process that owns its own estimator, rebuilt from picklable parts (ProcessWorker). Both
fit RME's executor protocol: submit(RME._estimate, q, tau) -> a future with done() / result() -> Estimate."""
from __future__ import annotations

import mmap
import os
import pickle
import select
import socket
import struct
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from multiprocessing.connection import Connection

import numpy as np

import checks
from dynamics import PANDA_XML
from nn_numpy import WEIGHTS
from rme import Estimate, RMESettings

WORKERS = ("thread", "process")
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))   # the project's modules, for the worker process


@dataclass(frozen=True)
class EstimatorSpec:
    """What a worker process needs to rebuild the loop's estimator: the arm's MJCF path and ee site, the network
    weights (None: zero prior mean), the settings, the seed of its Generator (the VI's sampling), an optional
    correction model file (diagnosis.effect_model.Model.save), error-model file (`rme.py calibrate --save`) and
    tool.json. build() gives the RME; same spec, same estimates."""
    xml_path: str = PANDA_XML
    ee: str = "ee"
    weights: str | None = WEIGHTS
    settings: RMESettings = RMESettings()
    seed: int = 0
    correction: str | None = None
    calibration: str | None = None
    tool: str | None = None            # a tool.json (motion.tool_forms): the known tool on the flange

    def __post_init__(self):
        for name in ("xml_path", "weights", "correction", "calibration", "tool"):
            path = getattr(self, name)
            if path is not None and not (isinstance(path, (str, os.PathLike)) and os.path.isfile(path)):
                raise ValueError(f"{name}: expected a file, found no file at {path!r}")
        checks.instance("settings", self.settings, RMESettings)
        checks.number("seed", self.seed, "0..18446744073709551615")          # (any 64-bit seed)
        if not isinstance(self.ee, str):
            raise ValueError(f"ee: expected the name of a site (text), found {self.ee!r}")

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
                   correction=correction, executor=executor, calibration=self.calibration, tool=self.tool)


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
    """A job of a ProcessWorker: done() polls the worker's pipe (never waits; with the worker's `collect_in_done`
    False, only reports what busy() has received), result() waits for it."""

    def __init__(self, worker, index):
        self._worker, self._index = worker, index

    def done(self) -> bool:
        w = self._worker
        return w._collect(self._index, wait=False) if w.collect_in_done else w._received > self._index

    def result(self):
        self._worker._collect(self._index, wait=True)
        out = self._worker._results.pop(self._index)
        if isinstance(out, BaseException):
            raise out
        return out


class ProcessWorker:
    """A worker process (a fresh interpreter, scheduled below the loop) that owns RME(spec.build()) and runs its _estimate
    on the windows each submit sends: the same Estimate as the loop's own estimator with the same spec and the
    same sequence of windows. submit accepts only the bound method RME._estimate (its estimator is the worker's own).
    The constructor waits until the worker is ready (at most `start_timeout` s; ValueError if the spec cannot be
    built there, RuntimeError if it does not answer). shutdown() ends it (killed by its own pid if it hangs).
    The arrays of a job and of its result travel through shared memory (_Boxes); the socket carries the rest.
    prepare and submit only queue their copy and send; flush() does them, and busy(), done() and result() flush
    first: a loop that calls busy() after writing its command keeps both off its state-to-command path."""

    def __init__(self, spec: EstimatorSpec, nice: int = 19, start_timeout: float = 60.0):
        if not isinstance(spec, EstimatorSpec):
            raise ValueError(f"spec: expected an EstimatorSpec, found {type(spec).__name__}")
        ours, theirs = socket.socketpair()
        self._boxes = _Boxes()
        code = (f"import sys; sys.path.insert(0, {ROOT!r}); from robot.worker import _serve; "
                f"_serve({theirs.fileno()}, {self._boxes.fd})")
        one = {k: "1" for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}   # no BLAS threads: they
        # would keep the normal priority (SCHED_IDLE is set per thread) and spin beside the loop after each product
        self._proc = subprocess.Popen([sys.executable, "-c", code], pass_fds=(theirs.fileno(), self._boxes.fd),
                                      env={**os.environ, **one})
        theirs.close()
        self._conn = Connection(ours.detach())
        self._arrived = _poller(self._conn)
        self._sent, self._received, self._results, self._prepared, self._outbox = 0, 0, {}, None, []
        self._flushed, self._unsent = 0, {}            # jobs sent so far; {index: error} of jobs that could not be
        self.collect_in_done = True                    # False: a loop receives results in its busy() after its write
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

    def prepare(self, *args):
        """Copy a job's arrays into shared memory ahead of submit(fn, *args) with the very same arrays (a loop can
        spread the two over cycles); ignored while a job is out (submit then pickles). The copy is made by the next
        flush (busy, done, result), like a submit's send."""
        if self._received == self._sent:
            self._prepared = [args, None]
            self._outbox.append(("copy", self._prepared))

    def submit(self, fn, *args):
        """Queue the job; it is sent by the next flush: busy() (which robot.loop.run_loop calls after writing each
        command, so the send is off the state-to-command path), or done() / result() of any job."""
        if getattr(fn, "__name__", None) != "_estimate":
            raise ValueError(f"fn: expected the bound method RME._estimate, found {fn!r}")
        shared = self._received == self._sent          # no job out: both boxes are free for this one
        ready, self._prepared = self._prepared, None
        same = ready is not None and len(ready[0]) == len(args) and all(a is b for a, b in zip(ready[0], args))
        self._outbox.append(("send", (args, shared, ready if same else None)))
        self._sent += 1
        return _Job(self, self._sent - 1)

    def flush(self):
        """Make the copies and send the jobs queued by prepare and submit, in order. A job that cannot be sent gets
        the error as its result (its result() raises it; later jobs are unaffected), and the error is raised here."""
        while self._outbox:
            kind, item = self._outbox.pop(0)
            if kind == "copy":
                item[1] = _put(self._boxes.jobs, item[0])
                continue
            (args, shared, ready), index = item, self._flushed
            self._flushed += 1
            try:                                       # b"W": the windows are in the box; else all pickled
                head = (ready[1] if ready is not None and ready[1] is not None else _put(self._boxes.jobs, args)) \
                    if shared else None
                self._conn.send_bytes(b"W" + head) if head is not None else self._conn.send(("estimate", args, shared))
            except Exception as err:
                why = (f"the estimate worker has ended (exit status {self._proc.poll()})"
                       if isinstance(err, OSError) else f"the job could not be sent: {type(err).__name__}: {err}")
                self._unsent[index] = RuntimeError(why)
                raise self._unsent[index] from None

    def busy(self) -> bool:
        self._collect(self._sent - 1, wait=False)
        return self._received < self._sent

    def _collect(self, index, wait):
        """Send what is queued, then receive the results that have arrived (all of them up to `index` if wait);
        True once `index`'s is in."""
        if self._outbox:
            self.flush()
        while self._received <= index:
            if self._received in self._unsent:        # never sent: nothing will arrive for it
                self._results[self._received] = self._unsent.pop(self._received)
                self._received += 1
                continue
            if not wait and not self._arrived():
                return False
            if wait and not self._conn.poll(1.0):
                if self._proc.poll() is not None:
                    self._results[self._received] = RuntimeError("the estimate worker ended during a job")
                    self._received += 1
                continue
            try:
                self._results[self._received] = _result(self._conn.recv_bytes(), self._boxes.results)
            except (EOFError, OSError):
                self._results[self._received] = RuntimeError("the estimate worker ended during a job")
            self._received += 1
        return True

    def shutdown(self, timeout: float = 5.0):
        if self._proc.poll() is None:
            try:
                self._conn.send(("stop", (), False))
            except OSError:
                pass
            try:
                self._proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self._proc.kill()                      # this worker's own process, by its pid
                self._proc.wait(timeout)
        self._conn.close()
        self._boxes.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.shutdown()


class _Boxes:
    """Shared memory between the loop and its worker process (a memfd, else a temporary file, mapped by both): `jobs`
    carries a job's windows to the worker, `results` its result back, each BOX bytes (a window pair is 22 kB, a
    result under 1 kB). A job uses them only when no other job is out, so neither side overwrites what the other
    has yet to read; the worker answers in the box only a job that came that way."""
    BOX = 1 << 20

    def __init__(self, fd: int | None = None):
        if fd is None:                                 # the loop's side creates it; the worker maps it by its fd
            fd = os.memfd_create("rme-worker") if hasattr(os, "memfd_create") else \
                os.dup(tempfile.TemporaryFile().fileno())
            os.ftruncate(fd, 2 * self.BOX)
        self.fd, self._map = fd, mmap.mmap(fd, 2 * self.BOX)
        self._map.write(bytes(2 * self.BOX))           # every page mapped now, none faulted in the loop later
        view = memoryview(self._map)
        self.jobs, self.results = view[:self.BOX], view[self.BOX:]

    def close(self):
        for v in (self.jobs, self.results):
            v.release()
        try:
            self._map.close()
        except BufferError:                            # a view still open: unmapped once it goes
            pass
        os.close(self.fd)


def _put(box, arrays):
    """Write float64 arrays one after another (64-byte aligned) into box (a memoryview); the header _take reads, or
    None when one is no float64 array or they do not fit (the caller then pickles them)."""
    size = lambda a: -(-a.nbytes // 64) * 64
    if not all(type(a) is np.ndarray and a.dtype == np.float64 for a in arrays) or sum(map(size, arrays)) > len(box):
        return None
    head, end = [struct.pack("<B", len(arrays))], 0
    for a in arrays:
        np.copyto(np.ndarray(a.shape, np.float64, box, end), a)
        head.append(struct.pack(f"<B{a.ndim}q", a.ndim, *a.shape))
        end += size(a)
    return b"".join(head)


def _take(box, msg, at=1):
    """(the arrays _put wrote, copied out of the box: it is written again by the next job; the offset in msg where
    the header _put gave, read from msg[at:], ends)."""
    (count,), arrays, end = struct.unpack_from("<B", msg, at), [], 0
    at += 1
    for _ in range(count):
        ndim = msg[at]
        shape = struct.unpack_from(f"<{ndim}q", msg, at + 1)
        at += 1 + 8 * ndim
        arrays.append(np.ndarray(shape, np.float64, box, end).copy())
        end += -(-arrays[-1].nbytes // 64) * 64
    return arrays, at


def _result(msg, box):
    """A worker's answer: b"Y" + _put's header for the Estimate's numbers in the box, else the pickled result."""
    if msg[:1] != b"Y":
        return pickle.loads(msg)
    (v,), _ = _take(box, msg)
    e = Estimate(v[0:4], v[4:8], v[8:24].reshape(4, 4), v[24:28], v[28:32] > 0.5, float(v[32]), int(v[33]),
                 bool(v[34]))
    e.prior_source = "broad" if v[35] > 0.5 else "network"
    return e


def _numbers(e) -> np.ndarray:
    """The fields of an Estimate that RME._estimate fills, as one float64 array (36,) (_result rebuilds it): no
    pickling on the loop's side, where unpickling cost 0.07 ms of a 1 ms cycle."""
    return np.concatenate([e.mean, e.std, e.cov.ravel(), e.prior, e.observed, [e.seconds, e.iterations, e.converged,
                                                                                e.prior_source == "broad"]])


def _poller(conn):
    """A call that says whether conn has data (or its end closed) without waiting: a registered poll(2), which costs
    about 1 us against the ~10-30 us of Connection.poll's selector."""
    if not hasattr(select, "poll"):
        return conn.poll
    p = select.poll()
    p.register(conn.fileno(), select.POLLIN)
    return lambda: bool(p.poll(0))


def _serve(fd: int, boxes_fd: int):
    """The worker process: receive (spec, nice), build the estimator, say "ready", then answer each job, b"W" + the
    header of (q, tau) in the jobs box or a pickled ("estimate", (q, tau), shared), with est._estimate(q, tau): its
    numbers in the results box if the job came through the boxes (_result reads them), else pickled; until a
    pickled ("stop", (), False) or the loop's end of the socket closes."""
    conn, boxes = Connection(fd), _Boxes(boxes_fd)
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
            msg = conn.recv_bytes()
        except (EOFError, OSError):
            return
        kind, args, shared = ("estimate", _take(boxes.jobs, msg)[0], True) if msg[:1] == b"W" else pickle.loads(msg)
        if kind != "estimate":
            return
        try:
            out = est._estimate(*args)
        except Exception as err:                       # handed to result() in the loop's process
            out = RuntimeError(f"the estimate failed in the worker: {type(err).__name__}: {err}")
        head = _put(boxes.results, (_numbers(out),)) if shared and not isinstance(out, Exception) else None
        conn.send_bytes(b"Y" + head) if head is not None else conn.send(out)


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

