"""Reading and building a path off the loop: a worker process, and a helper thread that talks
to it.

Why a process: the loop and a path build cannot share one interpreter. Python threads share
the GIL, and a build is long stretches of bytecode and of C calls that hold it (`tolist()` of
a million samples is one 60 ms call): with the build in a thread of the daemon, a 200 Hz
loop was late by 8 ms at the median and 60 ms at p99 (a 942 000 sample circle, switch
interval 0.5 ms). In a process it runs beside the loop, at nice 10, first in line for the
OOM killer (oom_score_adj 1000), and can be killed at `paths.build_timeout_s`, or when a stop
cancels it, which no thread can.

What comes back is compact: every sample series as raw float64 / bool bytes (a series that
the Path keeps both as a list and as a numpy array goes once), the few scalars pickled in a
header. The helper thread reads them straight into numpy arrays, 64 KiB per read (each read
releases the GIL while the kernel copies), and the Path's hot-path lists become read-only
memoryviews of those arrays: they index like the lists (a Python float or bool per item,
len, bisect, negative indices; about 20 ns more per lookup), cost 8 bytes a sample instead
of 32, and take no time to build or to free. Nothing is converted on this side, so the
loop waiting for the GIL waits microseconds. A Path the loop lets go of is handed back here
to be freed (`dispose`): giving a few hundred MB back to the kernel takes milliseconds.

One job at a time: a standby worker is started ahead (its imports done), takes one job, and
exits (whatever memory the build took goes with it); the next standby starts once that job
is over, so at most one worker process works beside the loop. The job and its file checks
(ddrt/service/pathjob.py) run in the worker: nothing here touches the file system from the
loop thread.

`python -m ddrt.service.pathworker` is the worker's own entry point (the protocol is private
to this module: an 8-byte length and a pickle each way, then the buffers).
"""

from __future__ import annotations

import logging
import os
import pickle
import queue
import select
import signal
import struct
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from ddrt.errors import DdrtError
from ddrt.service.pathjob import Build, BuildJob, build_path

if TYPE_CHECKING:
    from ddrt.path import Path

log = logging.getLogger("ddrt.service.pathworker")

CHUNK_BYTES = 64 * 1024
NICE = 10
PAUSE_S = 5e-5  # after a piece of work that held the GIL: lets a waiting loop thread take it
POLL_S = 0.05  # how often a wait checks for a cancel
MAX_HEADER_BYTES = 16 * 1024 * 1024
_LEN = struct.Struct("<Q")
READY = b"R"
START_TIMEOUT_S = 60.0  # a worker process that has not imported what it needs by then is stuck


# --------------------------------------------------------------------------- packing


def pack(path: Any) -> tuple[dict[str, Any], list[Any]]:
    """A Path as a small header and a list of numpy buffers (see the module docstring)."""
    import numpy as np

    attrs: dict[str, Any] = {}
    lists: dict[str, tuple[str, int]] = {}  # attribute -> (kind, buffer)
    npdicts: dict[str, dict[str, int]] = {}
    buffers: list[Any] = []
    state = vars(path)
    dicts = {k: v for k, v in state.items()
             if isinstance(v, dict) and v and all(isinstance(a, np.ndarray) for a in v.values())}
    shared = {key: arr for d in dicts.values() for key, arr in d.items()}
    used: dict[int, int] = {}  # id(ndarray) -> buffer

    def add(arr: Any) -> int:
        buffers.append(np.ascontiguousarray(arr))
        return len(buffers) - 1

    for name, value in state.items():
        if name in dicts:
            continue
        kind = _list_kind(value)
        if kind is None:
            attrs[name] = value
            continue
        dtype = {"d": np.float64, "q": np.int64, "b": np.bool_}[kind]
        arr = np.asarray(value, dtype=dtype)
        twin = shared.get(name)
        if (twin is not None and twin.dtype == arr.dtype and twin.shape == arr.shape
                and id(twin) not in used and np.array_equal(twin, arr)):
            used[id(twin)] = add(twin)
            lists[name] = (kind, used[id(twin)])
        else:
            lists[name] = (kind, add(arr))
    for dname, d in dicts.items():
        npdicts[dname] = {key: used[id(arr)] if id(arr) in used else add(arr) for key, arr in d.items()}
    header = {
        "cls": f"{type(path).__module__}:{type(path).__qualname__}",
        "attrs": attrs, "lists": lists, "npdicts": npdicts,
        "buffers": [(b.dtype.str, b.shape) for b in buffers],
    }
    return header, buffers


