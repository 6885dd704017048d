"""The bridge's two channels to the daemon: requests over the control socket, and the
loop's state as datagrams (ddrt/service/stream.py).

`DaemonLink.request` keeps one connection open and waits for each reply (one request at a
time: the bridge paces them, well inside the socket's 20 requests/s per connection); a
broken connection is opened again on the next request. `StateInbox` binds a datagram socket
in the abstract namespace, renews its subscription every RENEW_S and returns the newest
state it has received (older datagrams waiting in its buffer are read and dropped).
"""

from __future__ import annotations

import os
import socket
import time
from typing import Any

from ddrt.service.ctlclient import ControlClientError, connect
from ddrt.service.jsonlines import decode_strict, encode_line
from ddrt.service.stream import decode

RENEW_S = 2.0  # well inside the daemon's lease (stream.LEASE_S)


class DaemonLink:
    def __init__(self, socket_path: str, timeout_s: float = 2.0) -> None:
        self.path = socket_path
        self.timeout_s = timeout_s
        self._sock: socket.socket | None = None
        self._buf = bytearray()

    def request(self, payload: dict[str, Any]) -> dict[str, Any]:
        """One request and its reply; ControlClientError or TimeoutError when the daemon is
        unreachable (the connection is dropped and opened again next time)."""
        try:
            if self._sock is None:
                self._sock = connect(self.path, self.timeout_s)
                self._buf.clear()
            sock = self._sock
            sock.sendall(encode_line(payload))
            deadline = time.monotonic() + self.timeout_s
            while b"\n" not in self._buf:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError(f"control socket {self.path}: no reply within {self.timeout_s:g} s")
                sock.settimeout(remaining)
                chunk = sock.recv(65536)
                if not chunk:
                    raise ControlClientError(f"control socket {self.path}: connection closed")
                self._buf += chunk
        except (OSError, ValueError):
            self.close()
            raise
        i = self._buf.index(b"\n")
        line = bytes(self._buf[:i])
        del self._buf[: i + 1]
        reply = decode_strict(line)
        if not isinstance(reply, dict):
            raise ControlClientError(f"control socket {self.path}: reply is not a JSON object")
        return reply

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None


class StateInbox:
    """The newest loop state the daemon sent, as a name -> value mapping."""

    def __init__(self, link: DaemonLink, rate_hz: float) -> None:
        self.link = link
        self.rate_hz = rate_hz
        self.address = f"@ddrt-ros2-{os.getpid()}-{id(self):x}"
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
        self.sock.bind(b"\0" + self.address[1:].encode())
        self.sock.setblocking(False)
        self.names: tuple[str, ...] = ()
        self.received = 0
        self.bad = 0
        self._renew_at = 0.0

    def renew(self, now: float) -> str | None:
        """Ask for (more of) the stream when due; the error text if the daemon refused."""
        if now < self._renew_at:
            return None
        self._renew_at = now + RENEW_S
        reply = self.link.request({"cmd": "stream", "to": self.address, "rate_hz": self.rate_hz})
        if not reply.get("ok"):
            return str(reply.get("error"))
        self.names = tuple(reply["fields"])
        return None

    def fileno(self) -> int:
        return self.sock.fileno()

    def take(self) -> dict[str, float] | None:
        """The newest state waiting, or None."""
        newest = None
        while True:
            try:
                data = self.sock.recv(65536)
            except BlockingIOError:
                break
            try:
                newest = decode(data)
                self.received += 1
            except ValueError:
                self.bad += 1
        if newest is None or not self.names:
            return None
        return dict(zip(self.names, newest))

    def close(self) -> None:
        self.sock.close()
