"""The control socket: framing, validation in the I/O thread, and resistance to bad clients."""

from __future__ import annotations

import json
import os
import shutil
import socket
import stat
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from ddrt.service.ctlclient import ControlClientError, connect, request
from ddrt.service.ctlserver import ControlServer
from tests.support.cpu_queue import Stopwatch

WAIT_S = 30.0  # cap on waiting for a state a thread here reaches at once when it gets a CPU

COMMANDS = {"status", "stop", "estop", "gains", "boom", "bad"}


class Loop:
    """Stands in for the control loop: polls the server between 'ticks' of 1 ms."""

    def __init__(self, server: ControlServer) -> None:
        self.server = server
        self.seen: list[dict[str, Any]] = []
        self.longest_poll = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def handler(self, req: dict[str, Any]) -> dict[str, Any]:
        self.seen.append(req)
        if req["cmd"] == "boom":
            raise RuntimeError("controller exploded")
        if req["cmd"] == "bad":
            return ["not", "a", "dict"]  # type: ignore[return-value]
        return {"cmd": req["cmd"], "arg": req.get("arg")}

    def _run(self) -> None:
        while not self._stop.is_set():
            with Stopwatch() as watch:  # less any wait for a CPU: a loaded host's, not the poll's
                self.server.poll(self.handler)
            self.longest_poll = max(self.longest_poll, watch.running_s)
            time.sleep(0.001)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)


@pytest.fixture()
def sockdir() -> Iterator[str]:
    d = tempfile.mkdtemp(prefix="ddrt-ctl-", dir="/tmp")  # short: sun_path is 108 bytes
    yield d
    shutil.rmtree(d, ignore_errors=True)


@pytest.fixture()
def server(sockdir: str) -> Iterator[ControlServer]:
    srv = ControlServer(os.path.join(sockdir, "ddrt.sock"), commands=COMMANDS, max_request_bytes=1024,
                        request_timeout_s=0.4)
    yield srv
    srv.close()


@pytest.fixture()
def loop(server: ControlServer) -> Iterator[Loop]:
    lp = Loop(server)
    yield lp
    lp.stop()


def raw(server: ControlServer) -> socket.socket:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(WAIT_S)
    s.connect(server.path)
    return s


def read_line(s: socket.socket) -> dict[str, Any]:
    buf = b""
    while not buf.endswith(b"\n"):
        chunk = s.recv(4096)
        assert chunk, f"connection closed, got {buf!r}"
        buf += chunk
    return json.loads(buf)


def read_lines(s: socket.socket, n: int) -> list[dict[str, Any]]:
    buf = b""
    while buf.count(b"\n") < n:
        chunk = s.recv(4096)
        assert chunk, f"connection closed, got {buf!r}"
        buf += chunk
    return [json.loads(x) for x in buf.splitlines()]


# ----- round trips -------------------------------------------------------------------------

def test_round_trip(server: ControlServer, loop: Loop) -> None:
    reply = request(server.path, {"cmd": "gains", "arg": {"kp": 1.5}, "id": 7})
    assert reply == {"ok": True, "cmd": "gains", "arg": {"kp": 1.5}, "id": 7}
    assert loop.seen == [{"cmd": "gains", "arg": {"kp": 1.5}, "id": 7}]


def test_handler_exception_becomes_error_reply(server: ControlServer, loop: Loop) -> None:
    reply = request(server.path, {"cmd": "boom"})
    assert reply["ok"] is False and "controller exploded" in reply["error"] and "boom" in reply["error"]
    assert request(server.path, {"cmd": "bad"})["ok"] is False  # not a dict
    assert request(server.path, {"cmd": "status"})["ok"] is True  # the loop is still alive


def test_pipelined_requests_on_one_connection(server: ControlServer, loop: Loop) -> None:
    with raw(server) as s:
        s.sendall(b'{"cmd": "status", "id": 1}\n{"cmd": "stop", "id": 2}\n\n{"cmd": "estop", "id": 3}\n')
        replies = read_lines(s, 3)
    assert [(r["id"], r["cmd"]) for r in replies] == [(1, "status"), (2, "stop"), (3, "estop")]


