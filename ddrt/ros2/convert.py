"""Between ddrt's state and requests and ROS 2's messages: plain functions, one per message.

Conventions (REP-103, REP-105): x forward, y left, yaw counter-clockwise; `odom -> base_link`
is the dead-reckoned pose (continuous, never jumps), `map -> odom` the correction pose fixes
make. Covariances are row-major 6x6 over (x, y, z, roll, pitch, yaw). A planar robot's
z, roll and pitch (and its lateral, vertical and tilt rates) are zero by construction: they
get PLANAR_VAR, not zero, so a consumer inverting the matrix does not divide by zero. A
variance ddrt does not know yet (NaN in the state) is published as UNKNOWN_VAR, large enough
that a filter fusing it takes nothing from it.
"""

from __future__ import annotations

import math
from typing import Any, Mapping

from ddrt.ros2.idl import msg

PLANAR_VAR = 1e-9
UNKNOWN_VAR = 1e6
NS = 1_000_000_000


def stamp(epoch_s: float) -> Any:
    sec = math.floor(epoch_s)
    nsec = min(int(round((epoch_s - sec) * NS)), NS - 1)
    return msg("builtin_interfaces/msg/Time")(sec=int(sec), nanosec=nsec)


def stamp_seconds(t: Any) -> float:
    return t.sec + t.nanosec * 1e-9


def header(epoch_s: float, frame: str) -> Any:
    return msg("std_msgs/msg/Header")(stamp=stamp(epoch_s), frame_id=frame)


def yaw_quaternion(theta: float) -> Any:
    return msg("geometry_msgs/msg/Quaternion")(z=math.sin(0.5 * theta), w=math.cos(0.5 * theta))


def quaternion_yaw(q: Any) -> float:
    """The yaw of a quaternion (its tilt ignored)."""
    return math.atan2(2.0 * (q.w * q.z + q.x * q.y), 1.0 - 2.0 * (q.y * q.y + q.z * q.z))


def _var(value: float) -> float:
    return value if math.isfinite(value) else UNKNOWN_VAR


def pose_covariance(s: Mapping[str, float]) -> list[float]:
    c = [0.0] * 36
    c[0], c[7], c[35] = _var(s["var_x"]), _var(s["var_y"]), _var(s["var_theta"])
    if math.isfinite(s["cov_xy"]):
        c[1] = c[6] = s["cov_xy"]
    c[14] = c[21] = c[28] = PLANAR_VAR
    return c


def twist_covariance(s: Mapping[str, float]) -> list[float]:
    c = [0.0] * 36
    c[0], c[35] = _var(s["var_v"]), _var(s["var_omega"])
    c[7] = c[14] = c[21] = c[28] = PLANAR_VAR
    return c


def odometry(s: Mapping[str, float], epoch_s: float, odom_frame: str, base_frame: str) -> Any:
    o = msg("nav_msgs/msg/Odometry")(header=header(epoch_s, odom_frame), child_frame_id=base_frame)
    o.pose.pose.position.x = s["x"]
    o.pose.pose.position.y = s["y"]
    o.pose.pose.orientation = yaw_quaternion(s["theta"])
    o.pose.covariance = pose_covariance(s)
    o.twist.twist.linear.x = s["v"]
    o.twist.twist.angular.z = s["omega"]
    o.twist.covariance = twist_covariance(s)
    return o


def transform(epoch_s: float, parent: str, child: str, x: float, y: float, theta: float, z: float = 0.0) -> Any:
    tf = msg("geometry_msgs/msg/TransformStamped")(header=header(epoch_s, parent), child_frame_id=child)
    tf.transform.translation.x = x
    tf.transform.translation.y = y
    tf.transform.translation.z = z
    tf.transform.rotation = yaw_quaternion(theta)
    return tf


def map_to_odom(odom: tuple[float, float, float], in_map: tuple[float, float, float]) -> tuple[float, float, float]:
    """The transform map -> odom that puts the robot's odom pose at its map pose:
    T_map_odom = T_map_base * inverse(T_odom_base)."""
    ox, oy, oth = odom
    mx, my, mth = in_map
    d = math.atan2(math.sin(mth - oth), math.cos(mth - oth))
    c, s = math.cos(d), math.sin(d)
    return mx - (c * ox - s * oy), my - (s * ox + c * oy), d


