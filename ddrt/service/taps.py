"""What the daemon's loop hands its state to after each tick: the Foxglove/MCAP service
(ddrt/viz, when configured) and the state stream (ddrt/service/stream.py, whenever there is
a control socket to subscribe through), with the ROS 2 bridge's process when
`daemon.ros2.enabled`. One object with the viz service's interface, so the loop calls one
`put` and one `between_ticks` whatever is configured."""

from __future__ import annotations

import logging
import os
from typing import TYPE_CHECKING, Any

from ddrt.service.ros2proc import BridgeProcess
from ddrt.service.stream import StateStream

if TYPE_CHECKING:
    from ddrt.service.daemon import Daemon

log = logging.getLogger("ddrt.service.taps")


class Taps:
    """The stream, the optional viz service, the optional bridge process."""

    def __init__(self, stream: StateStream, viz: Any, bridge: BridgeProcess | None) -> None:
        self.stream = stream
        self.viz = viz
        self.bridge = bridge

    def put(self, row: Any, late_s: float, tick_s: float, mono_s: float, truth: tuple[float, ...] | None) -> None:
        self.stream.put(mono_s)
        if self.viz is not None:
            self.viz.put(row, late_s, tick_s, mono_s, truth)

    def between_ticks(self) -> None:
        if self.viz is not None:
            self.viz.between_ticks()

    def path_started(self, path: Any) -> None:
        if self.viz is not None:
            self.viz.path_started(path)

    def set_rotation(self, max_bytes: int, max_files: int) -> None:
        if self.viz is not None:
            self.viz.set_rotation(max_bytes, max_files)

    def close(self) -> None:
        try:
            if self.bridge is not None:
                self.bridge.close()
            self.stream.close()
        finally:
            if self.viz is not None:
                self.viz.close()


def start_taps(d: "Daemon", viz: Any) -> Any:
    """The daemon's taps: `viz` alone when there is no control socket (nothing can subscribe).
    The bridge process when `daemon.ros2.enabled` or `daemon.telemetry_format: rosbag2` (then
    it records the topics it publishes into the telemetry directory; without ROS 2, only that)."""
    dc = d.cfg.daemon
    record = dc.telemetry_format == "rosbag2"
    if not d.socket_path or d.loop is None:
        if dc.ros2.enabled or record:
            log.error("daemon.ros2.enabled / telemetry_format: rosbag2: the bridge talks to the daemon over its "
                      "control socket, and there is none (daemon.socket is empty): no ROS 2 bridge, no rosbag2")
        return viz
    stream = StateStream(d.loop, loop_priority=dc.rt_priority)
    bridge = None
    if dc.ros2.enabled or record:
        extra: tuple[str, ...] = ()
        if record:
            extra = ("--record", os.environ.get("LOGS_DIRECTORY") or dc.telemetry_dir)
            if not dc.ros2.enabled:
                extra += ("--no-dds",)
        bridge = BridgeProcess(d.socket_path, d.config_path, extra=extra)
    return Taps(stream, viz, bridge)
