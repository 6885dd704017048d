"""rosbag2 recordings (MCAP storage) of the bridge's topics, with rosbags.

`BagWriter` writes the same messages the live bridge publishes (ddrt/ros2/convert.py, the
same DDS types: a message's CDR bytes are what rosbag2 stores), with the type hashes ours
(ddrt/ros2/typehash.py) and the Jazzy message definitions from rosbags' type store, so
`ros2 bag info` and `ros2 bag play` read them. `export_csv` is `ddrt bag export`: a daemon's
or `ddrt sim`'s telemetry CSV as /odom, /tf, /tf_static and /diagnostics.
"""

from __future__ import annotations

import csv
import math
import os
import shutil
import time
from pathlib import Path
from typing import Any, Mapping

from ddrt.errors import DdrtError
from ddrt.config.ros2 import Ros2Config
from ddrt.loop.states import state_label
from ddrt.ros2 import convert
from ddrt.ros2.interfaces import MESSAGES
from ddrt.ros2.node import TF, TF_STATIC, QosProfile
from ddrt.ros2.typehash import type_hash

TOPICS: dict[str, tuple[str, QosProfile | None]] = {
    "odom": ("nav_msgs/msg/Odometry", None),
    "/tf": ("tf2_msgs/msg/TFMessage", TF),
    "/tf_static": ("tf2_msgs/msg/TFMessage", TF_STATIC),
    "imu/data_raw": ("sensor_msgs/msg/Imu", None),
    "battery_state": ("sensor_msgs/msg/BatteryState", None),
    "/diagnostics": ("diagnostic_msgs/msg/DiagnosticArray", None),
}
# The telemetry CSV's columns (ddrt/loop/record.py) -> the state's names (ddrt/service/stream.py).
FROM_CSV = {"t": "t", "x_est": "x", "y_est": "y", "theta_est": "theta", "v_est": "v", "omega_est": "omega",
            "gyro_bias": "gyro_bias", "state": "state"}


class BagError(DdrtError, ValueError):
    """A recording that cannot be written or an input that cannot be read (names the file)."""


def _topic(cfg: Ros2Config, name: str) -> str:
    if name.startswith("/"):
        return name
    ns = cfg.namespace.strip("/")
    return f"/{ns}/{name}" if ns else f"/{name}"


class BagWriter:
    """One rosbag2 (MCAP) folder; `write(topic, message, stamp_s)`."""

    def __init__(self, out_dir: str | os.PathLike[str], cfg: Ros2Config) -> None:
        from rosbags.rosbag2 import StoragePlugin, Writer
        from rosbags.typesys import Stores, get_typestore

        self.cfg = cfg
        store = get_typestore(Stores.ROS2_JAZZY)
        if Path(out_dir).exists():
            raise BagError(f"{out_dir}: exists already (rosbag2 writes a new folder)")
        self._writer = Writer(Path(out_dir), version=9, storage_plugin=StoragePlugin.MCAP)
        self._writer.open()
        self._conns: dict[str, Any] = {}
        for name, (type_name, _qos) in TOPICS.items():
            assert type_name in MESSAGES
            self._conns[name] = self._writer.add_connection(_topic(cfg, name), type_name, typestore=store,
                                                            rihs01=type_hash(type_name))
        self.count = 0
        self.bytes = 0

    def write(self, name: str, message: Any, stamp_s: float) -> None:
        data = message.serialize()
        self._writer.write(self._conns[name], int(round(stamp_s * 1e9)), data)
        self.count += 1
        self.bytes += len(data)

    def write_state(self, s: Mapping[str, float], stamp_s: float) -> None:
        c = self.cfg
        self.write("odom", convert.odometry(s, stamp_s, c.odom_frame, c.base_frame), stamp_s)
        self.write("/tf", convert.tf_message(s, stamp_s, c), stamp_s)

    def close(self) -> None:
        self._writer.close()