def test_last_line_without_newline_at_eof_is_answered(server: ControlServer, loop: Loop) -> None:
    with raw(server) as s:
        s.sendall(b'{"cmd": "status"}')
        s.shutdown(socket.SHUT_WR)
        assert read_line(s)["cmd"] == "status"
        assert s.recv(10) == b""  # then the server closes


# ----- rejected in the I/O thread ----------------------------------------------------------

@pytest.mark.parametrize("line, fragment", [
    (b"not json at all", "malformed JSON"),
    (b"\xff\xfe garbage \x00", "malformed JSON"),
    (b'{"cmd": "status"', "malformed JSON"),
    (b"[1, 2, 3]", "JSON object"),
    (b'"status"', "JSON object"),
    (b'{"command": "status"}', "missing field 'cmd'"),
    (b'{"cmd": 5}', "must be a string"),
    (b'{"cmd": "fly", "id": "x"}', "unknown command 'fly'"),
    # a duplicate key is refused, naming it, rather than the last one silently taking effect
    (b'{"cmd":"estop","cmd":"status"}', "duplicate key 'cmd'"),
    (b'{"cmd":"follow","pose":{"a":1,"a":2}}', "duplicate key 'a'"),
    (b"[" * 5000 + b"]" * 5000, None),  # too large here; deeply nested otherwise
])
def test_bad_requests_never_reach_the_loop(server: ControlServer, loop: Loop, line: bytes,
                                           fragment: str | None) -> None:
    with raw(server) as s:
        s.sendall(line + b"\n")
        reply = read_line(s)
        assert reply["ok"] is False
        if fragment:
            assert fragment in reply["error"]
        s.sendall(b'{"cmd": "status"}\n')  # the connection stays usable
        assert read_line(s)["ok"] is True
    assert [r["cmd"] for r in loop.seen] == ["status"]


def test_unknown_command_error_names_it_and_echoes_id(server: ControlServer, loop: Loop) -> None:
    reply = request(server.path, {"cmd": "selfdestruct", "id": 42})
    assert reply["ok"] is False and reply["id"] == 42
    assert "'selfdestruct'" in reply["error"] and "status" in reply["error"]


def test_deeply_nested_json_within_size_limit(sockdir: str) -> None:
    with ControlServer(os.path.join(sockdir, "n.sock"), commands={"status"}, max_request_bytes=60000) as srv:
        with raw(srv) as s:
            s.sendall(b'{"cmd": "status", "x": ' + b"[" * 25000 + b"]" * 25000 + b"}\n")
            reply = read_line(s)
        assert reply["ok"] is False and "malformed JSON" in reply["error"]
        assert srv.queued == 0


def test_oversized_line_rejected_then_connection_recovers(server: ControlServer, loop: Loop) -> None:
    with raw(server) as s:
        s.sendall(b'{"cmd": "status", "pad": "' + b"x" * 5000)  # no newline yet, > 1024 bytes
        reply = read_line(s)  # the error comes before the line even ends
        assert reply["ok"] is False and "too large" in reply["error"]
        s.sendall(b"x" * 3000 + b'"}\n{"cmd": "estop"}\n')  # rest of the big line is skipped
        assert read_line(s)["cmd"] == "estop"
    assert [r["cmd"] for r in loop.seen] == ["estop"]


def test_oversized_complete_line_rejected(server: ControlServer, loop: Loop) -> None:
    with raw(server) as s:
        s.sendall(b'{"cmd": "status", "pad": "' + b"y" * 1500 + b'"}\n')
        assert "too large" in read_line(s)["error"]
    assert loop.seen == []


# ----- many and misbehaving clients --------------------------------------------------------