def _list_kind(value: Any) -> str | None:
    if not isinstance(value, list) or not value:
        return None
    types = set(map(type, value))
    if types == {float}:
        return "d"
    if types == {bool}:
        return "b"
    if types == {int}:
        return "q"
    return None


# --------------------------------------------------------------------------- the worker process


def _write_msg(fh: Any, obj: Any) -> None:
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    fh.write(_LEN.pack(len(data)))
    fh.write(data)


def _read_exact_blocking(fh: Any, n: int) -> bytes | None:
    out = bytearray()
    while len(out) < n:
        chunk = fh.read(n - len(out))
        if not chunk:
            return None
        out += chunk
    return bytes(out)


def _demote_self() -> None:
    """The worker yields to the loop: normal policy, nice 10, first for the OOM killer."""
    try:
        if os.sched_getscheduler(0) in (os.SCHED_FIFO, os.SCHED_RR):
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (OSError, AttributeError):
        pass
    _renice(0)
    try:
        with open("/proc/self/oom_score_adj", "w") as fh:
            fh.write("1000")
    except OSError:
        pass


def _renice(who: int) -> None:
    """At least NICE (lowering one's own priority is always allowed)."""
    try:
        os.setpriority(os.PRIO_PROCESS, who, max(NICE, os.getpriority(os.PRIO_PROCESS, who)))
    except OSError:
        pass


def _error_text(exc: BaseException) -> str:
    from ddrt.config.schema import ConfigError
    from ddrt.path.spec import PathError

    if isinstance(exc, MemoryError):
        return "out of memory while building the path (lower paths.max_samples)"
    if isinstance(exc, (PathError, ConfigError, ValueError, TypeError, OSError)):
        return " ".join(str(exc).split())
    return f"{type(exc).__name__}: {' '.join(str(exc).split())}"


def worker_main() -> int:
    """The worker: read one job from stdin, write the built path (or the error) to stdout."""
    out_fd = os.dup(1)
    os.dup2(2, 1)  # anything printed goes to stderr, never into the protocol
    out = os.fdopen(out_fd, "wb", buffering=0)
    _demote_self()
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the daemon's ^C is the daemon's to handle
    import numpy  # noqa: F401 - the imports are the standby's head start

    import ddrt.path.spec  # noqa: F401

    out.write(READY)  # imports done: the build's time starts when the job comes
    raw = _read_exact_blocking(sys.stdin.buffer, _LEN.size)
    if raw is None:
        return 0  # the daemon closed the pipe: no job
    body = _read_exact_blocking(sys.stdin.buffer, _LEN.unpack(raw)[0])
    if body is None:
        return 0
    job: BuildJob = pickle.loads(body)
    try:
        path = build_path(job)
        header, buffers = pack(path)
    except Exception as exc:  # noqa: BLE001 - every failure becomes a message
        if not isinstance(exc, (ValueError, TypeError, OSError, MemoryError)):
            import traceback

            traceback.print_exc()
        _write_msg(out, {"ok": False, "error": _error_text(exc)})
        return 0
    del path
    _write_msg(out, {"ok": True, **header})
    for buf in buffers:
        out.write(memoryview(buf).cast("B"))
    return 0


# --------------------------------------------------------------------------- the daemon's side


class _Stop(DdrtError):
    """Why a job ended without a path (the message is the error)."""


