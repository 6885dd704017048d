"""Paths need not live in the power-on frame. `ddrt ctl pose X Y THETA` sets
the estimator's pose (refused while moving, named errors, nothing changed on a refusal),
`reset` zeroes it, and `ddrt ctl follow FILE --here` moves the path to start at the robot's
pose and heading."""

from __future__ import annotations

import json
import math
from typing import Any

import pytest

from ddrt.path import load_path
from tests.support.daemon import DaemonProc, PATHS, at_rest_and_reset, ctl, wait_for


@pytest.fixture()
def idle(module_daemon: DaemonProc) -> DaemonProc:
    """The module's daemon (conftest's `module_daemon`), stopped and reset for this test."""
    return at_rest_and_reset(module_daemon)


def pose_of(d: DaemonProc) -> tuple[float, float, float]:
    p = d.status()["pose"]
    return p["x"], p["y"], p["theta"]


def test_ctl_pose_sets_the_pose_and_reset_zeroes_it(idle: DaemonProc) -> None:
    res = ctl(idle.socket, "pose", "1.5", "-2", "0.5")
    assert res.returncode == 0, res.stdout + res.stderr
    x, y, th = pose_of(idle)
    assert x == pytest.approx(1.5, abs=0.01) and y == pytest.approx(-2.0, abs=0.01)
    assert th == pytest.approx(0.5, abs=0.01)
    assert "pose set to (1.5000, -2.0000, 0.5000) over the control socket (pid " in idle.stderr()
    reply = idle.request({"cmd": "reset"})
    assert reply == {"ok": True, "state": "idle"}
    x, y, th = pose_of(idle)
    assert abs(x) < 0.01 and abs(y) < 0.01 and abs(th) < 0.01


@pytest.mark.parametrize("payload, needle", [
    ({"cmd": "pose"}, "pose: pose: missing (the robot's pose, m, m, rad)"),
    ({"cmd": "pose", "pose": [1, 2]}, "pose: pose: expected [x, y, theta]"),
    ({"cmd": "pose", "pose": [1, "a", 0]}, "pose: pose[1] (y): expected a number, got str"),
    ({"cmd": "pose", "pose": [1, 2, True]}, "pose: pose[2] (theta): expected a number, got bool"),
    ({"cmd": "pose", "pose": [1e9, 0, 0]}, "pose: pose[0] (x): 1e+09 is beyond"),
    ({"cmd": "pose", "pose": [0, 0, 0], "speed": 1}, "pose: speed: unknown field (pose takes pose, cov)"),
    ({"cmd": "follow", "shape": "line", "length": 0.3, "here": 1}, "follow: here: expected true or false"),
    ({"cmd": "follow", "shape": "line", "length": 0.3, "here": True, "pose": [0, 0, 0]}, "here and pose"),
])
def test_bad_pose_requests_change_nothing(idle: DaemonProc, payload: dict[str, Any], needle: str) -> None:
    before = pose_of(idle)
    reply = idle.request(payload)
    assert reply["ok"] is False and needle in reply["error"], reply
    assert pose_of(idle) == pytest.approx(before, abs=1e-3)
    assert idle.status()["state"] == "idle"


def test_pose_is_refused_while_driving(idle: DaemonProc) -> None:
    assert idle.request({"cmd": "drive", "v": 0.05, "omega": 0.0})["ok"] is True
    reply = idle.request({"cmd": "pose", "pose": [3.0, 3.0, 0.0]})
    assert reply["ok"] is False and reply["error"].startswith("pose refused in driving: send stop")
    assert math.hypot(*pose_of(idle)[:2]) < 0.5
    idle.request({"cmd": "stop"})


def test_ctl_follow_here_starts_the_path_at_the_robot(idle: DaemonProc) -> None:
    # Move the robot's frame: every shipped path now starts far from it, and is refused...
    assert idle.request({"cmd": "pose", "pose": [2.0, 1.0, 1.2]})["ok"] is True
    circle = str(PATHS / "circle_1m.yaml")
    res = ctl(idle.socket, "follow", circle)
    error = json.loads(res.stdout)["error"]
    assert res.returncode == 1 and "limits.max_path_error_m" in error and "ddrt ctl follow FILE --here" in error
    # ... unless placed here: it starts at the robot's pose and heading
    res = ctl(idle.socket, "follow", circle, "--here")
    assert res.returncode == 0, res.stdout + res.stderr
    reply = json.loads(res.stdout)
    assert reply["state"] == "following"
    ref = load_path(circle)
    assert reply["length_m"] == pytest.approx(ref.length, rel=1e-6)

    def going() -> dict[str, Any] | None:
        s = idle.status()
        return s if s["progress"]["sigma_m"] > 0.3 else None
    s = wait_for(going, 10.0, "progress along the moved circle")
    # the robot is on the moved path: its cross-track error stays small, and no start stage
    # (turn or join) was needed
    assert abs(s["progress"]["cross_track_m"]) < 0.05
    idle.request({"cmd": "stop"})


def test_moved_path_is_a_rigid_transform() -> None:
    p = load_path(str(PATHS / "circle_1m.yaml"))
    m = p.moved((2.0, 1.0, 1.2))
    assert m.start_pose == pytest.approx((2.0, 1.0, 1.2))
    assert (m.x[0], m.y[0]) == pytest.approx((2.0, 1.0))
    assert m.length == p.length and m.duration == p.duration and m.kappa == p.kappa
    # distances between samples are kept
    for i in (10, len(p.x) // 2, len(p.x) - 1):
        assert math.hypot(m.x[i] - m.x[0], m.y[i] - m.y[0]) == pytest.approx(math.hypot(p.x[i] - p.x[0], p.y[i] - p.y[0]))
    assert m.arrays()["x"][5] == pytest.approx(m.x[5]) and m.tx[3] == pytest.approx(math.cos(m.theta[3]))
