"""The control socket's client: `control_socket` (which socket `ddrt ctl` talks to, and why),
`request` (behind `ddrt ctl`), and `connect`, the one way to open a connection to a control
socket (tests and benchmarks use it too).

A full listen backlog (a flood of connections) makes an AF_UNIX connect() fail with EAGAIN
at once rather than wait, so `connect` retries until its deadline. Requests and replies are
strict JSON lines (ddrt/service/jsonlines.py).
"""

from __future__ import annotations

import errno
import os
import socket
import sys
import time
from typing import Any

from ddrt.errors import DdrtError
from ddrt.service.jsonlines import decode_strict, encode_line

CONNECT_RETRY_S = 0.005  # between two connect() attempts while the listen backlog is full
DEFAULT_SOCKET = "/run/ddrt/ddrt.sock"  # the shipped unit's (configs/robot.yaml's daemon.socket)
SOCKET_ENV = "DDRT_SOCKET"


def control_socket(socket_arg: str | None, config: str | None) -> tuple[str, str]:
    """The daemon's socket for `ddrt ctl`, and where it came from (for an error that names what
    was tried): --socket, else the daemon.socket of --config, else $DDRT_SOCKET, else the
    system service's. A --config being edited still gives its daemon.socket (estop, the reload
    that reports the typo), with a warning that names what is wrong."""
    if socket_arg:
        return socket_arg, "--socket"
    if config:
        from ddrt.config import load_config
        from ddrt.config.load import daemon_socket_of

        try:
            path = load_config(config).daemon.socket
        except ValueError as exc:
            path = daemon_socket_of(config, exc)
            print(f"ddrt ctl: warning: {' '.join(str(exc).split())}; its daemon.socket is used all the same",
                  file=sys.stderr)
        if not path:
            raise ValueError(f"{config}: daemon.socket is empty: that daemon listens on no control socket")
        return path, f"daemon.socket of {config}"
    if os.environ.get(SOCKET_ENV):
        return os.environ[SOCKET_ENV], f"${SOCKET_ENV}"
    return DEFAULT_SOCKET, (f"the default; for another daemon give --config CONFIG, --socket PATH or "
                            f"set {SOCKET_ENV}")


class ControlClientError(DdrtError, OSError):
    """`request` could not reach the daemon or got no usable reply."""


def connect(path: str | os.PathLike[str], timeout: float = 5.0, retry_s: float = CONNECT_RETRY_S) -> socket.socket:
    """A blocking client socket connected to `path`, its timeout set to `timeout`.

    Retries every `retry_s` while the listen backlog is full; TimeoutError once `timeout`
    seconds have passed without getting in. Any other failure (no such socket, refused) is
    raised at once as the OSError it is.
    """
    deadline = time.monotonic() + timeout
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
    try:
        sock.settimeout(timeout)
        while True:
            try:
                sock.connect(os.fspath(path))
                return sock
            except BlockingIOError:
                if time.monotonic() + retry_s >= deadline:
                    raise TimeoutError(errno.EAGAIN, f"control socket {os.fspath(path)}: the listen backlog "
                                                     f"stayed full for {timeout:g} s") from None
                time.sleep(retry_s)
    except BaseException:
        sock.close()
        raise


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
        data = encode_line(payload)
    except ValueError as exc:
        raise ValueError(f"request: payload is not strict JSON ({exc}): NaN and Infinity cannot be sent") from None
    deadline = time.monotonic() + timeout
    try:
        with connect(path, timeout) as sock:
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
        reply = decode_strict(line)
    except ValueError as exc:
        raise ControlClientError(f"control socket {path}: reply is not strict JSON: {exc}") from None
    if not isinstance(reply, dict):
        raise ControlClientError(f"control socket {path}: reply is not a JSON object: {line[:80]!r}")
    return reply
