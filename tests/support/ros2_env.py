"""Real ROS 2 (Jazzy's rclpy from the unofficial PyPI wheels) for the bridge's tests.

The wheels (~300 MB) install a .pth file that re-launches Python, so they live in a venv of
their own, built once under ~/.cache/ddrt (DDRT_ROS2_VENV overrides) and reused: built in a
temporary folder and renamed when complete, so a build cut short is never taken for a venv.
`ros2_python()` returns its interpreter, or skips the test naming why (no network, pip
refused the wheels, a failed import). Its Fast DDS is Jazzy's default middleware (2.14).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from tests.support.repo import REPO

WHEELS = ("ros-jazzy-rclpy[fastrtps]", "ros-jazzy-nav-msgs", "ros-jazzy-geometry-msgs", "ros-jazzy-sensor-msgs",
          "ros-diagnostic-msgs<5.4", "ros-rmw-dds-common")  # tf2_msgs has no wheel on PyPI
VENV = Path(os.environ.get("DDRT_ROS2_VENV") or Path.home() / ".cache" / "ddrt" / "ros2-jazzy")
BUILD_TIMEOUT_S = 1800.0
NODE_SCRIPT = REPO / "tests" / "support" / "rclpy_node.py"

_failure: str | None = None


def _python() -> Path:
    return VENV / "bin" / "python"


def _works() -> str | None:
    try:
        out = subprocess.run([str(_python()), "-c", "import rclpy, nav_msgs.msg, geometry_msgs.msg; print('ok')"],
                             capture_output=True, text=True, timeout=120)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"{exc}"
    return None if out.stdout.strip().endswith("ok") else (out.stderr.strip().splitlines() or ["no output"])[-1]


def _build() -> str | None:
    tmp = VENV.with_name(VENV.name + ".building")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        subprocess.run([sys.executable, "-m", "venv", str(tmp)], check=True, capture_output=True, timeout=300)
        out = subprocess.run(["nice", "-n", "19", str(tmp / "bin" / "python"), "-m", "pip", "install", "-q", *WHEELS],
                             capture_output=True, text=True, timeout=BUILD_TIMEOUT_S)
    except (OSError, subprocess.SubprocessError) as exc:
        shutil.rmtree(tmp, ignore_errors=True)
        return f"cannot build the ROS 2 venv: {exc}"
    if out.returncode != 0:
        shutil.rmtree(tmp, ignore_errors=True)
        tail = [ln for ln in out.stderr.splitlines() if ln.startswith("ERROR")][-1:] or out.stderr.splitlines()[-1:]
        return f"pip could not install the ROS 2 Jazzy wheels ({', '.join(WHEELS)}): {' '.join(tail)}"
    os.replace(tmp, VENV)
    return None


def ros2_python() -> Path:
    """The ROS venv's interpreter (built on first use), or pytest.skip naming the reason."""
    global _failure
    if _failure is None and not _python().exists():
        _failure = _build() or ""
    if _failure is None or _failure == "":
        problem = _works()
        _failure = f"the ROS 2 venv at {VENV} does not import rclpy: {problem}" if problem else ""
    if _failure:
        pytest.skip(_failure)
    return _python()


def run_node(job: dict[str, Any], domain_id: int, timeout_s: float = 120.0) -> dict[str, Any]:
    """Run tests/support/rclpy_node.py with `job` in the ROS venv; its JSON result."""
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "VIRTUAL_ENV"))}
    env["ROS_DOMAIN_ID"] = str(domain_id)
    env.pop("RMW_IMPLEMENTATION", None)
    out = subprocess.run([str(ros2_python()), str(NODE_SCRIPT), json.dumps(job)], capture_output=True, text=True,
                         timeout=timeout_s, env=env, cwd="/tmp")
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith("{")]
    if out.returncode != 0 or not lines:
        pytest.fail(f"rclpy node failed ({out.returncode}):\n{out.stderr[-3000:]}")
    return json.loads(lines[-1])
