"""The ROS 2 bridge over DDS, without ROS installed (docs/ros2.md). Only `interfaces` and
`typehash` are importable without the `ros2` extra (cyclonedds)."""
