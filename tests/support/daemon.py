"""The real `ddrt run` process on the simulated robot, as tests drive it from outside: a config
over configs/sim.yaml, a child whose output goes to files (never pipes, so a chatty child
cannot block), its control socket, a stand-in for systemd's notification socket, `ddrt ctl`,
and the telemetry CSV it leaves behind. Every wait is bounded; `DaemonProc.close` kills the
child and removes its files."""

from __future__ import annotations

import contextlib
import csv
import json
import os
import shutil
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import yaml

from ddrt.cli import FOLLOW_TIMEOUT_S
from ddrt.service.ctlclient import ControlClientError, request
from ddrt.service.pathworker import START_TIMEOUT_S as WORKER_START_TIMEOUT_S
from ddrt.loop import COLUMNS
from tests.support.repo import REPO, SIM_YAML

PATHS = REPO / "configs" / "paths"
CALIBRATION_S = 0.5  # >= 10 ticks at 200 Hz; the default 3 s would make every start slow
RATE_HZ = 200.0
# Caps on waits that only a hang exceeds, whatever the load: the daemon bounds its own start
# (the worker's start and the start path's build, then calibration) and a follow's build
# (`ddrt ctl follow` waits as long); any other reply comes between two ticks.
START_TIMEOUT_S = WORKER_START_TIMEOUT_S + 30.0 + 30.0  # paths.build_timeout_s is 30 s by default
REPLY_TIMEOUT_S = 30.0
STATE_TIMEOUT_S = 60.0  # for a state the paced robot reaches within seconds of its own time

def wait_for(cond: Callable[[], Any], timeout: float, what: str, interval: float = 0.02) -> Any:
    """Poll `cond` until it returns something truthy; fail naming `what` after `timeout`."""
    deadline = time.monotonic() + timeout
    while True:
        value = cond()
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(interval)


def write_config(cfg_path: Path, telemetry_dir: Path, **sections: Any) -> None:
    """A config over configs/sim.yaml; written whole then renamed, so a reload never reads half."""
    doc: dict[str, Any] = {
        "extends": str(SIM_YAML),
        # SCHED_FIFO where permitted (as configs/robot.yaml), so a busy CI box does not stall
        # the loop past the estimator's 10-period sample-gap fault; elsewhere a warning.
        "daemon": {"telemetry_dir": str(telemetry_dir), "rt_priority": 10},
        "estimator": {"calibration_s": CALIBRATION_S},
        "controller": {"inner": {"kp": 40.0}},
        "path": str(PATHS / "figure8_slow.yaml"),
    }
    for key, value in sections.items():
        if isinstance(value, dict) and isinstance(doc.get(key), dict):
            merged = dict(doc[key])
            merged.update(value)
            doc[key] = merged
        else:
            doc[key] = value
    tmp = cfg_path.with_suffix(".tmp")
    tmp.write_text(yaml.safe_dump(doc, sort_keys=False))
    os.replace(tmp, cfg_path)


SO_TIMESTAMPNS = 35  # <asm-generic/socket.h>; the socket module does not name it
SCM_TIMESTAMPNS = SO_TIMESTAMPNS


class NotifyListener:
    """Stands in for systemd's notification socket; stamps each datagram with the time the
    kernel queued it (SO_TIMESTAMPNS, on the monotonic clock), not when this thread got round
    to reading it: on a loaded host a test process can lose the CPU for longer than the
    intervals measured here."""

    def __init__(self, path: str) -> None:
        self.path = path
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(path)
        self.sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        self.sock.settimeout(0.1)
        self.messages: list[tuple[float, str]] = []  # (time.monotonic(), text)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="notify-listener", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                data, ancillary, _flags, _addr = self.sock.recvmsg(4096, socket.CMSG_SPACE(16))
            except TimeoutError:
                continue
            except OSError:
                return
            stamp = time.monotonic()
            for level, kind, raw in ancillary:
                if level == socket.SOL_SOCKET and kind == SCM_TIMESTAMPNS and len(raw) == 16:
                    sec, nsec = struct.unpack("qq", raw)  # CLOCK_REALTIME: moved onto the monotonic clock
                    stamp -= time.time() - (sec + nsec * 1e-9)
            with self._lock:
                self.messages.append((stamp, data.decode()))

    def snapshot(self) -> list[tuple[float, str]]:
        with self._lock:
            return list(self.messages)

    def first(self, text: str, after: float = 0.0) -> float | None:
        """Arrival time of the first datagram equal to `text` that arrived after `after`."""
        return next((t for t, m in self.snapshot() if m == text and t > after), None)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.sock.close()