def tf_message(s: Mapping[str, float], epoch_s: float, frames: Any) -> Any:
    """odom -> base_link, and map -> odom once the state has a map pose."""
    out = [transform(epoch_s, frames.odom_frame, frames.base_frame, s["x"], s["y"], s["theta"])]
    if math.isfinite(s["map_x"]) and math.isfinite(s["map_y"]) and math.isfinite(s["map_theta"]):
        x, y, th = map_to_odom((s["x"], s["y"], s["theta"]), (s["map_x"], s["map_y"], s["map_theta"]))
        out.append(transform(epoch_s, frames.map_frame, frames.odom_frame, x, y, th))
    return msg("tf2_msgs/msg/TFMessage")(transforms=out)


def imu(s: Mapping[str, float], epoch_s: float, frame: str) -> Any:
    """The yaw rate, bias removed, with its noise; no orientation, no acceleration (-1: not
    provided, sensor_msgs/Imu's convention); x and y rates are not read (UNKNOWN_VAR)."""
    m = msg("sensor_msgs/msg/Imu")(header=header(epoch_s, frame))
    m.orientation.w = 1.0
    m.orientation_covariance = [-1.0] + [0.0] * 8
    m.angular_velocity.z = s["gyro"] - s["gyro_bias"]
    m.angular_velocity_covariance = [UNKNOWN_VAR, 0.0, 0.0, 0.0, UNKNOWN_VAR, 0.0, 0.0, 0.0, _var(s["var_gyro"])]
    m.linear_acceleration_covariance = [-1.0] + [0.0] * 8
    return m


def battery(s: Mapping[str, float], epoch_s: float, frame: str) -> Any | None:
    """sensor_msgs/BatteryState once the supply is measured (None before); what is not
    measured is NaN, as the message asks."""
    v = s["battery_v"]
    if not math.isfinite(v):
        return None
    nan = math.nan
    return msg("sensor_msgs/msg/BatteryState")(
        header=header(epoch_s, frame), voltage=v, temperature=nan, current=nan, charge=nan, capacity=nan,
        design_capacity=nan, percentage=nan, present=True, location="motor supply")


OK, WARN, ERROR, STALE = 0, 1, 2, 3


def diagnostics(epoch_s: float, state: str, fault: str, values: Mapping[str, Any], bridge: Mapping[str, Any],
                stale: bool) -> Any:
    """Two statuses: the loop (its state, fault and timing from `status`) and the bridge."""
    status_t = msg("diagnostic_msgs/msg/DiagnosticStatus")
    kv = msg("diagnostic_msgs/msg/KeyValue")
    if stale:
        level, text = STALE, "no state from the daemon"
    elif state in ("fault", "estop"):
        level, text = ERROR, f"{state}: {fault}" if fault else state
    elif state == "holding":
        level, text = WARN, state
    else:
        level, text = OK, state
    loop = status_t(level=level, name="ddrt: loop", message=text, hardware_id="ddrt",
                    values=[kv(key=str(k), value=str(v)) for k, v in values.items()])
    link = status_t(level=OK, name="ddrt: ros2 bridge", message="running", hardware_id="ddrt",
                    values=[kv(key=str(k), value=str(v)) for k, v in bridge.items()])
    return msg("diagnostic_msgs/msg/DiagnosticArray")(header=header(epoch_s, ""), status=[loop, link])


def cov3(c: list[float]) -> list[list[float]]:
    """The (x, y, yaw) block of a 6x6 row-major covariance."""
    idx = (0, 1, 5)
    return [[float(c[6 * i + j]) for j in idx] for i in idx]


def path_csv(poses: list[Any]) -> str:
    """A nav_msgs/Path's positions as the CSV a follow takes ("x,y" lines)."""
    lines = ["x,y"] + [f"{p.pose.position.x!r},{p.pose.position.y!r}" for p in poses]
    return "\n".join(lines) + "\n"
