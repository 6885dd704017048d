"""The path worker (ddrt/service/pathworker.py): what it builds is the path load_path builds,
its file checks never block, and its bounds (file size, build time) are enforced and named."""

from __future__ import annotations

import dataclasses
import logging
import os
import signal
import threading
import time
from dataclasses import replace
from pathlib import Path as FsPath

import numpy as np
import pytest

from ddrt.config import load_config
from ddrt.path import PathError
from ddrt.path.pursuit import PurePursuit
from ddrt.path.reference import PathReference
from ddrt.path.spec import load_path, speed_limits
from ddrt.core.types import Setpoint
from ddrt.service.pathjob import BuildJob, check_path_file
from ddrt.service.pathworker import START_TIMEOUT_S, PathWorker
from tests.support.repo import REPO, SIM_YAML

CFG = load_config(SIM_YAML)
LIMITS = speed_limits(CFG)
# The worker bounds its own start (START_TIMEOUT_S) and every build (paths.build_timeout_s) and
# says so in the build's error: a wait longer than both is a hang, whatever the machine's load.
WORKER_HANG_S = START_TIMEOUT_S + CFG.paths.build_timeout_s + 30.0


def _wait(cond, what: str) -> None:
    deadline = time.monotonic() + WORKER_HANG_S
    while not cond():
        assert time.monotonic() < deadline, f"no {what} within {WORKER_HANG_S:g} s: the worker hangs"
        time.sleep(0.005)


@pytest.fixture(scope="module")
def worker():
    w = PathWorker()
    yield w
    w.close()


def _build(worker: PathWorker, source, paths=None, **kw):
    b = worker.submit(BuildJob(source, LIMITS, paths or CFG.paths, **kw))
    _wait(lambda: b.done, "end of the build")
    return b


@pytest.mark.parametrize("spec", [
    {"shape": "rectangle", "width": 1.0, "height": 0.5, "speed": 0.3},  # pivots: bool series
    {"shape": "figure_eight", "width": 1.0, "height": 0.5, "speed": 0.5},
    {"points": [[0, 0], [0.5, 0], [0.5, 0.5], [1.0, 0.6]], "speed": 0.2},
    str(REPO / "configs" / "paths" / "circle_1m.yaml"),
])
def test_the_worker_builds_what_load_path_builds(worker: PathWorker, spec) -> None:
    b = _build(worker, spec, where="request")
    assert b.error == "", b.error
    got = b.path
    want = load_path(spec, LIMITS, paths=CFG.paths, where="request")
    assert set(vars(got)) == set(vars(want))
    for name, value in vars(want).items():
        mine = getattr(got, name)
        if isinstance(value, list) and value:
            assert mine.tolist() == value, name  # the same items, of the same types
            assert type(mine[0]) is type(value[0]), name
            assert mine[-1] == value[-1] and len(mine) == len(value)
        elif isinstance(value, dict):
            assert set(mine) == set(value)
            for key, arr in value.items():
                assert np.array_equal(mine[key], arr) and mine[key].dtype == arr.dtype, key
                assert not mine[key].flags.writeable
        elif dataclasses.is_dataclass(value):  # e.g. Path.conditioning, which holds arrays
            assert _equal(mine, value), name
        else:
            assert mine == value, name
    # The same reference, tick for tick.
    ra = PathReference(got, 0.05, 0.3, 0.005)
    rb = PathReference(want, 0.05, 0.3, 0.005)
    sa, sb = Setpoint(), Setpoint()
    for k in range(300):
        p = want.at(min(want.length, 0.004 * k))
        ra.update(p.x + 0.001, p.y - 0.002, p.theta, sa, 0.005)
        rb.update(p.x + 0.001, p.y - 0.002, p.theta, sb, 0.005)
        assert sa == sb and ra.sigma == rb.sigma
    assert got.at_time(1.234) == want.at_time(1.234)
    assert PurePursuit(got).update(0.1, 0.0, 0.0) == PurePursuit(want).update(0.1, 0.0, 0.0)


def test_errors_come_back_as_the_loaders_messages(worker: PathWorker) -> None:
    b = _build(worker, {"shape": "circle", "radius": -1.0}, where="request")
    assert b.path is None and b.error.startswith("request: key 'radius'"), b.error
    b = _build(worker, {"shape": "circle", "radius": 1e6}, where="request")
    assert "paths.max_samples" in b.error


