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

from ddrt.config.textfile import read_state_text
from ddrt.sweep.campaign import CampaignError, file_kind
from ddrt.sweep.cases import Case, Plan
from ddrt.sweep.columns import STATUSES
from ddrt.sweep.table import fits, value_kinds

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
        if out.exists() and not out.is_dir():
            raise CampaignError(f"--out {out}: {file_kind(out)}, not a folder")
        out.mkdir(parents=True, exist_ok=True)
        state_path, rows_path = out / STATE, out / ROWS
        for p in (state_path, rows_path):
            if file_kind(p) not in ("a file", "missing"):  # a FIFO would block the read
                raise CampaignError(f"--out {out}: {p.name} is {file_kind(p)}, not the file a campaign writes")
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
        cases = {c.case_id: c for c in plan.cases}
        kinds = value_kinds(plan)
        self.rows: dict[str, Row] = {r["case_id"]: r for r in rows if _is_row_of(r, cases, kinds)}
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


def _is_row_of(row: Any, cases: dict[str, Case], kinds: dict[str, str]) -> bool:
    """Whether a journal line is a row of one of `cases`: a mapping with its case's id, index
    and parameters, a known status and values of its columns' types. Anything else (a line
    edited by hand, a row of another campaign) is not kept, so its case runs again, rather
    than failing the table after the runs."""
    if not isinstance(row, dict) or not isinstance(row.get("case_id"), str):
        return False
    case = cases.get(row["case_id"])
    return (case is not None and row.get("case") == case.index and row.get("status") in STATUSES
            and all(row.get(k) == v for k, v in case.params.items())
            and all(fits(row.get(name), kind) for name, kind in kinds.items()))


def _state(path: FsPath) -> dict[str, Any]:
    try:
        state = json.loads(read_state_text(path, ValueError))
    except (OSError, ValueError):
        return {}
    return state if isinstance(state, dict) else {}