def test_twenty_concurrent_clients(server: ControlServer, loop: Loop) -> None:
    results: dict[int, dict] = {}
    errors: list[BaseException] = []

    def client(i: int) -> None:
        try:
            for k in range(3):
                results[i * 10 + k] = request(server.path, {"cmd": "status", "arg": i * 10 + k}, timeout=WAIT_S)
        except BaseException as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=client, args=(i,)) for i in range(20)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=2 * WAIT_S)
    assert not errors, errors
    assert len(results) == 60
    assert all(r["ok"] and r["arg"] == key for key, r in results.items())


def test_slowloris_does_not_block_others_and_is_cut_off(server: ControlServer, loop: Loop) -> None:
    hang = raw(server)
    hang.sendall(b'{"cmd": "sta')  # half a line, then nothing
    with Stopwatch("self") as watch:  # less what this process's threads waited for a CPU
        for _ in range(5):
            assert request(server.path, {"cmd": "status"}, timeout=WAIT_S)["ok"]
    assert watch.running_s < 1.0, (watch.wall, watch.queued)
    # After request_timeout_s (0.4 s) the half-line connection gets an error and is closed.
    reply = read_line(hang)
    assert reply["ok"] is False and "not finished" in reply["error"]
    assert hang.recv(10) == b""
    hang.close()
    assert loop.longest_poll < 0.05


def test_client_disconnecting_mid_request(server: ControlServer, loop: Loop) -> None:
    s = raw(server)
    s.sendall(b'{"cmd": "stat')
    s.close()
    s = raw(server)
    s.sendall(b'{"cmd": "estop"}\n')
    s.close()  # gone before the reply: the command still runs, the reply is dropped
    deadline = time.monotonic() + WAIT_S
    while not loop.seen and time.monotonic() < deadline:
        time.sleep(0.005)
    assert [r["cmd"] for r in loop.seen] == ["estop"]
    assert request(server.path, {"cmd": "status"})["ok"]
    deadline = time.monotonic() + WAIT_S
    while server.clients and time.monotonic() < deadline:
        time.sleep(0.005)
    assert server.clients == 0


def test_client_that_never_reads_replies(sockdir: str) -> None:
    srv = ControlServer(os.path.join(sockdir, "r.sock"), commands={"status"}, max_reply_backlog_bytes=4096)
    lp = Loop(srv)
    try:
        hog = raw(srv)
        try:
            hog.sendall(b"junk\n" * 20000)  # 20000 error replies it never reads
        except (BrokenPipeError, ConnectionResetError):
            pass  # already cut off: fine
        assert request(srv.path, {"cmd": "status"}, timeout=WAIT_S)["ok"] is True
        deadline = time.monotonic() + WAIT_S
        while srv.clients and time.monotonic() < deadline:
            time.sleep(0.01)
        assert srv.clients == 0  # dropped once its unread backlog passed the bound
        hog.close()
    finally:
        lp.stop()
        srv.close()


def test_client_limit(sockdir: str) -> None:
    """At the cap a newcomer is still served: the longest-idle client is told and closed.

    (Refusing the newcomer with "too many clients" would let 32 idle connections lock out an
    estop, so that message goes to the evicted one.)
    """
    with ControlServer(os.path.join(sockdir, "m.sock"), commands={"status"}, max_clients=3) as srv:
        lp = Loop(srv)
        try:
            held = []
            for _ in range(3):
                held.append(raw(srv))
                time.sleep(0.02)  # held[0] is the longest idle
            deadline = time.monotonic() + WAIT_S
            while srv.clients < 3 and time.monotonic() < deadline:
                time.sleep(0.005)
            with raw(srv) as extra:
                reply = read_line(held[0])
                assert reply["ok"] is False and "too many clients (max 3)" in reply["error"]
                assert held[0].recv(10) == b""
                extra.sendall(b'{"cmd": "status", "id": "new"}\n')
                assert read_line(extra) == {"ok": True, "cmd": "status", "arg": None, "id": "new"}
                assert srv.clients == 3 and srv.evicted == 1
            for h in held:
                h.close()
        finally:
            lp.stop()


# ----- the loop side -----------------------------------------------------------------------

