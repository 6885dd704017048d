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


def test_the_config_page_has_a_row_for_every_declared_key_with_its_declaration() -> None:
    from ddrt.config.keys import declared_keys
    from ddrt.config.reference import MODE_WORDS
    from ddrt.config.sections import Config
    page = docgen.config_md()
    rows = {m.group(1): m.group(0) for m in re.finditer(r"^\| `([^`]+)` \|.*\|$", page, re.M)}
    for k in declared_keys(Config):
        row = rows.get(k.key)
        if row is None:  # under a section that takes another's keys (plant: robot:'s)
            assert any(k.key.startswith(head + ".") and "(keys as `" in r for head, r in rows.items()), k.key
            continue
        assert f"| {MODE_WORDS[k.mode]} |" in row and k.decl.doc.replace("|", "\\|") in row.replace("](../", "]("), k.key
        assert k.decl.bounds() in row, k.key


def test_the_paths_page_lists_every_kind_and_key() -> None:
    import dataclasses
    from ddrt.path.shapes import KINDS, SHAPES, PathCommon
    page = docgen.PAGES["paths.md"]()
    assert re.findall(r"^## `(?:shape: )?([a-z_]+):?`$", page, re.M) == list(SHAPES) + list(KINDS)
    for cls in (PathCommon, *SHAPES.values(), *KINDS.values()):
        for f in dataclasses.fields(cls):
            assert f"| `{f.name}` |" in page, (cls.__name__, f.name)


def test_the_campaign_page_has_every_declared_key_with_its_declaration() -> None:
    """Every key of a campaign file, its sections' and a range's, each row carrying the key's
    bounds and description (a key added to CampaignKeys is in the page or the page is stale)."""
    from ddrt.config.keys import declared_keys
    from ddrt.sweep.campaign import KEYS, CampaignKeys
    from ddrt.sweep.ranges import RangeSpec

    page = docgen.PAGES["campaign.md"]()
    rows = {m.group(1): m.group(0) for m in re.finditer(r"^\| `([^`]+)` \|.*\|$", page, re.M)}
    keys = [*declared_keys(CampaignKeys), *declared_keys(RangeSpec, "axes.KEY")]
    assert sorted(k.key for k in keys) == sorted(rows)  # the top level first, then each section
    assert [k.key for k in keys if "." not in k.key] == list(KEYS)
    for k in keys:
        assert k.decl.bounds().replace("|", "\\|") in rows[k.key], k.key
        assert k.decl.doc.replace("|", "\\|") in rows[k.key].replace("](../", "]("), k.key


def test_the_references_links_resolve() -> None:
    """Every relative link of a generated page names a file that exists, and a heading there
    when it names one (GitHub's anchors: lower case, punctuation dropped, spaces to '-')."""
    def anchors(md: Path) -> set[str]:
        heads = re.findall(r"^#+ (.+)$", md.read_text(encoding="utf-8"), re.M)
        return {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-") for h in heads}
    for name, make in docgen.PAGES.items():
        for target, anchor in re.findall(r"\]\((?![a-z]+:)([^)#]+\.md)(?:#([^)]+))?\)", make()):
            md = (REFERENCE / target).resolve()
            assert md.is_file(), (name, target)
            if anchor:
                assert anchor in anchors(md), (name, target, anchor)


def _anchors(md: Path) -> set[str]:
    heads = re.findall(r"^#+ (.+)$", md.read_text(encoding="utf-8"), re.M)
    return {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-") for h in heads}


def test_links_into_the_config_pages_resolve() -> None:
    """A link from any doc to config.md or a reference page names a heading that is there (the
    key tables moved to the generated reference; the explanation's headings stayed)."""
    docs = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
    checked = 0
    for doc in docs:
        text = doc.read_text(encoding="utf-8")
        for target, anchor in re.findall(r"\]\(((?:[\w./-]*/)?(?:config|paths|commands|telemetry|modes|campaign|sweep)\.md)#([^)]+)\)", text):
            md = (doc.parent / target).resolve()
            assert md.is_file(), (doc.name, target)
            assert anchor in _anchors(md), (doc.name, target, anchor)
            checked += 1
    assert checked > 10
