"""`ddrt ctl`: one command to a running daemon over its control socket, the reply printed as
JSON. The commands, their usage and their help are the socket's declarations
(ddrt/service/commands.py), less those for processes (stream) and the pose fix that
`pose --cov` sends; `ddrt ctl -h` lists them."""

from __future__ import annotations

import argparse
import json
import sys
from importlib import import_module
from pathlib import Path

from ddrt.service import ctlclient
from ddrt.service.commands import ctl_commands, ctl_epilog, ctl_number
from ddrt.service.ctlclient import DEFAULT_SOCKET, SOCKET_ENV

FOLLOW_TIMEOUT_S = 120.0
RELOAD_TIMEOUT_S = 60.0

def control_socket(args: argparse.Namespace) -> tuple[str, str]:
    """`ddrt ctl`'s socket and where it came from (ddrt/service/ctlclient.py)."""
    return ctlclient.control_socket(args.socket, args.config)


def cmd_ctl(args: argparse.Namespace) -> int:
    """`ddrt ctl COMMAND [ARGS]`: exit 0 when the daemon did it, 1 when refused or unreachable."""
    from ddrt.service.ctlclient import request

    for flag, value, cmd in (("--for", args.for_s, "drive"), ("--here", args.here or None, "follow"), ("--cov", args.cov, "pose"),
                             ("--stamp", args.stamp, "pose"), ("--frame", args.frame, "follow")):
        if value is not None and args.command_name != cmd:
            raise ValueError(f"ctl: {flag} is for {cmd} only")
    payload: dict = {"cmd": args.command_name}
    if args.command_name == "drive":
        return _ctl_drive(args)
    if args.command_name == "follow":
        if not args.args:
            raise ValueError("ctl follow: give a path file")
        try:
            payload.update(_follow_content(args.args[0], args))
        except ValueError as exc:  # as the daemon's refusal would look: a JSON reply, exit 1
            print(json.dumps({"ok": False, "error": f"follow: {exc}"}, indent=2, sort_keys=True))
            return 1
        if args.here:
            payload["here"] = True  # the daemon moves the path to start at the robot's pose
        if args.frame is not None:
            payload["frame"] = args.frame
    elif args.command_name == "pose":
        if len(args.args) != 3:
            raise ValueError("ctl pose: give X Y THETA (metres, metres, radians)")
        xyt = [ctl_number(v, name, "pose") for v, name in zip(args.args, ("X", "Y", "THETA"))]
        payload["pose"] = xyt  # set the pose (at rest); with --cov a measured pose: a fix (docs/estimation.md)
        if args.cov is not None or args.stamp is not None:
            payload = import_module("ddrt.service.posefix").ctl_fix_request(xyt, args.cov, args.stamp)
    elif args.args:
        raise ValueError(f"ctl {args.command_name}: takes no arguments, got {' '.join(args.args)!r}")
    timeout = args.timeout
    if timeout is None:
        # A follow is answered once its path is built and followed (within the daemon's
        # paths.build_timeout_s), a reload once the file is read beside the loop (seconds for
        # a config of hundreds of KB); everything else between two ticks.
        timeout = {"follow": FOLLOW_TIMEOUT_S, "reload": RELOAD_TIMEOUT_S}.get(args.command_name, 2.0)
    socket, source = control_socket(args)
    try:
        reply = request(socket, payload, timeout=timeout)
    except (OSError, TimeoutError) as exc:
        print(f"ddrt ctl: cannot reach {socket} ({source}): {exc}", file=sys.stderr)
        return 1
    print(json.dumps(reply, indent=2, sort_keys=True))
    return 0 if reply.get("ok") else 1


def _follow_content(fname: str, args: argparse.Namespace) -> dict:
    """`ddrt ctl follow FILE` sends the file's content, not its name: a sandboxed service
    (ProtectHome, PrivateTmp, its own user) cannot see a user's files. Held to
    paths.max_file_bytes (of --config, else the default) here too; the daemon checks again."""
    from ddrt.config.sections import PathsConfig
    from ddrt.config.textfile import read_text

    limit = PathsConfig().max_file_bytes
    if args.config:
        from ddrt.config import load_config

        limit = load_config(args.config).paths.max_file_bytes
    low = fname.lower()
    fmt = "csv" if low.endswith(".csv") else "yaml" if low.endswith((".yaml", ".yml")) else None
    if fmt is None:
        raise ValueError(f"{fname}: unknown path file type (expected .csv, .yaml or .yml)")
    text = read_text(fname, ValueError, limit, "paths.max_file_bytes", regular_only=True, what="a path")
    return {"content": text, "format": fmt, "name": Path(fname).name}