def test_poll_never_blocks_when_idle(server: ControlServer) -> None:
    calls = []
    with Stopwatch() as watch:  # less any wait for a CPU: a blocking poll would still show
        for _ in range(2000):
            assert server.poll(calls.append) == 0
    elapsed = watch.running_s
    assert calls == []
    assert elapsed < 0.2, f"2000 idle polls took {elapsed:.3f} s"


def test_poll_bounds_work_per_tick(server: ControlServer) -> None:
    with raw(server) as s:
        s.sendall(b"".join(b'{"cmd": "status", "id": %d}\n' % i for i in range(6)))
        deadline = time.monotonic() + WAIT_S
        while server.queued < 6 and time.monotonic() < deadline:
            time.sleep(0.005)
        handled: list[int] = []
        assert server.poll(lambda r: handled.append(r["id"]) or {}, max_requests=4) == 4
        assert server.poll(lambda r: handled.append(r["id"]) or {}, max_requests=4) == 2
        assert handled == list(range(6))
        assert [r["id"] for r in read_lines(s, 6)] == list(range(6))


def test_queue_is_bounded(sockdir: str) -> None:
    with ControlServer(os.path.join(sockdir, "q.sock"), commands={"status"}, max_pending_per_client=2) as srv:
        with raw(srv) as s:
            s.sendall(b'{"cmd": "status", "id": 1}\n{"cmd": "status", "id": 2}\n{"cmd": "status", "id": 3}\n')
            reply = read_line(s)  # the third is refused at once; nobody is polling
            assert reply == {"ok": False, "error": reply["error"], "id": 3} and "busy" in reply["error"]
            assert srv.queued == 2


def test_request_times_out_when_loop_does_not_poll(server: ControlServer) -> None:
    with Stopwatch() as watch:
        with pytest.raises(TimeoutError, match="no reply"):
            request(server.path, {"cmd": "status"}, timeout=0.3)
    assert watch.wall > 0.25 and watch.running_s < 2.0, (watch.wall, watch.queued)


# ----- the socket file ---------------------------------------------------------------------

def test_socket_file_mode_and_removal(server: ControlServer) -> None:
    st = os.stat(server.path)
    assert stat.S_ISSOCK(st.st_mode)
    assert stat.S_IMODE(st.st_mode) == 0o660
    assert server._listener.family == socket.AF_UNIX  # never a network listener
    path = server.path
    server.close()
    assert not os.path.exists(path)
    with pytest.raises(ControlClientError, match="does not exist"):
        request(path, {"cmd": "status"})


def test_stale_socket_from_crash_is_replaced(sockdir: str) -> None:
    path = os.path.join(sockdir, "stale.sock")
    dead = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    dead.bind(path)
    dead.close()  # the file stays, nobody listens: what a crash leaves behind
    assert os.path.exists(path)
    with ControlServer(path, commands={"status"}) as srv:
        lp = Loop(srv)
        try:
            assert request(path, {"cmd": "status"})["ok"]
        finally:
            lp.stop()


def test_live_socket_is_not_stolen(server: ControlServer) -> None:
    with pytest.raises(OSError, match="another process"):
        ControlServer(server.path, commands={"status"})
    assert os.path.exists(server.path)


def test_regular_file_is_not_replaced(sockdir: str) -> None:
    path = os.path.join(sockdir, "notasocket")
    with open(path, "w") as f:
        f.write("keep me")
    with pytest.raises(FileExistsError, match="not a socket"):
        ControlServer(path)
    assert open(path).read() == "keep me"


@pytest.mark.parametrize("kwargs, field", [
    (dict(max_request_bytes=0), "max_request_bytes"), (dict(commands=[]), "commands"),
    (dict(idle_timeout_s=0), "idle_timeout_s"), (dict(path="/tmp/" + "x" * 200), "path"),
])
def test_rejects_bad_config(sockdir: str, kwargs: dict, field: str) -> None:
    args: dict[str, Any] = dict(path=os.path.join(sockdir, "c.sock"))
    args.update(kwargs)
    with pytest.raises(ValueError, match=field):
        ControlServer(**args)


