"""The ROS 2 bridge against real ROS 2: rclpy from the unofficial PyPI wheels, on each
distribution's default middleware, in subprocesses: Jazzy (Fast DDS 2.14) and Kilted (Fast DDS
3.2, which sends XTypes type information that ddrt/ros2/node.py's domain has to ignore), against
a `ddrt run` daemon on the simulated robot with `daemon.ros2.enabled`. Skipped, naming the
reason, when a distribution's wheels cannot be installed (tests/support/ros2_env.py); the
bridge needs the `ros2` extra (cyclonedds)."""

from __future__ import annotations

import math
import statistics
import os
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Iterator

import pytest

from tests.support.daemon import DaemonProc, ready_daemon, wait_for
from tests.support.ros2_env import DISTROS, ros2_python, run_node

pytest.importorskip("cyclonedds", reason="the bridge needs the ros2 extra: pip install 'ddrt[ros2]'")

from ddrt.ros2.interfaces import MESSAGES  # noqa: E402
from ddrt.ros2.typehash import type_hash  # noqa: E402

pytestmark = pytest.mark.slow

# Apart from other runs on this host: a daemon's domain per distribution (+0, +1) and one for
# the type test's (+2, +3); ROS 2 domain ids end at 232.
DOMAIN = 10 + 4 * (os.getpid() % 50)
ODOM_HZ = 40.0
IMU_HZ = 80.0
DIAG_HZ = 2.0
TIMEOUT_S = 0.5
BARE_DDS_APP = "_CREATED_BY_BARE_DDS_APP_"


@pytest.fixture(scope="module", params=sorted(DISTROS))
def distro(request: pytest.FixtureRequest) -> str:
    return request.param


@pytest.fixture(scope="module")
def bridged(distro: str) -> Iterator[DaemonProc]:
    ros2_python(distro)  # skip before starting anything when there is no ROS 2
    with ready_daemon(path=None, daemon={"command_timeout_s": TIMEOUT_S,
                                         "ros2": {"enabled": True, "domain_id": domain_of(distro),
                                                  "odom_rate_hz": ODOM_HZ, "imu_rate_hz": IMU_HZ,
                                                  "diagnostics_rate_hz": DIAG_HZ}}) as d:
        wait_for(lambda: "sending the loop's state to @ddrt-ros2" in d.stderr(), 60.0, "the bridge's state stream")
        yield d


def ours(graph: dict, topic: str, distro: str) -> list[dict]:
    """The bridge's endpoints on `topic` in rclpy's graph. Fast DDS 3.2 (Kilted) names the node
    of no endpoint that Cyclone DDS announces (it lists the node `ddrt` from ros_discovery_info,
    but shows its readers and writers as created by a bare DDS application), so there they are
    the endpoints that are not the test node's."""
    ends = graph["topics"][topic]
    if distro == "kilted":
        return [e for e in ends if e["node"] in ("ddrt", BARE_DDS_APP)]
    return [e for e in ends if e["node"] == "ddrt"]


def domain_of(distro: str) -> int:
    return DOMAIN + sorted(DISTROS).index(distro)


def node(job: dict, distro: str) -> dict:
    """One rclpy job of tests/support/rclpy_node.py on `distro`, in the bridged daemon's domain."""
    return run_node(job, domain_of(distro), distro=distro)


def pose_of(d: DaemonProc) -> tuple[float, float, float]:
    p = d.status()["pose"]
    return p["x"], p["y"], p["theta"]


def wait_state(d: DaemonProc, states: tuple[str, ...], timeout: float = 30.0) -> str:
    return wait_for(lambda: (s := d.status()["state"]) in states and s, timeout, f"state in {states}")


