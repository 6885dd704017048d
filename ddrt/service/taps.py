"""What the daemon's loop hands its state to after each tick: the Foxglove/MCAP service
(ddrt/viz, when configured) and the state stream (ddrt/service/stream.py, whenever there is
a control socket to subscribe through), with the ROS 2 bridge's process when
`daemon.ros2.enabled`. One object with the viz service's interface, so the loop calls one
`put` and one `between_ticks` whatever is configured."""

from __future__ import annotations

import logging
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
    """The daemon's taps: `viz` alone when there is no control socket (nothing can subscribe)."""
    if not d.socket_path or d.loop is None:
        if d.cfg.daemon.ros2.enabled:
            log.error("daemon.ros2.enabled: the bridge talks to the daemon over its control socket, and "
                      "there is none (daemon.socket is empty): no ROS 2 bridge")
        return viz
    stream = StateStream(d.loop, loop_priority=d.cfg.daemon.rt_priority)
    bridge = None
    if d.cfg.daemon.ros2.enabled:
        bridge = BridgeProcess(d.socket_path, d.config_path)
    return Taps(stream, viz, bridge)
