"""The ROS 2 message types the bridge speaks, written once as .msg text.

Everything else is derived from this table: the DDS types (ddrt/ros2/idl.py), the type
descriptions and their RIHS01 hashes (ddrt/ros2/typehash.py), and the rosbag2 message
definitions (ddrt/ros2/bag.py). Field lists follow the ROS 2 Jazzy interface packages
(common_interfaces, rcl_interfaces, rmw_dds_common) field for field, in their order; constants
are left out (they are neither on the wire nor in the type hash). Default values are left out
too: RIHS01 hashes the description without them.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

MESSAGES: dict[str, str] = {
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec",
    "std_msgs/msg/Header": "builtin_interfaces/msg/Time stamp\nstring frame_id",
    "geometry_msgs/msg/Vector3": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/msg/Point": "float64 x\nfloat64 y\nfloat64 z",
    "geometry_msgs/msg/Quaternion": "float64 x\nfloat64 y\nfloat64 z\nfloat64 w",
    "geometry_msgs/msg/Pose": "geometry_msgs/msg/Point position\ngeometry_msgs/msg/Quaternion orientation",
    "geometry_msgs/msg/PoseStamped": "std_msgs/msg/Header header\ngeometry_msgs/msg/Pose pose",
    "geometry_msgs/msg/PoseWithCovariance": "geometry_msgs/msg/Pose pose\nfloat64[36] covariance",
    "geometry_msgs/msg/PoseWithCovarianceStamped":
        "std_msgs/msg/Header header\ngeometry_msgs/msg/PoseWithCovariance pose",
    "geometry_msgs/msg/Twist": "geometry_msgs/msg/Vector3 linear\ngeometry_msgs/msg/Vector3 angular",
    "geometry_msgs/msg/TwistStamped": "std_msgs/msg/Header header\ngeometry_msgs/msg/Twist twist",
    "geometry_msgs/msg/TwistWithCovariance": "geometry_msgs/msg/Twist twist\nfloat64[36] covariance",
    "geometry_msgs/msg/Transform": "geometry_msgs/msg/Vector3 translation\ngeometry_msgs/msg/Quaternion rotation",
    "geometry_msgs/msg/TransformStamped":
        "std_msgs/msg/Header header\nstring child_frame_id\ngeometry_msgs/msg/Transform transform",
    "nav_msgs/msg/Odometry": "std_msgs/msg/Header header\nstring child_frame_id\n"
                             "geometry_msgs/msg/PoseWithCovariance pose\ngeometry_msgs/msg/TwistWithCovariance twist",
    "nav_msgs/msg/Path": "std_msgs/msg/Header header\ngeometry_msgs/msg/PoseStamped[] poses",
    "tf2_msgs/msg/TFMessage": "geometry_msgs/msg/TransformStamped[] transforms",
    "sensor_msgs/msg/Imu": "std_msgs/msg/Header header\ngeometry_msgs/msg/Quaternion orientation\n"
                           "float64[9] orientation_covariance\ngeometry_msgs/msg/Vector3 angular_velocity\n"
                           "float64[9] angular_velocity_covariance\ngeometry_msgs/msg/Vector3 linear_acceleration\n"
                           "float64[9] linear_acceleration_covariance",
    "sensor_msgs/msg/BatteryState": "std_msgs/msg/Header header\nfloat32 voltage\nfloat32 temperature\n"
                                    "float32 current\nfloat32 charge\nfloat32 capacity\nfloat32 design_capacity\n"
                                    "float32 percentage\nuint8 power_supply_status\nuint8 power_supply_health\n"
                                    "uint8 power_supply_technology\nbool present\nfloat32[] cell_voltage\n"
                                    "float32[] cell_temperature\nstring location\nstring serial_number",
    "diagnostic_msgs/msg/KeyValue": "string key\nstring value",
    "diagnostic_msgs/msg/DiagnosticStatus": "byte level\nstring name\nstring message\nstring hardware_id\n"
                                            "diagnostic_msgs/msg/KeyValue[] values",
    "diagnostic_msgs/msg/DiagnosticArray": "std_msgs/msg/Header header\n"
                                           "diagnostic_msgs/msg/DiagnosticStatus[] status",
    "rmw_dds_common/msg/Gid": "uint8[16] data",
    "rmw_dds_common/msg/NodeEntitiesInfo": "string<=256 node_namespace\nstring<=256 node_name\n"
                                           "rmw_dds_common/msg/Gid[] reader_gid_seq\n"
                                           "rmw_dds_common/msg/Gid[] writer_gid_seq",
    "rmw_dds_common/msg/ParticipantEntitiesInfo": "rmw_dds_common/msg/Gid gid\n"
                                                  "rmw_dds_common/msg/NodeEntitiesInfo[] node_entities_info_seq",
}

PRIMITIVES = ("bool", "byte", "char", "int8", "uint8", "int16", "uint16", "int32", "uint32", "int64", "uint64",
              "float32", "float64", "string")

_FIELD = re.compile(r"^(?P<base>[A-Za-z0-9_/]+)(?:<=(?P<strbound>\d+))?"
                    r"(?:\[(?P<seq><=)?(?P<n>\d*)\])?\s+(?P<name>[a-z][a-z0-9_]*)$")


@dataclass(frozen=True)
class Field:
    """One field of a message: `kind` is "single", "array" (fixed size), "bounded" or "sequence"."""

    name: str
    base: str  # a primitive of PRIMITIVES, or a full message name "pkg/msg/Type"
    kind: str = "single"
    size: int = 0  # the array's size or the sequence's bound
    string_bound: int = 0  # string<=N

    @property
    def nested(self) -> bool:
        return self.base not in PRIMITIVES


def fields_of(type_name: str) -> tuple[Field, ...]:
    """The parsed fields of a message of MESSAGES; ValueError naming a line it cannot read."""
    out = []
    for line in MESSAGES[type_name].splitlines():
        m = _FIELD.match(line.strip())
        if m is None:
            raise ValueError(f"{type_name}: cannot read field {line!r}")
        base = m["base"]
        if base not in PRIMITIVES and base not in MESSAGES:
            raise ValueError(f"{type_name}: {line!r}: unknown type {base}")
        if m["n"] is None:
            kind, size = "single", 0
        elif m["seq"]:
            kind, size = "bounded", int(m["n"])
        elif m["n"]:
            kind, size = "array", int(m["n"])
        else:
            kind, size = "sequence", 0
        out.append(Field(m["name"], base, kind, size, int(m["strbound"] or 0)))
    return tuple(out)


def dependencies(type_name: str) -> list[str]:
    """Every message type `type_name` uses, directly or not, sorted by name (itself excluded)."""
    seen: set[str] = set()
    todo = [type_name]
    while todo:
        for f in fields_of(todo.pop()):
            if f.nested and f.base not in seen:
                seen.add(f.base)
                todo.append(f.base)
    seen.discard(type_name)
    return sorted(seen)


def dds_type_name(type_name: str) -> str:
    """"nav_msgs/msg/Odometry" -> "nav_msgs::msg::dds_::Odometry_" (the name on the wire)."""
    pkg, sub, name = type_name.split("/")
    return f"{pkg}::{sub}::dds_::{name}_"
