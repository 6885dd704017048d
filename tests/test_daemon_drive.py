"""The velocity mode over the real daemon's socket (`ddrt run` on the simulated robot, paced
to the wall clock): `ddrt ctl drive --for`, the timeout, strict JSON, estop. Wall-clock
bounds are generous (a loaded 2-core host); the exact bounds are in tests/test_drive.py,
in simulated time."""

from __future__ import annotations

import json
import time

import pytest

from ddrt.loop import LoopState
from tests.support.daemon import DaemonProc, ctl, raw_exchange, wait_for

SETTLE_S = 60.0  # cap on driving to rest (1.6 s of braking at most): only a hang takes longer
# daemon.command_timeout_s here: long beside the 0.1 s between `ctl drive --for`'s commands,
# so a loaded host that holds the client back between two cannot make it look silent.
TIMEOUT_S = 2.0


DAEMON_SECTIONS = {"daemon": {"command_timeout_s": TIMEOUT_S}}  # module_daemon's config


@pytest.fixture()
def dd(module_daemon: DaemonProc) -> DaemonProc:
    d = module_daemon
    d.check_alive()
    d.request({"cmd": "stop"})
    wait_for(lambda: d.status()["state"] in ("idle", "stopped", "estop"), SETTLE_S, "the robot at rest")
    assert d.request({"cmd": "reset"}) == {"ok": True, "state": "idle"}
    return d


def test_ctl_drive_for_drives_then_stops(dd: DaemonProc) -> None:
    out = ctl(dd.socket, "drive", "0.4", "0.5", "--for", "1.0")
    assert out.returncode == 0, out.stderr
    reply = json.loads(out.stdout)
    assert reply["ok"] is True and reply["stop"] == {"ok": True, "state": "driving"}
    assert 8 <= reply["sent"] <= 11 and reply["last"]["v"] == 0.4
    s = wait_for(lambda: (st := dd.status())["state"] == "stopped" and st, SETTLE_S, "stopped")
    assert s["drive"]["braking_for"] == "stop" and s["drive"]["timeouts"] == 0
    assert s["duty"] == {"l": 0.0, "r": 0.0}
    rows = dd.telemetry()
    driving = [r for r in rows if r["state"] == LoopState.DRIVING]
    assert driving and max(r["v_ref"] for r in driving) == pytest.approx(0.4)
    assert max(r["v_est"] for r in driving) == pytest.approx(0.4, abs=0.03)


def test_one_command_then_silence_stops_after_the_timeout(dd: DaemonProc) -> None:
    t0 = time.monotonic()
    reply = dd.request({"cmd": "drive", "v": 0.5, "omega": 0.0, "id": 7})
    assert reply == {"ok": True, "state": "driving", "v": 0.5, "omega": 0.0, "timeout_s": TIMEOUT_S, "id": 7}
    assert dd.status()["mode"] == "drive"
    s = wait_for(lambda: (st := dd.status())["state"] == "stopped" and st, SETTLE_S, "stopped by the timeout")
    took = time.monotonic() - t0
    # the timeout + 0.6 s braking (0.5 / accel + accel / jerk), on the wall clock
    assert took >= TIMEOUT_S + 0.5, took
    assert s["drive"]["braking_for"] == "timeout" and s["drive"]["timeouts"] == 1
    assert s["duty"] == {"l": 0.0, "r": 0.0} and s["mode"] == "none"


@pytest.mark.parametrize(("line", "where"), [
    (b'{"cmd": "drive", "v": NaN, "omega": 0}\n', "v is NaN"),
    (b'{"cmd": "drive", "v": 0.1, "omega": -Infinity}\n', "omega is -Infinity"),
    (b'{"cmd": "drive", "v": 1e999, "omega": 0}\n', "v is 1e999"),
])
def test_non_finite_numbers_are_refused_by_the_socket_naming_the_field(dd: DaemonProc, line: bytes, where: str) -> None:
    reply = raw_exchange(dd.socket, line)
    assert reply["ok"] is False and where in reply["error"], reply
    assert dd.status()["state"] == "idle"


def test_estop_during_drive_zeroes_the_motors_and_drive_waits_for_reset(dd: DaemonProc) -> None:
    assert dd.request({"cmd": "drive", "v": 0.5, "omega": 0.0})["ok"]
    time.sleep(0.2)
    assert dd.request({"cmd": "estop"}) == {"ok": True, "state": "estop"}
    assert dd.status()["duty"] == {"l": 0.0, "r": 0.0}
    reply = dd.request({"cmd": "drive", "v": 0.5, "omega": 0.0})
    assert reply == {"ok": False, "error": "drive refused in estop: send reset first"}
    assert dd.status()["state"] == "estop"
