"""The control socket's commands, declared once (ddrt/service/commands.py): the handler table
answers exactly the declared commands (and the check that says so can fail), a request is
parsed into its typed form or refused naming the field, and the server's rules and `ddrt ctl -h`
come from the declarations (the reference page: tests/test_docgen.py)."""

from __future__ import annotations

import math
import random
import subprocess
import sys

import pytest

from ddrt.service.commands import (
    COMMANDS, DECLARED, NEVER_REFUSED, PRIORITY, STREAMS, CommandError, Request, parse, payload,
)
from ddrt.service.handlers import HANDLERS, command_table
from tests.support.repo import REPO


def test_every_command_has_a_handler_and_every_handler_a_command() -> None:
    assert set(HANDLERS) == set(COMMANDS) and len(HANDLERS) == len(COMMANDS)
    assert all(callable(h) for h in HANDLERS.values())
    assert set(PRIORITY) | set(NEVER_REFUSED) <= set(HANDLERS)


def test_a_command_without_a_handler_is_refused_naming_it() -> None:
    table = {name: h for name, h in HANDLERS.items() if name != "reset"}
    with pytest.raises(ValueError, match=r"without a handler \['reset'\], handlers without a command \[\]"):
        command_table(table, COMMANDS)


def test_a_handler_without_a_command_is_refused_naming_it() -> None:
    table = {**HANDLERS, "launch": HANDLERS["status"]}
    with pytest.raises(ValueError, match=r"without a handler \[\], handlers without a command \['launch'\]"):
        command_table(table, COMMANDS)


def test_the_table_it_returns_is_its_own_copy() -> None:
    table = dict(HANDLERS)
    checked = command_table(table, COMMANDS)
    table.pop("status")
    assert "status" in checked


def test_the_server_rules_are_read_off_the_declarations() -> None:
    assert PRIORITY == {"stop": ("follow", "drive", "resume"), "estop": ("follow", "reset", "drive", "resume", "pose")}
    assert NEVER_REFUSED == ("estop",) and STREAMS == ("stream",)
    assert COMMANDS == tuple(DECLARED) and all(DECLARED[n].name == n for n in DECLARED)


def test_a_request_becomes_its_typed_form_with_defaults() -> None:
    req = parse({"cmd": "drive", "v": 1, "omega": -0.5, "id": [7]})
    assert req == Request("drive", {"v": 1.0, "omega": -0.5}, {}, [7])
    assert isinstance(req.args["v"], float)
    assert parse({"cmd": "stream", "to": "@a"}).args == {"to": "@a", "rate_hz": 50.0}
    follow = parse({"cmd": "follow", "shape": "line", "length": 0.3})
    assert follow.args == {"here": False, "frame": "odom"} and follow.extra == {"shape": "line", "length": 0.3}
    assert parse({"cmd": "pose", "pose": [1, 2, 3], "cov": None}).args == {"pose": [1.0, 2.0, 3.0]}


@pytest.mark.parametrize(("req", "error"), [
    ({"cmd": "launch"}, "unknown command 'launch' (known: drive, estop, follow, gains,"),
    ({"cmd": 5}, "unknown command 5"),
    ({"cmd": "status", "verbose": True}, "status: verbose: unknown field (status takes no fields)"),
    ({"cmd": "drive", "v": 0.1}, "drive: omega: missing (yaw rate, rad/s)"),
    ({"cmd": "drive", "v": [0.1], "omega": 0}, "drive: v: expected a number in m/s, got list"),
    ({"cmd": "drive", "v": 10 ** 400, "omega": 0}, "drive: v: expected a finite number in m/s"),
    ({"cmd": "stream", "to": "@a", "rate_hz": 0}, "stream: rate_hz: expected a finite number in (0, 500] (Hz), got 0"),
    ({"cmd": "stream", "to": "@a", "rate_hz": 500.5}, "stream: rate_hz: expected a finite number in (0, 500]"),
    ({"cmd": "stream", "to": "x" * 101}, "stream: to: expected text of 1..100 characters"),
    ({"cmd": "follow", "frame": "world", "shape": "line"}, "follow: frame: expected 'odom' or 'map', got 'world'"),
    ({"cmd": "follow", "path": "a\0b"}, "follow: path: expected a file name of 1..4096 characters"),
    ({"cmd": "pose", "pose": [0, 0]}, "pose: pose: expected [x, y, theta] (m, m, rad)"),
    ({"cmd": "pose", "pose": [0, -2e6, 0]}, "pose: pose[1] (y): -2e+06 is beyond +-1e+06"),
    ({"cmd": "pose_fix", "x": 0, "y": 0, "theta": 0, "cov": "big"}, "pose_fix: cov: expected a 3x3 matrix"),
])
def test_a_request_that_does_not_fit_its_declaration_is_refused_naming_the_field(req: dict, error: str) -> None:
    with pytest.raises(CommandError) as err:
        parse(req)
    assert str(err.value).startswith(error), str(err.value)


