"""The loop's side of the control socket: valid requests wait here until the loop serves
them between two ticks (`poll`); their replies go back to the server's I/O thread.

- **Fair service.** Each connection's requests are answered in order, connections in turn
  (round robin), so one client's burst cannot starve another's request.
- **Priority.** A connection whose next request is in `priority` (the daemon: estop, stop)
  is served before the rest; so that a priority command cannot be undone by one sent before
  it, `priority[cmd]` names the commands it supersedes (estop: follow, reset, drive,
  resume; stop: follow, drive, resume): such a request that arrived before it and is still
  waiting is answered with an error and not run.
- **Replies that come later.** A handler that cannot answer between two ticks returns a
  `Deferred` and completes it later, from the loop thread: the connection stays open for
  that reply, and other requests, on it and on other connections, are answered meanwhile.

A handler that raises, or returns something that is not a JSON-able dict, produces an error
reply: the loop survives any command.
"""

from __future__ import annotations

import logging
from collections import deque
from typing import Any, Callable, Mapping, Protocol

from ddrt.service.jsonlines import encode_reply, error_line

log = logging.getLogger("ddrt.service.ctlserver")

Handler = Callable[[dict[str, Any]], "dict[str, Any] | Deferred"]


class Client(Protocol):
    """A connection as the loop sees it: its requests waiting, with their arrival numbers."""

    queue: deque[tuple[int, dict[str, Any]]]
    peer: str  # who it is ("pid P, uid U"), for the log's audit lines


class Deferred:
    """A reply that comes later: a handler returns one, and its owner calls `complete(reply)`
    once (from the loop thread) when the answer is known. Until then the request counts as
    pending on its connection. Completing it after the server closed, or twice, does nothing.
    """

    __slots__ = ("_queue", "_conn", "_rid", "_cmd", "done")

    def __init__(self) -> None:
        self._queue: LoopQueue | None = None
        self._conn: Client | None = None
        self._rid: Any = None
        self._cmd: Any = None
        self.done = False

    def _bind(self, queue: "LoopQueue", conn: Client, request: dict[str, Any]) -> None:
        self._queue, self._conn = queue, conn
        self._rid, self._cmd = request.get("id"), request.get("cmd")

    def complete(self, reply: dict[str, Any]) -> None:
        if self.done:
            return
        self.done = True
        queue, conn = self._queue, self._conn
        self._queue = self._conn = None
        if queue is None or conn is None or queue.closed:
            return
        queue.replies.append((conn, reply_line(reply, self._rid, self._cmd), self._cmd in queue.never_refused))
        queue.wake()


def reply_line(reply: Any, rid: Any, cmd: Any) -> bytes:
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
        return error_line(f"{cmd}: {type(exc).__name__}: {exc}", rid)


class LoopQueue:
    """Requests from the I/O thread (`incoming`), served by `poll` on the loop thread; the
    encoded replies go to `replies` (connection, line, whether the command is never refused)
    and `wake` tells the I/O thread to send them."""

    def __init__(self, priority: Mapping[str, frozenset[str]], never_refused: frozenset[str],
                 max_priority_per_poll: int, wake: Callable[[], None]) -> None:
        self.priority = priority
        self.never_refused = never_refused
        self.max_priority_per_poll = max_priority_per_poll
        self.wake = wake
        self.closed = False  # the server closed: a Deferred completed now goes nowhere
        # I/O thread -> loop: valid requests in arrival order; loop -> I/O thread: replies.
        self.incoming: deque[tuple[Client, dict[str, Any]]] = deque()
        self.replies: deque[tuple[Any, bytes, bool]] = deque()
        # Loop thread only: connections with requests waiting, in turn; arrival numbers; for
        # each superseded command, the arrival number before which it is not run, and why.
        self._ring: deque[Client] = deque()
        self._seq = 0
        self._cut: dict[str, tuple[int, str]] = {}
        self.serving: Client | None = None  # whose request the handler is answering (loop thread)

    def poll(self, handler: Handler, max_requests: int = 4) -> int:
        """Answer waiting requests; return how many. Never blocks.

        First the connections whose next request is a priority command (at most
        `max_priority_per_poll`), then up to `max_requests` others, one per connection in
        turn. A handler that returns a `Deferred` answers when it completes it.
        """
        incoming = self.incoming
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
            self.wake()
        return n

    def _serve(self, conn: Client, handler: Handler) -> None:
        seq, request = conn.queue.popleft()
        cmd = request["cmd"]
        rid = request.get("id")
        for other in self.priority.get(cmd, ()):
            self._cut[other] = (seq, cmd)
        cut = self._cut.get(cmd)
        if cut is not None and seq < cut[0]:
            data = error_line(f"{cmd} not run: the {cut[1]} sent after it was served first; "
                              f"send {cmd} again if you still mean it", rid)
        else:
            self.serving = conn
            try:
                reply = handler(request)
            except Exception as exc:  # the loop must survive any command
                log.warning("control command %r failed: %s: %s", cmd, type(exc).__name__, exc)
                data = error_line(f"{cmd}: {type(exc).__name__}: {exc}", rid)
            else:
                if isinstance(reply, Deferred):
                    reply._bind(self, conn, request)  # answered by reply.complete(), later
                    return
                data = reply_line(reply, rid, cmd)
            finally:
                self.serving = None
        self.replies.append((conn, data, cmd in self.never_refused))