def test_request_rejects_bad_payload(sockdir: str) -> None:
    with pytest.raises(ValueError, match="cmd"):
        request(os.path.join(sockdir, "x.sock"), {"command": "status"})


# ----- nobody locks a command out ----------------------------------------------------------

DAEMON_LIKE = dict(priority={"estop": ("follow", "reset"), "stop": ("follow",)}, never_refused=("estop",))
SAFETY_COMMANDS = {"status", "stop", "estop", "reset", "follow"}


def strict(data: bytes) -> Any:
    def no_constants(token: str) -> Any:
        raise ValueError(f"{token} in a reply: not JSON")
    return json.loads(data, parse_constant=no_constants)


def _room_for(n: int) -> None:
    """n client sockets in this process need descriptors: raise the soft limit, or skip."""
    import resource

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    need = n + 200
    if soft != resource.RLIM_INFINITY and soft < need:
        if hard != resource.RLIM_INFINITY and hard < need:
            pytest.skip(f"RLIMIT_NOFILE hard limit {hard} < {need}")
        resource.setrlimit(resource.RLIMIT_NOFILE, (need, hard))


class Dribbler:
    """Keeps sending what is not a command (blank lines, whitespace, a malformed line) on
    every socket it holds, as an attacker keeping connections alive would."""

    CHAFF = (b"\n", b"   \n", b"\t \r\n", b'{"cmd"\n')

    def __init__(self, socks: list[socket.socket], period_s: float, drain: bool = True) -> None:
        self.socks = socks
        self.period_s = period_s
        self.drain = drain
        for s in socks:
            s.setblocking(False)  # with a timeout, Python waits for readiness even with MSG_DONTWAIT
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        i = 0
        while not self._stop.is_set():
            for s in self.socks:
                try:
                    s.send(self.CHAFF[i % len(self.CHAFF)])
                    if self.drain:
                        s.recv(65536)  # its error replies
                except OSError:
                    pass
            i += 1
            self._stop.wait(self.period_s)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)


@pytest.mark.parametrize("n", [32, 100, 1000])
@pytest.mark.parametrize("kind", ["idle", "dribbling"])
def test_estop_is_answered_whatever_other_connections_do(sockdir: str, n: int, kind: str) -> None:
    _room_for(n)
    srv = ControlServer(os.path.join(sockdir, "e.sock"), commands=SAFETY_COMMANDS, **DAEMON_LIKE)
    lp = Loop(srv)
    held: list[socket.socket] = []
    dribbler = None
    try:
        for _ in range(n):
            held.append(connect(srv.path, WAIT_S))
        if kind == "dribbling":
            dribbler = Dribbler(held, 0.02)
        deadline = time.monotonic() + WAIT_S
        while srv.clients < min(n, srv.max_clients) and time.monotonic() < deadline:
            time.sleep(0.01)
        time.sleep(0.1)
        for attempt in range(3):
            # Less what this process's threads (client, I/O, loop, dribbler) waited for a CPU.
            with Stopwatch("self") as watch:
                reply = request(srv.path, {"cmd": "estop", "id": attempt}, timeout=WAIT_S)
            elapsed = watch.running_s
            assert reply == {"ok": True, "cmd": "estop", "arg": None, "id": attempt}
            assert elapsed < 1.0, f"estop took {elapsed:.3f} s ({watch.wall:.3f} s) with {n} {kind} connections"
        assert srv.clients <= srv.max_clients
        assert srv.evicted >= n + 1 - srv.max_clients
    finally:
        if dribbler is not None:
            dribbler.stop()
        for s in held:
            s.close()
        lp.stop()
        srv.close()


IDLE_S = 2.0  # test_only_commands_keep_a_connection_open's idle timeout


