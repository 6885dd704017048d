"""Pose fixes and the pose over the control socket (ddrt/service/posefix.py): `pose_fix` fuses
in any state and answers what it did; bad input names its field and changes nothing; `ddrt
ctl pose X Y THETA --cov C [--stamp T]` sends a fix, without --cov it sets the pose; status
carries the map pose, the uncertainty and the fix counters; a follow takes frame: map."""

from __future__ import annotations

import math
from typing import Any

import pytest

from tests.support.daemon import DaemonProc, at_rest_and_reset, ctl, wait_for

COV = [[1e-4, 0.0, 0.0], [0.0, 1e-4, 0.0], [0.0, 0.0, 3e-4]]


@pytest.fixture()
def idle(module_daemon: DaemonProc) -> DaemonProc:
    """The module's daemon (conftest's `module_daemon`), stopped and reset for this test."""
    return at_rest_and_reset(module_daemon)


def _snapshot(d: DaemonProc) -> tuple[Any, ...]:
    """What a refused fix must not change."""
    s = d.status()
    pm = s["pose_map"]
    return (pm["x"], pm["y"], pm["theta"], s["pose_fixes"]["fused"], s["pose_fixes"]["anchored"],
            *s["learnt"].values())


def _same(a: tuple[Any, ...], b: tuple[Any, ...]) -> bool:
    """Equal but for what standing still does meanwhile (the gyro's noise turns the estimate
    by microradians; a change a fix makes is millimetres)."""
    return a[3:5] == b[3:5] and a[5:] == b[5:] and all(abs(u - v) < 1e-4 for u, v in zip(a[:3], b[:3]))


def test_status_carries_the_map_pose_the_uncertainty_and_the_clock(idle: DaemonProc) -> None:
    s = idle.status()
    assert s["pose_map"] == pytest.approx({"x": s["pose"]["x"], "y": s["pose"]["y"], "theta": s["pose"]["theta"]})
    u = s["uncertainty"]
    assert u["std_x"] >= 0.0 and u["std_theta"] >= 0.0 and len(u["cov_map"]) == 3 and len(u["cov_odom"][0]) == 3
    # After a reset nothing says where map is: the first fix will.
    assert s["pose_fixes"] == {"anchored": False, "fused": 0, "outliers": 0, "reanchors": 0, "last_d2": None,
                               "last_stamp_s": None}
    t1 = s["clock_s"]
    assert idle.status()["clock_s"] > t1  # the loop's clock runs: what a stamp is on


def test_a_fix_is_fused_at_rest_and_moves_map_not_odom(idle: DaemonProc) -> None:
    before = idle.status()
    old = idle.request({"cmd": "pose_fix", "x": 0.0, "y": 0.0, "theta": 0.0, "cov": COV,
                        "stamp": before["clock_s"] - 1000.0})
    assert old["ok"] is False and old["error"].startswith("pose_fix: stamp: ") and "older than the history" in old["error"]
    reply = idle.request({"cmd": "pose_fix", "x": 0.01, "y": -0.005, "theta": 0.01, "cov": COV})
    assert reply["ok"] is True and reply["fused"] is True and reply["anchored"] is True, reply
    assert reply["fixes"] == {"fused": 1, "outliers": 0}
    s = idle.status()
    assert s["pose"] == pytest.approx(before["pose"], abs=1e-4)  # odom did not jump
    assert s["pose_map"] == pytest.approx({"x": 0.01, "y": -0.005, "theta": 0.01}, abs=1e-4)  # the first fix anchors map
    assert s["uncertainty"]["std_x"] == pytest.approx(0.01, rel=0.05)  # known as well as that fix
    assert s["pose_fixes"]["anchored"] is True
    # A second fix is fused, weighed against what the first one said.
    second = idle.request({"cmd": "pose_fix", "x": 0.02, "y": -0.005, "theta": 0.01, "cov": COV})
    assert second["fused"] is True and second["anchored"] is False and second["d2"] > 0.0, second
    x = idle.status()["pose_map"]["x"]
    assert 0.012 < x < 0.018  # between the two, as their equal weights say
    reply = second
    # A stamp before that fix, or ahead of the loop's clock, is refused and changes nothing.
    snap = _snapshot(idle)
    for stamp, words in ((reply["stamp"] - 0.05, "before the last fix"), (s["clock_s"] + 100.0, "in the future")):
        bad = idle.request({"cmd": "pose_fix", "x": 0.0, "y": 0.0, "theta": 0.0, "cov": COV, "stamp": stamp})
        assert bad["ok"] is False and bad["error"].startswith("pose_fix: stamp: ") and words in bad["error"], bad
        assert _same(_snapshot(idle), snap)
    # Setting the pose makes the two frames one again.
    assert idle.request({"cmd": "pose", "pose": [1.0, 2.0, 0.5], "cov": COV})["ok"] is True
    s = idle.status()
    assert s["pose_map"] == pytest.approx({"x": 1.0, "y": 2.0, "theta": 0.5})
    assert s["map_to_odom"] == pytest.approx({"x": 0.0, "y": 0.0, "theta": 0.0}, abs=1e-9)
    assert s["pose_fixes"]["anchored"] is True
    assert s["uncertainty"]["std_x"] == pytest.approx(0.01, rel=0.01)