def test_odom_arrives_at_the_configured_rate_with_the_robots_pose(bridged: DaemonProc, distro: str) -> None:
    before = pose_of(bridged)
    out = node({"do": "listen", "seconds": 4.0}, distro)
    odom = out["odom"]
    after = pose_of(bridged)
    assert len(odom) >= 10, out
    # The rate from the median gap between arrivals: a host that preempts the bridge now and
    # then stretches a few gaps, not the rate the bridge keeps.
    rate = 1.0 / statistics.median(b["recv"] - a["recv"] for a, b in zip(odom, odom[1:]))
    assert 0.6 * ODOM_HZ <= rate <= 1.1 * ODOM_HZ, f"{rate:.1f} Hz"
    stamps = [m["t"] for m in odom]
    assert all(b > a for a, b in zip(stamps, stamps[1:])), "stamps must increase"
    assert {(m["frame"], m["child"]) for m in odom} == {("odom", "base_link")}
    # At rest: every message carries the pose the daemon reports (which only the gyro's
    # noise moves, integrated: within what it was before and after, give or take 1e-4).
    for i, key in enumerate(("x", "y", "theta")):
        lo, hi = min(before[i], after[i]) - 1e-4, max(before[i], after[i]) + 1e-4
        assert all(lo <= m[key] <= hi for m in odom), (key, lo, hi, [m[key] for m in odom][:5])
    assert all(m["cov_v"] > 0.0 for m in odom)
    # The gyro at its own rate, with its noise; the measured supply, as status reports it.
    imu = out["imu"]
    assert len(imu) >= 10 and {m["frame"] for m in imu} == {"imu_link"}
    imu_rate = 1.0 / statistics.median(b["recv"] - a["recv"] for a, b in zip(imu, imu[1:]))
    assert 0.6 * IMU_HZ <= imu_rate <= 1.1 * IMU_HZ, f"{imu_rate:.1f} Hz"
    assert all(abs(m["wz"]) < 0.05 and m["var"] > 0.0 for m in imu)  # at rest, bias removed
    supply = bridged.status()["supply"]
    if supply["measured"]:
        assert out["battery"] and out["battery"][-1]["present"]
        assert out["battery"][-1]["v"] == pytest.approx(supply["v_slow"], rel=0.02)
    # Diagnostics (a sequence of structs of sequences): the loop's status at rest is OK (0) or
    # WARN (1: holding), never ERROR or STALE; at DIAG_HZ, a 6 s listen holds several.
    diags = out["diagnostics"]
    assert len(diags) >= 3, diags
    assert all(m["names"] == ["ddrt: loop", "ddrt: ros2 bridge"] and m["levels"][0] in (0, 1) for m in diags), diags
    graph = out["graph"]
    assert "ddrt" in graph["nodes"]
    tf = ours(graph, "/tf", distro)
    assert [(e["kind"], e["type"]) for e in tf] == [("pub", "tf2_msgs/msg/TFMessage")]


@pytest.mark.parametrize("stamped", [False, True], ids=["Twist", "TwistStamped"])
def test_cmd_vel_drives_the_robot_and_silence_stops_it(bridged: DaemonProc, distro: str, stamped: bool) -> None:
    wait_state(bridged, ("idle", "stopped"))
    v, w = 0.15, 0.4
    out = node({"do": "cmd_vel", "stamped": stamped, "v": v, "omega": w, "rate_hz": 20.0,
                "seconds": 3.0, "after_s": 2.5}, distro)
    odom = out["odom"]
    driving = [m for m in odom if out["t_start"] + 1.5 <= m["recv"] <= out["t_silent"]]
    assert driving, out
    # The median, not the mean: on a loaded host a command the bridge forwards late lets the
    # daemon's 0.5 s timeout brake the robot for a moment (seen: a mean of 0.12 for 0.15 m/s).
    assert statistics.median(m["v"] for m in driving) == pytest.approx(v, rel=0.15)
    assert statistics.median(m["omega"] for m in driving) == pytest.approx(w, rel=0.15)
    # The pose the messages carry integrates their velocities (unicycle, trapezoid rule).
    x, y, th = odom[0]["x"], odom[0]["y"], odom[0]["theta"]
    for a, b in zip(odom, odom[1:]):
        dt = b["t"] - a["t"]
        vm, wm = 0.5 * (a["v"] + b["v"]), 0.5 * (a["omega"] + b["omega"])
        x += vm * dt * math.cos(th + 0.5 * wm * dt)
        y += vm * dt * math.sin(th + 0.5 * wm * dt)
        th += wm * dt
    travelled = math.hypot(odom[-1]["x"] - odom[0]["x"], odom[-1]["y"] - odom[0]["y"])
    assert travelled > 0.25
    assert math.hypot(x - odom[-1]["x"], y - odom[-1]["y"]) < 0.05 * travelled
    # Silence: the daemon's command timeout, then braking; the last second is at rest.
    last = [m for m in odom if m["recv"] >= out["t_silent"] + 1.5]
    assert last and max(abs(m["v"]) for m in last) < 0.01, last[-3:]
    assert bridged.status()["state"] == "stopped"


def test_a_path_published_in_odom_is_followed(bridged: DaemonProc, distro: str) -> None:
    wait_state(bridged, ("idle", "stopped"))
    x0, y0, th0 = pose_of(bridged)
    pts = [(x0 + d * math.cos(th0), y0 + d * math.sin(th0)) for d in (0.0, 0.3, 0.6)]
    out = node({"do": "path", "frame": "odom", "points": pts, "seconds": 2.0}, distro)
    assert any(m["v"] > 0.05 for m in out["odom"]), "the robot did not start along the path"
    wait_state(bridged, ("idle", "stopped"), timeout=60.0)
    x, y, _ = pose_of(bridged)
    assert math.hypot(x - pts[-1][0], y - pts[-1][1]) < 0.03