JUNK = [None, True, False, 0, -1, 1.5, -0.0, 1e300, -1e300, 10 ** 30, 10 ** 400, "", "x", "\0", "nan", [], [1],
        [1, 2, 3], [1, "a", 3], [[1, 0, 0], [0, 1, 0], [0, 0, 1]], {}, {"a": 1}, "x" * 5000]


def test_any_junk_in_any_field_is_a_command_error_or_a_value_of_the_declared_kind() -> None:
    rng = random.Random(31)
    kinds = {"number": float, "bool": bool, "text": str, "file": str, "choice": str, "content": str, "xyt": list,
             "matrix": list}
    for _ in range(4000):
        command = rng.choice(list(DECLARED.values()))
        req: dict = {"cmd": command.name}
        for f in command.fields:
            if rng.random() < 0.7:
                req[f.name] = rng.choice(JUNK)
        if rng.random() < 0.2:
            req[rng.choice(["speed", "points", "x", 3, "id"])] = rng.choice(JUNK)
        try:
            parsed = parse(req)
        except CommandError as exc:
            assert str(exc).startswith(f"{command.name}: "), (req, exc)
            continue
        for name, value in parsed.args.items():
            f = command.field(name)
            assert isinstance(value, kinds[f.kind]), (req, name, value)
            if f.kind == "number":
                assert math.isfinite(value)
                assert f.low is None or value >= f.low and (not f.low_open or value > f.low)
                assert f.high is None or value <= f.high
            if f.kind == "xyt":
                assert len(value) == 3 and all(abs(v) <= f.high for v in value)
        assert all(f.name in parsed.args for f in command.fields if f.required)
        assert not parsed.extra or command.passes_on


def test_a_payload_is_checked_before_it_is_sent() -> None:
    assert payload("drive", v=0.2, omega=0.0) == {"cmd": "drive", "v": 0.2, "omega": 0.0}
    assert payload("pose_fix", x=1, y=2, theta=0, cov=[[1, 0, 0], [0, 1, 0], [0, 0, 1]], stamp=None) == {
        "cmd": "pose_fix", "x": 1, "y": 2, "theta": 0, "cov": [[1, 0, 0], [0, 1, 0], [0, 0, 1]]}
    with pytest.raises(CommandError, match="drive: v: expected a finite number in m/s"):
        payload("drive", v=math.nan, omega=0.0)


def test_ddrt_ctl_help_lists_every_command_it_offers() -> None:
    out = subprocess.run([sys.executable, "-m", "ddrt", "ctl", "-h"], capture_output=True, text=True, timeout=60,
                         cwd=REPO).stdout
    listed = out.split("commands:", 1)[1]
    for c in DECLARED.values():
        offered = not c.stream and not c.ctl.startswith("(")
        assert (f"\n  {c.name} " in listed or f"\n  {c.name}\n" in listed) == offered, c.name


def test_a_command_added_by_its_declaration_and_handler_is_served_and_listed(capsys) -> None:
    # `version`: one declaration (commands.py) and one handler (handlers.py) is all it took.
    from ddrt import __version__
    from ddrt.cli import main
    from ddrt.service.handlers import SOCKET_PROTOCOL

    reply = HANDLERS["version"](None, parse({"cmd": "version"}))  # type: ignore[arg-type]
    assert reply == {"ok": True, "version": __version__, "socket_protocol": SOCKET_PROTOCOL}
    with pytest.raises(CommandError, match="version: verbose: unknown field"):
        parse({"cmd": "version", "verbose": True})
    with pytest.raises(SystemExit):
        main(["ctl", "-h"])
    assert "\n  version " in capsys.readouterr().out
