"""The control socket's commands, each declared once with its fields (type, unit, bounds), its
priority and its reply.

From these declarations come: the daemon's parsing of a request into a typed `Request`
(`parse`, the one entry every way in goes through: the socket, Foxglove's teleop, the ROS 2
bridge's payloads, `ddrt ctl`, in-process rigs), the control server's priority rules
(`PRIORITY`, `NEVER_REFUSED`), `ddrt ctl`'s command list and help, and the reference
docs/reference/commands.md (`reference_markdown`, written by `python -m ddrt.docgen`). A field's shape is checked here, against its
declaration; what depends on the running robot (a speed against the config's limits, a
covariance that must be positive definite, the loop's state) is checked by the handler.
Importing this costs nothing, so `ddrt ctl --help` stays fast.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import Any, Mapping

from ddrt.errors import DdrtError
from ddrt.params.numbers import POSE_BOUND_M

__all__ = ["Field", "Command", "Request", "CommandError", "DECLARED", "COMMANDS", "PRIORITY", "NEVER_REFUSED",
           "STREAMS", "parse", "payload", "ctl_commands", "ctl_epilog", "ctl_number", "reference_markdown"]

STREAM_MAX_RATE_HZ = 500.0
STREAM_MAX_ADDRESS = 100
TEXT_MAX = 4096  # a file name, a label: the content of a path file is bounded by paths.max_file_bytes instead
ENVELOPE = ("cmd", "id")  # every request's own keys, beside its command's fields

KINDS = {
    "number": "a finite number",
    "bool": "true or false",
    "text": "text",
    "file": "a file name",
    "choice": "one of the listed words",
    "xyt": "[x, y, theta]",
    "matrix": "a 3x3 matrix, row by row",
    "content": "a file's text",
}


class CommandError(DdrtError, ValueError):
    """A request that does not fit its command's declaration; the message names the command and field."""


@dataclass(frozen=True)
class Field:
    """One field of a request: its JSON type (`kind`, a key of KINDS), unit and bounds."""

    name: str
    kind: str
    help: str
    unit: str = ""
    required: bool = False
    default: Any = None
    low: float | None = None  # numbers: the least value; text: the least length
    high: float | None = None  # numbers: the most; text: the longest
    low_open: bool = False  # the least value itself is refused: (low, high]
    choices: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"Field {self.name}: kind {self.kind!r} is not one of {sorted(KINDS)}")

    def describe(self) -> str:
        """The field's type and bounds in words, for errors, help and the reference."""
        if self.kind == "choice":
            return " or ".join(repr(c) for c in self.choices)
        text = KINDS[self.kind]
        if self.kind == "number" and (self.low is not None or self.high is not None):
            lo = "(" if self.low_open else "["
            text += f" in {lo}{_g(self.low, '-inf')}, {_g(self.high, 'inf')}]"
        elif self.kind == "xyt" and self.high is not None:
            text += f", each within +-{self.high:g}"
        elif self.kind in ("text", "file") and self.high is not None:
            text += f" of {_g(self.low, '0')}..{self.high:g} characters"
        return text + (f" ({self.unit})" if self.unit else "")


def _g(value: float | None, none: str) -> str:
    return none if value is None else f"{value:g}"


@dataclass(frozen=True)
class Command:
    """A socket command: its fields, its reply, and how the server ranks it."""

    name: str
    help: str
    fields: tuple[Field, ...] = ()
    reply: str = "ok and the loop's state"
    supersedes: tuple[str, ...] = ()  # served before other requests; drops these that wait behind it
    never_refused: bool = False  # no rate limit, no shared queue bound
    stream: bool = False  # for processes, not people: `ddrt ctl` does not offer it
    passes_on: str = ""  # other keys are not refused here but handed on to this reader (follow: a path spec)
    ctl: str = ""  # `ddrt ctl`'s usage after the command name; "(...)": not offered, sent by another command

    def field(self, name: str) -> Field:
        return next(f for f in self.fields if f.name == name)