@dataclass
class DaemonProc:
    """One `ddrt run` child with its files."""

    proc: subprocess.Popen[bytes]
    workdir: Path
    config: Path
    socket: str
    telemetry_dir: Path
    stats_json: Path
    stderr_file: Path
    t_start: float
    notify: NotifyListener | None = None
    _closed: bool = field(default=False, repr=False)

    def request(self, payload: dict[str, Any], timeout: float | None = None) -> dict[str, Any]:
        if timeout is None:
            timeout = FOLLOW_TIMEOUT_S if payload.get("cmd") == "follow" else REPLY_TIMEOUT_S
        try:
            return request(self.socket, payload, timeout=timeout)
        except (ControlClientError, TimeoutError):
            self.check_alive()  # a dead daemon: fail with its log, not a socket error
            raise

    def status(self) -> dict[str, Any]:
        reply = self.request({"cmd": "status"})
        assert reply["ok"] is True, reply
        return reply["status"]

    def stderr(self) -> str:
        return self.stderr_file.read_text(errors="replace")

    def telemetry(self) -> list[dict[str, float]]:
        with open(self.telemetry_dir / "telemetry.csv", newline="") as f:
            reader = csv.reader(f)
            header = next(reader)
            assert tuple(header) == COLUMNS
            return [dict(zip(header, map(float, row))) for row in reader if len(row) == len(header)]

    def check_alive(self) -> None:
        if self.proc.poll() is not None:
            pytest.fail(f"daemon exited with {self.proc.returncode}:\n{self.stderr()}")

    def wait_ready(self) -> None:
        """Until the loop answers on its socket (the socket exists before calibration ends)."""
        def answers() -> bool:
            self.check_alive()
            try:
                return bool(self.request({"cmd": "status"}, timeout=1.0).get("ok"))
            except (ControlClientError, TimeoutError):
                return False
        wait_for(answers, START_TIMEOUT_S, "the daemon's first status reply", interval=0.05)

    def close(self) -> None:
        """Kill the child if it still runs; close the notify socket; remove the files."""
        if self._closed:
            return
        self._closed = True
        if self.proc.poll() is None:
            self.proc.kill()
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            pass
        if self.notify is not None:
            self.notify.close()
        shutil.rmtree(self.workdir, ignore_errors=True)


def start_daemon(*args: str, notify: bool = False, env_extra: dict[str, str] | None = None,
                 **sections: Any) -> DaemonProc:
    """Write a config (sim.yaml plus `sections`) and start `ddrt run` on it with `args`."""
    workdir = Path(tempfile.mkdtemp(prefix="ddrtd-", dir="/tmp"))  # short: sun_path is 108 bytes
    listener = None
    try:
        telemetry_dir = workdir / "tel"
        config = workdir / "cfg.yaml"
        write_config(config, telemetry_dir, **sections)
        sock = str(workdir / "ctl.sock")
        stats = workdir / "stats.json"
        stderr_file = workdir / "stderr.log"
        env = {k: v for k, v in os.environ.items()
               if k not in ("NOTIFY_SOCKET", "WATCHDOG_USEC", "WATCHDOG_PID", "JOURNAL_STREAM", "LOGS_DIRECTORY")}
        if notify:
            listener = NotifyListener(str(workdir / "notify"))
            env["NOTIFY_SOCKET"] = listener.path
        env.update(env_extra or {})
        cmd = [sys.executable, "-m", "ddrt.cli", "run", str(config), "--socket", sock,
               "--stats-json", str(stats), *args]
        with open(stderr_file, "wb") as err, open(workdir / "stdout.log", "wb") as out:
            t_start = time.monotonic()
            proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=out, stderr=err, stdin=subprocess.DEVNULL)
    except BaseException:
        if listener is not None:
            listener.close()
        shutil.rmtree(workdir, ignore_errors=True)
        raise
    return DaemonProc(proc, workdir, config, sock, telemetry_dir, stats, stderr_file, t_start, listener)


@contextlib.contextmanager
def ready_daemon(*args: str, **sections: Any) -> Iterator[DaemonProc]:
    """A daemon started as start_daemon does, past its calibration, closed afterwards."""
    d = start_daemon(*args, **sections)
    try:
        d.wait_ready()
        yield d
    finally:
        d.close()


def ctl(sock: str, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "ddrt.cli", "ctl", "--socket", sock, *args],
                          cwd=REPO, capture_output=True, text=True, timeout=FOLLOW_TIMEOUT_S + REPLY_TIMEOUT_S)


def raw_exchange(sock_path: str, data: bytes, timeout: float = REPLY_TIMEOUT_S) -> dict[str, Any]:
    """Send raw bytes on a fresh connection and return the first reply line as JSON."""
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(timeout)
        s.connect(sock_path)
        s.sendall(data)
        return read_reply(s)


def read_reply(s: socket.socket) -> dict[str, Any]:
    buf = b""
    while b"\n" not in buf:
        chunk = s.recv(65536)
        if not chunk:
            raise AssertionError(f"connection closed without a reply (got {buf[:200]!r})")
        buf += chunk
    return json.loads(buf[: buf.index(b"\n")])


def at_rest_and_reset(d: "DaemonProc") -> "DaemonProc":
    """A shared daemon stopped, at rest and reset: a clean start for the next test on it."""
    d.request({"cmd": "stop"})
    wait_for(lambda: d.status()["state"] in ("idle", "stopped"), 10.0, "at rest")
    assert d.request({"cmd": "reset"})["ok"] is True
    return d
