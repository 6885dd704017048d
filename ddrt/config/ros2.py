"""`daemon.ros2`: the ROS 2 bridge's section (docs/ros2.md). A module of its own so that the
shared sections.py only names it."""

from __future__ import annotations

from dataclasses import dataclass

from ddrt.params.decl import Text
from ddrt.config.schema import Section, setting

# A ROS name: letters, digits, _ and /, not starting with a digit; a namespace may be empty.
ROS_NAME = Text(r"(?:[^\W\d]|/)[\w/]*", "a ROS name (letters, digits, _ and /, not starting with a digit)")
ROS_NAMESPACE = Text(r"[\w/]*", "a ROS namespace (letters, digits, _ and /)")
MAX_RATE_HZ = 500.0  # the state stream's rate: a topic cannot be fresher


@dataclass(frozen=True)
class Ros2Config(Section):
    """The ROS 2 bridge (docs/ros2.md): a process of its own, started and supervised by the
    daemon when enabled; needs `pip install 'ddrt[ros2]'`."""

    enabled: bool = setting(
        False,
        doc="Start the bridge (`python -m ddrt.ros2`). `ddrt ros2 --socket ...` runs the same bridge by hand "
            "against a running daemon.")
    domain_id: int = setting(0, ge=0, le=232, doc="ROS_DOMAIN_ID.")
    namespace: str = setting(
        "", text=ROS_NAMESPACE,
        doc="The node's namespace; relative topics (`odom`, `cmd_vel`, ...) are in it, `/tf`, `/tf_static` and "
            "`/diagnostics` are not.")
    node_name: str = setting("ddrt", text=ROS_NAME, doc="The node's name (`ros2 node list`).")
    odom_frame: str = setting(
        "odom", text=ROS_NAME, doc="The odometry frame (REP-105): /odom's header, the parent of `base_frame` in /tf.")
    base_frame: str = setting(
        "base_link", text=ROS_NAME, doc="The robot's frame: /odom's child frame, at the rear axle's midpoint A.")
    map_frame: str = setting(
        "map", text=ROS_NAME,
        doc="The frame pose fixes are in: `map -> odom` in /tf; a path whose header names it is followed in it.")
    imu_frame: str = setting(
        "imu_link", text=ROS_NAME, doc="/imu/data_raw's frame; /tf_static places it in `base_frame`.")
    imu_xyz: tuple[float, float, float] = setting(
        (0.0, 0.0, 0.0), unit="m", gt=-10.0, lt=10.0,
        doc="Where the gyro sits in `base_frame` (x forward, y left, z up): /tf_static's "
            "`base_frame -> imu_frame`.")
    odom_rate_hz: float = setting(
        50.0, unit="Hz", gt=0, le=MAX_RATE_HZ, doc="/odom and /tf (diff_drive_controller's publish_rate).")
    imu_rate_hz: float = setting(100.0, unit="Hz", gt=0, le=MAX_RATE_HZ, doc="/imu/data_raw.")
    diagnostics_rate_hz: float = setting(
        1.0, unit="Hz", gt=0, le=MAX_RATE_HZ, doc="/diagnostics and /battery_state.")
    path_topic: str = setting(
        "plan", text=ROS_NAME, doc="nav_msgs/Path to follow (Nav2's planner publishes `plan`).")
    pose_topic: str = setting(
        "pose", text=ROS_NAME,
        doc="A localiser's geometry_msgs/PoseWithCovarianceStamped, taken as pose fixes (`/initialpose` too).")