def test_type_names_and_hashes_rclpy_reports_are_ours(bridged: DaemonProc, distro: str) -> None:
    out = node({"do": "listen", "seconds": 0.5}, distro)
    mine = [e for topic in out["graph"]["topics"] for e in ours(out["graph"], topic, distro)]
    seen = {(e["kind"], e["type"]) for e in mine}
    assert {("pub", "nav_msgs/msg/Odometry"), ("pub", "tf2_msgs/msg/TFMessage"), ("pub", "sensor_msgs/msg/Imu"),
            ("pub", "diagnostic_msgs/msg/DiagnosticArray"), ("sub", "geometry_msgs/msg/Twist"),
            ("sub", "geometry_msgs/msg/TwistStamped"), ("sub", "nav_msgs/msg/Path"),
            ("sub", "geometry_msgs/msg/PoseWithCovarianceStamped")} <= seen
    for e in mine:
        assert e["type"] in MESSAGES
        assert e["hash"] == type_hash(e["type"]), e
    # rclpy's own endpoints carry the hashes its generated code holds: the same for the same types.
    theirs = [e for ends in out["graph"]["topics"].values() for e in ends if e["node"] == "ddrt_test"]
    assert theirs and all(e["hash"] == type_hash(e["type"]) for e in theirs)


def test_a_localiser_pose_becomes_a_pose_fix(bridged: DaemonProc, distro: str) -> None:
    probe = bridged.request({"cmd": "pose_fix"})
    if "unknown command" in str(probe.get("error", "")):
        pytest.skip("the daemon has no pose_fix command, so a localiser's pose cannot become a fix")
    wait_state(bridged, ("idle", "stopped"))
    x0, y0, th0 = pose_of(bridged)
    before = bridged.status()["pose_fixes"]
    node({"do": "pose", "topic": "/pose", "x": x0 + 0.02, "y": y0 - 0.01, "theta": th0,
          "var_xy": 1e-6, "var_theta": 1e-4, "seconds": 1.5}, distro)
    # The daemon counts every fix that reaches it, fused (the first anchors the map) or gated
    # out: the PoseWithCovarianceStamped (a float64[36] inside) crossed over.
    wait_for(lambda: (f := bridged.status()["pose_fixes"])["fused"] + f["outliers"] > before["fused"] + before["outliers"],
             10.0, "the fix counted in the status")


# Every type the bridge has on the wire (tf2_msgs/TFMessage has no wheel to test it with).
WIRE_TYPES = ("geometry_msgs/msg/Twist", "geometry_msgs/msg/TwistStamped", "nav_msgs/msg/Odometry",
              "nav_msgs/msg/Path", "sensor_msgs/msg/Imu", "sensor_msgs/msg/BatteryState",
              "diagnostic_msgs/msg/DiagnosticArray", "geometry_msgs/msg/PoseWithCovarianceStamped")


def test_every_type_crosses_both_ways(distro: str) -> None:
    """Each type from a node of ours (ddrt/ros2/node.py, in this process) to rclpy and back, at
    10 Hz each way for 6 s. On Kilted, before the bridge ignored Fast DDS 3.2's type information,
    Twist and TwistStamped crossed and every type with an array or a sequence did not, either way."""
    ros2_python(distro)
    from ddrt.ros2.idl import msg
    from ddrt.ros2.node import Node

    domain = domain_of(distro) + 2  # a domain of its own: no daemon here
    ours_node = Node("ddrt_types", "/", domain)
    writers = {t: ours_node.writer(f"/p/{t.rsplit('/', 1)[1]}", t) for t in WIRE_TYPES}
    readers = {t: ours_node.reader(f"/q/{t.rsplit('/', 1)[1]}", t) for t in WIRE_TYPES}
    ours_node.announce()
    got = dict.fromkeys(WIRE_TYPES, 0)
    with ThreadPoolExecutor(1) as pool:
        job = pool.submit(run_node, {"do": "types", "types": list(WIRE_TYPES), "seconds": 6.0}, domain,
                          distro=distro)
        while not job.done():
            for t, w in writers.items():
                w.write(msg(t)())
            for t, r in readers.items():
                got[t] += len(r.take(N=100))
            time.sleep(0.1)
        theirs = job.result()["received"]
    # ~60 a type each way once matched; discovery takes the first second or two of a loaded host.
    assert all(n >= 10 for n in theirs.values()), f"rclpy ({distro}) received {theirs}"
    assert all(n >= 10 for n in got.values()), f"ddrt received from rclpy ({distro}) {got}"
