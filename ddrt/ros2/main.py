"""`ddrt ros2` and `python -m ddrt.ros2` (how the daemon starts it): arguments, set-up, exit codes.

Exit status: 0 after SIGTERM/SIGINT, 2 for bad input (config, arguments) or when the `ros2`
extra is not installed (the supervising daemon does not retry those), 1 otherwise.
"""

from __future__ import annotations

import argparse
import importlib.util
import logging
import os
import signal
from typing import Sequence

log = logging.getLogger("ddrt.ros2")

DEFAULT_SOCKET = "/run/ddrt/ddrt.sock"
NICE = 5  # below the daemon's helpers: ROS traffic is never more urgent than the robot


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--socket", help=f"the daemon's control socket (default: the config's daemon.socket, "
                                    f"else {DEFAULT_SOCKET})")
    p.add_argument("--config", help="read daemon.ros2 (domain, namespace, frames, rates, topics) from this config")
    p.add_argument("--domain-id", type=int, help="ROS_DOMAIN_ID (overrides daemon.ros2.domain_id)")
    p.add_argument("--namespace", help="the node's namespace (overrides daemon.ros2.namespace)")
    p.add_argument("--record", metavar="DIR", help="also record the published topics as rosbag2 (MCAP) in DIR, "
                                                 "rotated by the config's daemon.telemetry_max_bytes and _max_files")
    p.add_argument("--no-dds", action="store_true", help="do not join ROS 2 (with --record: record only)")
    p.add_argument("--supervised", type=int, metavar="PID", help=argparse.SUPPRESS)  # the daemon's pid


def _leave_realtime() -> None:
    """A child of a real-time daemon inherits its policy and CPU set: back to normal, niced."""
    try:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        os.sched_setaffinity(0, range(os.cpu_count() or 1))
    except (OSError, AttributeError):
        pass
    try:
        os.nice(NICE)
    except OSError:
        pass


def run(args: argparse.Namespace) -> int:
    if args.supervised is not None:
        _leave_realtime()  # before the imports: they are the bridge's biggest burst of CPU
    from ddrt.config import ConfigError, load_config
    from ddrt.config.ros2 import Ros2Config
    from ddrt.config.schema import build

    cfg = Ros2Config()
    rotation = (20_000_000, 5)
    socket_path = args.socket
    if args.config:
        try:
            full = load_config(args.config)
        except (ConfigError, OSError) as exc:
            log.error("%s", exc)
            return 2
        cfg = full.daemon.ros2
        rotation = (full.daemon.telemetry_max_bytes, full.daemon.telemetry_max_files)
        socket_path = socket_path or full.daemon.socket or None
    socket_path = socket_path or DEFAULT_SOCKET
    try:
        changes = {k: v for k, v in (("domain_id", args.domain_id), ("namespace", args.namespace)) if v is not None}
        cfg = build(Ros2Config, changes, "ddrt ros2", base=cfg)  # checked as the config's keys are
    except (ConfigError, TypeError) as exc:
        log.error("%s", exc)
        return 2
    if importlib.util.find_spec("cyclonedds") is None:
        log.error("ddrt ros2: needs the cyclonedds package: pip install 'ddrt[ros2]'")
        return 2
    if args.supervised is None:
        _leave_realtime()
    if args.no_dds and not args.record:
        log.error("ddrt ros2: --no-dds without --record has nothing to do")
        return 2
    from ddrt.ros2.bag import RotatingBag
    from ddrt.ros2.bridge import Bridge

    record = None
    if args.record:
        try:
            record = RotatingBag(os.path.abspath(args.record), cfg, *rotation)
        except (OSError, ValueError) as exc:
            log.error("ddrt ros2: --record %s: %s", args.record, exc)
            return 2
    from cyclonedds.core import DDSException

    try:
        bridge = Bridge(socket_path, cfg, dds=not args.no_dds, record=record)
    except DDSException as exc:  # Cyclone logs its reason (a bad CYCLONEDDS_URI, say) to stderr first
        log.error("ddrt ros2: Cyclone DDS cannot join domain %d (CYCLONEDDS_URI=%r): %s", cfg.domain_id,
                  os.environ.get("CYCLONEDDS_URI", ""), exc)
        if record is not None:
            record.close()
        return 2

    def on_stop(_signum: int, _frame: object) -> None:
        bridge.stop = True

    signal.signal(signal.SIGTERM, on_stop)
    signal.signal(signal.SIGINT, on_stop)
    log.info("ros2: node %s%s on domain %d, daemon at %s", (cfg.namespace.rstrip("/") + "/") if cfg.namespace else "/",
             cfg.node_name, cfg.domain_id, socket_path)
    try:
        bridge.run(parent=args.supervised)
    finally:
        bridge.close()
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="ddrt ros2", description="the ROS 2 bridge to a running ddrt daemon")
    add_arguments(p)
    args = p.parse_args(argv)
    from ddrt.service.telemetry import configure_logging

    configure_logging("info")
    return run(args)
