"""The ROS 2 bridge's process: ROS 2 topics on one side, a running daemon on the other.

One thread, one loop: it waits on the state datagrams (ddrt/ros2/link.py), publishes what is
due (/odom and /tf at `odom_rate_hz`, /imu/data_raw at `imu_rate_hz`, /diagnostics and
/battery_state at `diagnostics_rate_hz`), and takes what ROS 2 sent (DDS readers keep it in
their own bounded histories meanwhile). Requests to the daemon are paced:

- /cmd_vel (TwistStamped or Twist, either one, same topic): the newest command wins; a
  `drive` goes out when a new one has arrived, at most every DRIVE_INTERVAL_S. Silence sends
  nothing, so the daemon's `daemon.command_timeout_s` stops the robot as for any client. A
  10 kHz flood costs the daemon at most 1 / DRIVE_INTERVAL_S requests a second.
- the path topic: the newest path is sent as a `follow` (its positions as CSV; `frame: map`
  when its header names the map frame); an empty path is a `stop`.
- /initialpose and the localiser's pose topic: a `pose_fix` each (newest first, at most one
  per FIX_INTERVAL_S), with the pose's (x, y, yaw) covariance and its stamp on the loop's clock.

Nothing here can hold the loop up: the daemon never waits for this process (the stream's
sends are non-blocking, requests are answered between ticks like any client's).
"""

from __future__ import annotations

import logging
import math
import os
import select
import time
from dataclasses import dataclass, field
from typing import Any

from cyclonedds.internal import InvalidSample

from ddrt.config.ros2 import Ros2Config
from ddrt.loop.states import state_label
from ddrt.ros2 import convert
from ddrt.ros2.link import DaemonLink, StateInbox
from ddrt.ros2.node import DEFAULT, TF, TF_STATIC, Node
from ddrt.service.commands import CommandError, payload

log = logging.getLogger("ddrt.ros2")

DRIVE_INTERVAL_S = 0.08  # 12.5 drives/s at most: inside the socket's 20/s, 6 per default timeout
FIX_INTERVAL_S = 0.1
STATUS_TIMEOUT_S = 1.0  # no state for this long: diagnostics say stale, nothing else published
RETRY_S = 1.0


@dataclass
class Counters:
    states: int = 0
    cmd_vel: int = 0
    drives: int = 0
    refused: int = 0
    paths: int = 0
    fixes: int = 0
    errors: dict[str, int] = field(default_factory=dict)


def _samples(reader: Any, n: int) -> list[Any]:
    """Up to `n` messages waiting; a writer's disposal or unregistration (no data) is skipped."""
    return [m for m in reader.take(N=n) if not isinstance(m, InvalidSample)]


# (name, type, QoS) of every topic the bridge publishes; the recording has the same.
PUBLISHED = (("odom", "nav_msgs/msg/Odometry", DEFAULT), ("/tf", "tf2_msgs/msg/TFMessage", TF),
             ("/tf_static", "tf2_msgs/msg/TFMessage", TF_STATIC), ("imu/data_raw", "sensor_msgs/msg/Imu", DEFAULT),
             ("battery_state", "sensor_msgs/msg/BatteryState", DEFAULT),
             ("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray", DEFAULT))


