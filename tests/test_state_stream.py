"""The daemon's state stream (ddrt/service/stream.py): what a subscriber receives, what a bad
request gets, and that a slow, vanished or silent subscriber costs the sender nothing but
itself. In-process, over real Unix datagram sockets, with a stand-in for the loop's state."""

from __future__ import annotations

import contextlib
import math
import socket
import threading
import time
from types import SimpleNamespace
from typing import Iterator

import pytest

from ddrt.loop import LoopState
from ddrt.service.commands import CommandError, parse
from ddrt.service import stream as st
from tests.support.daemon import wait_for


def fake_loop() -> SimpleNamespace:
    est = SimpleNamespace(x=1.5, y=-2.0, theta=0.25, speed=SimpleNamespace(v=0.3, p11=1e-4),
                          yaw=SimpleNamespace(w=0.1, p00=2e-4, meas_var=3e-5, b=0.01), rad_s_per_lsb=0.001,
                          track=SimpleNamespace(p_odom=[float(i) for i in range(36)]),
                          frame=SimpleNamespace(x=1.6, y=-1.9, th=0.3, counters=SimpleNamespace(fused=0)))
    sample = SimpleNamespace(t=12.5, gyro_z_raw=150, fresh=True)
    power = SimpleNamespace(v_slow=11.7, good=True, hw_estop=False)
    return SimpleNamespace(estimator=est, sample=sample, state=LoopState.DRIVING, power=power)


class Clock:
    def __init__(self) -> None:
        self.offset = 0.0

    def __call__(self) -> float:
        return time.monotonic() + self.offset


@pytest.fixture
def stream() -> Iterator[tuple[st.StateStream, SimpleNamespace, Clock]]:
    loop, clock = fake_loop(), Clock()
    s = st.StateStream(loop, clock=clock)  # type: ignore[arg-type]
    try:
        yield s, loop, clock
    finally:
        s.close()


@contextlib.contextmanager
def ticking(s: st.StateStream, hz: float = 200.0) -> Iterator[None]:
    """A stand-in for the loop thread: `put` at `hz` meanwhile."""
    stop = threading.Event()

    def run() -> None:
        while not stop.wait(1.0 / hz):
            s.put(time.monotonic())

    t = threading.Thread(target=run, daemon=True)
    t.start()
    try:
        yield
    finally:
        stop.set()
        t.join()


def reader(name: str) -> socket.socket:
    r = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    r.bind(b"\0" + name.encode())
    r.settimeout(5.0)
    return r


def test_a_subscriber_gets_the_loops_state_at_its_rate(stream) -> None:
    s, loop, _ = stream
    name = f"ddrt-test-{id(s):x}"
    with reader(name) as r:
        s.put(0.0)
        assert s._seq == 0  # nobody listens: nothing packed
        reply = s.subscribe("@" + name, 100)
        assert reply["ok"] and reply["fields"] == list(st.NAMES)
        s.put(42.0)
        values = dict(zip(reply["fields"], st.decode(r.recv(4096))))
        assert values["seq"] == 1.0 and values["mono"] == 42.0 and values["t"] == 12.5
        assert (values["x"], values["y"], values["theta"], values["v"], values["omega"]) == (1.5, -2.0, 0.25, 0.3, 0.1)
        assert values["gyro"] == pytest.approx(0.15) and values["state"] == float(LoopState.DRIVING)
        assert values["battery_v"] == 11.7 and values["hw_estop"] == 0.0
        # The odometry's covariance (x, y, theta entries of the 6x6); no map pose before a fix.
        assert (values["var_x"], values["var_y"], values["cov_xy"], values["var_theta"]) == (0.0, 7.0, 1.0, 14.0)
        assert math.isnan(values["map_x"]) and math.isnan(values["map_theta"])
        loop.estimator.frame.counters.fused = 1
        s.put(43.0)
        values = dict(zip(reply["fields"], st.decode(r.recv(4096))))
        assert (values["map_x"], values["map_y"], values["map_theta"]) == (1.6, -1.9, 0.3)
        with ticking(s):
            t0, n0 = time.monotonic(), 0
            while time.monotonic() - t0 < 1.0:
                r.recv(4096)
                n0 += 1
        assert 50 <= n0 <= 110, n0  # 100 Hz, give or take a loaded host
        # A loop that stalls sends nothing more: a state goes out once.
        time.sleep(0.1)
        r.setblocking(False)
        while True:
            try:
                r.recv(4096)
            except BlockingIOError:
                break
        time.sleep(0.2)
        with pytest.raises(BlockingIOError):
            r.recv(4096)


