"""The control socket's command table (ddrt/service/handlers.py) answers exactly the command
list of ddrt/service/commands.py, and the check that says so can fail."""

from __future__ import annotations

import pytest

from ddrt.service.commands import COMMANDS, NEVER_REFUSED, PRIORITY
from ddrt.service.handlers import HANDLERS, command_table


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
