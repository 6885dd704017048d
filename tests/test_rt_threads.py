"""The scheduling of a live `ddrt run` daemon's threads, read from outside the process.

What keeps a SCHED_FIFO loop from waiting on the GIL behind a preempted helper is that every
helper taking the GIL per tick runs at SCHED_FIFO just below the loop, and nothing at or above
it (rt.raise_gil_helper); the control socket's thread, which any local client can keep busy,
stays a normal thread (docs/BENCHMARKS.md section 14 measured this arrangement). Without the
privilege the daemon must still run, every thread a normal one, with a warning.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
LOOP_PRIORITY = 10


def _config(tmp_path: Path) -> Path:
    cfg = {"extends": str(REPO / "configs" / "sim.yaml"),
           "daemon": {"telemetry_dir": str(tmp_path / "tel"), "rt_priority": LOOP_PRIORITY},
           "estimator": {"calibration_s": 0.2},
           "path": str(REPO / "configs" / "paths" / "figure8_slow.yaml")}
    path = tmp_path / "cfg.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path


def _threads_while_following(tmp_path: Path, prefix: list[str]) -> tuple[dict[int, tuple[int, int]], str, dict]:
    """Start the daemon (following its path), wait until it is ready, read every thread's
    (policy, priority), stop it with SIGTERM; return them, its stderr and its stats."""
    err_path, stats = tmp_path / "stderr.log", tmp_path / "stats.json"
    env = dict(os.environ, PYTHONPATH=str(REPO))
    with open(err_path, "wb") as err:
        proc = subprocess.Popen([*prefix, sys.executable, "-m", "ddrt.cli", "run", str(_config(tmp_path)),
                                 "--socket", str(tmp_path / "ctl.sock"), "--follow", "--duration", "120",
                                 "--stats-json", str(stats)], cwd=REPO, env=env, stdin=subprocess.DEVNULL,
                                stdout=subprocess.DEVNULL, stderr=err)
    try:
        deadline = time.monotonic() + 90.0
        while "ready after" not in err_path.read_text(errors="replace"):
            assert proc.poll() is None, err_path.read_text(errors="replace")
            assert time.monotonic() < deadline, "the daemon did not get ready in 90 s"
            time.sleep(0.1)
        # Helpers set their own policy as their first step: on a loaded machine give them time.
        until = time.monotonic() + 10.0
        while True:
            time.sleep(0.5)
            threads = {}
            for entry in os.listdir(f"/proc/{proc.pid}/task"):
                tid = int(entry)
                try:
                    threads[tid] = (os.sched_getscheduler(tid) & ~os.SCHED_RESET_ON_FORK,
                                    os.sched_getparam(tid).sched_priority)
                except ProcessLookupError:  # a thread that just ended
                    pass
            raised = sum(policy == os.SCHED_FIFO for policy, _ in threads.values())
            if raised >= 2 or time.monotonic() > until:  # the loop and a helper
                break
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(60.0) == 0, err_path.read_text(errors="replace")
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return threads, err_path.read_text(errors="replace"), json.loads(stats.read_text())


def _privileged() -> bool:
    try:
        pid = os.fork()
    except OSError:
        return False
    if pid == 0:  # try in a child: the test runner itself must stay a normal process
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(LOOP_PRIORITY))
            os._exit(0)
        except OSError:
            os._exit(1)
    return os.waitpid(pid, 0)[1] == 0


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="per-thread scheduling is Linux's")
def test_no_helper_thread_at_or_above_the_loop_and_the_gil_helpers_just_below(tmp_path: Path) -> None:
    if not _privileged():
        pytest.skip("no CAP_SYS_NICE / RLIMIT_RTPRIO here: the unprivileged test covers this machine")
    threads, err, stats = _threads_while_following(tmp_path, [])
    pid = min(threads)  # the main thread's id is the process id; it runs the loop
    assert threads[pid] == (os.SCHED_FIFO, LOOP_PRIORITY), (threads, err)
    helpers = {tid: pp for tid, pp in threads.items() if tid != pid}
    assert len(helpers) >= 2, threads  # at least the telemetry writer and the control socket's thread
    for tid, (policy, priority) in helpers.items():
        if policy == os.SCHED_FIFO:
            assert 1 <= priority < LOOP_PRIORITY, (tid, threads)
        else:
            assert policy in (os.SCHED_OTHER, os.SCHED_BATCH), (tid, threads)
    below = [tid for tid, (policy, _) in helpers.items() if policy == os.SCHED_FIFO]
    normal = [tid for tid, (policy, _) in helpers.items() if policy != os.SCHED_FIFO]
    assert below, f"no GIL helper below the loop: {threads}"
    assert normal, f"the control socket's thread must stay a normal thread: {threads}"
    assert "sched_setscheduler" not in err, err
    assert stats["ticks"] > 0 and stats["exit_code"] == 0


@pytest.mark.skipif(shutil.which("setpriv") is None or os.geteuid() != 0,
                    reason="needs root and setpriv to take CAP_SYS_NICE away")
def test_without_the_privilege_the_daemon_runs_all_threads_normal_with_a_warning(tmp_path: Path) -> None:
    # Root without CAP_SYS_NICE in its bounding set gets EPERM for SCHED_FIFO, as a unit
    # without LimitRTPRIO= would.
    threads, err, stats = _threads_while_following(tmp_path, ["setpriv", "--bounding-set=-sys_nice"])
    assert f"sched_setscheduler(SCHED_FIFO, {LOOP_PRIORITY})" in err, err
    assert all(policy == os.SCHED_OTHER for policy, _ in threads.values()), threads
    assert stats["ticks"] > 0 and stats["exit_code"] == 0
    assert "Traceback" not in err, err
