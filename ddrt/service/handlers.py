"""The control socket's command table: each command of ddrt/service/commands.py and the
function that answers it, between two ticks, on the loop thread.

`command_table` checks the table against the command list when this module is imported: a
command without a handler, or a handler for a command the list does not have, stops the
daemon before it starts (the server refuses unknown commands by that same list). A handler
takes the daemon and the request, already checked against its command's declaration (a
`Request`), and returns the reply, or a `Deferred` that the loop completes later (a follow,
once its path is built).
"""

from __future__ import annotations

import logging
from dataclasses import asdict
from typing import TYPE_CHECKING, Any, Callable, Iterable, Mapping

from ddrt.service.audit import peer_text
from ddrt.service.commands import COMMANDS, Request
from ddrt.service.ctlqueue import Deferred
from ddrt.service.follow import cancel_follow, start_follow
from ddrt.service.posefix import pose_cmd, pose_fix_cmd
from ddrt.loop import ModeRefused

if TYPE_CHECKING:
    from ddrt.service.daemon import Daemon

log = logging.getLogger("ddrt.service.daemon")

SOCKET_PROTOCOL = 1  # the control socket's request and reply format (docs/reference/commands.md)

CommandHandler = Callable[["Daemon", Request], "dict[str, Any] | Deferred"]


def command_table(handlers: Mapping[str, CommandHandler], commands: Iterable[str]) -> dict[str, CommandHandler]:
    """`handlers` as the table, if it answers exactly `commands`; ValueError naming the gaps."""
    names = set(commands)
    missing = sorted(names - set(handlers))
    extra = sorted(set(handlers) - names)
    if missing or extra:
        raise ValueError(f"control commands and handlers differ: without a handler {missing}, "
                         f"handlers without a command {extra} (ddrt/service/commands.py)")
    return dict(handlers)


def drive(d: Daemon, v: object, omega: object, source: str, channel: str = "") -> dict[str, Any]:
    """Velocity mode (ddrt/core/drive.py): hold (v, omega) until the next drive, a stop
    or daemon.command_timeout_s without one. The one entry for every caller (the control
    socket, a teleop bridge), between two ticks; a refusal changes nothing."""
    loop = d.loop
    assert loop is not None
    if d.follows.busy_text():
        return {"ok": False, "error": f"drive: busy: preparing {d.follows.busy_text()} to follow: "
                                      "send stop to cancel it"}
    old = loop.path
    try:
        v_lim, w_lim, clamped = loop.drive(v, omega, source)
    except ModeRefused as exc:
        return {"ok": False, "error": str(exc)}
    except (ValueError, RuntimeError) as exc:
        return {"ok": False, "error": f"drive: {exc}"}
    d.audit.note(f"drive {channel or 'over ' + source}", always=False)
    if old is not None and loop.path is None and d.paths is not None:
        d.paths.dispose(old)  # the last path's samples are freed off the loop
    reply: dict[str, Any] = {"ok": True, "state": loop.state.label, "v": v_lim, "omega": w_lim,
                             "timeout_s": d.cfg.daemon.command_timeout_s}
    if clamped:
        reply["clamped"] = list(clamped)
    return reply


def who(d: Daemon) -> str:
    """'over the control socket (pid P, uid U)': the request being answered."""
    return peer_text(d.server.peer if d.server is not None else "")


def _status(d: Daemon, req: Request) -> dict[str, Any]:
    return {"ok": True, "status": d.status()}


def _gains(d: Daemon, req: Request) -> dict[str, Any]:
    c = d.cfg.controller
    return {"ok": True, "mode": c.mode, "outer": asdict(c.outer), "inner": asdict(c.inner),
            "wheel_pid": asdict(c.wheel_pid), "heading_gain": c.heading_gain}


def _version(d: Daemon, req: Request) -> dict[str, Any]:
    from ddrt import __version__

    return {"ok": True, "version": __version__, "socket_protocol": SOCKET_PROTOCOL}


def _stop(d: Daemon, req: Request) -> dict[str, Any]:
    loop = d.loop
    assert loop is not None
    d.audit.note(f"stop {who(d)}")
    cancelled = cancel_follow(d, "cancelled by stop")
    loop.stop()
    return {"ok": True, "state": loop.state.label, **cancelled}


def _estop(d: Daemon, req: Request) -> dict[str, Any]:
    loop = d.loop
    assert loop is not None
    d.audit.note(f"estop {who(d)}")
    loop.estop("estop requested over the control socket")
    cancelled = cancel_follow(d, "cancelled by estop")
    return {"ok": True, "state": loop.state.label, **cancelled}


def _resume(d: Daemon, req: Request) -> dict[str, Any]:
    # After a hold ended stopped (daemon.on_recover: wait): the path from where the robot
    # stands, the schedule ramping up from rest.
    loop = d.loop
    assert loop is not None
    try:
        loop.resume()
        d.audit.note(f"resume {who(d)}")
    except ModeRefused as exc:
        return {"ok": False, "error": str(exc)}
    return {"ok": True, "state": loop.state.label}


def _reset(d: Daemon, req: Request) -> dict[str, Any]:
    loop = d.loop
    assert loop is not None
    try:
        loop.reset()
    except ModeRefused as exc:  # the hardware estop input is still open
        return {"ok": False, "error": str(exc)}
    d.audit.note(f"reset {who(d)}")
    # The pose starts again from (0, 0, 0): a path is placed in this frame (or with --here).
    loop.estimator.set_pose((0.0, 0.0, 0.0), anchored=False)  # the first fix says where map is
    return {"ok": True, "state": loop.state.label}


def _pose(d: Daemon, req: Request) -> dict[str, Any]:
    return pose_cmd(d, req, req.channel or who(d))  # ddrt/service/posefix.py, beside pose_fix


def _pose_fix(d: Daemon, req: Request) -> dict[str, Any]:
    return pose_fix_cmd(d, req, req.channel or who(d))


def _stream(d: Daemon, req: Request) -> dict[str, Any]:
    """Send the loop's state to a datagram socket (ddrt/service/stream.py; the ROS 2 bridge)."""
    from ddrt.service.taps import Taps

    if not isinstance(d.viz, Taps):
        return {"ok": False, "error": "stream: this daemon has no state stream"}
    return d.viz.stream.subscribe(req.args["to"], req.args["rate_hz"])


def _reload(d: Daemon, req: Request) -> Deferred:
    """The file is read off the loop thread (Reloader.request); the reply waits for that."""
    reply = Deferred()
    d.reloader.request(reply.complete)
    return reply


def _drive(d: Daemon, req: Request) -> dict[str, Any]:
    return drive(d, req.args["v"], req.args["omega"], req.origin or "control socket", req.channel or who(d))


HANDLERS = command_table({
    "status": _status, "follow": start_follow, "drive": _drive, "stop": _stop, "resume": _resume,
    "estop": _estop, "reset": _reset, "gains": _gains, "reload": _reload, "pose": _pose,
    "stream": _stream, "pose_fix": _pose_fix, "version": _version,
}, COMMANDS)
