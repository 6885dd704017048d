"""The control socket's commands: one list for the daemon that serves them and the CLI that
sends them (importing this costs nothing, so `ddrt ctl --help` stays fast)."""

from __future__ import annotations

import math

COMMANDS = ("status", "follow", "drive", "stop", "resume", "estop", "reset", "gains", "reload", "pose", "stream",
            "pose_fix")
# Served before other clients' requests; each supersedes the listed commands sent before it
# and still waiting (so an estop cannot be undone by a reset that was queued ahead of it).
PRIORITY = {"estop": ("follow", "reset", "drive", "resume", "pose"), "stop": ("follow", "drive", "resume")}
NEVER_REFUSED = ("estop",)  # no rate limit, no shared queue bound
STREAMS = ("stream",)  # for processes, not people: `ddrt ctl` does not offer them (ddrt/service/stream.py)


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
