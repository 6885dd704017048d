"""systemd's sd_notify protocol, without libsystemd: one datagram per state change.

Under `Type=notify` systemd passes $NOTIFY_SOCKET (a path, or "@name" for the abstract
namespace) and expects "READY=1" once the loop runs; with `WatchdogSec=` it also expects
"WATCHDOG=1" more often than $WATCHDOG_USEC. Outside systemd every call is a no-op, so the
daemon needs no special case for running in a terminal. Sending never raises: a lost
notification must not stop the robot (systemd's watchdog catches the real failures).
"""

from __future__ import annotations

import os
import socket
import time
from typing import Mapping

_READY = b"READY=1"
_WATCHDOG = b"WATCHDOG=1"
_STOPPING = b"STOPPING=1"


def _address(value: str) -> str | bytes:
    # "@foo" is the abstract socket "\0foo"; Linux needs it as bytes with the leading NUL.
    if value.startswith("@"):
        return b"\0" + value[1:].encode()
    return value


class Notifier:
    """A connection to the service manager's notification socket (or nothing)."""

    def __init__(self, environ: Mapping[str, str] | None = None) -> None:
        env = os.environ if environ is None else environ
        self._env = env
        path = env.get("NOTIFY_SOCKET", "")
        self._addr: str | bytes | None = None
        self._sock: socket.socket | None = None
        if path:
            if not (path.startswith("/") or path.startswith("@")):
                raise ValueError(f"NOTIFY_SOCKET: expected an absolute path or @abstract name, got {path!r}")
            self._addr = _address(path)
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)

    @property
    def enabled(self) -> bool:
        return self._sock is not None

    def notify(self, message: bytes) -> bool:
        """Send one raw message ("KEY=value" lines); True if it was sent."""
        sock = self._sock
        if sock is None:
            return False
        try:
            sock.sendto(message, self._addr)  # type: ignore[arg-type]
        except OSError:
            return False
        return True

    def ready(self) -> bool:
        return self.notify(_READY)

    def status(self, text: str) -> bool:
        """One-line free text shown by `systemctl status` (newlines would end the field)."""
        return self.notify(b"STATUS=" + text.replace("\n", " ").encode("utf-8", "replace"))

    def watchdog(self) -> bool:
        return self.notify(_WATCHDOG)

    def reloading(self) -> bool:
        """Start of a config reload; send ready() when done. MONOTONIC_USEC lets systemd
        order this against the reload request (required by Type=notify-reload)."""
        usec = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
        return self.notify(b"RELOADING=1\nMONOTONIC_USEC=%d" % usec)

    def stopping(self) -> bool:
        return self.notify(_STOPPING)

    def watchdog_interval(self) -> float | None:
        """Recommended ping period in seconds (half of WatchdogSec=), None if no watchdog.

        Like sd_watchdog_enabled(): WATCHDOG_PID, when set, must be our pid (the variable
        may have leaked from a parent).
        """
        usec_text = self._env.get("WATCHDOG_USEC", "")
        if not usec_text:
            return None
        pid_text = self._env.get("WATCHDOG_PID", "")
        if pid_text:
            try:
                pid = int(pid_text)
            except ValueError:
                raise ValueError(f"WATCHDOG_PID: expected a process id, got {pid_text!r}") from None
            if pid != os.getpid():
                return None
        try:
            usec = int(usec_text)
        except ValueError:
            raise ValueError(f"WATCHDOG_USEC: expected a whole number of microseconds, got {usec_text!r}") from None
        if usec <= 0:
            raise ValueError(f"WATCHDOG_USEC: must be > 0, got {usec}")
        return usec / 2e6

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def __enter__(self) -> "Notifier":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