def test_only_commands_keep_a_connection_open(sockdir: str) -> None:
    """Blank lines, whitespace and malformed lines are no activity: the idle timeout still
    closes the connection (a stream of blank lines must not hold it open). The
    idle timeout is long beside the active client's 0.1 s between commands, so a loaded host
    cannot make that one look idle."""
    srv = ControlServer(os.path.join(sockdir, "i.sock"), commands={"status"}, idle_timeout_s=IDLE_S,
                        request_timeout_s=0.4)
    lp = Loop(srv)
    try:
        chaff = raw(srv)
        active = raw(srv)
        dribbler = Dribbler([chaff], 0.05, drain=False)
        t0 = time.monotonic()
        try:
            while time.monotonic() - t0 < IDLE_S + 1.0:
                active.sendall(b'{"cmd": "status"}\n')
                assert read_line(active)["ok"] is True
                time.sleep(0.1)
        finally:
            dribbler.stop()
        # The dribbler's socket: its error replies to '{"cmd"', then the closing notice, then EOF.
        chaff.settimeout(WAIT_S)
        data = b""
        while True:
            chunk = chaff.recv(65536)
            if not chunk:
                break
            data += chunk
        lines = [strict(x) for x in data.splitlines()]
        assert lines and f"no command for {IDLE_S:g} s" in lines[-1]["error"]
        assert all(r["ok"] is False for r in lines)
        active.sendall(b'{"cmd": "status"}\n')
        assert read_line(active)["ok"] is True  # a client that sends commands stays
        assert srv.idle_closed == 1
        chaff.close()
        active.close()
    finally:
        lp.stop()
        srv.close()


def test_rate_limit_answers_at_once_and_spares_estop(sockdir: str) -> None:
    srv = ControlServer(os.path.join(sockdir, "r.sock"), commands=SAFETY_COMMANDS, rate_per_s=2.0, rate_burst=3,
                        **DAEMON_LIKE)
    try:
        with raw(srv) as s:
            s.sendall(b"".join(b'{"cmd": "status", "id": %d}\n' % i for i in range(6)))
            refused = read_lines(s, 3)  # nobody polls: only the refusals come back, at once
            assert [r["id"] for r in refused] == [3, 4, 5]
            assert all(r["ok"] is False and "rate limit" in r["error"] and "2 requests/s" in r["error"]
                       for r in refused)
            assert srv.queued == 3  # the burst, not the refused ones
            s.sendall(b"".join(b'{"cmd": "estop", "id": %d}\n' % i for i in range(10, 15)))
            deadline = time.monotonic() + WAIT_S
            while srv.queued < 8 and time.monotonic() < deadline:
                time.sleep(0.005)
            assert srv.queued == 8  # estop is never rate limited
            handled: list[Any] = []
            while srv.poll(lambda r: handled.append(r["id"]) or {}):
                pass
            assert handled == [0, 1, 2, 10, 11, 12, 13, 14]  # one connection's requests stay in order
            replies = read_lines(s, 8)
            assert [r["id"] for r in replies] == handled and all(r["ok"] for r in replies)
        assert srv.rate_limited == 3
    finally:
        srv.close()


def _wait_queued(srv: ControlServer, n: int) -> None:
    deadline = time.monotonic() + WAIT_S
    while srv.queued < n and time.monotonic() < deadline:
        time.sleep(0.005)
    assert srv.queued == n


def test_a_burst_from_one_client_does_not_starve_another(sockdir: str) -> None:
    with ControlServer(os.path.join(sockdir, "f.sock"), commands=SAFETY_COMMANDS, **DAEMON_LIKE) as srv:
        with raw(srv) as hog, raw(srv) as other, raw(srv) as operator:
            hog.sendall(b"".join(b'{"cmd": "status", "id": "hog%d"}\n' % i for i in range(8)))
            _wait_queued(srv, 8)
            other.sendall(b'{"cmd": "status", "id": "other"}\n')
            _wait_queued(srv, 9)
            operator.sendall(b'{"cmd": "estop", "id": "op"}\n')
            _wait_queued(srv, 10)
            handled: list[str] = []

            def handler(r: dict[str, Any]) -> dict[str, Any]:
                handled.append(r["id"])
                return {}
            assert srv.poll(handler, max_requests=1) == 2
            assert handled == ["op", "hog0"]  # estop first, though it came last
            assert srv.poll(handler, max_requests=1) == 1
            assert handled[-1] == "other"  # then in turn: not behind the hog's whole burst
            while srv.poll(handler, max_requests=1):
                pass
            assert handled[3:] == [f"hog{i}" for i in range(1, 8)]
            assert read_line(operator) == {"ok": True, "id": "op"}
            assert read_line(other) == {"ok": True, "id": "other"}