class Bridge:
    """The node, its topics, the link; `run` until `stop` is set."""

    def __init__(self, socket_path: str, cfg: Ros2Config, dds: bool = True, record: Any = None) -> None:
        """`dds`: on ROS 2 (daemon.ros2.enabled); `record`: a RotatingBag the same messages go
        to as well (daemon.telemetry_format: rosbag2), or None."""
        self.cfg = cfg
        self.link = DaemonLink(socket_path)
        self.inbox = StateInbox(self.link, max(cfg.odom_rate_hz, cfg.imu_rate_hz))
        self.record = record
        self.writers: dict[str, Any] = {}
        self.node = None
        if dds:
            self.node = node = Node(cfg.node_name, cfg.namespace or "/", cfg.domain_id)
            for name, type_name, profile in PUBLISHED:
                self.writers[name] = node.writer(name, type_name, profile)
            self.sub_twist = node.reader("cmd_vel", "geometry_msgs/msg/Twist", DEFAULT)
            self.sub_twist_stamped = node.reader("cmd_vel", "geometry_msgs/msg/TwistStamped", DEFAULT)
            self.sub_path = node.reader(cfg.path_topic, "nav_msgs/msg/Path", DEFAULT)
            self.sub_initial = node.reader("initialpose", "geometry_msgs/msg/PoseWithCovarianceStamped", DEFAULT)
            self.sub_pose = node.reader(cfg.pose_topic, "geometry_msgs/msg/PoseWithCovarianceStamped", DEFAULT)
            node.announce()
        self.count = Counters()
        self.stop = False
        self.state: dict[str, float] | None = None
        self._state_at = -math.inf  # monotonic time the newest state arrived
        self._seq_odom = self._seq_imu = -1.0
        self._epoch = time.time() - time.monotonic()  # the loop's monotonic stamps -> ROS time
        self._cmd: tuple[float, float] | None = None
        self._last_drive = -math.inf
        self._path: Any = None
        self._fix: tuple[str, Any] | None = None
        self._last_fix = -math.inf
        self._status: dict[str, Any] = {}
        self._refusal = ""
        self._down = ""
        t_now = time.monotonic()
        self._next = {"odom": t_now, "imu": t_now, "diag": t_now}
        self._publish_static()

    # ------------------------------------------------------------------ publishing

    def _publish_static(self) -> None:
        c = self.cfg
        x, y, z = c.imu_xyz
        tf = convert.transform(time.time(), c.base_frame, c.imu_frame, x, y, 0.0, z)
        self._out("/tf_static", convert.msg("tf2_msgs/msg/TFMessage")(transforms=[tf]), time.time())

    def _stamp(self, s: dict[str, float]) -> float:
        return s["mono"] + self._epoch

    def _publish_due(self, now: float) -> None:
        s, c = self.state, self.cfg
        fresh = s is not None and now - self._state_at < STATUS_TIMEOUT_S
        if fresh and s is not None:
            if now >= self._next["odom"] and s["seq"] != self._seq_odom:
                self._seq_odom = s["seq"]
                stamp = self._stamp(s)
                self._out("odom", convert.odometry(s, stamp, c.odom_frame, c.base_frame), stamp)
                self._out("/tf", convert.tf_message(s, stamp, c), stamp)
                self._next["odom"] = max(self._next["odom"] + 1.0 / c.odom_rate_hz, now)
            if now >= self._next["imu"] and s["seq"] != self._seq_imu:
                self._seq_imu = s["seq"]
                self._out("imu/data_raw", convert.imu(s, self._stamp(s), c.imu_frame), self._stamp(s))
                self._next["imu"] = max(self._next["imu"] + 1.0 / c.imu_rate_hz, now)
        if now >= self._next["diag"]:
            self._next["diag"] = max(self._next["diag"] + 1.0 / c.diagnostics_rate_hz, now)
            self._publish_diagnostics(s if fresh else None)

    def _publish_diagnostics(self, s: dict[str, float] | None) -> None:
        self._status = self._request("status").get("status") or {}
        st = self._status
        timing = st.get("timing") if isinstance(st.get("timing"), dict) else {}
        values = {k: timing[k] for k in sorted(timing) if not isinstance(timing[k], (dict, list))}
        if s is not None:
            values.update({"gyro_bias_rad_s": f"{s['gyro_bias']:.6g}", "battery_v": f"{s['battery_v']:.4g}",
                           "hw_estop_open": str(s["hw_estop"] > 0.5)})
        state = state_label(int(s["state"])) if s is not None else "unknown"
        c = self.count
        bridge = {"states_received": self.inbox.received, "cmd_vel_received": c.cmd_vel, "drives_sent": c.drives,
                  "drives_refused": c.refused, "paths_sent": c.paths, "pose_fixes_sent": c.fixes,
                  "errors": sum(c.errors.values())}
        now = time.time()
        self._out("/diagnostics", convert.diagnostics(now, state, str(st.get("fault") or ""), values, bridge,
                                                      s is None), now)
        if s is not None:
            b = convert.battery(s, self._stamp(s), self.cfg.base_frame)
            if b is not None:
                self._out("battery_state", b, self._stamp(s))

    def _out(self, name: str, message: Any, stamp_s: float) -> None:
        writer = self.writers.get(name)
        if writer is not None:
            writer.write(message)
        if self.record is not None:
            self.record.write(name, message, stamp_s)

    # ------------------------------------------------------------------ subscriptions

    def _take_ros(self) -> None:
        if self.node is None:
            return
        newest = None
        for m in _samples(self.sub_twist, 1000):
            newest = (m.linear.x, m.angular.z)
            self.count.cmd_vel += 1
        for m in _samples(self.sub_twist_stamped, 1000):
            newest = (m.twist.linear.x, m.twist.angular.z)
            self.count.cmd_vel += 1
        if newest is not None:
            self._cmd = newest
        paths = _samples(self.sub_path, 100)
        if paths:
            self._path = paths[-1]
        for topic, reader in (("initialpose", self.sub_initial), (self.cfg.pose_topic, self.sub_pose)):
            fixes = _samples(reader, 100)
            if fixes:
                self._fix = (topic, fixes[-1])

    def _send_due(self, now: float) -> None:
        if self._cmd is not None and now - self._last_drive >= DRIVE_INTERVAL_S:
            v, w = self._cmd
            self._cmd = None
            self._last_drive = now
            if math.isfinite(v) and math.isfinite(w):
                self.count.drives += 1
                self._answer(self._request("drive", v=v, omega=w), "cmd_vel")
            else:
                self._error("cmd_vel: a non-finite velocity, dropped")
        if self._path is not None:
            path, self._path = self._path, None
            self._follow(path)
        if self._fix is not None and now - self._last_fix >= FIX_INTERVAL_S:
            (topic, m), self._fix = self._fix, None
            self._last_fix = now
            self._pose_fix(topic, m)

    def _follow(self, path: Any) -> None:
        c = self.cfg
        self.count.paths += 1
        if not path.poses:
            self._answer(self._request("stop"), "path (empty: stop)")
            return
        frame = path.header.frame_id.lstrip("/")
        req: dict[str, Any] = {"content": convert.path_csv(path.poses), "format": "csv", "name": "ros2-path.csv"}
        if frame == c.map_frame:
            req["frame"] = "map"
        elif frame not in ("", c.odom_frame):
            self._error(f"{c.path_topic}: a path in frame {frame!r}: only {c.odom_frame!r} and "
                        f"{c.map_frame!r} are followed")
            return
        self._answer(self._request("follow", timeout_s=10.0, **req), c.path_topic)

    def _pose_fix(self, topic: str, m: Any) -> None:
        s = self.state
        if s is None:
            self._error(f"{topic}: no state from the daemon yet: the fix's time cannot be placed")
            return
        p = m.pose.pose
        # The message's stamp on the loop's clock: ROS time -> monotonic -> the sample clock.
        stamp = convert.stamp_seconds(m.header.stamp) - self._epoch + (s["t"] - s["mono"])
        self.count.fixes += 1
        self._answer(self._request("pose_fix", x=p.position.x, y=p.position.y,
                                   theta=convert.quaternion_yaw(p.orientation),
                                   cov=convert.cov3(list(m.pose.covariance)), stamp=stamp), topic)

    # ------------------------------------------------------------------ the daemon

    def _request(self, cmd: str, timeout_s: float = 2.0, **fields: Any) -> dict[str, Any]:
        """The daemon's reply to one command, built and checked against its declaration here
        (a message that fits no request is answered as the daemon would refuse it)."""
        try:
            wire = payload(cmd, **fields)
        except CommandError as exc:
            return {"ok": False, "error": str(exc)}
        self.link.timeout_s = timeout_s
        try:
            reply = self.link.request(wire)
        except (OSError, ValueError) as exc:
            text = f"{exc}"
            if text != self._down:
                log.warning("ros2: cannot reach the daemon: %s (retrying)", text)
            self._down = text
            return {"ok": False, "error": text}
        if self._down:
            log.info("ros2: the daemon answers again")
            self._down = ""
        return reply

    def _answer(self, reply: dict[str, Any], what: str) -> None:
        if reply.get("ok"):
            self._refusal = ""
            return
        self.count.refused += 1
        self._error(f"{what}: {reply.get('error')}")

    def _error(self, text: str) -> None:
        key = text.split(":", 1)[0]
        self.count.errors[key] = self.count.errors.get(key, 0) + 1
        if text != self._refusal:  # once until it changes: a 10 kHz flood must not flood the log
            log.warning("ros2: %s", text)
        self._refusal = text

    # ------------------------------------------------------------------ main loop

    def step(self, timeout_s: float) -> None:
        now = time.monotonic()
        try:
            err = self.inbox.renew(now)
        except (OSError, ValueError) as exc:
            err = f"{exc}"
        if err and err != self._down:
            log.warning("ros2: no state stream: %s (retrying)", err)
            self._down = err
        ready, _, _ = select.select([self.inbox], [], [], timeout_s)
        now = time.monotonic()
        if ready:
            s = self.inbox.take()
            if s is not None:
                self.state = s
                self._state_at = now
                self.count.states += 1
        self._take_ros()
        self._send_due(now)
        self._publish_due(now)

    def run(self, parent: int | None = None) -> None:
        """Until `stop`; with `parent` (supervised), also once that process is gone: a daemon
        killed outright leaves no bridge behind."""
        tick = 1.0 / max(self.cfg.odom_rate_hz, self.cfg.imu_rate_hz, 20.0)
        while not self.stop:
            self.step(tick / 2.0)
            if parent is not None and os.getppid() != parent:
                log.info("ros2: the daemon is gone; stopping")
                break

    def close(self) -> None:
        self.link.close()
        self.inbox.close()
        if self.record is not None:
            self.record.close()