class RotatingBag:
    """`daemon.telemetry_format: rosbag2`: bags `rosbag2-<UTC time>` in `directory`, a new one
    once the current one holds `max_bytes` of messages, at most `max_files` kept (the oldest
    removed), as the CSV and MCAP files rotate (daemon.telemetry_max_bytes, _max_files)."""

    PREFIX = "rosbag2-"

    def __init__(self, directory: str | os.PathLike[str], cfg: Ros2Config, max_bytes: int, max_files: int) -> None:
        self.directory = Path(directory)
        self.cfg = cfg
        self.max_bytes = max_bytes
        self.max_files = max_files
        self.directory.mkdir(parents=True, exist_ok=True)
        self.current: BagWriter | None = None
        self._open()

    def _open(self) -> None:
        name = self.PREFIX + time.strftime("%Y%m%d-%H%M%S", time.gmtime())
        n = 0
        while (self.directory / (name + (f"-{n}" if n else ""))).exists():
            n += 1
        self.current = BagWriter(self.directory / (name + (f"-{n}" if n else "")), self.cfg)
        bags = sorted(p for p in self.directory.iterdir() if p.is_dir() and p.name.startswith(self.PREFIX))
        for old in bags[: max(0, len(bags) - self.max_files)]:
            shutil.rmtree(old, ignore_errors=True)

    def write(self, name: str, message: Any, stamp_s: float) -> None:
        assert self.current is not None
        self.current.write(name, message, stamp_s)
        if self.current.bytes >= self.max_bytes:
            self.current.close()
            self._open()

    def close(self) -> None:
        if self.current is not None:
            self.current.close()
            self.current = None


def _state(row: Mapping[str, float]) -> dict[str, float]:
    nan = math.nan
    s = {k: nan for k in ("var_x", "var_y", "cov_xy", "var_theta", "var_v", "var_omega", "var_gyro", "gyro",
                          "battery_v", "hw_estop", "map_x", "map_y", "map_theta")}
    s.update({ours: row[col] for col, ours in FROM_CSV.items()})
    return s


def _rows(path: Path, f: Any) -> list[dict[str, float]]:
    """The telemetry columns the bag needs, one dict a whole row; BagError naming the line."""
    reader = csv.reader(f)
    header = next(reader, None)
    missing = sorted(set(FROM_CSV) - set(header or []))
    if header is None or missing:
        raise BagError(f"{path}: not a ddrt telemetry CSV (no column {', '.join(missing) or 'at all'})")
    idx = {name: header.index(name) for name in FROM_CSV}
    rows = []
    for lineno, cells in enumerate(reader, start=2):
        if len(cells) != len(header):
            continue  # a row cut short by a daemon's end
        try:
            rows.append({k: float(cells[i]) for k, i in idx.items()})
        except ValueError:
            raise BagError(f"{path}: line {lineno}: not a number in {cells[:3]}...") from None
    return rows


def export_csv(csv_path: str | os.PathLike[str], out_dir: str | os.PathLike[str], cfg: Ros2Config,
               epoch_s: float | None = None) -> dict[str, Any]:
    """The telemetry CSV as a rosbag2: /odom and /tf at cfg.odom_rate_hz (of the rows' time),
    /diagnostics at each change of state and at cfg.diagnostics_rate_hz, /tf_static once.
    Stamps: the rows' `t` plus `epoch_s` (default: the file's modification time less its
    last row's `t`, so a daemon's recording lands at the wall time it was made)."""
    path = Path(csv_path)
    try:
        f = open(path, newline="", encoding="ascii")
    except OSError as exc:
        raise BagError(f"{path}: cannot read: {exc.strerror or exc}") from None
    with f:
        try:
            rows = _rows(path, f)
        except (UnicodeDecodeError, csv.Error) as exc:
            raise BagError(f"{path}: not a ddrt telemetry CSV ({exc})") from None
    if not rows:
        raise BagError(f"{path}: no rows")
    if epoch_s is None:
        epoch_s = path.stat().st_mtime - rows[-1]["t"]
    writer = BagWriter(out_dir, cfg)
    c = cfg
    try:
        x, y, z = c.imu_xyz
        first = epoch_s + rows[0]["t"]
        writer.write("/tf_static", convert.msg("tf2_msgs/msg/TFMessage")(
            transforms=[convert.transform(first, c.base_frame, c.imu_frame, x, y, 0.0, z)]), first)
        t0 = rows[0]["t"]
        last_slot = -1
        next_diag = -math.inf
        last_state = None
        for seq, row in enumerate(rows):
            s = _state(row)
            s["seq"] = float(seq)
            stamp = epoch_s + row["t"]
            slot = math.floor((row["t"] - t0) * c.odom_rate_hz + 1e-6)  # odom_rate_hz of the rows' time
            if slot != last_slot:
                writer.write_state(s, stamp)
                last_slot = slot
            if row["t"] >= next_diag or row["state"] != last_state:
                label = state_label(int(row["state"]))
                writer.write("/diagnostics", convert.diagnostics(stamp, label, "", {"t": f"{row['t']:.3f}"}, {},
                                                                 False), stamp)
                next_diag = row["t"] + 1.0 / c.diagnostics_rate_hz
                last_state = row["state"]
    finally:
        writer.close()
    return {"rows": len(rows), "messages": writer.count, "seconds": rows[-1]["t"] - rows[0]["t"],
            "out": str(out_dir)}