@pytest.mark.parametrize("req, field", [
    ({}, "to"), ({"to": ""}, "to"), ({"to": "x" * 101}, "to"), ({"to": 5}, "to"), ({"to": "@a\0b"}, "to"),
    ({"to": "@a", "rate_hz": 0}, "rate_hz"), ({"to": "@a", "rate_hz": -5}, "rate_hz"),
    ({"to": "@a", "rate_hz": 1e6}, "rate_hz"), ({"to": "@a", "rate_hz": True}, "rate_hz"),
    ({"to": "@a", "rate_hz": "fast"}, "rate_hz"), ({"to": "@a", "every": 1}, "every"),
])
def test_a_bad_request_is_refused_naming_the_field_and_changes_nothing(stream, req, field) -> None:
    s, _, _ = stream
    with pytest.raises(CommandError) as err:
        parse({"cmd": "stream", **req})  # what the daemon does before the subscription is touched
    assert str(err.value).startswith(f"stream: {field}: ")
    assert s.counts() == {} and not s.active


def test_beyond_the_subscriber_bound_is_busy(stream) -> None:
    s, _, _ = stream
    socks = [reader(f"ddrt-busy-{i}-{id(s):x}") for i in range(st.MAX_SUBSCRIBERS)]
    try:
        for i in range(st.MAX_SUBSCRIBERS):
            assert s.subscribe(f"@ddrt-busy-{i}-{id(s):x}", 10)["ok"]
        reply = s.subscribe("@one-more", 10)
        assert reply["ok"] is False and "busy" in reply["error"]
        # A renewal of a subscriber already there is not a new one.
        assert s.subscribe(f"@ddrt-busy-0-{id(s):x}", 20)["ok"]
    finally:
        for r in socks:
            r.close()


def test_a_slow_reader_is_dropped_for_and_a_vanished_one_removed_while_others_still_receive(stream) -> None:
    s, _, _ = stream
    slow, fast, gone = (f"ddrt-{k}-{id(s):x}" for k in ("slow", "fast", "gone"))
    with reader(slow) as rs, reader(fast) as rf:
        rs.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # fills after a few datagrams
        for name in (slow, fast, gone):
            assert s.subscribe("@" + name, 400)["ok"]
        with ticking(s, 1000.0):
            wait_for(lambda: s.counts().get("@" + slow, {}).get("dropped", 0) > 20, 10.0, "drops for the slow reader")
            assert "@" + gone not in s.counts()  # nobody at that address: removed on the first send
            got = 0
            t0 = time.monotonic()
            while time.monotonic() - t0 < 0.5:
                rf.recv(4096)
                got += 1
        assert got > 50  # the fast reader was not held up by the slow one
        counts = s.counts()
        assert counts["@" + slow]["sent"] < counts["@" + fast]["sent"]


def test_a_subscriber_that_stops_renewing_expires(stream) -> None:
    s, _, clock = stream
    name = f"ddrt-lease-{id(s):x}"
    with reader(name) as r:
        assert s.subscribe("@" + name, 50)["ok"]
        s.put(1.0)
        r.recv(4096)  # sent once: the lease, not the loop, decides from here
        clock.offset = st.LEASE_S + 0.1
        wait_for(lambda: s.counts() == {}, 5.0, "the lease to run out")
        assert not s.active


def test_decode_refuses_what_is_not_a_state() -> None:
    with pytest.raises(ValueError, match="shorter than its header"):
        st.decode(b"DD")
    with pytest.raises(ValueError, match="magic"):
        st.decode(st.HEADER.pack(b"XXXX", st.VERSION, 0))
    with pytest.raises(ValueError, match="bytes for 3 fields"):
        st.decode(st.HEADER.pack(st.MAGIC, st.VERSION, 3) + b"\0" * 8)
