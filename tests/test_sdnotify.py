"""sd_notify messages, byte for byte, on a datagram socket standing in for systemd."""

from __future__ import annotations

import os
import re
import socket
import tempfile
import time
from collections.abc import Iterator

import pytest

from ddrt.service.sdnotify import Notifier


@pytest.fixture()
def listener() -> Iterator[tuple[socket.socket, str]]:
    d = tempfile.mkdtemp(prefix="ddrt-sdn-")
    path = os.path.join(d, "notify")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    sock.settimeout(2.0)
    yield sock, path
    sock.close()
    if os.path.exists(path):
        os.unlink(path)
    os.rmdir(d)


def test_messages_byte_for_byte(listener: tuple[socket.socket, str]) -> None:
    sock, path = listener
    n = Notifier({"NOTIFY_SOCKET": path})
    assert n.enabled
    assert n.ready()
    assert sock.recv(4096) == b"READY=1"
    assert n.status("running at 200 Hz, 0 overruns")
    assert sock.recv(4096) == b"STATUS=running at 200 Hz, 0 overruns"
    assert n.status("two\nlines")
    assert sock.recv(4096) == b"STATUS=two lines"  # a newline would start a new field
    assert n.watchdog()
    assert sock.recv(4096) == b"WATCHDOG=1"
    assert n.stopping()
    assert sock.recv(4096) == b"STOPPING=1"
    n.close()
    assert not n.ready()


def test_reloading_is_one_datagram_with_monotonic_usec(listener: tuple[socket.socket, str]) -> None:
    sock, path = listener
    n = Notifier({"NOTIFY_SOCKET": path})
    before = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
    assert n.reloading()
    after = time.clock_gettime_ns(time.CLOCK_MONOTONIC) // 1000
    msg = sock.recv(4096)
    m = re.fullmatch(rb"RELOADING=1\nMONOTONIC_USEC=([0-9]+)", msg)
    assert m, msg
    assert before <= int(m.group(1)) <= after
    n.close()


def test_abstract_namespace_socket() -> None:
    name = f"ddrt-test-{os.getpid()}-{time.monotonic_ns()}"
    with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM) as sock:
        sock.bind(b"\0" + name.encode())
        sock.settimeout(2.0)
        with Notifier({"NOTIFY_SOCKET": "@" + name}) as n:
            assert n.ready()
            assert sock.recv(4096) == b"READY=1"


def test_no_notify_socket_is_a_silent_no_op() -> None:
    n = Notifier({})
    assert not n.enabled
    for call in (n.ready, n.watchdog, n.reloading, n.stopping):
        assert call() is False
    assert n.status("x") is False
    assert n.watchdog_interval() is None


def test_reads_os_environ_by_default(monkeypatch: pytest.MonkeyPatch, listener: tuple[socket.socket, str]) -> None:
    sock, path = listener
    monkeypatch.setenv("NOTIFY_SOCKET", path)
    with Notifier() as n:
        assert n.watchdog()
        assert sock.recv(4096) == b"WATCHDOG=1"


def test_send_to_vanished_manager_does_not_raise(listener: tuple[socket.socket, str]) -> None:
    sock, path = listener
    n = Notifier({"NOTIFY_SOCKET": path})
    sock.close()
    os.unlink(path)
    assert n.watchdog() is False


def test_relative_notify_socket_rejected() -> None:
    with pytest.raises(ValueError, match="NOTIFY_SOCKET"):
        Notifier({"NOTIFY_SOCKET": "relative/path"})


@pytest.mark.parametrize("env, expected", [
    ({"WATCHDOG_USEC": "2000000"}, 1.0),
    ({"WATCHDOG_USEC": "2000000", "WATCHDOG_PID": str(os.getpid())}, 1.0),
    ({"WATCHDOG_USEC": "500000", "WATCHDOG_PID": str(os.getpid() + 1)}, None),  # meant for another process
    ({"WATCHDOG_USEC": "300"}, 150e-6),
    ({}, None),
])
def test_watchdog_interval(env: dict[str, str], expected: float | None) -> None:
    got = Notifier(env).watchdog_interval()
    if expected is None:
        assert got is None
    else:
        assert got == pytest.approx(expected)


@pytest.mark.parametrize("env, field", [
    ({"WATCHDOG_USEC": "2s"}, "WATCHDOG_USEC"),
    ({"WATCHDOG_USEC": "0"}, "WATCHDOG_USEC"),
    ({"WATCHDOG_USEC": "100", "WATCHDOG_PID": "me"}, "WATCHDOG_PID"),
])
def test_watchdog_interval_bad_environment(env: dict[str, str], field: str) -> None:
    with pytest.raises(ValueError, match=field):
        Notifier(env).watchdog_interval()
