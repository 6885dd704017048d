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
from typing import Any

import pytest

from ddrt.service.ctlsocket import ControlClientError, ControlServer, request

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
            t0 = time.monotonic()
            self.server.poll(self.handler)
            self.longest_poll = max(self.longest_poll, time.monotonic() - t0)
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
    s.settimeout(3.0)
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
                results[i * 10 + k] = request(server.path, {"cmd": "status", "arg": i * 10 + k}, timeout=5.0)
        except BaseException as exc:  # noqa: BLE001 - reported below
            errors.append(exc)

    threads = [threading.Thread(target=client, args=(i,)) for i in range(20)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=10)
    assert not errors, errors
    assert len(results) == 60
    assert all(r["ok"] and r["arg"] == key for key, r in results.items())


def test_slowloris_does_not_block_others_and_is_cut_off(server: ControlServer, loop: Loop) -> None:
    hang = raw(server)
    hang.sendall(b'{"cmd": "sta')  # half a line, then nothing
    t0 = time.monotonic()
    for _ in range(5):
        assert request(server.path, {"cmd": "status"}, timeout=2.0)["ok"]
    assert time.monotonic() - t0 < 1.0
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
    deadline = time.monotonic() + 2
    while not loop.seen and time.monotonic() < deadline:
        time.sleep(0.005)
    assert [r["cmd"] for r in loop.seen] == ["estop"]
    assert request(server.path, {"cmd": "status"})["ok"]
    deadline = time.monotonic() + 2
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
        assert request(srv.path, {"cmd": "status"}, timeout=2.0)["ok"] is True
        deadline = time.monotonic() + 3
        while srv.clients and time.monotonic() < deadline:
            time.sleep(0.01)
        assert srv.clients == 0  # dropped once its unread backlog passed the bound
        hog.close()
    finally:
        lp.stop()
        srv.close()


def test_client_limit(sockdir: str) -> None:
    with ControlServer(os.path.join(sockdir, "m.sock"), commands={"status"}, max_clients=3) as srv:
        held = [raw(srv) for _ in range(3)]
        deadline = time.monotonic() + 2
        while srv.clients < 3 and time.monotonic() < deadline:
            time.sleep(0.005)
        with raw(srv) as extra:
            reply = read_line(extra)
        assert reply["ok"] is False and "too many clients" in reply["error"]
        for h in held:
            h.close()


# ----- the loop side -----------------------------------------------------------------------

def test_poll_never_blocks_when_idle(server: ControlServer) -> None:
    calls = []
    t0 = time.perf_counter()
    for _ in range(2000):
        assert server.poll(calls.append) == 0
    elapsed = time.perf_counter() - t0
    assert calls == []
    assert elapsed < 0.2, f"2000 idle polls took {elapsed:.3f} s"


def test_poll_bounds_work_per_tick(server: ControlServer) -> None:
    with raw(server) as s:
        s.sendall(b"".join(b'{"cmd": "status", "id": %d}\n' % i for i in range(6)))
        deadline = time.monotonic() + 2
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
    t0 = time.monotonic()
    with pytest.raises(TimeoutError, match="no reply"):
        request(server.path, {"cmd": "status"}, timeout=0.3)
    assert 0.25 < time.monotonic() - t0 < 2.0


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