class PathWorker:
    """The daemon's path builder: `submit` a job, poll its `Build`; `dispose` old paths.

    Create it before the loop goes real-time, so its helper thread keeps every CPU. With the
    loop at SCHED_FIFO `loop_priority`, the helper runs just below it (SCHED_FIFO 1): it takes
    the GIL for every chunk it reads and every piece it frees, and niced among the machine's
    other work it was preempted holding it, the loop waiting behind (40-60 ms under CPU hogs).
    The worker processes it starts begin at SCHED_OTHER, niced (SCHED_RESET_ON_FORK).
    """

    def __init__(self, python: str | None = None, loop_priority: int = 0) -> None:
        self.python = python or sys.executable
        self.loop_priority = loop_priority
        self._queue: queue.SimpleQueue[Any] = queue.SimpleQueue()
        self._standby: subprocess.Popen[bytes] | None = None
        self._active: subprocess.Popen[bytes] | None = None
        self._closed = False
        self.started = 0  # worker processes started
        self._thread = threading.Thread(target=self._run, name="ddrt-path", daemon=True)
        self._thread.start()

    # ----- loop side (any thread) ---------------------------------------------------------
    def submit(self, job: BuildJob) -> Build:
        build = Build(job)
        self._queue.put(build)
        return build

    def cancel(self, build: Build) -> None:
        """The result is no longer wanted: the worker is stopped, a finished path freed here."""
        self.dispose(build.cancel())

    def dispose(self, path: Path | None) -> None:
        """Free a (large) path on the helper thread, in pieces, not on the caller's."""
        if path is not None:
            self._queue.put(_Dispose(path))

    def close(self, timeout: float = 5.0) -> None:
        if self._closed:
            return
        self._closed = True
        self._queue.put(None)
        # Only signal the workers here: their pipes are the helper thread's, which may be
        # reading one right now (closed under it, the read fails with EBADF, or reads whatever
        # file is opened next under that number). It sees the worker gone, or `_closed` within
        # POLL_S, and closes them on its way out.
        for proc in (self._active, self._standby):
            _signal_kill(proc)
        self._thread.join(timeout)

    # ----- helper thread ------------------------------------------------------------------
    def _run(self) -> None:
        from ddrt.runtime.rt import demote_current_thread, raise_gil_helper

        demote_current_thread()
        # Nice is per thread on Linux, and a child starts with its parent thread's: the worker
        # processes are niced from their first instruction (their imports included).
        _renice(threading.get_native_id())
        why = raise_gil_helper(self.loop_priority, reset_on_fork=True)
        if why:
            log.warning("path worker's reader: %s (at normal priority, niced)", why)
        try:
            self._standby = self._spawn()
        except OSError as exc:
            log.error("cannot start the path worker: %s", exc)
        while True:
            item = self._queue.get()
            if item is None:
                break
            try:
                if isinstance(item, _Dispose):
                    _free(item.path)
                    continue
                self._do(item)
            except Exception:  # noqa: BLE001 - a bug here must not end path building
                log.exception("path worker failed")
                if isinstance(item, Build) and not item.done:
                    item.finish(error="the path worker failed (see the log)")
        for proc in (self._active, self._standby):
            _kill(proc)

    def _spawn(self) -> subprocess.Popen[bytes]:
        env = dict(os.environ)
        root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
        env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
        env.setdefault("OPENBLAS_NUM_THREADS", "1")
        for key in ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID"):
            env.pop(key, None)  # the worker never talks to systemd
        proc = subprocess.Popen([self.python, "-m", "ddrt.service.pathworker"], stdin=subprocess.PIPE,
                                stdout=subprocess.PIPE, bufsize=0, close_fds=True, env=env)
        self.started += 1
        return proc

    def _do(self, build: Build) -> None:
        if build.cancelled:
            build.finish(error="cancelled")
            return
        build.advance("starting")
        proc, self._standby = self._standby, None
        try:
            if proc is None or proc.poll() is not None:
                _kill(proc)
                try:
                    proc = self._spawn()
                except OSError as exc:
                    build.finish(error=f"cannot start the path worker: {exc}")
                    return
            self._active = proc
            try:
                path = self._exchange(proc, build)
            except _Stop as exc:
                build.finish(error=str(exc))
            else:
                if build.cancelled:
                    build.finish(error="cancelled")
                    _free(path)
                else:
                    build.finish(path=path)
        finally:
            self._active = None
            _kill(proc)
            if not self._closed and self._standby is None:
                # The next job's worker starts now (not during this build: one worker process
                # at a time beside the loop), so its imports are done when that job comes.
                try:
                    self._standby = self._spawn()
                except OSError as exc:
                    log.error("cannot start the path worker: %s", exc)

    def _exchange(self, proc: subprocess.Popen[bytes], build: Build) -> Path:
        job = build.job
        data = pickle.dumps(job, protocol=pickle.HIGHEST_PROTOCOL)
        assert proc.stdin is not None and proc.stdout is not None
        # The worker says when its imports are done; paths.build_timeout_s counts from then.
        started = _Reader(proc.stdout.fileno(), time.monotonic() + START_TIMEOUT_S, build, None, self, proc)
        if started.read_bytes(len(READY)) != READY:
            raise _Stop("the path worker sent a malformed reply")
        deadline = time.monotonic() + job.paths.build_timeout_s
        try:
            proc.stdin.write(_LEN.pack(len(data)) + data)
            proc.stdin.close()
        except OSError:
            raise _Stop(self._died(proc)) from None
        build.advance("building")
        reader = _Reader(proc.stdout.fileno(), deadline, build, job.paths.build_timeout_s, self, proc)
        n = _LEN.unpack(reader.read_bytes(_LEN.size))[0]
        if n > MAX_HEADER_BYTES:
            raise _Stop("the path worker sent a malformed reply")
        header = pickle.loads(reader.read_bytes(n))
        if not header.get("ok"):
            raise _Stop(str(header.get("error", "the path worker failed")))
        build.advance("receiving")
        return _unpack(header, reader)

    def _died(self, proc: subprocess.Popen[bytes]) -> str:
        try:
            code = proc.wait(timeout=1.0)
        except subprocess.TimeoutExpired:
            return "the path worker stopped answering"
        if code < 0:
            name = signal.Signals(-code).name if -code in signal.valid_signals() else str(-code)
            hint = " (out of memory? lower paths.max_samples)" if code == -signal.SIGKILL else ""
            return f"the path worker was killed by {name}{hint}"
        return f"the path worker exited with status {code} without a path"


