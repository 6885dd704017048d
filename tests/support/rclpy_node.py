"""An rclpy node for the ROS 2 tests: run by the ROS venv's python (tests/support/ros2_env.py),
never imported by the suite. Reads one JSON job from argv, prints one JSON result line.

Jobs ("do"):
- "listen": subscribe to /odom, /imu/data_raw, /battery_state and /diagnostics for `seconds`; report the
  messages' stamps and values, and what the graph says: node names, and per topic the
  publishers' and subscribers' node names, type names and type hashes.
- "cmd_vel": publish Twist or TwistStamped (`stamped`) with `v`, `omega` at `rate_hz` for
  `seconds`, listening to /odom meanwhile and for `after_s` more (the silence).
- "path": publish one nav_msgs/Path of `points` in `frame` (transient local, reliable, as
  Nav2's planner does), then listen to /odom for `seconds`.
- "pose": publish one PoseWithCovarianceStamped on `topic`.
- "types": for each of `types` ("nav_msgs/msg/Odometry", ...), subscribe to /p/<Type> and publish
  a default message on /q/<Type> at 10 Hz for `seconds`; report the messages received per type.
"""

import importlib
import json
import math
import sys
import time

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped, Twist, TwistStamped
from nav_msgs.msg import Odometry, Path
from sensor_msgs.msg import BatteryState, Imu
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

TOPICS = ("/odom", "/tf", "/tf_static", "/cmd_vel", "/imu/data_raw", "/diagnostics", "/plan", "/initialpose", "/pose")


def odom_row(m):
    q = m.pose.pose.orientation
    return {"t": m.header.stamp.sec + m.header.stamp.nanosec * 1e-9, "frame": m.header.frame_id,
            "child": m.child_frame_id, "x": m.pose.pose.position.x, "y": m.pose.pose.position.y,
            "theta": math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z)),
            "v": m.twist.twist.linear.x, "omega": m.twist.twist.angular.z,
            "cov_v": m.twist.covariance[0], "recv": time.monotonic()}


def spin_for(node, seconds, each=None):
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if each is not None:
            each()
        rclpy.spin_once(node, timeout_sec=0.005)


def graph(node):
    out = {"nodes": [n for n, _ns in node.get_node_names_and_namespaces()], "topics": {}}
    for t in TOPICS:
        ends = [("pub", i) for i in node.get_publishers_info_by_topic(t)] + \
               [("sub", i) for i in node.get_subscriptions_info_by_topic(t)]
        out["topics"][t] = [{"kind": k, "node": i.node_name, "type": i.topic_type,
                             "hash": str(i.topic_type_hash)} for k, i in ends]
    return out


def echo_types(job):
    node = rclpy.create_node("ddrt_types")
    got = {t: 0 for t in job["types"]}
    pubs = []
    for t in job["types"]:
        pkg, sub, name = t.split("/")
        cls = getattr(importlib.import_module(f"{pkg}.{sub}"), name)
        node.create_subscription(cls, f"/p/{name}", lambda _m, t=t: got.__setitem__(t, got[t] + 1), 10)
        pubs.append((node.create_publisher(cls, f"/q/{name}", 10), cls))
    next_t = [time.monotonic()]

    def publish():
        if time.monotonic() >= next_t[0]:
            next_t[0] += 0.1
            for pub, cls in pubs:
                pub.publish(cls())

    spin_for(node, job["seconds"], publish)
    print(json.dumps({"received": got}))


def main():
    job = json.loads(sys.argv[1])
    rclpy.init()
    if job["do"] == "types":
        echo_types(job)
        rclpy.shutdown()
        return
    node = rclpy.create_node("ddrt_test")
    odom = []
    node.create_subscription(Odometry, "/odom", lambda m: odom.append(odom_row(m)), 50)
    imu, battery = [], []
    node.create_subscription(Imu, "/imu/data_raw", lambda m: imu.append(
        {"wz": m.angular_velocity.z, "var": m.angular_velocity_covariance[8], "frame": m.header.frame_id,
         "recv": time.monotonic()}), 50)
    node.create_subscription(BatteryState, "/battery_state", lambda m: battery.append(
        {"v": m.voltage, "present": m.present}), 10)
    diagnostics = []  # byte fields arrive as bytes of length 1
    node.create_subscription(DiagnosticArray, "/diagnostics", lambda m: diagnostics.append(
        {"names": [st.name for st in m.status], "levels": [ord(st.level) for st in m.status]}), 10)
    spin_for(node, job.get("settle_s", 2.0))  # discovery
    odom.clear()
    imu.clear()
    do = job["do"]
    if do == "listen":
        spin_for(node, job["seconds"])
    elif do == "cmd_vel":
        stamped = job.get("stamped", False)
        pub = node.create_publisher(TwistStamped if stamped else Twist, "/cmd_vel", 10)
        spin_for(node, 1.0)
        sent = [0]
        next_t = [time.monotonic()]

        def publish():
            now = time.monotonic()
            if now < next_t[0]:
                return
            next_t[0] += 1.0 / job["rate_hz"]
            if stamped:
                m = TwistStamped()
                m.header.stamp = node.get_clock().now().to_msg()
                m.header.frame_id = "base_link"
                tw = m.twist
            else:
                m = tw = Twist()
            tw.linear.x = float(job["v"])
            tw.angular.z = float(job["omega"])
            pub.publish(m)
            sent[0] += 1

        t_start = time.monotonic()
        spin_for(node, job["seconds"], publish)
        t_silent = time.monotonic()
        spin_for(node, job["after_s"])
        print(json.dumps({"odom": odom, "sent": sent[0], "t_start": t_start, "t_silent": t_silent}))
        rclpy.shutdown()
        return
    elif do == "path":
        qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        pub = node.create_publisher(Path, job.get("topic", "/plan"), qos)
        spin_for(node, 1.0)
        p = Path()
        p.header.frame_id = job["frame"]
        p.header.stamp = node.get_clock().now().to_msg()
        for x, y in job["points"]:
            ps = PoseStamped()
            ps.header = p.header
            ps.pose.position.x = float(x)
            ps.pose.position.y = float(y)
            ps.pose.orientation.w = 1.0
            p.poses.append(ps)
        pub.publish(p)
        spin_for(node, job["seconds"])
    elif do == "pose":
        pub = node.create_publisher(PoseWithCovarianceStamped, job["topic"], 10)
        spin_for(node, 1.0)
        m = PoseWithCovarianceStamped()
        m.header.frame_id = "map"
        m.header.stamp = node.get_clock().now().to_msg()
        m.pose.pose.position.x, m.pose.pose.position.y = job["x"], job["y"]
        m.pose.pose.orientation.z, m.pose.pose.orientation.w = math.sin(job["theta"] / 2), math.cos(job["theta"] / 2)
        cov = [0.0] * 36
        cov[0] = cov[7] = job["var_xy"]
        cov[35] = job["var_theta"]
        m.pose.covariance = cov
        pub.publish(m)
        spin_for(node, job["seconds"])
    print(json.dumps({"odom": odom, "imu": imu, "battery": battery, "diagnostics": diagnostics,
                      "graph": graph(node)}))
    rclpy.shutdown()


main()