@dataclass(frozen=True)
class Request:
    """A request checked against its command's declaration: what every way in hands the daemon.

    `args` holds each declared field that was given (or has a default), its value of the
    declared kind (numbers as float); `extra` the keys handed on (`Command.passes_on`);
    `origin` and `channel` say who sent it, for the status and the journal ("" for the
    control socket, whose peer the daemon knows).
    """

    name: str
    args: Mapping[str, Any]
    extra: Mapping[str, Any] = field(default_factory=dict)
    id: Any = None
    origin: str = ""
    channel: str = ""

    def get(self, key: str, default: Any = None) -> Any:
        return self.args.get(key, default)


_X, _Y, _THETA = "x", "y", "theta"
DECLARED: dict[str, Command] = {c.name: c for c in (
    Command("status", "the loop's state, pose, path progress, timing, faults and counters",
            reply="ok and status: the daemon's whole state (see docs/commands.md)"),
    Command("follow", "follow a path: a file the daemon reads, a file's content, inline points or a shape",
            fields=(
                Field("path", "file", "a path file the daemon reads itself (.yaml or .csv)", low=1, high=TEXT_MAX),
                Field("content", "content", "a path file's text, read as that file would be"),
                Field("format", "choice", "the content's format", choices=("csv", "yaml")),
                Field("name", "text", "the content's file name, for messages", low=1, high=TEXT_MAX),
                Field("pose", "xyt", "where the robot is now, before the path starts", unit="m, m, rad",
                      high=POSE_BOUND_M),
                Field("here", "bool", "place the path so that it starts at the robot's pose and heading",
                      default=False),
                Field("frame", "choice", "the frame the path is in", choices=("odom", "map"), default="odom"),
            ),
            passes_on="an inline path spec: points: [[x, y], ...] or shape: with its keys (docs/reference/paths.md)",
            reply="ok, once the path is built and the loop follows it; id, length, duration, clamped limits",
            ctl="FILE [--here] [--frame odom|map]"),
    Command("drive", "velocity mode: hold (v, omega) until the next drive, a stop or daemon.command_timeout_s",
            fields=(Field("v", "number", "forward speed", unit="m/s", required=True),
                    Field("omega", "number", "yaw rate", unit="rad/s", required=True)),
            reply="ok, the state, v and omega as limited, timeout_s, and clamped: the fields held to the limits",
            ctl="V OMEGA [--for S]"),
    Command("stop", "brake to rest along the current reference; cancels a follow being prepared",
            supersedes=("follow", "drive", "resume")),
    Command("resume", "continue a path interrupted by a hold (daemon.on_recover: wait)"),
    Command("estop", "zero the motors at once and latch until reset", never_refused=True,
            supersedes=("follow", "reset", "drive", "resume", "pose")),
    Command("reset", "leave estop or fault; the pose starts again from (0, 0, 0)"),
    Command("gains", "the controller's gains in force", reply="ok, mode, outer, inner, wheel_pid, heading_gain"),
    Command("version", "the daemon's ddrt version and the protocol of its control socket",
            reply="ok, version and socket_protocol"),
    Command("reload", "re-read the config file and put what changed in force between two ticks",
            reply="ok, and what changed, how each change was applied, or the error naming the key"),
    Command("pose", "set the estimator's pose at rest (with cov: and its covariance)",
            fields=(Field("pose", "xyt", "the robot's pose", unit="m, m, rad", required=True, high=POSE_BOUND_M),
                    Field("cov", "matrix", "its covariance (m^2, rad^2), symmetric positive definite")),
            reply="ok, the state and the pose set", ctl="X Y THETA [--cov C [--stamp T]]"),
    Command("stream", "send the loop's state as datagrams to a local socket (the ROS 2 bridge)", stream=True,
            fields=(Field("to", "text", "a socket path or '@name' (abstract)", required=True, low=1,
                          high=STREAM_MAX_ADDRESS),
                    Field("rate_hz", "number", "datagrams a second", unit="Hz", default=50.0, low=0.0,
                          high=STREAM_MAX_RATE_HZ, low_open=True)),
            reply="ok and the subscription"),
    Command("pose_fix", "fuse a measured pose (a localisation fix) into the map frame, in any state",
            fields=(Field(_X, "number", "measured x", unit="m", required=True, low=-POSE_BOUND_M, high=POSE_BOUND_M),
                    Field(_Y, "number", "measured y", unit="m", required=True, low=-POSE_BOUND_M, high=POSE_BOUND_M),
                    Field(_THETA, "number", "measured heading", unit="rad", required=True,
                          low=-POSE_BOUND_M, high=POSE_BOUND_M),
                    Field("cov", "matrix", "its covariance (m^2, rad^2)", required=True),
                    Field("stamp", "number", "when the pose was true, on the loop's clock (status clock_s)",
                          unit="s")),
            reply="ok, fused or outlier with its d2 and gate, the map pose and its std",
            ctl="(sent by ddrt ctl pose X Y THETA --cov C)"),
)}

