"""The control socket's server: JSON lines over a local Unix stream socket, answered between
ticks.

A helper thread owns every connection: it accepts, reads, splits lines, parses JSON and
rejects anything malformed on its own (bad or non-strict JSON, not an object, missing or
unknown "cmd", a line over `max_request_bytes`, a client over its request rate), so junk
never costs the loop a microsecond. Valid requests wait for the loop in a `LoopQueue`
(ddrt/service/ctlqueue.py: fair turns, priority commands first, replies that come later),
which the loop serves with `poll(handler)` between ticks; poll never blocks, runs at most a
few handlers and hands the encoded replies back to the thread to send.

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

Strict JSON both ways (ddrt/service/jsonlines.py): NaN and Infinity are not JSON, in a
request (answered with an error naming the field) or in a reply (a non-finite float from
the handler goes out as null and the reply lists it in "non_finite").

Replies: `{"ok": true, ...}` from the handler, or `{"ok": false, "error": "..."}`. A request
with an "id" gets it back in the reply. Errors found by the thread are sent at once and may
overtake replies still queued for the loop; use "id" to match them when pipelining. A client
that leaves (or is closed) before its reply does not cancel its request: it still runs.

It is a filesystem socket (mode 0660: owner and group only), never a network listener.
"""

from __future__ import annotations

import errno
import logging
import math
import os
import selectors
import socket
import struct
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Iterable, Mapping

from ddrt.service.ctlqueue import Handler, LoopQueue
from ddrt.service.jsonlines import DuplicateKey, error_line, find_non_finite, strict_loads
from ddrt.service.sockfile import listen_unix, remove_if_ours

log = logging.getLogger(__name__)

DEFAULT_PATH = "/run/ddrt/ddrt.sock"
_MAX_UNIX_PATH = 107  # sun_path is 108 bytes including the terminating NUL
_READ_CHUNK = 4096
_LISTEN_BACKLOG = 128
_FD_ERRORS = (errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM)
_ACCEPT_PAUSE_S = 0.1


def _peer_of(sock: socket.socket) -> str:
    """The client's process and user, as the kernel tells (Linux SO_PEERCRED); '' elsewhere."""
    try:
        pid, uid, _gid = struct.unpack("3i", sock.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED,
                                                             struct.calcsize("3i")))
    except (AttributeError, OSError, struct.error):
        return ""
    return f"pid {pid}, uid {uid}"


SMALL_LINE_BYTES = 65536  # every command but a follow with content fits in this


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
    peer: str = ""  # "pid P, uid U" of the client (SO_PEERCRED), for the log's audit lines


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
        # Unfinished lines over SMALL_LINE_BYTES share one budget, so a large line limit (a
        # path sent as content) lets two such requests in at a time, not one per client.
        self.max_large_buffered = 2 * max_request_bytes
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

        # Valid requests wait there for the loop; their replies come back through it.
        self._queue = LoopQueue(self.priority, self.never_refused, max_priority_per_poll, self._wake)
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

        self._listener = listen_unix(self.path, mode, _LISTEN_BACKLOG)
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

    @staticmethod
    def _open_reserve() -> int | None:
        """A spare descriptor, given up to accept() one more client when the process has none."""
        try:
            return os.open(os.devnull, os.O_RDONLY | os.O_CLOEXEC)
        except OSError:
            return None

    # ----- loop side ----------------------------------------------------------------------

    def poll(self, handler: Handler, max_requests: int = 4) -> int:
        """Answer waiting requests between two ticks (`LoopQueue.poll`); never blocks."""
        return self._queue.poll(handler, max_requests)

    @property
    def peer(self) -> str:
        """Who sent the request being answered ("pid P, uid U"), '' outside a handler."""
        conn = self._queue.serving
        return conn.peer if conn is not None else ""

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
                         round=self._accept_round, peer=_peer_of(sock))
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
            conn.sock.send(bytes(conn.out) + error_line(message), socket.MSG_NOSIGNAL)
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
        scan_from = len(buf)  # what was held has no newline: look in the new bytes only
        buf += data
        finished_line = False
        while True:
            i = buf.find(b"\n", scan_from)
            scan_from = 0
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
                elif len(buf) > SMALL_LINE_BYTES and self._large_buffered() > self.max_large_buffered:
                    self._reject(conn, "request refused: other large requests are being received; send it again")
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

    def _large_buffered(self) -> int:
        """Bytes held in unfinished lines longer than SMALL_LINE_BYTES, over every client."""
        return sum(len(c.buf) for c in self._conns.values() if len(c.buf) > SMALL_LINE_BYTES)

    def _handle_line(self, conn: _Conn, line: bytes, now: float) -> None:
        try:
            request, non_finite = strict_loads(line)
        except DuplicateKey as exc:
            self._reject(conn, f"request refused: {exc}")
            return
        except (ValueError, RecursionError) as exc:
            self._reject(conn, f"malformed JSON: {exc}")
            return
        if not isinstance(request, dict):
            self._reject(conn, f"request must be a JSON object, got {type(request).__name__}")
            return
        rid = request.get("id")
        if non_finite:
            bad = find_non_finite(request)
            where, token = bad if bad is not None else ("a value", "not finite")
            self._reject(conn, f"request is not strict JSON: {where} is {token}; JSON has no NaN or Infinity "
                               "(send a finite number)", rid if find_non_finite(rid) is None else None)
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
        self._queue.incoming.append((conn, request))

    def _reject(self, conn: _Conn, message: str, request_id: Any = None) -> None:
        self.rejected += 1
        self._queue_out(conn, error_line(message, request_id))

    def _send_replies(self) -> None:
        replies = self._queue.replies
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
        self._queue.closed = True
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
        remove_if_ours(self.path, self._inode)

    def __enter__(self) -> "ControlServer":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

