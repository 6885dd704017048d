"""The control socket: JSON lines over a local Unix stream socket, answered between ticks.

A helper thread owns every connection: it accepts, reads, splits lines, parses JSON and
rejects anything malformed on its own (bad JSON, not an object, missing or unknown "cmd",
a line over `max_request_bytes`), so junk never costs the loop a microsecond. Valid requests
wait in a queue; the loop calls `poll(handler)` between ticks, which never blocks, runs at
most a few handlers and hands the encoded replies back to the thread to send.

Defences, because `ddrt ctl` users make mistakes and shells hang: non-blocking sockets behind
one selector (a client that stops reading or sends half a line blocks nobody), bounded
per-connection buffers, a deadline on an unfinished line, an idle timeout, a cap on clients
and on queued requests. It is a filesystem socket (mode 0660: owner and group only), never a
network listener.

Replies: `{"ok": true, ...}` from the handler, or `{"ok": false, "error": "..."}`. A request
with an "id" gets it back in the reply. A handler that cannot answer between two ticks
returns a `Deferred` and completes it later, from the loop thread (`Deferred.complete`): the
connection stays open for that reply, and other requests, on it and on other connections,
are answered meanwhile. Errors found by the thread are sent at once and may
overtake replies still queued for the loop; use "id" to match them when pipelining.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import selectors
import socket
import stat
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable

log = logging.getLogger(__name__)

DEFAULT_PATH = "/run/ddrt/ddrt.sock"
_MAX_UNIX_PATH = 107  # sun_path is 108 bytes including the terminating NUL
_READ_CHUNK = 4096


class ControlClientError(OSError):
    """`request` could not reach the daemon or got no usable reply."""


def _error_line(message: str, request_id: Any = None) -> bytes:
    reply: dict[str, Any] = {"ok": False, "error": message}
    if request_id is not None:
        reply["id"] = request_id
    return (json.dumps(reply) + "\n").encode()


class Deferred:
    """A reply that comes later: a handler returns one, and its owner calls `complete(reply)`
    once (from the loop thread) when the answer is known. Until then the request counts as
    pending on its connection. Completing it after the server closed, or twice, does nothing.
    """

    __slots__ = ("_server", "_conn", "_rid", "_cmd", "done")

    def __init__(self) -> None:
        self._server: ControlServer | None = None
        self._conn: _Conn | None = None
        self._rid: Any = None
        self._cmd: Any = None
        self.done = False

    def _bind(self, server: "ControlServer", conn: "_Conn", request: dict[str, Any]) -> None:
        self._server, self._conn = server, conn
        self._rid, self._cmd = request.get("id"), request.get("cmd")

    def complete(self, reply: dict[str, Any]) -> None:
        if self.done:
            return
        self.done = True
        server, conn = self._server, self._conn
        self._server = self._conn = None
        if server is None or conn is None or server._closed:
            return
        server._replies.append((conn, _encode_reply(reply, self._rid, self._cmd)))
        server._wake()


def _encode_reply(reply: Any, rid: Any, cmd: Any) -> bytes:
    """A handler's reply as one JSON line (an error line if it is not a JSON-able dict)."""
    try:
        if not isinstance(reply, dict):
            raise TypeError(f"handler returned {type(reply).__name__}, expected dict")
        if "ok" not in reply or (rid is not None and "id" not in reply):
            reply = {"ok": True, **reply}
            if rid is not None:
                reply.setdefault("id", rid)
        return (json.dumps(reply) + "\n").encode()
    except Exception as exc:  # the loop must survive any command
        log.warning("control command %r failed: %s: %s", cmd, type(exc).__name__, exc)
        return _error_line(f"{cmd}: {type(exc).__name__}: {exc}", rid)


