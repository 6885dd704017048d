"""The control socket's client side: `connect` retries while the listen backlog is full, up
to its deadline (ddrt/service/ctlclient.py)."""

from __future__ import annotations

import os
import shutil
import socket
import tempfile
import threading
import time
from collections.abc import Iterator

import pytest

from ddrt.service.ctlclient import connect


@pytest.fixture()
def listener() -> Iterator[socket.socket]:
    d = tempfile.mkdtemp(prefix="ddrt-cli-", dir="/tmp")  # short: sun_path is 108 bytes
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    srv.bind(os.path.join(d, "c.sock"))
    srv.listen(0)  # accepts nothing: the backlog fills after a connection or two
    yield srv
    srv.close()
    shutil.rmtree(d, ignore_errors=True)


def test_connect_gives_up_at_its_deadline_while_the_backlog_stays_full(listener: socket.socket) -> None:
    held: list[socket.socket] = []
    try:
        with pytest.raises(TimeoutError, match="backlog stayed full"):
            for _ in range(64):
                t0 = time.monotonic()
                held.append(connect(listener.getsockname(), timeout=0.2))
        assert time.monotonic() - t0 >= 0.15  # it retried until the deadline, then gave up
        assert len(held) < 64
    finally:
        for s in held:
            s.close()


def test_connect_gets_in_once_the_server_makes_room(listener: socket.socket) -> None:
    held: list[socket.socket] = []
    try:
        with pytest.raises(TimeoutError):
            for _ in range(64):
                held.append(connect(listener.getsockname(), timeout=0.1))
        accepted: list[socket.socket] = []
        timer = threading.Timer(0.2, lambda: accepted.append(listener.accept()[0]))
        timer.start()
        t0 = time.monotonic()
        s = connect(listener.getsockname(), timeout=5.0)
        held.append(s)
        timer.join()
        assert time.monotonic() - t0 >= 0.15 and s.gettimeout() == 5.0  # it waited for the room
        for a in accepted:
            a.close()
    finally:
        for s in held:
            s.close()


def test_connect_to_no_socket_raises_what_the_os_said(tmp_path) -> None:
    with pytest.raises(FileNotFoundError):
        connect(str(tmp_path / "none.sock"), timeout=5.0)