@dataclass
class _Dispose:
    path: Path


class _Reader:
    """Exact reads from the worker's pipe, with the job's deadline and cancel honoured."""

    def __init__(self, fd: int, deadline: float, build: Build, timeout_s: float | None, owner: PathWorker,
                 proc: subprocess.Popen[bytes]) -> None:
        self.fd = fd
        self.deadline = deadline
        self.build = build
        self.timeout_s = timeout_s
        self.owner = owner
        self.proc = proc

    def _wait(self) -> None:
        while True:
            if self.build.cancelled:
                raise _Stop("cancelled")
            if self.owner._closed:
                raise _Stop("the daemon is stopping")
            left = self.deadline - time.monotonic()
            if left <= 0.0:
                if self.timeout_s is None:
                    raise _Stop(f"the path worker did not start within {START_TIMEOUT_S:g} s")
                raise _Stop(f"not ready within paths.build_timeout_s = {self.timeout_s:g} s "
                            f"(the path worker was stopped)")
            ready, _, _ = select.select([self.fd], [], [], min(POLL_S, left))
            if ready:
                return

    def read_into(self, mv: memoryview) -> None:
        """Fill `mv` from the pipe (each read releases the GIL; the kernel does the copy)."""
        got, n = 0, len(mv)
        while got < n:
            self._wait()
            k = os.readv(self.fd, [mv[got:got + CHUNK_BYTES]])
            if k == 0:
                raise _Stop("the daemon is stopping" if self.owner._closed else self.owner._died(self.proc))
            got += k

    def read_bytes(self, n: int) -> bytes:
        out = bytearray(n)
        self.read_into(memoryview(out))
        return bytes(out)


def _unpack(header: dict[str, Any], reader: _Reader) -> Path:
    import numpy as np

    from ddrt.path.sampled import Path

    if header.get("cls") != f"{Path.__module__}:{Path.__qualname__}":
        raise _Stop(f"the path worker built a {header.get('cls')}, expected a Path")
    arrays: list[Any] = []
    for dtype_str, shape in header["buffers"]:
        out = np.empty(shape, dtype=np.dtype(dtype_str))
        if out.nbytes:
            reader.read_into(memoryview(out.reshape(-1)).cast("B"))
        out.flags.writeable = False
        arrays.append(out)
    obj = Path.__new__(Path)
    state = dict(header["attrs"])
    for name, (_kind, i) in header["lists"].items():
        # A read-only memoryview indexes like the list it replaces (a Python float, int or
        # bool per item; len, bisect, negative indices), on the numpy array's memory.
        state[name] = memoryview(arrays[i])
    for dname, keys in header["npdicts"].items():
        state[dname] = {key: arrays[i] for key, i in keys.items()}
    obj.__dict__.update(state)
    return obj


def _free(path: Path) -> None:
    """Drop a Path's buffers one by one, with a pause between (freeing a few hundred MB of
    pages costs milliseconds: not on the loop thread, and not in one go)."""
    state = path.__dict__
    for key in list(state):
        value = state.pop(key)
        if isinstance(value, dict):
            while value:
                value.popitem()
                time.sleep(PAUSE_S)
        del value
        time.sleep(PAUSE_S)


def _signal_kill(proc: subprocess.Popen[bytes] | None) -> None:
    """SIGKILL a worker that still runs; its pipes stay open for the thread that reads them."""
    if proc is not None and proc.poll() is None:
        try:
            proc.kill()
        except OSError:
            pass


def _kill(proc: subprocess.Popen[bytes] | None) -> None:
    if proc is None:
        return
    for fh in (proc.stdin, proc.stdout):
        try:
            if fh is not None:
                fh.close()
        except OSError:
            pass
    if proc.poll() is None:
        try:
            proc.kill()
        except OSError:
            pass
    try:
        proc.wait(timeout=5.0)
    except subprocess.TimeoutExpired:
        log.error("path worker %d did not exit after SIGKILL", proc.pid)


if __name__ == "__main__":
    sys.exit(worker_main())
