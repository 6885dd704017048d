"""Real ROS 2 (rclpy from the unofficial PyPI wheels) for the bridge's tests, per distribution:
Jazzy (its default middleware Fast DDS 2.14) and Kilted (Fast DDS 3.2).

The wheels (~270 MB a distribution) install a .pth file that re-launches Python, and the two
distributions' wheels share package names (ros-rclpy 7 and 9), so each lives in a venv of its
own, built once under ~/.cache/ddrt/ros2-<distro> (DDRT_ROS2_VENV overrides Jazzy's,
DDRT_ROS2_KILTED_VENV Kilted's) and reused: built in a temporary folder and renamed when
complete, so a build cut short is never taken for a venv. `ros2_python(distro)` returns its
interpreter, or skips the test naming why (no network, pip refused the wheels, a failed import).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from tests.support.repo import REPO

BUILD_TIMEOUT_S = 1800.0
NODE_SCRIPT = REPO / "tests" / "support" / "rclpy_node.py"
CACHE = Path.home() / ".cache" / "ddrt"


@dataclass(frozen=True)
class Distro:
    """One ROS 2 distribution's wheels, where its venv lives, and its default middleware."""

    name: str
    wheels: tuple[str, ...]
    venv: Path
    middleware: str


DISTROS = {
    "jazzy": Distro("jazzy", ("ros-jazzy-rclpy[fastrtps]", "ros-jazzy-nav-msgs", "ros-jazzy-geometry-msgs",
                              "ros-jazzy-sensor-msgs", "ros-diagnostic-msgs<5.4", "ros-rmw-dds-common"),
                    Path(os.environ.get("DDRT_ROS2_VENV") or CACHE / "ros2-jazzy"), "Fast DDS 2.14"),
    # ros-kilted-rclpy[fastrtps] brings rmw_fastrtps_cpp 9.3 and ros-fastdds 3.2.
    "kilted": Distro("kilted", ("ros-kilted-rclpy[fastrtps]", "ros-kilted-nav-msgs", "ros-kilted-geometry-msgs",
                                "ros-kilted-sensor-msgs", "ros-diagnostic-msgs>=5.5,<5.6", "ros-rmw-dds-common>=4,<5"),
                     Path(os.environ.get("DDRT_ROS2_KILTED_VENV") or CACHE / "ros2-kilted"), "Fast DDS 3.2"),
}  # tf2_msgs has no wheel on PyPI
VENV = DISTROS["jazzy"].venv  # the Jazzy venv, whose type descriptions tests/test_ros2_types.py reads

_failure: dict[str, str] = {}  # distro -> "" (works) or why not


def _python(d: Distro) -> Path:
    return d.venv / "bin" / "python"


def _works(d: Distro) -> str | None:
    try:
        out = subprocess.run([str(_python(d)), "-c", "import rclpy, nav_msgs.msg, geometry_msgs.msg; print('ok')"],
                             capture_output=True, text=True, timeout=120)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"{exc}"
    return None if out.stdout.strip().endswith("ok") else (out.stderr.strip().splitlines() or ["no output"])[-1]


def _build(d: Distro) -> str | None:
    tmp = d.venv.with_name(d.venv.name + ".building")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        subprocess.run([sys.executable, "-m", "venv", str(tmp)], check=True, capture_output=True, timeout=300)
        out = subprocess.run(["nice", "-n", "19", str(tmp / "bin" / "python"), "-m", "pip", "install", "-q",
                              *d.wheels], capture_output=True, text=True, timeout=BUILD_TIMEOUT_S)
    except (OSError, subprocess.SubprocessError) as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        return f"cannot build the ROS 2 {d.name} venv: {exc}"
    if out.returncode != 0:
        shutil.rmtree(tmp, ignore_errors=True)
        tail = [ln for ln in out.stderr.splitlines() if ln.startswith("ERROR")][-1:] or out.stderr.splitlines()[-1:]
        return f"pip could not install the ROS 2 {d.name} wheels ({', '.join(d.wheels)}): {' '.join(tail)}"
    os.replace(tmp, d.venv)
    return None


def ros2_python(distro: str = "jazzy") -> Path:
    """The distribution's venv interpreter (built on first use), or pytest.skip naming the reason."""
    d = DISTROS[distro]
    if distro not in _failure and not _python(d).exists():
        _failure[distro] = _build(d) or ""
    if not _failure.get(distro):
        problem = _works(d)
        _failure[distro] = f"the ROS 2 {distro} venv at {d.venv} does not import rclpy: {problem}" if problem else ""
    if _failure[distro]:
        pytest.skip(_failure[distro])
    return _python(d)


def run_node(job: dict[str, Any], domain_id: int, timeout_s: float = 120.0, distro: str = "jazzy") -> dict[str, Any]:
    """Run tests/support/rclpy_node.py with `job` in the distribution's venv; its JSON result.
    The node runs on the distribution's default middleware (RMW_IMPLEMENTATION unset)."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "VIRTUAL_ENV"))}
    env["ROS_DOMAIN_ID"] = str(domain_id)
    env.pop("RMW_IMPLEMENTATION", None)
    out = subprocess.run([str(ros2_python(distro)), str(NODE_SCRIPT), json.dumps(job)], capture_output=True,
                         text=True, timeout=timeout_s, env=env, cwd="/tmp")
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith("{")]
    if out.returncode != 0 or not lines:
        pytest.fail(f"rclpy node ({distro}) failed ({out.returncode}):\n{out.stderr[-3000:]}")
    return json.loads(lines[-1])