def test_estop_supersedes_a_reset_sent_before_it(sockdir: str) -> None:
    """Served first, an estop must not be undone by a reset (or a follow) queued ahead of it."""
    with ControlServer(os.path.join(sockdir, "s.sock"), commands=SAFETY_COMMANDS, **DAEMON_LIKE) as srv:
        with raw(srv) as a, raw(srv) as b:
            a.sendall(b'{"cmd": "status", "id": 1}\n{"cmd": "reset", "id": 2}\n{"cmd": "follow", "id": 3}\n')
            _wait_queued(srv, 3)
            b.sendall(b'{"cmd": "estop", "id": 4}\n')
            _wait_queued(srv, 4)
            handled: list[str] = []
            while srv.poll(lambda r: handled.append(r["cmd"]) or {}):
                pass
            assert handled == ["estop", "status"]
            replies = read_lines(a, 3)
            assert replies[0] == {"ok": True, "id": 1}
            for r, cmd in zip(replies[1:], ("reset", "follow")):
                assert r["ok"] is False and r["error"].startswith(f"{cmd} not run: the estop sent after it")
            assert read_line(b) == {"ok": True, "id": 4}
            a.sendall(b'{"cmd": "reset", "id": 5}\n')  # sent after the estop: it runs
            _wait_queued(srv, 1)
            assert srv.poll(lambda r: handled.append(r["cmd"]) or {}) == 1
            assert handled[-1] == "reset" and read_line(a) == {"ok": True, "id": 5}


# ----- strict JSON -------------------------------------------------------------------------

@pytest.mark.parametrize("line, where, token, rid", [
    (b'{"cmd": "status", "id": NaN}', "id", "NaN", None),
    (b'{"cmd": "status", "id": 1, "arg": Infinity}', "arg", "Infinity", 1),
    (b'{"cmd": "status", "id": "x", "arg": {"pose": [0, -Infinity, 0]}}', "arg.pose[1]", "-Infinity", "x"),
    (b'{"cmd": "status", "id": 2, "arg": 1e999}', "arg", "1e999", 2),
    (b'{"cmd": NaN}', "cmd", "NaN", None),
])
def test_non_finite_numbers_are_refused_in_strict_json(server: ControlServer, loop: Loop, line: bytes,
                                                       where: str, token: str, rid: Any) -> None:
    with raw(server) as s:
        s.sendall(line + b"\n")
        buf = b""
        while not buf.endswith(b"\n"):
            buf += s.recv(4096)
    reply = strict(buf)  # the reply itself is strict JSON (an id of NaN must not come back as NaN)
    assert reply["ok"] is False and reply.get("id") == rid
    assert f"{where} is {token}" in reply["error"] and "NaN or Infinity" in reply["error"]
    assert loop.seen == []


def test_non_finite_reply_goes_out_as_null_and_says_so(sockdir: str) -> None:
    with ControlServer(os.path.join(sockdir, "n.sock"), commands={"status"}) as srv:
        with raw(srv) as s:
            s.sendall(b'{"cmd": "status", "id": 1}\n')
            _wait_queued(srv, 1)
            srv.poll(lambda r: {"pose": {"x": float("nan"), "y": 1.0}, "v": [float("inf")]})
            buf = b""
            while not buf.endswith(b"\n"):
                buf += s.recv(4096)
    assert strict(buf) == {"ok": True, "pose": {"x": None, "y": 1.0}, "v": [None], "id": 1,
                           "non_finite": ["pose.x", "v[0]"]}


def test_client_refuses_to_send_nan(sockdir: str) -> None:
    with pytest.raises(ValueError, match="strict JSON"):
        request(os.path.join(sockdir, "x.sock"), {"cmd": "follow", "pose": [0.0, float("nan"), 0.0]})