def _ctl_drive(args: argparse.Namespace) -> int:
    """`ddrt ctl drive V W [--for S]`: one drive command, or S seconds of them then a stop."""
    from ddrt.service.ctlclient import request
    from ddrt.service.drivecmd import drive_for

    if len(args.args) != 2:
        raise ValueError("ctl drive: give V (m/s) and OMEGA (rad/s), e.g. ddrt ctl drive 0.3 0 --for 2")
    v = ctl_number(args.args[0], "V (m/s)", "drive")
    omega = ctl_number(args.args[1], "OMEGA (rad/s)", "drive")
    timeout = args.timeout if args.timeout is not None else 2.0
    socket, source = control_socket(args)

    def send(payload: dict) -> dict:
        return request(socket, payload, timeout=timeout)

    try:
        if args.for_s is None:
            reply = send({"cmd": "drive", "v": v, "omega": omega})
        else:
            if not 0.0 < args.for_s < float("inf"):
                raise ValueError(f"ctl drive: --for: expected seconds > 0, got {args.for_s:g}")
            try:
                reply = drive_for(send, v, omega, args.for_s)
            except KeyboardInterrupt:  # drive_for sent the stop on its way out
                return 130
    except (OSError, TimeoutError) as exc:
        print(f"ddrt ctl: cannot reach {socket} ({source}): {exc}", file=sys.stderr)
        return 1
    print(json.dumps(reply, indent=2, sort_keys=True))
    return 0 if reply.get("ok") else 1


def add_ctl_parser(sub: "argparse._SubParsersAction[argparse.ArgumentParser]") -> None:
    """`ddrt ctl`'s arguments; `ddrt ctl -h` lists the commands with what each does."""
    ctl = sub.add_parser("ctl", help="talk to a running daemon over its control socket",
                         description="Send one command to a running daemon (ddrt run) and print its JSON reply; "
                                     "exit 0 when it was done, 1 when refused or unreachable.",
                         epilog=ctl_epilog(), formatter_class=argparse.RawDescriptionHelpFormatter)
    ctl.add_argument("--socket", default=None,
                     help=f"control socket path (default: --config's daemon.socket, else ${SOCKET_ENV}, "
                          f"else {DEFAULT_SOCKET})")
    ctl.add_argument("--config", default=None, help="the daemon's YAML config: its daemon.socket is the socket")
    ctl.add_argument("--timeout", type=float, default=None,
                     help=f"seconds to wait for the reply (default 2; {FOLLOW_TIMEOUT_S:g} for follow, "
                          f"{RELOAD_TIMEOUT_S:g} for reload)")
    ctl.add_argument("command_name", metavar="COMMAND", choices=ctl_commands(),
                     help="one of: " + ", ".join(ctl_commands()) + " (below)")
    ctl.add_argument("args", nargs="*", help="follow: the path file (its content is sent); drive: V (m/s) and "
                                             "OMEGA (rad/s); pose: X Y THETA (m, m, rad) sets the pose (--cov: a fix)")
    ctl.add_argument("--here", action="store_true",
                     help="follow: place the path so that it starts at the robot's current pose and heading")
    ctl.add_argument("--for", dest="for_s", type=float, metavar="S",
                     help="drive: re-send the command at 10 Hz for S seconds, then stop")
    ctl.add_argument("--cov", metavar="C", help="pose: send a pose fix (fused in map, any state) with this covariance: "
                                                "3 variances (m^2, m^2, rad^2) or 9 entries, comma-separated")
    ctl.add_argument("--stamp", metavar="T", help="pose --cov: when the pose was true (the loop's clock: status clock_s)")
    ctl.add_argument("--frame", choices=("odom", "map"), help="follow: the frame the path is in (default odom)")
    ctl.set_defaults(func=cmd_ctl)
