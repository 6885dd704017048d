"""The campaign's rows as they finish: one JSON line each in DIR/rows.jsonl, flushed at once.

A Ctrl-C, a kill or a lost machine keeps every row that was written; `--resume` reads them
back and runs only the cases that have none. DIR/campaign.json records which campaign the
rows belong to (a digest of its cases and of what a row keeps), so a resume with a changed
campaign is refused instead of mixing two campaigns in one table. A line cut short by a
kill is dropped, and the file is trimmed back to its last whole line before appending.
"""

from __future__ import annotations

import json
import os
from pathlib import Path as FsPath
from typing import Any, TextIO

from ddrt.sweep.campaign import CampaignError
from ddrt.sweep.cases import Plan

ROWS = "rows.jsonl"
STATE = "campaign.json"

Row = dict[str, Any]


def read_rows(path: FsPath) -> tuple[list[Row], int]:
    """The whole rows of a journal and the byte length they take (a cut-off tail excluded)."""
    rows: list[Row] = []
    good = 0
    if not path.exists():
        return rows, 0
    with open(path, "rb") as fh:
        for line in fh:
            if not line.endswith(b"\n"):
                break
            try:
                rows.append(json.loads(line))
            except ValueError:
                break
            good += len(line)
    return rows, good


class Journal:
    """DIR/rows.jsonl opened for appending, with the rows already there."""

    def __init__(self, out: FsPath, plan: Plan, resume: bool) -> None:
        self.out = out
        out.mkdir(parents=True, exist_ok=True)
        state_path, rows_path = out / STATE, out / ROWS
        rows, good = read_rows(rows_path)
        if rows and not resume:
            raise CampaignError(f"{out}: already holds {len(rows)} rows of a campaign; --resume continues it, "
                                "or give another --out")
        if rows:
            state = _state(state_path)
            if state.get("fingerprint") != plan.fingerprint:
                raise CampaignError(f"{out}: its rows are of another campaign ({state.get('campaign', '?')}, "
                                    f"{state.get('cases', '?')} cases); --resume needs the same campaign and cases")
        else:
            good = 0
        ids = {c.case_id for c in plan.cases}
        self.rows: dict[str, Row] = {r["case_id"]: r for r in rows if r.get("case_id") in ids}
        self.resumed = len(self.rows)
        tmp = state_path.with_suffix(".tmp")
        tmp.write_text(json.dumps({"campaign": plan.campaign.source, "name": plan.campaign.name,
                                   "cases": len(plan.cases), "fingerprint": plan.fingerprint}, indent=1) + "\n")
        os.replace(tmp, state_path)
        self._fh: TextIO | None = open(rows_path, "r+" if rows_path.exists() else "w", encoding="utf-8")
        self._fh.truncate(good)  # a line cut short by a kill goes
        self._fh.seek(good)

    def append(self, row: Row) -> None:
        """Write one finished row and flush it to the operating system at once."""
        assert self._fh is not None
        self._fh.write(json.dumps(row, separators=(",", ":")) + "\n")
        self._fh.flush()
        self.rows[row["case_id"]] = row

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
            self._fh = None


def _state(path: FsPath) -> dict[str, Any]:
    try:
        state = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return {}
    return state if isinstance(state, dict) else {}