def test_file_checks_never_block(tmp_path: FsPath) -> None:
    fifo = tmp_path / "p.csv"
    os.mkfifo(fifo)
    done = threading.Event()

    def check() -> None:
        with pytest.raises(PathError, match="is a FIFO: a path is read from a regular file only"):
            check_path_file(str(fifo), 1000, PathError)
        done.set()

    t = threading.Thread(target=check, daemon=True)
    t.start()
    assert done.wait(5.0), "check_path_file blocked on a FIFO"
    with pytest.raises(PathError, match="is a directory"):
        check_path_file(str(tmp_path), 1000, PathError)
    with pytest.raises(PathError, match="is a device"):
        check_path_file("/dev/null", 1000, PathError)
    with pytest.raises(PathError, match="cannot read: No such file"):
        check_path_file(str(tmp_path / "none.csv"), 1000, PathError)
    big = tmp_path / "big.csv"
    big.write_text("x,y\n" + "0,0\n" * 500)
    with pytest.raises(PathError, match=r"big.csv: 2004 bytes, more than paths.max_file_bytes = 1000"):
        check_path_file(str(big), 1000, PathError)
    check_path_file(str(big), 5000, PathError)


@pytest.mark.skipif(os.geteuid() == 0, reason="root reads any file")
def test_an_unreadable_file_is_refused(tmp_path: FsPath) -> None:
    f = tmp_path / "p.csv"
    f.write_text("x,y\n0,0\n1,0\n")
    f.chmod(0)
    with pytest.raises(PathError, match="cannot read: Permission denied"):
        check_path_file(str(f), 1000, PathError)


def test_a_fifo_named_by_a_yaml_files_file_key_is_refused(worker: PathWorker, tmp_path: FsPath) -> None:
    fifo = tmp_path / "p.csv"
    os.mkfifo(fifo)
    spec = tmp_path / "via.yaml"
    spec.write_text("file: p.csv\nspeed: 0.2\n")
    # Refused by its type, never opened: a worker blocked in open() would end at
    # paths.build_timeout_s with that error instead.
    b = _build(worker, str(spec))
    assert "key 'file'" in b.error and "is a FIFO" in b.error, b.error
    # And in a mapping (a config's inline path:), resolved against its base_dir.
    b = _build(worker, {"file": "p.csv", "speed": 0.2}, base_dir=str(tmp_path), where="cfg.yaml: path")
    assert b.error.startswith("cfg.yaml: path: key 'file'") and "is a FIFO" in b.error, b.error


def test_a_build_over_its_time_is_stopped_naming_the_key(worker: PathWorker) -> None:
    paths = replace(CFG.paths, build_timeout_s=0.2)
    b = _build(worker, {"shape": "circle", "radius": 300.0, "speed": 0.6}, paths=paths)
    # The circle is valid: only the deadline can end its build with an error, and it names it.
    assert "not ready within paths.build_timeout_s = 0.2 s" in b.error, b.error
    assert b.path is None
    # The next job gets a fresh worker.
    assert _build(worker, {"shape": "circle", "radius": 0.5, "speed": 0.3}).error == ""


def test_cancel_stops_the_worker_and_the_next_job_runs(worker: PathWorker) -> None:
    b = worker.submit(BuildJob({"shape": "circle", "radius": 300.0, "speed": 0.6}, LIMITS, CFG.paths))
    _wait(lambda: b.phase == "building", "start of the build")
    worker.cancel(b)
    _wait(lambda: b.done, "end of the cancelled build")
    assert b.error == "cancelled" and b.path is None
    assert _build(worker, {"shape": "circle", "radius": 0.5, "speed": 0.3}).error == ""


def test_a_worker_that_dies_is_reported_not_waited_for(worker: PathWorker) -> None:
    b = worker.submit(BuildJob({"shape": "circle", "radius": 300.0, "speed": 0.6}, LIMITS, CFG.paths))
    _wait(lambda: b.phase == "building" and worker._active is not None, "start of the build")
    os.kill(worker._active.pid, signal.SIGKILL)  # what the OOM killer does
    _wait(lambda: b.done, "end of the build")
    assert "killed by SIGKILL" in b.error and "paths.max_samples" in b.error, b.error
    assert _build(worker, {"shape": "circle", "radius": 0.5, "speed": 0.3}).error == ""


