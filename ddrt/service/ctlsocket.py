"""The control socket: JSON lines over a local Unix stream socket, answered between ticks.

A helper thread owns every connection: it accepts, reads, splits lines, parses JSON and
rejects anything malformed on its own (bad or non-strict JSON, not an object, missing or
unknown "cmd", a line over `max_request_bytes`, a client over its request rate), so junk
never costs the loop a microsecond. Valid requests wait for the loop, which calls
`poll(handler)` between ticks; poll never blocks, runs at most a few handlers and hands the
encoded replies back to the thread to send.

Nobody can lock a command out (the operator's estop above all):

- **Room for a newcomer.** At `max_clients`, a new connection is still accepted: the client
  that has gone longest without sending a command (one with no reply owed first) is told why
  in one JSON line and closed. Running out of file descriptors (EMFILE) is handled the same
  way, then with a reserve descriptor, then by pausing accept() for 0.1 s: never a busy loop.
- **Only commands count.** A client is closed after `idle_timeout_s` without a *command*:
  blank lines, whitespace, bytes of an unfinished line and rejected lines do not keep it. An
  unfinished line is cut off after `request_timeout_s`.
- **A rate per connection.** A token bucket (`rate_per_s`, `rate_burst`) per connection;
  over it a request is answered with an error at once, never queued. The commands in
  `never_refused` (the daemon: estop) skip the bucket and the shared queue bound.
- **Fair service.** Each connection's requests are answered in order, connections in turn
  (round robin), so one client's burst cannot starve another's request. A connection whose
  next request is in `priority` (the daemon: estop, stop) is served before the rest; so that
  a priority command cannot be undone by one sent before it, `priority[cmd]` names the
  commands it supersedes (estop: follow, reset, drive; stop: follow, drive): such a request that arrived
  before it and is still waiting is answered with an error and not run.

Strict JSON both ways: NaN and Infinity are not JSON, in a request (answered with an error
naming the field) or in a reply (a non-finite float from the handler goes out as null and
the reply lists it in "non_finite").

Replies: `{"ok": true, ...}` from the handler, or `{"ok": false, "error": "..."}`. A request
with an "id" gets it back in the reply. A handler that cannot answer between two ticks
returns a `Deferred` and completes it later, from the loop thread (`Deferred.complete`): the
connection stays open for that reply, and other requests, on it and on other connections,
are answered meanwhile. Errors found by the thread are sent at once and may
overtake replies still queued for the loop; use "id" to match them when pipelining. A client
that leaves (or is closed) before its reply does not cancel its request: it still runs.

It is a filesystem socket (mode 0660: owner and group only), never a network listener.
"""

from __future__ import annotations

import errno
import json
import logging
import math
import os
import selectors
import socket
import stat
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Mapping

log = logging.getLogger(__name__)

DEFAULT_PATH = "/run/ddrt/ddrt.sock"
_MAX_UNIX_PATH = 107  # sun_path is 108 bytes including the terminating NUL
_READ_CHUNK = 4096
_LISTEN_BACKLOG = 128
_FD_ERRORS = (errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM)
_ACCEPT_PAUSE_S = 0.1


class ControlClientError(OSError):
    """`request` could not reach the daemon or got no usable reply."""


class _NonFinite:
    """What a NaN, Infinity or out-of-range number in a request parses to."""

    __slots__ = ("token",)

    def __init__(self, token: str) -> None:
        self.token = token


def _strict_loads(line: bytes | str) -> tuple[Any, bool]:
    """json.loads that turns NaN, Infinity, -Infinity and 1e999 into _NonFinite markers;
    returns (value, whether any was found), so a clean request costs no second walk."""
    found = False

    def constant(token: str) -> _NonFinite:
        nonlocal found
        found = True
        return _NonFinite(token)

    def number(token: str) -> float | _NonFinite:
        value = float(token)
        return value if math.isfinite(value) else constant(token)

    value = json.loads(line, parse_constant=constant, parse_float=number)
    return (value, found)


