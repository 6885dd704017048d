"""The control socket's commands: one list for the daemon that serves them and the CLI that
sends them (importing this costs nothing, so `ddrt ctl --help` stays fast)."""

from __future__ import annotations

import math
from dataclasses import dataclass

COMMANDS = ("status", "follow", "drive", "stop", "resume", "estop", "reset", "gains", "reload", "pose", "stream",
            "pose_fix")
# Served before other clients' requests; each supersedes the listed commands sent before it
# and still waiting (so an estop cannot be undone by a reset that was queued ahead of it).
PRIORITY = {"estop": ("follow", "reset", "drive", "resume", "pose"), "stop": ("follow", "drive", "resume")}
NEVER_REFUSED = ("estop",)  # no rate limit, no shared queue bound
STREAMS = ("stream",)  # for processes, not people: `ddrt ctl` does not offer them (ddrt/service/stream.py)


@dataclass(frozen=True)
class Request:
    """A command's request line: the fields it takes besides "cmd" and "id" (a JSON sketch),
    and what it does. The command reference (docs/reference/commands.md) is generated from
    these by `python -m ddrt.docgen`; the handlers check the fields themselves."""

    fields: str
    does: str


REQUESTS: dict[str, Request] = {
    "status": Request("", "the daemon's state, pose, timing, faults and counters "
                      "(docs/deploy.md, \"The status reply\")"),
    "follow": Request('"path": FILE | "content": TEXT, "format": "csv"|"yaml", "name": NAME | "points": [[x, y], ...] '
                      '| "shape": ...; optional "here": true | "pose": [x, y, theta]; "frame": "odom"|"map"',
                      "follow a path: a file the daemon reads, a file's text, or an inline spec; answered once the "
                      "path is built and the robot is on it"),
    "drive": Request('"v": m/s, "omega": rad/s', "the velocity mode: hold (v, omega) within the limits and a jerk "
                     "limit until the next drive; braking to rest after daemon.command_timeout_s without one"),
    "stop": Request("", "a controlled stop along the path at its braking limit; cancels a follow being prepared"),
    "resume": Request("", "continue a path that a sensor-gap hold left stopped (daemon.on_recover: wait)"),
    "estop": Request("", "motors to zero at once, latched until reset; never rate limited"),
    "reset": Request("", "leave estop or fault for idle and put the pose at (0, 0, 0); refused while the hardware "
                     "estop input is open"),
    "gains": Request("", "the controller's mode and gains in force"),
    "reload": Request("", "re-read the config file beside the loop; the reply lists what applies at once, from the "
                      "next path, and at a restart"),
    "pose": Request('"pose": [x, y, theta]; optional "cov": 3x3', "set the pose in both frames; only at rest"),
    "stream": Request('"to": SOCKET | "@name"; optional "rate_hz"', "send the loop's state as datagrams to a "
                      "subscriber (the ROS 2 bridge), never waited for"),
    "pose_fix": Request('"x", "y", "theta", "cov": 3x3; optional "stamp": s on the loop\'s clock',
                        "fuse a measured pose into the map frame, in any state; an outlier is counted, not fused"),
}


def ctl_number(text: str, what: str, command: str) -> float:
    """A number given to `ddrt ctl COMMAND` (an argument or option named `what`), finite, or a
    ValueError naming both."""
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"ctl {command}: {what}: expected a number, got {text!r}") from None
    if not math.isfinite(value):
        raise ValueError(f"ctl {command}: {what}: must be finite, got {text!r}")
    return value
