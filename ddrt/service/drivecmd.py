"""The control socket's `drive` request and the velocity mode's part of `status`.

`{"cmd": "drive", "v": V, "omega": W}` (m/s, rad/s; an "id" may ride along): the request's
shape is checked here (both fields present, nothing else), the values by the loop
(ddrt.core.drive.check_command), so every caller of `Daemon.drive` gets the same checks.
NaN, Infinity and 1e999 never get this far: the socket's strict JSON refuses them.
"""

from __future__ import annotations

from typing import Any

from ddrt.core.drive import DriveReference

REQUEST_KEYS = ("cmd", "id", "v", "omega")


def drive_fields(req: dict[str, Any]) -> tuple[Any, Any]:
    """The request's (v, omega), unchecked; ValueError naming a missing or unknown field."""
    for name, unit in (("v", "m/s"), ("omega", "rad/s")):
        if name not in req:
            raise ValueError(f"missing field {name!r} ({unit}); expected "
                             '{"cmd": "drive", "v": V, "omega": W}')
    extra = sorted(str(k)[:40] for k in req if k not in REQUEST_KEYS)
    if extra:
        raise ValueError(f"unknown field {extra[0]!r} (drive takes v in m/s and omega in rad/s)")
    return req["v"], req["omega"]


def drive_status(loop: Any) -> dict[str, Any]:
    """`mode` (drive, follow or none) and, once the velocity mode has run, its `drive` block:
    the velocities as commanded, as limited, the ramped setpoint, the time since the last
    command."""
    ref = loop.reference
    state = loop.state
    is_drive = isinstance(ref, DriveReference)
    if state in ("driving", "following", "stopping", "holding") and ref is not None:
        mode = "drive" if is_drive else "follow"
    else:
        mode = "none"
    return {"mode": mode, "drive": ref.status() if is_drive else None}