def _find_non_finite(obj: Any) -> tuple[str, str] | None:
    """(where, token) of the first _NonFinite in a parsed request, e.g. ("pose[1]", "NaN")."""
    stack: list[tuple[Any, str]] = [(obj, "")]
    while stack:
        item, where = stack.pop()
        if isinstance(item, _NonFinite):
            return where or "the request", item.token
        if isinstance(item, dict):
            stack.extend((v, f"{where}.{k}" if where else str(k)) for k, v in reversed(item.items()))
        elif isinstance(item, list):
            stack.extend((v, f"{where}[{i}]") for i, v in reversed(list(enumerate(item))))
    return None


def finite_or_null(obj: Any, where: str = "", found: list[str] | None = None) -> Any:
    """A copy of `obj` with every NaN/Infinity float replaced by None; their paths go to `found`."""
    if isinstance(obj, float):
        if math.isfinite(obj):
            return obj
        if found is not None:
            found.append(where)
        return None
    if isinstance(obj, dict):
        return {k: finite_or_null(v, f"{where}.{k}" if where else str(k), found) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite_or_null(v, f"{where}[{i}]", found) for i, v in enumerate(obj)]
    return obj


def encode_reply(reply: dict[str, Any]) -> bytes:
    """One strict JSON line. A non-finite float goes out as null, listed in "non_finite"."""
    try:
        text = json.dumps(reply, allow_nan=False)
    except ValueError:
        found: list[str] = []
        clean = finite_or_null(reply, "", found)
        clean["non_finite"] = found
        text = json.dumps(clean, allow_nan=False)
    return (text + "\n").encode()


def _error_line(message: str, request_id: Any = None) -> bytes:
    reply: dict[str, Any] = {"ok": False, "error": message}
    if request_id is not None:
        reply["id"] = request_id
    return encode_reply(reply)


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
        server._replies.append((conn, _reply_line(reply, self._rid, self._cmd), self._cmd in server.never_refused))
        server._wake()


def _reply_line(reply: Any, rid: Any, cmd: Any) -> bytes:
    """A handler's reply as one strict JSON line (an error line if it is not a JSON-able dict)."""
    try:
        if not isinstance(reply, dict):
            raise TypeError(f"handler returned {type(reply).__name__}, expected dict")
        if "ok" not in reply or (rid is not None and "id" not in reply):
            reply = {"ok": True, **reply}
            if rid is not None:
                reply.setdefault("id", rid)
        return encode_reply(reply)
    except Exception as exc:  # the loop must survive any command
        log.warning("control command %r failed: %s: %s", cmd, type(exc).__name__, exc)
        return _error_line(f"{cmd}: {type(exc).__name__}: {exc}", rid)