COMMANDS = tuple(DECLARED)
PRIORITY = {c.name: c.supersedes for c in DECLARED.values() if c.supersedes}
NEVER_REFUSED = tuple(c.name for c in DECLARED.values() if c.never_refused)
STREAMS = tuple(c.name for c in DECLARED.values() if c.stream)


def _number(cmd: str, f: Field, name: str, value: Any) -> float:
    unit = f" in {f.unit}" if f.unit and f.kind == "number" else ""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise CommandError(f"{cmd}: {name}: expected a number{unit}, got {type(value).__name__}")
    try:
        x = float(value)
    except OverflowError:
        x = math.inf
    if not math.isfinite(x):
        raise CommandError(f"{cmd}: {name}: expected a finite number{unit}, got {value!r:.40}")
    return x


def _check(cmd: str, f: Field, value: Any) -> Any:
    """The value as its declared kind, or a CommandError naming the command and field."""
    if f.kind == "number":
        x = _number(cmd, f, f.name, value)
        below = f.low is not None and (x <= f.low if f.low_open else x < f.low)
        if below or (f.high is not None and x > f.high):
            raise CommandError(f"{cmd}: {f.name}: expected {f.describe()}, got {x:g}")
        return x
    if f.kind == "bool":
        if not isinstance(value, bool):
            raise CommandError(f"{cmd}: {f.name}: expected true or false, got {value!r:.40}")
        return value
    if f.kind == "choice":
        if not isinstance(value, str) or value not in f.choices:
            raise CommandError(f"{cmd}: {f.name}: expected {f.describe()}, got {value!r:.40}")
        return value
    if f.kind in ("text", "file", "content"):
        low = int(f.low or 0)
        high = int(f.high) if f.high is not None else None
        if (not isinstance(value, str) or len(value) < low or (high is not None and len(value) > high)
                or (f.kind != "content" and "\0" in value)):
            raise CommandError(f"{cmd}: {f.name}: expected {f.describe()}, got {value!r:.60}")
        return value
    if f.kind == "xyt":
        if not isinstance(value, list) or len(value) != 3:
            raise CommandError(f"{cmd}: {f.name}: expected [x, y, theta] ({f.unit}), got {value!r:.60}")
        out = []
        for i, (name, v) in enumerate(zip((_X, _Y, _THETA), value)):
            where = f"{f.name}[{i}] ({name})"
            x = _number(cmd, f, where, v)
            if f.high is not None and abs(x) > f.high:
                raise CommandError(f"{cmd}: {where}: {x:g} is beyond +-{f.high:g}")
            out.append(x)
        return out
    if f.kind == "matrix":
        if not isinstance(value, list):
            raise CommandError(f"{cmd}: {f.name}: expected a 3x3 matrix (a list of 3 rows), got {value!r:.60}")
        return value
    raise AssertionError(f.kind)