@dataclass(eq=False)
class _Conn:
    sock: socket.socket
    last_active: float
    buf: bytearray = field(default_factory=bytearray)
    out: bytearray = field(default_factory=bytearray)
    line_started: float | None = None  # first byte of the unfinished line
    discarding: bool = False  # skipping the rest of an oversized line
    eof: bool = False  # the client shut its sending side
    pending: int = 0  # requests queued for the loop, not yet answered
    closed: bool = False
    writing: bool = False  # registered for EVENT_WRITE


class ControlServer:
    """Listen on `path`; answer valid requests through `poll(handler)` from the loop thread."""

    def __init__(
        self,
        path: str | os.PathLike[str] = DEFAULT_PATH,
        commands: Iterable[str] | None = None,
        max_request_bytes: int = 65536,
        *,
        mode: int = 0o660,
        max_clients: int = 32,
        max_queued: int = 64,
        max_pending_per_client: int = 8,
        request_timeout_s: float = 5.0,
        idle_timeout_s: float = 60.0,
        max_reply_backlog_bytes: int = 1 << 20,
    ) -> None:
        self.path = os.fspath(path)
        if len(os.fsencode(self.path)) > _MAX_UNIX_PATH:
            raise ValueError(f"ControlServer.path: {self.path!r} is longer than {_MAX_UNIX_PATH} bytes")
        if commands is None:
            self.commands: frozenset[str] | None = None
        else:
            self.commands = frozenset(commands)
            bad = [c for c in self.commands if not isinstance(c, str) or not c]
            if bad or not self.commands:
                names = sorted(map(repr, self.commands))
                raise ValueError(f"ControlServer.commands: expected non-empty command names, got {names}")
        for name, value in (("max_request_bytes", max_request_bytes), ("max_clients", max_clients),
                            ("max_queued", max_queued), ("max_pending_per_client", max_pending_per_client),
                            ("max_reply_backlog_bytes", max_reply_backlog_bytes)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"ControlServer.{name}: expected an int >= 1, got {value!r}")
        for name, value in (("request_timeout_s", request_timeout_s), ("idle_timeout_s", idle_timeout_s)):
            if not isinstance(value, (int, float)) or not value > 0:
                raise ValueError(f"ControlServer.{name}: expected seconds > 0, got {value!r}")
        self.max_request_bytes = max_request_bytes
        self.max_clients = max_clients
        self.max_queued = max_queued
        self.max_pending_per_client = max_pending_per_client
        self.request_timeout_s = float(request_timeout_s)
        self.idle_timeout_s = float(idle_timeout_s)
        self.max_reply_backlog_bytes = max_reply_backlog_bytes

        self._requests: deque[tuple[_Conn, dict[str, Any]]] = deque()
        self._replies: deque[tuple[_Conn, bytes]] = deque()
        self._conns: dict[int, _Conn] = {}
        self.rejected = 0  # requests answered with an error by the thread
        self._stopping = False
        self._closed = False

        self._listener = self._bind(mode)
        self._inode = os.stat(self.path).st_ino
        self._wake_r, self._wake_w = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)
        self._sel = selectors.DefaultSelector()
        self._sel.register(self._listener, selectors.EVENT_READ, "listen")
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        self._thread = threading.Thread(target=self._run, name="ddrt-ctl", daemon=True)
        self._thread.start()

    # ----- set-up -------------------------------------------------------------------------

    def _bind(self, mode: int) -> socket.socket:
        path = self.path
        try:
            st = os.lstat(path)
        except FileNotFoundError:
            pass
        else:
            if not stat.S_ISSOCK(st.st_mode):
                raise FileExistsError(errno.EEXIST,
                                      f"control socket {path}: exists and is not a socket, not replacing it")
            with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
                probe.settimeout(0.5)
                try:
                    probe.connect(path)
                except ConnectionRefusedError:
                    os.unlink(path)  # left behind by a crashed run: nobody listens
                except OSError as exc:
                    raise OSError(exc.errno, f"control socket {path}: exists and cannot be probed: {exc}") from exc
                else:
                    raise OSError(errno.EADDRINUSE, f"control socket {path}: another process is listening on it")
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
        try:
            sock.bind(path)
            # Before listen(), nobody can connect, so there is no window with looser permissions.
            os.chmod(path, mode)
            sock.listen(16)
        except OSError as exc:
            sock.close()
            raise OSError(exc.errno, f"control socket {path}: {exc.strerror or exc}") from exc
        sock.setblocking(False)
        return sock

    # ----- loop side ----------------------------------------------------------------------

    def poll(self, handler: Callable[[dict[str, Any]], "dict[str, Any] | Deferred"], max_requests: int = 4) -> int:
        """Answer up to `max_requests` queued requests; return how many. Never blocks.

        A handler that raises, or returns something that is not a JSON-able dict, produces an
        error reply; the exception does not propagate. A handler that returns a `Deferred`
        answers when it completes it.
        """
        requests = self._requests
        if not requests:  # the common case, every tick: no allocation, no exception
            return 0
        n = 0
        while n < max_requests:
            try:
                conn, request = requests.popleft()
            except IndexError:
                break
            n += 1
            rid = request.get("id")
            try:
                reply = handler(request)
            except Exception as exc:  # the loop must survive any command
                log.warning("control command %r failed: %s: %s", request.get("cmd"), type(exc).__name__, exc)
                self._replies.append((conn, _error_line(f"{request.get('cmd')}: {type(exc).__name__}: {exc}", rid)))
                continue
            if isinstance(reply, Deferred):
                reply._bind(self, conn, request)  # answered by reply.complete(), later
                continue
            self._replies.append((conn, _encode_reply(reply, rid, request.get("cmd"))))
        if n:
            self._wake()
        return n

    @property
    def queued(self) -> int:
        """Valid requests waiting for `poll`."""
        return len(self._requests)

    @property
    def clients(self) -> int:
        return len(self._conns)

    def _wake(self) -> None:
        try:
            os.write(self._wake_w, b"\0")
        except (BlockingIOError, OSError):
            pass  # the pipe is full: a wake-up is already pending (or we are closing)

    # ----- I/O thread ---------------------------------------------------------------------

    def _run(self) -> None:
        from ddrt.service.rt import demote_current_thread

        demote_current_thread()
        tick = min(0.5, self.request_timeout_s / 4, self.idle_timeout_s / 4)
        try:
            while not self._stopping:
                for key, mask in self._sel.select(tick):
                    tag = key.data
                    if tag == "listen":
                        self._accept()
                    elif tag == "wake":
                        try:
                            while os.read(self._wake_r, 512):
                                pass
                        except BlockingIOError:
                            pass
                    else:
                        conn: _Conn = tag
                        if mask & selectors.EVENT_READ and not conn.closed:
                            self._read(conn)
                        if mask & selectors.EVENT_WRITE and not conn.closed:
                            self._flush(conn)
                self._send_replies()
                self._expire(time.monotonic())
        except Exception:  # a bug here must not kill the robot, only the control socket
            log.exception("control socket thread failed; control commands are unavailable")

    def _accept(self) -> None:
        for _ in range(16):
            try:
                sock, _addr = self._listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # EMFILE and friends: try again on the next event
                log.warning("control socket accept failed: %s", exc)
                return
            sock.setblocking(False)
            if len(self._conns) >= self.max_clients:
                self.rejected += 1
                try:
                    sock.send(_error_line(f"too many clients (max {self.max_clients})"), socket.MSG_NOSIGNAL)
                except OSError:
                    pass
                sock.close()
                continue
            conn = _Conn(sock=sock, last_active=time.monotonic())
            self._conns[sock.fileno()] = conn
            self._sel.register(sock, selectors.EVENT_READ, conn)

    def _read(self, conn: _Conn) -> None:
        try:
            data = conn.sock.recv(_READ_CHUNK)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self._close_conn(conn)
            return
        now = time.monotonic()
        conn.last_active = now
        if not data:
            conn.eof = True
            self._set_events(conn, selectors.EVENT_WRITE if conn.writing else 0)
            if conn.buf and not conn.discarding:  # a last line without newline still counts
                line = bytes(conn.buf)
                conn.buf.clear()
                self._handle_line(conn, line)
            conn.buf.clear()
            conn.line_started = None
            self._maybe_finish(conn)
            return
        buf = conn.buf
        buf += data
        finished_line = False
        while True:
            i = buf.find(b"\n")
            if conn.discarding:
                if i < 0:
                    buf.clear()
                    break
                del buf[: i + 1]
                conn.discarding = False
                finished_line = True
                continue
            if i < 0:
                if len(buf) > self.max_request_bytes:
                    self._reject(conn, f"request too large (max {self.max_request_bytes} bytes per line)")
                    buf.clear()
                    conn.discarding = True
                break
            line = bytes(buf[:i])
            del buf[: i + 1]
            finished_line = True
            if i > self.max_request_bytes:
                self._reject(conn, f"request too large (max {self.max_request_bytes} bytes per line)")
            elif line.strip():
                self._handle_line(conn, line)
            if conn.closed:
                return
        if buf or conn.discarding:
            if finished_line or conn.line_started is None:
                conn.line_started = now
        else:
            conn.line_started = None

    def _handle_line(self, conn: _Conn, line: bytes) -> None:
        try:
            request = json.loads(line)
        except (ValueError, RecursionError) as exc:
            self._reject(conn, f"malformed JSON: {exc}")
            return
        if not isinstance(request, dict):
            self._reject(conn, f"request must be a JSON object, got {type(request).__name__}")
            return
        rid = request.get("id")
        if "cmd" not in request:
            self._reject(conn, "missing field 'cmd'", rid)
            return
        cmd = request["cmd"]
        if not isinstance(cmd, str):
            self._reject(conn, f"field 'cmd' must be a string, got {type(cmd).__name__}", rid)
            return
        if self.commands is not None and cmd not in self.commands:
            self._reject(conn, f"unknown command {cmd!r} (known: {', '.join(sorted(self.commands))})", rid)
            return
        if len(self._requests) >= self.max_queued or conn.pending >= self.max_pending_per_client:
            self._reject(conn, f"busy: too many queued requests, {cmd!r} not run", rid)
            return
        conn.pending += 1
        self._requests.append((conn, request))

    def _reject(self, conn: _Conn, message: str, request_id: Any = None) -> None:
        self.rejected += 1
        self._queue_out(conn, _error_line(message, request_id))

    def _send_replies(self) -> None:
        replies = self._replies
        while True:
            try:
                conn, data = replies.popleft()
            except IndexError:
                return
            if conn.closed:
                continue  # the client left; the command still ran
            conn.pending -= 1
            self._queue_out(conn, data)
            if not conn.closed:
                self._maybe_finish(conn)

    def _queue_out(self, conn: _Conn, data: bytes) -> None:
        conn.out += data
        self._flush(conn)

    def _flush(self, conn: _Conn) -> None:
        if conn.out:
            try:
                sent = conn.sock.send(conn.out, socket.MSG_NOSIGNAL)
            except (BlockingIOError, InterruptedError):
                sent = 0
            except OSError:
                self._close_conn(conn)
                return
            del conn.out[:sent]
        if conn.out:
            if len(conn.out) > self.max_reply_backlog_bytes:
                self._close_conn(conn)  # it does not read its replies
                return
            if not conn.writing:
                conn.writing = True
                events = selectors.EVENT_WRITE | (0 if conn.eof else selectors.EVENT_READ)
                self._set_events(conn, events)
        else:
            if conn.writing:
                conn.writing = False
                self._set_events(conn, 0 if conn.eof else selectors.EVENT_READ)
            self._maybe_finish(conn)

    def _set_events(self, conn: _Conn, events: int) -> None:
        registered = self._is_registered(conn)
        if events and registered:
            self._sel.modify(conn.sock, events, conn)
        elif events:
            self._sel.register(conn.sock, events, conn)
        elif registered:
            self._sel.unregister(conn.sock)

    def _is_registered(self, conn: _Conn) -> bool:
        try:
            self._sel.get_key(conn.sock)
        except KeyError:
            return False
        return True

    def _maybe_finish(self, conn: _Conn) -> None:
        if conn.eof and not conn.out and conn.pending == 0 and not conn.closed:
            self._close_conn(conn)

    def _expire(self, now: float) -> None:
        for conn in list(self._conns.values()):
            if conn.line_started is not None and now - conn.line_started > self.request_timeout_s:
                self.rejected += 1
                try:
                    conn.sock.send(_error_line(f"request not finished within {self.request_timeout_s:g} s"),
                                   socket.MSG_NOSIGNAL)
                except OSError:
                    pass
                self._close_conn(conn)
            elif (not conn.buf and not conn.out and conn.pending == 0
                  and now - conn.last_active > self.idle_timeout_s):
                self._close_conn(conn)

    def _close_conn(self, conn: _Conn) -> None:
        if conn.closed:
            return
        conn.closed = True
        if self._is_registered(conn):
            self._sel.unregister(conn.sock)
        self._conns.pop(conn.sock.fileno(), None)
        conn.sock.close()

    # ----- shutdown -----------------------------------------------------------------------

    def close(self) -> None:
        """Stop the thread, drop every client, remove the socket file (if still ours)."""
        if self._closed:
            return
        self._closed = True
        self._stopping = True
        self._wake()
        self._thread.join(timeout=5.0)
        for conn in list(self._conns.values()):
            self._close_conn(conn)
        self._sel.close()
        self._listener.close()
        os.close(self._wake_r)
        os.close(self._wake_w)
        try:
            if os.stat(self.path).st_ino == self._inode:
                os.unlink(self.path)
        except FileNotFoundError:
            pass

    def __enter__(self) -> "ControlServer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def request(path: str | os.PathLike[str], payload: dict[str, Any], timeout: float = 2.0,
            max_reply_bytes: int = 1 << 22) -> dict[str, Any]:
    """Send one request, wait for its reply line; the client behind `ddrt ctl`.

    Raises ControlClientError when the socket is missing, refuses, or the reply is not a
    JSON object; TimeoutError when no reply arrives within `timeout` seconds.
    """
    path = os.fspath(path)
    if not isinstance(payload, dict) or not isinstance(payload.get("cmd"), str):
        raise ValueError(f"request: payload must be a dict with a string 'cmd', got {payload!r}")
    if not timeout > 0:
        raise ValueError(f"request: timeout must be > 0 seconds, got {timeout!r}")
    data = (json.dumps(payload) + "\n").encode()
    deadline = time.monotonic() + timeout
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC) as sock:
        sock.settimeout(timeout)
        try:
            sock.connect(path)
            sock.sendall(data)
            buf = bytearray()
            while b"\n" not in buf:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError
                sock.settimeout(remaining)
                chunk = sock.recv(65536)
                if not chunk:
                    raise ControlClientError(f"control socket {path}: connection closed without a reply")
                buf += chunk
                if len(buf) > max_reply_bytes:
                    raise ControlClientError(f"control socket {path}: reply longer than {max_reply_bytes} bytes")
        except TimeoutError:
            raise TimeoutError(f"control socket {path}: no reply within {timeout:g} s") from None
        except FileNotFoundError:
            raise ControlClientError(errno.ENOENT, f"control socket {path} does not exist: is ddrt running?") from None
        except ControlClientError:
            raise
        except OSError as exc:
            raise ControlClientError(exc.errno, f"control socket {path}: {exc.strerror or exc}") from exc
    line = bytes(buf[: buf.index(b"\n")])
    try:
        reply = json.loads(line)
    except ValueError as exc:
        raise ControlClientError(f"control socket {path}: reply is not JSON: {exc}") from None
    if not isinstance(reply, dict):
        raise ControlClientError(f"control socket {path}: reply is not a JSON object: {line[:80]!r}")
    return reply