@dataclass(eq=False)
class _Conn:
    sock: socket.socket
    opened: float
    last_command: float  # the last request handed to the loop (or the connect), for the idle rule
    tokens: float  # the rate limit's bucket
    tokens_t: float
    round: int  # the I/O thread's round that accepted it
    buf: bytearray = field(default_factory=bytearray)
    out: bytearray = field(default_factory=bytearray)
    line_started: float | None = None  # first byte of the unfinished line
    discarding: bool = False  # skipping the rest of an oversized line
    eof: bool = False  # the client shut its sending side
    pending: int = 0  # requests handed to the loop, reply not yet back (I/O thread's count)
    pending_exempt: int = 0  # of which `never_refused` commands
    closed: bool = False
    writing: bool = False  # registered for EVENT_WRITE
    queue: deque = field(default_factory=deque)  # (seq, request) waiting for poll: loop thread only


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
        rate_per_s: float = 20.0,
        rate_burst: int = 20,
        priority: Mapping[str, Iterable[str]] | None = None,
        never_refused: Iterable[str] = (),
        max_priority_per_poll: int = 16,
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
                            ("max_reply_backlog_bytes", max_reply_backlog_bytes), ("rate_burst", rate_burst),
                            ("max_priority_per_poll", max_priority_per_poll)):
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"ControlServer.{name}: expected an int >= 1, got {value!r}")
        for name, value in (("request_timeout_s", request_timeout_s), ("idle_timeout_s", idle_timeout_s),
                            ("rate_per_s", rate_per_s)):
            if (isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value)
                    or not value > 0):
                raise ValueError(f"ControlServer.{name}: expected a finite number > 0, got {value!r}")
        self.priority: dict[str, frozenset[str]] = {c: frozenset(s) for c, s in (priority or {}).items()}
        self.never_refused = frozenset(never_refused)
        if self.commands is not None:
            unknown = (set(self.priority) | set().union(*self.priority.values(), self.never_refused)) - self.commands
            if unknown:
                raise ValueError(f"ControlServer: priority/never_refused name unknown commands {sorted(unknown)}")
        self.max_request_bytes = max_request_bytes
        self.max_clients = max_clients
        self.max_queued = max_queued
        self.max_pending_per_client = max_pending_per_client
        self.request_timeout_s = float(request_timeout_s)
        self.idle_timeout_s = float(idle_timeout_s)
        self.max_reply_backlog_bytes = max_reply_backlog_bytes
        self.rate_per_s = float(rate_per_s)
        self.rate_burst = rate_burst
        self.max_priority_per_poll = max_priority_per_poll
        # A hard bound on requests waiting for the loop, whatever the clients do: every live
        # connection may have one request waiting even when max_queued are.
        self._hard_queue_bound = max_queued + max_clients

        # I/O thread -> loop: valid requests in arrival order; loop -> I/O thread: replies.
        self._requests: deque[tuple[_Conn, dict[str, Any]]] = deque()
        self._replies: deque[tuple[_Conn, bytes, bool]] = deque()
        # Loop thread only: connections with requests waiting, in turn; arrival numbers; for
        # each superseded command, the arrival number before which it is not run, and why.
        self._ring: deque[_Conn] = deque()
        self._seq = 0
        self._cut: dict[str, tuple[int, str]] = {}
        # I/O thread only.
        self._conns: dict[int, _Conn] = {}
        self._outstanding = 0  # requests handed to the loop whose reply is not back
        self._outstanding_exempt = 0
        self._accept_paused_until: float | None = None
        self._accept_round = 0
        self._next_fd_warning = 0.0
        self.rejected = 0  # requests answered with an error by the thread
        self.rate_limited = 0  # of which over the rate
        self.evicted = 0  # connections closed to make room
        self.idle_closed = 0  # connections closed for sending no command
        self._stopping = False
        self._closed = False

        self._listener = self._bind(mode)
        self._inode = os.stat(self.path).st_ino
        self._wake_r, self._wake_w = os.pipe2(os.O_NONBLOCK | os.O_CLOEXEC)
        self._reserve_fd: int | None = self._open_reserve()
        self._sel = selectors.DefaultSelector()
        self._sel.register(self._listener, selectors.EVENT_READ, "listen")
        self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        from ddrt.runtime.rt import demote_current_thread  # here, not in the thread: no import there

        self._demote = demote_current_thread
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
            sock.listen(_LISTEN_BACKLOG)
        except OSError as exc:
            sock.close()
            raise OSError(exc.errno, f"control socket {path}: {exc.strerror or exc}") from exc
        sock.setblocking(False)
        return sock

    @staticmethod
    def _open_reserve() -> int | None:
        """A spare descriptor, given up to accept() one more client when the process has none."""
        try:
            return os.open(os.devnull, os.O_RDONLY | os.O_CLOEXEC)
        except OSError:
            return None

    # ----- loop side ----------------------------------------------------------------------

    def poll(self, handler: Callable[[dict[str, Any]], "dict[str, Any] | Deferred"], max_requests: int = 4) -> int:
        """Answer waiting requests; return how many. Never blocks.

        First the connections whose next request is a priority command (at most
        `max_priority_per_poll`), then up to `max_requests` others, one per connection in
        turn. A handler that raises, or returns something that is not a JSON-able dict,
        produces an error reply; the exception does not propagate. A handler that returns a
        `Deferred` answers when it completes it.
        """
        incoming = self._requests
        ring = self._ring
        if not incoming and not ring:  # the common case, every tick: no allocation, no exception
            return 0
        while True:
            try:
                conn, request = incoming.popleft()
            except IndexError:
                break
            self._seq += 1
            if not conn.queue:
                ring.append(conn)
            conn.queue.append((self._seq, request))
        n = 0
        if self.priority:
            for conn in ring:
                if n >= self.max_priority_per_poll:
                    break
                if conn.queue and conn.queue[0][1]["cmd"] in self.priority:
                    self._serve(conn, handler)
                    n += 1
            if n:
                self._ring = ring = deque(c for c in ring if c.queue)
        served = 0
        while served < max_requests and ring:
            conn = ring.popleft()
            self._serve(conn, handler)
            served += 1
            if conn.queue:
                ring.append(conn)
        n += served
        if n:
            self._wake()
        return n

    def _serve(self, conn: _Conn, handler: Callable[[dict[str, Any]], dict[str, Any]]) -> None:
        seq, request = conn.queue.popleft()
        cmd = request["cmd"]
        rid = request.get("id")
        for other in self.priority.get(cmd, ()):
            self._cut[other] = (seq, cmd)
        cut = self._cut.get(cmd)
        if cut is not None and seq < cut[0]:
            data = _error_line(f"{cmd} not run: the {cut[1]} sent after it was served first; "
                               f"send {cmd} again if you still mean it", rid)
        else:
            try:
                reply = handler(request)
            except Exception as exc:  # the loop must survive any command
                log.warning("control command %r failed: %s: %s", cmd, type(exc).__name__, exc)
                data = _error_line(f"{cmd}: {type(exc).__name__}: {exc}", rid)
            else:
                if isinstance(reply, Deferred):
                    reply._bind(self, conn, request)  # answered by reply.complete(), later
                    return
                data = _reply_line(reply, rid, cmd)
        self._replies.append((conn, data, cmd in self.never_refused))

    @property
    def queued(self) -> int:
        """Valid requests handed to the loop whose reply has not come back yet."""
        return self._outstanding + self._outstanding_exempt

    @property
    def clients(self) -> int:
        return len(self._conns)

    def counters(self) -> dict[str, int]:
        """What the socket has refused and closed so far (for status)."""
        return {"clients": len(self._conns), "rejected": self.rejected, "rate_limited": self.rate_limited,
                "evicted": self.evicted, "idle_closed": self.idle_closed}

    def _wake(self) -> None:
        try:
            os.write(self._wake_w, b"\0")
        except (BlockingIOError, OSError):
            pass  # the pipe is full: a wake-up is already pending (or we are closing)

    # ----- I/O thread ---------------------------------------------------------------------

    def _run(self) -> None:
        self._demote()
        tick = min(0.5, self.request_timeout_s / 4, self.idle_timeout_s / 4)
        try:
            while not self._stopping:
                self._accept_round += 1  # connections accepted in this round cannot be evicted in it
                timeout = tick
                if self._accept_paused_until is not None:
                    timeout = max(0.0, min(tick, self._accept_paused_until - time.monotonic()))
                listen = False
                for key, mask in self._sel.select(timeout):
                    tag = key.data
                    if tag == "listen":
                        listen = True  # after the reads: a request already sent is read before
                        # any newcomer can push its connection out
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
                now = time.monotonic()
                if listen:
                    self._accept()
                elif self._accept_paused_until is not None and now >= self._accept_paused_until:
                    self._accept_paused_until = None
                    self._sel.register(self._listener, selectors.EVENT_READ, "listen")
                if self._reserve_fd is None:
                    self._reserve_fd = self._open_reserve()
                self._expire(time.monotonic())
        except Exception:  # a bug here must not kill the robot, only the control socket
            log.exception("control socket thread failed; control commands are unavailable")

    def _accept(self) -> None:
        """Accept what is waiting (up to 16). A connection accepted here is never evicted in
        the same round: the next one reads whatever it has sent before it can be pushed out."""
        for _ in range(16):
            try:
                sock, _addr = self._listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except ConnectionAbortedError:
                continue
            except OSError as exc:
                if exc.errno in _FD_ERRORS:
                    # Out of descriptors: make room by closing the longest-idle client, else
                    # give up the reserve descriptor for this one.
                    if self._evict_one("the server is out of file descriptors"):
                        continue
                    if self._reserve_fd is not None:
                        os.close(self._reserve_fd)
                        self._reserve_fd = None
                        continue
                    if any(c.round == self._accept_round for c in self._conns.values()):
                        return  # progress was made; the new ones become evictable next round
                self._pause_accept(exc)
                return
            sock.setblocking(False)
            if len(self._conns) >= self.max_clients:
                # Room for the newcomer. If every client came in this very call, it waits:
                # the cap is exceeded until the next round (at most by one call's accepts).
                self._evict_one(f"too many clients (max {self.max_clients})")
            now = time.monotonic()
            conn = _Conn(sock=sock, opened=now, last_command=now, tokens=float(self.rate_burst), tokens_t=now,
                         round=self._accept_round)
            self._conns[sock.fileno()] = conn
            self._sel.register(sock, selectors.EVENT_READ, conn)

    def _pause_accept(self, exc: OSError) -> None:
        """accept() keeps failing: stop watching the listener for a moment (no busy loop)."""
        now = time.monotonic()
        if now >= self._next_fd_warning:
            log.warning("control socket accept failed: %s; new connections wait %g s", exc, _ACCEPT_PAUSE_S)
            self._next_fd_warning = now + 10.0
        self._accept_paused_until = now + _ACCEPT_PAUSE_S
        try:
            self._sel.unregister(self._listener)
        except KeyError:
            pass

    def _evict_one(self, why: str) -> bool:
        """Close the client that has gone longest without a command (one owed no reply first)."""
        victim = min((c for c in self._conns.values() if c.round != self._accept_round),
                     key=lambda c: (c.pending > 0, c.last_command), default=None)
        if victim is None:
            return False
        idle = time.monotonic() - victim.last_command
        self.evicted += 1
        self._say_and_close(victim, f"connection closed: {why}; this one had sent no command for the longest "
                                    f"({idle:.1f} s)")
        return True

    def _say_and_close(self, conn: _Conn, message: str) -> None:
        """Best effort: what is still unsent, then one error line, then close."""
        try:
            conn.sock.send(bytes(conn.out) + _error_line(message), socket.MSG_NOSIGNAL)
        except OSError:
            pass
        self._close_conn(conn)

    def _read(self, conn: _Conn) -> None:
        try:
            data = conn.sock.recv(_READ_CHUNK)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self._close_conn(conn)
            return
        now = time.monotonic()
        if not data:
            conn.eof = True
            self._set_events(conn, selectors.EVENT_WRITE if conn.writing else 0)
            if conn.buf and not conn.discarding and conn.buf.strip():  # a last line without newline still counts
                line = bytes(conn.buf)
                conn.buf.clear()
                self._handle_line(conn, line, now)
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
                self._handle_line(conn, line, now)
            if conn.closed:
                return
        if buf or conn.discarding:
            if finished_line or conn.line_started is None:
                conn.line_started = now
        else:
            conn.line_started = None

    def _handle_line(self, conn: _Conn, line: bytes, now: float) -> None:
        try:
            request, non_finite = _strict_loads(line)
        except (ValueError, RecursionError) as exc:
            self._reject(conn, f"malformed JSON: {exc}")
            return
        if not isinstance(request, dict):
            self._reject(conn, f"request must be a JSON object, got {type(request).__name__}")
            return
        rid = request.get("id")
        if non_finite:
            bad = _find_non_finite(request)
            where, token = bad if bad is not None else ("a value", "not finite")
            self._reject(conn, f"request is not strict JSON: {where} is {token}; JSON has no NaN or Infinity "
                               "(send a finite number)", rid if _find_non_finite(rid) is None else None)
            return
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
        if cmd in self.never_refused:
            if conn.pending_exempt >= self.max_pending_per_client:
                self._reject(conn, f"busy: {conn.pending_exempt} {cmd!r} requests from this connection are "
                                   f"already waiting (they will run); this one not queued", rid)
                return
            if self._outstanding_exempt >= self._hard_queue_bound:
                self._reject(conn, f"busy: {self._outstanding_exempt} {cmd!r} requests are already waiting "
                                   f"(they will run); this one not queued", rid)
                return
            conn.pending_exempt += 1
            self._outstanding_exempt += 1
        else:
            tokens = min(float(self.rate_burst), conn.tokens + (now - conn.tokens_t) * self.rate_per_s)
            conn.tokens_t = now
            if tokens < 1.0:
                conn.tokens = tokens
                self.rate_limited += 1
                self._reject(conn, f"rate limit: over {self.rate_per_s:g} requests/s on this connection "
                                   f"(bursts of {self.rate_burst}); {cmd!r} not run", rid)
                return
            conn.tokens = tokens - 1.0
            own = conn.pending - conn.pending_exempt
            if own >= self.max_pending_per_client:
                self._reject(conn, f"busy: {own} requests from this connection are still waiting; "
                                   f"{cmd!r} not run", rid)
                return
            total = self._outstanding
            if total >= self._hard_queue_bound or (total >= self.max_queued and own > 0):
                self._reject(conn, f"busy: too many queued requests ({total}), {cmd!r} not run", rid)
                return
            self._outstanding += 1
        conn.pending += 1
        conn.last_command = now
        self._requests.append((conn, request))

    def _reject(self, conn: _Conn, message: str, request_id: Any = None) -> None:
        self.rejected += 1
        self._queue_out(conn, _error_line(message, request_id))

    def _send_replies(self) -> None:
        replies = self._replies
        while True:
            try:
                conn, data, exempt = replies.popleft()
            except IndexError:
                return
            if exempt:
                self._outstanding_exempt -= 1
                conn.pending_exempt -= 1
            else:
                self._outstanding -= 1
            conn.pending -= 1
            if conn.closed:
                continue  # the client left; the command still ran
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
        while len(self._conns) > self.max_clients and self._evict_one(f"too many clients (max {self.max_clients})"):
            pass
        for conn in list(self._conns.values()):
            if conn.line_started is not None and now - conn.line_started > self.request_timeout_s:
                self.rejected += 1
                self._say_and_close(conn, f"request not finished within {self.request_timeout_s:g} s")
            elif conn.pending == 0 and now - conn.last_command > self.idle_timeout_s:
                # Only a command counts: blank lines, whitespace and rejected lines do not.
                self.idle_closed += 1
                self._say_and_close(conn, f"connection closed: no command for {self.idle_timeout_s:g} s")

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
        if self._reserve_fd is not None:
            os.close(self._reserve_fd)
            self._reserve_fd = None
        try:
            if os.stat(self.path).st_ino == self._inode:
                os.unlink(self.path)
        except FileNotFoundError:
            pass

    def __enter__(self) -> "ControlServer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _reject_constant(token: str) -> Any:
    raise ValueError(f"{token} is not JSON")


