"""`daemon.ros2`: the ROS 2 bridge's section (docs/config.md, docs/ros2.md). A module of its
own so that the shared sections.py only names it."""

from __future__ import annotations

import math
from dataclasses import dataclass

from ddrt.config.schema import ConfigError, positive


@dataclass(frozen=True)
class Ros2Config:
    """The ROS 2 bridge (docs/ros2.md): a process of its own, started and supervised by the
    daemon when enabled; needs `pip install 'ddrt[ros2]'`."""

    enabled: bool = False
    domain_id: int = 0  # ROS_DOMAIN_ID
    namespace: str = ""  # the node's namespace; topics are relative to it
    node_name: str = "ddrt"
    odom_frame: str = "odom"
    base_frame: str = "base_link"
    map_frame: str = "map"
    imu_frame: str = "imu_link"
    imu_xyz: tuple[float, ...] = (0.0, 0.0, 0.0)  # m: imu_frame's origin in base_frame (/tf_static)
    odom_rate_hz: float = 50.0  # /odom and /tf (diff_drive_controller's publish_rate)
    imu_rate_hz: float = 100.0  # /imu/data_raw
    diagnostics_rate_hz: float = 1.0  # /diagnostics and /battery_state
    path_topic: str = "plan"  # nav_msgs/Path to follow
    pose_topic: str = "pose"  # a localiser's PoseWithCovarianceStamped, taken as pose fixes

    def validate(self, where: str) -> None:
        if not 0 <= self.domain_id <= 232:
            raise ConfigError(f"{where}.domain_id: must be 0..232, got {self.domain_id}")
        for key in ("node_name", "odom_frame", "base_frame", "map_frame", "imu_frame", "path_topic", "pose_topic"):
            value = getattr(self, key)
            if not value or not all(c.isalnum() or c in "_/" for c in value) or value[0].isdigit():
                raise ConfigError(f"{where}.{key}: expected a ROS name (letters, digits, _ and /), got {value!r}")
        if self.namespace and not all(c.isalnum() or c in "_/" for c in self.namespace):
            raise ConfigError(f"{where}.namespace: expected a ROS namespace, got {self.namespace!r}")
        if len(self.imu_xyz) != 3 or not all(math.isfinite(v) and abs(v) < 10.0 for v in self.imu_xyz):
            raise ConfigError(f"{where}.imu_xyz: expected [x, y, z] in metres, each within 10 m, got {list(self.imu_xyz)}")
        positive(where, odom_rate_hz=self.odom_rate_hz, imu_rate_hz=self.imu_rate_hz,
                 diagnostics_rate_hz=self.diagnostics_rate_hz)
        for key in ("odom_rate_hz", "imu_rate_hz", "diagnostics_rate_hz"):
            if getattr(self, key) > 500.0:
                raise ConfigError(f"{where}.{key}: at most 500 Hz (the state stream's rate), got {getattr(self, key):g}")
