"""The control socket under abuse: how long an operator's estop takes to be answered while
other clients hold connections open, dribble blank lines or flood connect().

The server is the daemon's (ddrt.service.ctlserver.ControlServer with the daemon's
commands, priorities and never-refused set); a stand-in loop thread polls it every 5 ms, the
200 Hz tick, with a handler that does no work, so the figure is the socket's own share: the
wait for the next poll plus the I/O thread. `python -m bench.ctl_flood` prints the table.
"""

from __future__ import annotations

import collections
import os
import resource
import shutil
import socket
import statistics
import tempfile
import threading
import time
from dataclasses import dataclass
from typing import Any, Sequence

from bench.common import percentile
from ddrt.service.commands import COMMANDS, NEVER_REFUSED, PRIORITY
from ddrt.service.ctlclient import connect, request
from ddrt.service.ctlserver import ControlServer

COUNTS = (0, 32, 100, 1000)
POLL_PERIOD_S = 0.005
ESTOPS = 50


@dataclass(frozen=True)
class FloodRow:
    kind: str  # "idle", "dribbling" or "connect flood"
    connections: int  # held by the attacker (for the flood: opened during the run)
    answered: int
    sent: int
    median_ms: float | None
    p99_ms: float | None
    max_ms: float | None
    evicted: int
    note: str = ""


def _connect(path: str, timeout: float = 5.0) -> socket.socket | None:
    """A non-blocking client socket, or None if the server did not let it in within `timeout`."""
    try:
        s = connect(path, timeout, retry_s=0.001)
    except OSError:  # the backlog stayed full (TimeoutError), or the server is gone
        return None
    s.setblocking(False)
    return s


def _fd_room(n: int) -> bool:
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    need = n + 200
    if soft == resource.RLIM_INFINITY or soft >= need:
        return True
    if hard != resource.RLIM_INFINITY and hard < need:
        return False
    resource.setrlimit(resource.RLIMIT_NOFILE, (need, hard))
    return True


def measure_one(kind: str, n: int, estops: int = ESTOPS) -> FloodRow:
    if not _fd_room(n):
        return FloodRow(kind, n, 0, 0, None, None, None, 0, note="RLIMIT_NOFILE too low for the clients")
    workdir = tempfile.mkdtemp(prefix="ddrt-bench-", dir="/tmp")
    srv = ControlServer(os.path.join(workdir, "b.sock"), commands=COMMANDS, priority=PRIORITY,
                        never_refused=NEVER_REFUSED)
    stop = threading.Event()

    def handler(req: dict[str, Any]) -> dict[str, Any]:
        return {"ok": True, "state": "estop" if req["cmd"] == "estop" else "idle"}

    def loop() -> None:
        while not stop.is_set():
            srv.poll(handler)
            time.sleep(POLL_PERIOD_S)

    held: list[socket.socket] = []
    opened = [0]

    def dribble() -> None:
        while not stop.is_set():
            for s in held:
                try:
                    s.send(b"\n")
                    s.recv(65536)
                except OSError:
                    pass
            stop.wait(0.02)

    def flood() -> None:
        mine: collections.deque[socket.socket] = collections.deque()
        while not stop.is_set():
            s = _connect(srv.path, 0.5)
            if s is None:
                continue
            mine.append(s)
            opened[0] += 1
            if len(mine) > 200:
                mine.popleft().close()
        for s in mine:
            s.close()

    threads = [threading.Thread(target=loop, daemon=True)]
    try:
        threads[0].start()
        if kind == "connect flood":
            threads += [threading.Thread(target=flood, daemon=True) for _ in range(2)]
        else:
            for _ in range(n):
                s = _connect(srv.path)
                if s is not None:
                    held.append(s)
            if kind == "dribbling":
                threads.append(threading.Thread(target=dribble, daemon=True))
        for t in threads[1:]:
            t.start()
        time.sleep(0.3)
        lat: list[float] = []
        for i in range(estops):
            t0 = time.perf_counter()
            try:
                reply = request(srv.path, {"cmd": "estop", "id": i}, timeout=5.0)
            except (OSError, TimeoutError):
                continue
            if reply.get("ok") is True and reply.get("id") == i:
                lat.append(time.perf_counter() - t0)
            time.sleep(0.01)
    finally:
        stop.set()
        for t in threads:
            t.join(timeout=5.0)
        for s in held:
            s.close()
        evicted = srv.evicted
        srv.close()
        shutil.rmtree(workdir, ignore_errors=True)
    count = opened[0] if kind == "connect flood" else n
    if not lat:
        return FloodRow(kind, count, 0, estops, None, None, None, evicted)
    return FloodRow(kind, count, len(lat), estops, statistics.median(lat) * 1e3, percentile(lat, 99) * 1e3,
                    max(lat) * 1e3, evicted)


def measure_ctl_flood(counts: Sequence[int] = COUNTS, estops: int = ESTOPS) -> list[FloodRow]:
    rows = [measure_one("idle", n, estops) for n in counts]
    rows += [measure_one("dribbling", n, estops) for n in counts if n > 0]
    rows.append(measure_one("connect flood", 0, estops))
    return rows


def _ms(x: float | None) -> str:
    return "-" if x is None else f"{x:.1f}"


def render(rows: Sequence[FloodRow]) -> list[str]:
    lines = [
        "An operator's `estop` over the control socket (a fresh connection, `ddrt.service.ctlclient.request`) "
        f"while other clients abuse it; the daemon's server settings (32 clients, 60 s idle rule, 20 requests/s "
        f"per connection); a stand-in loop polls every {POLL_PERIOD_S * 1e3:g} ms (the 200 Hz tick) with a "
        "handler that does nothing, so this is the socket's own share. idle: connections opened and left silent; "
        "dribbling: each sends a blank line every 20 ms; connect flood: two threads connect as fast as they "
        "can throughout (count = connections opened during the run). Round trip in ms.",
        "",
        "| others | kind | answered | median | p99 | max | evicted |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        note = f" ({r.note})" if r.note else ""
        lines.append(f"| {r.connections} | {r.kind}{note} | {r.answered}/{r.sent} | {_ms(r.median_ms)} | "
                     f"{_ms(r.p99_ms)} | {_ms(r.max_ms)} | {r.evicted} |")
    return lines


if __name__ == "__main__":
    print("\n".join(render(measure_ctl_flood())))
