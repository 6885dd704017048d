"""ddrt.docgen: the committed references are what it writes, and what it writes follows the
declarations (the socket's commands, the telemetry row) it is generated from."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pytest

from ddrt import docgen
from ddrt.core.pose_fix import FIELDS as FIX_FIELDS
from ddrt.loop.record import ADAPTER_COLUMNS, COLUMNS, LATER_COLUMNS, TICK_COLUMNS
from ddrt.service.commands import COMMANDS, DECLARED
from ddrt.simrun.runner import SIM_COLUMNS, TRUTH_COLUMNS
from tests.support.repo import REPO

REFERENCE = REPO / "docs" / "reference"


def test_the_committed_references_are_generated() -> None:
    assert docgen.stale(REFERENCE) == [], "run: python -m ddrt.docgen"


def test_check_names_a_page_that_differs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    shutil.copytree(REFERENCE, tmp_path / "ref")
    assert docgen.main(["--out", str(tmp_path / "ref"), "--check"]) == 0
    page = tmp_path / "ref" / "telemetry.md"
    page.write_text(page.read_text().replace("| `x_est` |", "| `x_estimate` |"))
    assert docgen.main(["--out", str(tmp_path / "ref"), "--check"]) == 1
    assert "telemetry.md: not what python -m ddrt.docgen writes" in capsys.readouterr().err
    (tmp_path / "ref" / "commands.md").unlink()
    assert docgen.stale(tmp_path / "ref") == ["commands.md", "telemetry.md"]
    assert docgen.main(["--out", str(tmp_path / "ref")]) == 0 and docgen.stale(tmp_path / "ref") == []


def test_every_command_is_in_the_reference_with_its_fields() -> None:
    page = docgen.commands_md()
    assert re.findall(r"^## `([a-z_]+)`$", page, re.M) == list(COMMANDS)
    for c in DECLARED.values():
        assert all(f"| `{f.name}` | {f.describe()} |" in page for f in c.fields), c.name
    # The fields a handler reads are declared: pose_fix's are the core's fix fields.
    assert {f.name for f in DECLARED["pose_fix"].fields} == set(FIX_FIELDS)


def test_the_telemetry_page_lists_the_columns_in_the_order_they_are_written() -> None:
    page, codes = docgen.telemetry_md().split("`state` codes:")
    names = re.findall(r"^\| \d+ \| `([A-Za-z_]+)` \|", page, re.M)
    assert re.findall(r"^\| (\d+) \| `([a-z]+)` \|$", codes, re.M)[-1] == ("7", "driving")
    assert names == list(SIM_COLUMNS)  # ddrt sim's order: t, the truth, then the loop's row
    assert [c.name for c in docgen.TRUTH] == list(TRUTH_COLUMNS)
    assert [n for n in names if n not in TRUTH_COLUMNS] == list(COLUMNS)  # the daemon's CSV
    for c in TICK_COLUMNS + ADAPTER_COLUMNS + LATER_COLUMNS + docgen.TRUTH:
        assert c.unit.strip() and len(c.about) > 10, c.name