# ----- out of file descriptors -------------------------------------------------------------

_EMFILE_CHILD = r"""
import os, resource, sys, threading, time
from ddrt.service.ctlserver import ControlServer
srv = ControlServer(sys.argv[1], commands={"status", "estop"}, max_clients=10000)
stop = threading.Event()
def loop():
    while not stop.is_set():
        srv.poll(lambda r: {"cmd": r["cmd"]})
        time.sleep(0.001)
threading.Thread(target=loop, daemon=True).start()
# As good as no descriptor left: the soft limit just above what is open now.
n_open = len(os.listdir("/proc/self/fd"))
resource.setrlimit(resource.RLIMIT_NOFILE, (n_open + 8, resource.getrlimit(resource.RLIMIT_NOFILE)[1]))
filler = []
try:
    while True:
        filler.append(os.open(os.devnull, os.O_RDONLY))
except OSError:
    pass
for fd in filler[:4]:  # room for a handful of clients, no more
    os.close(fd)
print("ready", flush=True)
sys.stdin.readline()
print(srv.evicted, srv.clients, flush=True)
"""


def _cpu_s(pid: int) -> float:
    fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def test_out_of_descriptors_still_serves_a_newcomer_without_spinning(sockdir: str, repo_root: Path) -> None:
    import subprocess
    import sys

    path = os.path.join(sockdir, "fd.sock")
    repo = str(repo_root)
    env = dict(os.environ, PYTHONPATH=repo)
    child = subprocess.Popen([sys.executable, "-c", _EMFILE_CHILD, path], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, env=env, cwd=repo)
    held: list[socket.socket] = []
    try:
        assert child.stdout is not None and child.stdin is not None
        assert child.stdout.readline().strip() == b"ready"
        for _ in range(100):  # far more than the few descriptors it has left
            held.append(connect(path, WAIT_S))
        time.sleep(0.3)
        with Stopwatch("self", child.pid) as watch:  # less what either process waited for a CPU
            assert request(path, {"cmd": "estop", "id": 1}, timeout=WAIT_S) == {"ok": True, "cmd": "estop", "id": 1}
        assert watch.running_s < 1.0, (watch.wall, watch.queued)
        cpu0 = _cpu_s(child.pid)
        time.sleep(1.0)
        cpu = _cpu_s(child.pid) - cpu0
        assert cpu < 0.3, f"the server used {cpu:.2f} s of CPU in 1 s while out of descriptors"
        child.stdin.write(b"\n")
        child.stdin.flush()
        evicted, clients = map(int, child.stdout.readline().split())
        assert evicted >= 90 and clients < 10
    finally:
        for s in held:
            s.close()
        child.kill()
        child.wait(timeout=10)


def test_large_unfinished_lines_share_one_budget(sockdir: str) -> None:
    """A line limit sized for a path sent as content lets two such lines be received at a
    time, not one per client: the third is refused (and discarded), the first two go through."""
    limit = 300_000
    srv = ControlServer(os.path.join(sockdir, "big.sock"), commands=COMMANDS, max_request_bytes=limit)
    lp = Loop(srv)
    try:
        pad = b"x" * (limit - 1000)
        head = b'{"cmd": "gains", "arg": "'
        socks = [raw(srv) for _ in range(3)]
        for s in socks[:2]:
            s.sendall(head + pad)
        # Both unfinished lines are held before the third one arrives.
        t_end = time.monotonic() + 60.0
        while srv._large_buffered() < 2 * len(pad) and time.monotonic() < t_end:
            time.sleep(0.01)
        socks[2].sendall(head + pad[:100_000])
        refused = read_line(socks[2])
        assert refused["ok"] is False and "other large requests" in refused["error"]
        for s in socks[:2]:
            s.sendall(b'"}\n')
            reply = read_line(s)
            assert reply["ok"] is True and len(reply["arg"]) == len(pad)
        for s in socks:
            s.close()
    finally:
        lp.stop()
        srv.close()