def parse(req: Mapping[str, Any], origin: str = "", channel: str = "") -> Request:
    """The request as its command's typed `Request`; CommandError naming the field otherwise."""
    cmd = req.get("cmd")
    command = DECLARED.get(cmd) if isinstance(cmd, str) else None
    if command is None:
        raise CommandError(f"unknown command {cmd!r:.60} (known: {', '.join(sorted(COMMANDS))})")
    declared = {f.name: f for f in command.fields}
    args: dict[str, Any] = {}
    extra: dict[str, Any] = {}
    for key, value in req.items():
        if key in ENVELOPE:
            continue
        f = declared.get(key) if isinstance(key, str) else None
        if f is None:
            if command.passes_on:
                extra[key] = value
                continue
            takes = ", ".join(declared) or "no fields"
            raise CommandError(f"{command.name}: {str(key)[:40]}: unknown field ({command.name} takes {takes})")
        if value is None and not f.required:
            continue
        args[key] = _check(command.name, f, value)
    for f in command.fields:
        if f.name not in args:
            if f.required:
                unit = f", {f.unit}" if f.unit else ""
                raise CommandError(f"{command.name}: {f.name}: missing ({f.help}{unit})")
            if f.default is not None:
                args[f.name] = f.default
    return Request(command.name, args, extra, req.get("id"), origin, channel)


def payload(cmd: str, **fields: Any) -> dict[str, Any]:
    """A request as it goes over the socket, checked against the declaration first (the ROS 2
    bridge and `ddrt ctl` build theirs here); CommandError naming the field."""
    wire = {"cmd": cmd, **{k: v for k, v in fields.items() if v is not None}}
    parse(wire)
    return wire


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


def ctl_commands() -> list[str]:
    """The commands `ddrt ctl` offers: not those for processes, nor pose_fix (`pose --cov` sends it)."""
    return [c.name for c in DECLARED.values() if not c.stream and not c.ctl.startswith("(")]


def ctl_epilog() -> str:
    """`ddrt ctl -h`'s list of commands, from the declarations."""
    lines = ["commands:"]
    for name in ctl_commands():
        c = DECLARED[name]
        lines.append(f"  {f'{c.name} {c.ctl}'.strip():<40} {c.help}")
    return "\n".join(lines)


def reference_markdown() -> str:
    """docs/reference/commands.md: every command, its fields and its reply, from the declarations."""
    out = ["# Control socket commands", "",
           "Generated by `python -m ddrt.docgen` from ddrt/service/commands.py; do not edit by hand. How to send",
           "them: `ddrt ctl` ([commands.md](../commands.md#ddrt-ctl)); the wire, the limits per connection and",
           "the status reply: [deploy.md](../deploy.md#day-to-day).", "",
           "A request is one JSON object on one line: `{\"cmd\": NAME, ...fields}`; an `id` of any JSON value",
           "rides along and comes back in the reply. A field that is not declared is refused, naming it,",
           "as is a value of the wrong type or out of its bounds; nothing changes on a refusal.", ""]
    for c in DECLARED.values():
        out += [f"## `{c.name}`", "", c.help[0].upper() + c.help[1:] + ".", ""]
        if c.fields:
            out += ["| field | type | required | default | what |", "|---|---|---|---|---|"]
            for f in c.fields:
                default = "" if f.default is None else f"`{json.dumps(f.default)}`"
                out.append(f"| `{f.name}` | {f.describe()} | {'yes' if f.required else 'no'} | {default} | {f.help} |")
            out.append("")
        if c.passes_on:
            out += [f"Other keys: {c.passes_on}.", ""]
        notes = [f"Reply: {c.reply}."]
        if c.supersedes:
            notes.append(f"Served before other clients' requests; drops the {', '.join(c.supersedes)} requests "
                         "still waiting.")
        if c.never_refused:
            notes.append("Never refused: no rate limit, no shared queue bound.")
        if c.stream:
            notes.append("For processes: `ddrt ctl` does not offer it.")
        elif c.ctl:
            notes.append(f"`ddrt ctl {c.name} {c.ctl}`." if not c.ctl.startswith("(") else f"`ddrt ctl`: {c.ctl[1:-1]}.")
        else:
            notes.append(f"`ddrt ctl {c.name}`.")
        out += [" ".join(notes), ""]
    return "\n".join(out).rstrip() + "\n"
