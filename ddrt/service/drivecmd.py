"""The control socket's `drive` request and the velocity mode's part of `status`.

`{"cmd": "drive", "v": V, "omega": W}` (m/s, rad/s; an "id" may ride along): the request's
shape is checked by its declaration (ddrt/service/commands.py), the values against the limits
by the loop (ddrt.core.drive.check_command), so every way in gets the same checks.
"""

from __future__ import annotations

import time
from typing import Any, Callable

from ddrt.core.drive import DriveReference


def drive_status(loop: Any) -> dict[str, Any]:
    """`mode` (drive, follow or none) and, once the velocity mode has run, its `drive` block:
    the velocities as commanded, as limited, the ramped setpoint, the time since the last
    command."""
    from ddrt.loop import LoopState  # here: `ddrt ctl` imports this module and needs no loop

    ref = loop.reference
    state = loop.state
    is_drive = isinstance(ref, DriveReference)
    if state in (LoopState.DRIVING, LoopState.FOLLOWING, LoopState.STOPPING, LoopState.HOLDING) and ref is not None:
        mode = "drive" if is_drive else "follow"
    else:
        mode = "none"
    return {"mode": mode, "drive": ref.status() if is_drive else None}


RESEND_HZ = 10.0  # `ddrt ctl drive --for`: well inside the default 0.5 s timeout, the socket's 20/s rate


def drive_for(send: Callable[[dict[str, Any]], dict[str, Any]], v: float, omega: float, seconds: float,
              clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], None] = time.sleep
              ) -> dict[str, Any]:
    """`ddrt ctl drive V W --for S`: send the drive at RESEND_HZ for `seconds`, then `stop`.

    The stop (rather than falling silent and letting daemon.command_timeout_s stop the
    robot) starts the braking at once, so the robot drives for S seconds, not S + the
    timeout; it is sent only when the last reply said "driving", so a drive that was
    refused or cut short (estop, a fault) sends no stop to whatever runs then. If this
    process dies meanwhile, the timeout stops the robot. Ctrl-C sends the stop too.
    """
    t0 = clock()
    sent = 0
    last: dict[str, Any] = {}
    stop: dict[str, Any] | None = None
    payload = {"cmd": "drive", "v": v, "omega": omega}
    try:
        while True:
            last = send(payload)
            sent += 1
            if not last.get("ok") or last.get("state") != "driving":
                break
            next_t = t0 + sent / RESEND_HZ
            if next_t - t0 >= seconds:
                sleep(max(0.0, t0 + seconds - clock()))
                break
            sleep(max(0.0, next_t - clock()))
    finally:
        if last.get("ok") and last.get("state") == "driving":
            stop = send({"cmd": "stop"})
    return {"ok": bool(last.get("ok")) and (stop is None or bool(stop.get("ok"))), "sent": sent,
            "seconds": clock() - t0, "last": last, "stop": stop}