def test_close_during_a_build_ends_it_quietly(caplog: pytest.LogCaptureFixture) -> None:
    """The daemon stopping while a path is read: the build ends with why, nothing is logged as
    a failure (close must not close the worker's pipe under the helper thread's read: that
    gives EBADF and a traceback, or a read of whatever file took that descriptor next)."""
    w = PathWorker()
    try:
        b = w.submit(BuildJob({"shape": "circle", "radius": 300.0, "speed": 0.6}, LIMITS, CFG.paths))
        _wait(lambda: b.phase == "building" and w._active is not None, "the build to start")
    finally:
        w.close(timeout=WORKER_HANG_S)
    assert not w._thread.is_alive()
    assert b.done and b.path is None and b.error == "the daemon is stopping", b.error
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR], caplog.text


def test_the_worker_runs_below_the_loop() -> None:
    """Not real-time, niced, first for the OOM killer: the loop always wins the CPU."""
    w = PathWorker()
    try:
        _wait(lambda: w._standby is not None, "standby worker")
        pid = w._standby.pid

        def demoted() -> bool:  # the first thing the worker does
            try:
                return int(FsPath(f"/proc/{pid}/oom_score_adj").read_text()) == 1000
            except OSError:
                return False
        _wait(demoted, "demotion of the worker")
        assert os.sched_getscheduler(pid) == os.SCHED_OTHER
        assert os.getpriority(os.PRIO_PROCESS, pid) >= 10
    finally:
        w.close()


def test_below_a_real_time_loop_the_reader_runs_just_under_it_and_the_workers_do_not() -> None:
    """With the loop at SCHED_FIFO 10 the helper thread that reads the built paths runs at
    SCHED_FIFO 1 (a niced reader, preempted by other work holding the GIL, left the loop
    waiting 40-60 ms), and the worker processes it starts still begin at SCHED_OTHER, niced.
    In a subprocess, so the test runner never has a real-time thread."""
    import json
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent("""
        import json, os, time
        from ddrt.service.pathworker import PathWorker
        w = PathWorker(loop_priority=10)
        deadline = time.monotonic() + %r
        while w._standby is None or int(open(f"/proc/{w._standby.pid}/oom_score_adj").read()) != 1000:
            assert time.monotonic() < deadline
            time.sleep(0.01)
        tid, pid = w._thread.native_id, w._standby.pid
        print(json.dumps({"reader": [os.sched_getscheduler(tid) & ~os.SCHED_RESET_ON_FORK,
                                     os.sched_getparam(tid).sched_priority],
                          "worker": [os.sched_getscheduler(pid), os.getpriority(os.PRIO_PROCESS, pid)],
                          "fifo": os.SCHED_FIFO, "other": os.SCHED_OTHER}))
        w.close()
    """ % WORKER_HANG_S)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO,
                         timeout=2 * WORKER_HANG_S)
    assert out.returncode == 0, out.stderr
    res = json.loads(out.stdout.strip().splitlines()[-1])
    if "sched_setscheduler(SCHED_FIFO, 1)" in out.stderr:  # not permitted here: normal, niced
        assert res["reader"] == [res["other"], 0]
    else:
        assert res["reader"] == [res["fifo"], 1], out.stderr
    assert res["worker"][0] == res["other"] and res["worker"][1] >= 10


def _equal(a: object, b: object) -> bool:
    """Equality through dataclasses, sequences and mappings, with arrays compared by value."""
    if isinstance(b, np.ndarray):
        return isinstance(a, np.ndarray) and np.array_equal(a, b)
    if dataclasses.is_dataclass(b):
        return type(a) is type(b) and all(_equal(getattr(a, f.name), getattr(b, f.name)) for f in dataclasses.fields(b))
    if isinstance(b, (list, tuple)):
        return isinstance(a, (list, tuple)) and len(a) == len(b) and all(_equal(x, y) for x, y in zip(a, b))
    if isinstance(b, dict):
        return isinstance(a, dict) and a.keys() == b.keys() and all(_equal(a[k], b[k]) for k in b)
    return a == b