@pytest.mark.parametrize("payload, needle", [
    ({"x": 0, "y": 0, "theta": 0}, "pose_fix: cov: missing"),
    ({"y": 0, "theta": 0, "cov": COV}, "pose_fix: x: missing"),
    ({"x": "1", "y": 0, "theta": 0, "cov": COV}, "pose_fix: x: expected a number"),
    ({"x": 0, "y": 1e301, "theta": 0, "cov": COV}, "pose_fix: y: expected a finite number in [-1e+06, 1e+06] (m), got 1e+301"),
    ({"x": 0, "y": 0, "theta": 0, "cov": [[1, 0, 0], [0, 1, 0]]}, "pose_fix: cov: expected a 3x3 matrix"),
    ({"x": 0, "y": 0, "theta": 0, "cov": [[1, 0.2, 0], [0, 1, 0], [0, 0, 1]]}, "pose_fix: cov: not symmetric"),
    ({"x": 0, "y": 0, "theta": 0, "cov": [[1, 0, 0], [0, -1, 0], [0, 0, 1]]}, "pose_fix: cov: not positive definite"),
    ({"x": 0, "y": 0, "theta": 0, "cov": COV, "stamp": "now"}, "pose_fix: stamp: expected a number"),
    ({"x": 0, "y": 0, "theta": 0, "cov": COV, "frame": "map"}, "pose_fix: frame: unknown field"),
    ({"pose": [0, 0, 0], "cov": [[1, 0, 0], [0, 0, 0], [0, 0, 1]], "cmd": "pose"}, "pose: cov: not positive definite"),
])
def test_bad_fixes_name_their_field_and_change_nothing(idle: DaemonProc, payload: dict[str, Any], needle: str) -> None:
    snap = _snapshot(idle)
    reply = idle.request({"cmd": "pose_fix", **payload})
    assert reply["ok"] is False and reply["error"].startswith(needle), reply
    assert _same(_snapshot(idle), snap)


def test_a_far_fix_is_an_outlier_counted_and_not_fused(idle: DaemonProc) -> None:
    assert idle.request({"cmd": "pose", "pose": [0.0, 0.0, 0.0], "cov": COV})["ok"] is True  # map anchored here
    snap = _snapshot(idle)
    reply = idle.request({"cmd": "pose_fix", "x": 3.0, "y": 0.0, "theta": 0.0, "cov": COV})
    assert reply["ok"] is True and reply["fused"] is False and reply["outlier"] is True and reply["d2"] > reply["gate"]
    assert idle.status()["pose_fixes"]["outliers"] >= 1
    assert _same(_snapshot(idle), snap)


def test_ctl_pose_with_cov_sends_a_fix_and_without_sets_the_pose(idle: DaemonProc) -> None:
    res = ctl(idle.socket, "pose", "0.004", "0", "0", "--cov", "1e-4,1e-4,3e-4")
    assert res.returncode == 0, res.stdout + res.stderr
    assert '"fused": true' in res.stdout
    assert idle.status()["pose_fixes"]["fused"] >= 1
    res = ctl(idle.socket, "pose", "0", "0", "0", "--stamp", "1")
    assert res.returncode != 0 and "--cov" in res.stderr
    res = ctl(idle.socket, "pose", "0.5", "0", "0")
    assert res.returncode == 0 and idle.status()["pose"]["x"] == pytest.approx(0.5)


def test_a_fix_while_following_a_path_in_map(idle: DaemonProc) -> None:
    reply = idle.request({"cmd": "follow", "shape": "circle", "radius": 0.4, "speed": 0.2, "frame": "map"})
    assert reply["ok"] is True, reply
    assert idle.status()["state"] == "following"
    bad = idle.request({"cmd": "follow", "shape": "line", "length": 0.3, "frame": "world"})
    assert bad["ok"] is False  # (already following; a bad frame is checked below at rest)
    s = idle.status()
    fix = idle.request({"cmd": "pose_fix", "x": s["pose_map"]["x"], "y": s["pose_map"]["y"] + 0.003,
                        "theta": s["pose_map"]["theta"], "cov": COV, "stamp": s["clock_s"]})
    assert fix["ok"] is True and fix["fused"] is True, fix
    assert idle.status()["state"] == "following"
    idle.request({"cmd": "stop"})
    wait_for(lambda: idle.status()["state"] in ("idle", "stopped"), 15.0, "stopped")
    bad = idle.request({"cmd": "follow", "shape": "line", "length": 0.3, "frame": "world"})
    assert bad["ok"] is False and "follow: frame: expected 'odom' or 'map'" in bad["error"]
    bad = idle.request({"cmd": "follow", "shape": "line", "length": 0.3, "frame": "map", "pose": [0, 0, 0]})
    assert bad["ok"] is False and "pose and frame map" in bad["error"]
    assert not math.isnan(idle.status()["uncertainty"]["std_x"])
