"""What the bench scripts share, defined once: where the repository is and its simulated robot's
config, the environment of a child python, the percentile every table uses, the way a `ddrt run`
daemon is started, and a process pool that groups its results by key."""

from __future__ import annotations

import multiprocessing
import os
import subprocess
import sys
import time
from collections.abc import Callable, Hashable, Sequence
from pathlib import Path
from typing import IO, Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SIM_CONFIG = REPO / "configs" / "sim.yaml"
# What systemd gives a unit: a bench started under one must not have its children notify,
# log or be watched as that unit.
SYSTEMD_VARIABLES = ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID", "JOURNAL_STREAM", "LOGS_DIRECTORY")


def child_env(repo: Path = REPO, **extra: str) -> dict[str, str]:
    """This process's environment for a child python: `repo` first on PYTHONPATH (its ddrt is
    the one imported, however the bench was started), systemd's variables left out, `extra` set."""
    env = {k: v for k, v in os.environ.items() if k not in SYSTEMD_VARIABLES}
    env["PYTHONPATH"] = str(repo) + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    env.update(extra)
    return env


def percentile(values: Sequence[float] | np.ndarray, q: float) -> float:
    """The q-th percentile (0..100) of non-empty values, interpolated linearly between ranks:
    numpy.percentile's default, the definition of the daemon's own timing statistics
    (ddrt/service/timing.py), so every percentile in BENCHMARKS.md is the same kind."""
    if len(values) == 0:
        raise ValueError("percentile: no values")
    return float(np.percentile(np.asarray(values, dtype=np.float64), q))


def spawn_daemon(config: Path, *args: str, stdout: IO[Any] | int | None = subprocess.DEVNULL,
                 stderr: IO[Any] | int | None = subprocess.DEVNULL, text: bool = False,
                 repo: Path = REPO) -> subprocess.Popen:
    """`ddrt run CONFIG ARGS...` as a child python in `repo` (child_env, no stdin)."""
    return subprocess.Popen([sys.executable, "-m", "ddrt.cli", "run", str(config), *args], cwd=repo,
                            env=child_env(repo), stdin=subprocess.DEVNULL, stdout=stdout, stderr=stderr, text=text)


def await_daemon(proc: subprocess.Popen, sock: str, ready: Callable[[dict[str, Any]], bool], what: str,
                 stderr_file: Path, timeout: float = 60.0) -> None:
    """Poll the daemon's `status` every 0.1 s until `ready(reply)`; RuntimeError (with the end
    of its stderr) if it exits first, or after `timeout` seconds ("did not WHAT")."""
    from ddrt.service.ctlclient import ControlClientError, request

    deadline = time.monotonic() + timeout
    while True:
        if proc.poll() is not None:
            raise RuntimeError(f"the daemon exited: {stderr_file.read_text()[-500:]}")
        try:
            if ready(request(sock, {"cmd": "status"}, timeout=1.0)):
                return
        except (ControlClientError, TimeoutError, OSError):
            pass
        if time.monotonic() > deadline:
            raise RuntimeError(f"the daemon did not {what} within {timeout:g} s")
        time.sleep(0.1)


def pooled_by_key(fn: Callable[[Any], tuple[Any, ...]], jobs: list[Any],
                  workers: int) -> dict[Hashable, list[tuple[Any, ...]]]:
    """Run `fn` over `jobs` (in `workers` forked processes when more than one); `fn` returns
    (key, *values), and the values are grouped by key in the order of the jobs."""
    if workers > 1:
        with multiprocessing.get_context("fork").Pool(workers) as pool:
            out = pool.map(fn, jobs, chunksize=1)
    else:
        out = [fn(j) for j in jobs]
    acc: dict[Hashable, list[tuple[Any, ...]]] = {}
    for key, *values in out:
        acc.setdefault(key, []).append(tuple(values))
    return acc
