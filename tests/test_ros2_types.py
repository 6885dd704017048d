"""The bridge's message types: RIHS01 hashes against two independent sources (the type
descriptions that ROS 2 Jazzy's and Kilted's wheels ship, and rosbags' own implementation), the DDS types
on the wire, and the frame arithmetic of ddrt/ros2/convert.py."""

from __future__ import annotations

import cmath
import json
import math

import pytest

from ddrt.ros2.interfaces import MESSAGES, dds_type_name, dependencies, fields_of
from ddrt.ros2.typehash import type_description, type_hash, user_data
from tests.support.ros2_env import DISTROS


def test_the_hash_is_sha256_of_the_description_and_changes_with_any_field() -> None:
    h = type_hash("geometry_msgs/msg/Vector3")
    assert h.startswith("RIHS01_") and len(h) == 7 + 64
    desc = type_description("nav_msgs/msg/Odometry")
    names = [d["type_name"] for d in desc["referenced_type_descriptions"]]
    assert names == sorted(names) and "builtin_interfaces/msg/Time" in names
    assert all("default_value" not in f for d in [desc["type_description"]] for f in d["fields"])
    # Renaming a field must change the hash (it is not a hash of the type name alone).
    saved = MESSAGES["geometry_msgs/msg/Vector3"]
    try:
        MESSAGES["geometry_msgs/msg/Vector3"] = saved.replace("float64 z", "float64 w")
        type_hash.cache_clear()
        assert type_hash("geometry_msgs/msg/Vector3") != h
    finally:
        MESSAGES["geometry_msgs/msg/Vector3"] = saved
        type_hash.cache_clear()
    assert type_hash("geometry_msgs/msg/Vector3") == h


def test_every_message_parses_and_refers_only_to_known_types() -> None:
    for name in MESSAGES:
        assert fields_of(name)
        assert all(dep in MESSAGES for dep in dependencies(name))
    assert dds_type_name("nav_msgs/msg/Odometry") == "nav_msgs::msg::dds_::Odometry_"
    assert user_data("nav_msgs/msg/Odometry") == f"typehash={type_hash('nav_msgs/msg/Odometry')};".encode()


@pytest.mark.parametrize("name", sorted(MESSAGES))
def test_hashes_match_rosbags(name: str) -> None:
    """rosbags computes RIHS01 from its own Jazzy type store (its Gid uses `char`, which it
    hashes differently from rosidl: rmw_dds_common is checked against Jazzy's files only)."""
    typesys = pytest.importorskip("rosbags.typesys", reason="rosbags is in the ros2 extra")
    if name.startswith("rmw_dds_common/"):
        pytest.skip("rosbags hashes rmw_dds_common's char[16] as char; rosidl as uint8 (checked below)")
    store = typesys.get_typestore(typesys.Stores.ROS2_JAZZY)
    assert type_hash(name) == store.hash_rihs01(name)


@pytest.mark.parametrize("distro", sorted(DISTROS))
def test_hashes_match_the_type_descriptions_the_wheels_ship(distro: str) -> None:
    """The JSON files rosidl_generator_type_description wrote into the distribution's wheels (in
    the ROS venv the rclpy tests build): every type of ours they include has our hash (Kilted
    changed none of these types)."""
    venv = DISTROS[distro].venv
    share = venv / "share"
    if not share.is_dir():
        pytest.skip(f"no ROS 2 {distro} venv at {venv} (tests/test_ros2_rclpy.py builds it)")
    checked = []
    for name in MESSAGES:
        pkg, _, short = name.split("/")
        f = share / pkg / "msg" / f"{short}.json"
        if f.exists():
            doc = json.loads(f.read_text())
            theirs = {h["type_name"]: h["hash_string"] for h in doc["type_hashes"]}
            assert type_hash(name) == theirs[name], name
            checked.append(name)
    assert "nav_msgs/msg/Odometry" in checked and "rmw_dds_common/msg/ParticipantEntitiesInfo" in checked


def test_the_dds_types_use_xcdr1_and_round_trip() -> None:
    pytest.importorskip("cyclonedds", reason="the ros2 extra")
    from ddrt.ros2.idl import msg

    odom_t = msg("nav_msgs/msg/Odometry")
    assert odom_t.__idl_typename__ == "nav_msgs::msg::dds_::Odometry_"
    o = odom_t(child_frame_id="base_link")
    o.pose.pose.position.x = 1.25
    o.pose.covariance = [float(i) for i in range(36)]
    data = o.serialize()
    assert data[:2] == b"\x00\x01"  # CDR little-endian: XCDR1, what ROS 2's middlewares send
    back = odom_t.deserialize(data)
    assert back == o and back.pose.covariance[35] == 35.0
    assert msg("nav_msgs/msg/Odometry") is odom_t


def test_map_to_odom_composes_to_the_map_pose() -> None:
    pytest.importorskip("cyclonedds", reason="the ros2 extra")
    from ddrt.ros2 import convert

    # Independently, with complex numbers: pose = (translation, rotation e^{i theta}).
    for odom, in_map in [((1.0, 2.0, 0.3), (1.5, 1.0, -2.8)), ((0.0, 0.0, 0.0), (0.2, -0.1, 0.5)),
                         ((-3.0, 0.5, 3.1), (-2.9, 0.7, -3.1))]:
        x, y, d = convert.map_to_odom(odom, in_map)
        composed = complex(x, y) + cmath.exp(1j * d) * complex(odom[0], odom[1])
        assert composed == pytest.approx(complex(in_map[0], in_map[1]), abs=1e-12)
        assert math.remainder(d + odom[2] - in_map[2], 2 * math.pi) == pytest.approx(0.0, abs=1e-12)
    for th in (-3.0, -1.0, 0.0, 0.7, 3.1):
        assert convert.quaternion_yaw(convert.yaw_quaternion(th)) == pytest.approx(th, abs=1e-12)


def test_covariances_keep_what_is_known_and_flag_what_is_not() -> None:
    pytest.importorskip("cyclonedds", reason="the ros2 extra")
    from ddrt.ros2 import convert

    nan = math.nan
    s = {"var_x": nan, "var_y": nan, "cov_xy": nan, "var_theta": nan, "var_v": 4e-6, "var_omega": 9e-6}
    pose = convert.pose_covariance(s)
    assert pose[0] == pose[7] == pose[35] == convert.UNKNOWN_VAR and pose[1] == 0.0
    s.update(var_x=1e-4, var_y=2e-4, cov_xy=5e-5, var_theta=3e-4)
    pose = convert.pose_covariance(s)
    assert (pose[0], pose[1], pose[6], pose[7], pose[35]) == (1e-4, 5e-5, 5e-5, 2e-4, 3e-4)
    twist = convert.twist_covariance(s)
    assert (twist[0], twist[35]) == (4e-6, 9e-6)
    cov6 = [float(i) for i in range(36)]
    assert convert.cov3(cov6) == [[0.0, 1.0, 5.0], [6.0, 7.0, 11.0], [30.0, 31.0, 35.0]]