def request(path: str | os.PathLike[str], payload: dict[str, Any], timeout: float = 2.0,
            max_reply_bytes: int = 1 << 22) -> dict[str, Any]:
    """Send one request, wait for its reply line; the client behind `ddrt ctl`.

    Raises ValueError for a payload that is not strict JSON (NaN, Infinity);
    ControlClientError when the socket is missing, refuses, or the reply is not a strict JSON
    object; TimeoutError when no reply arrives within `timeout` seconds.
    """
    path = os.fspath(path)
    if not isinstance(payload, dict) or not isinstance(payload.get("cmd"), str):
        raise ValueError(f"request: payload must be a dict with a string 'cmd', got {payload!r}")
    if not timeout > 0:
        raise ValueError(f"request: timeout must be > 0 seconds, got {timeout!r}")
    try:
        data = (json.dumps(payload, allow_nan=False) + "\n").encode()
    except ValueError as exc:
        raise ValueError(f"request: payload is not strict JSON ({exc}): NaN and Infinity cannot be sent") from None
    deadline = time.monotonic() + timeout
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC) as sock:
        sock.settimeout(timeout)
        try:
            while True:
                try:
                    sock.connect(path)
                    break
                except BlockingIOError:
                    # The listen backlog is full (a flood of connections): AF_UNIX says EAGAIN
                    # at once rather than wait; keep trying until the deadline.
                    if time.monotonic() + 0.005 >= deadline:
                        raise TimeoutError from None
                    time.sleep(0.005)
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
        reply = json.loads(line, parse_constant=_reject_constant)
    except ValueError as exc:
        raise ControlClientError(f"control socket {path}: reply is not strict JSON: {exc}") from None
    if not isinstance(reply, dict):
        raise ControlClientError(f"control socket {path}: reply is not a JSON object: {line[:80]!r}")
    return reply
