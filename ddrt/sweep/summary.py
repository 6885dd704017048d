"""The summary beside the table (summary.md): how many runs passed, and the spread of the
campaign's error figures for each value of each axis.

The question a sweep answers is "where does it break": so for every column that varies, each
of its values gets its runs, how many ran to the end, how many passed, and percentiles of
the summary metrics (by default the ones the pass criteria name) over the runs that ended.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Iterable, Sequence

import numpy as np

from ddrt.sweep.cases import Plan
from ddrt.sweep.run import Row

SUMMARY = "summary.md"
PERCENTILES = (50, 90, 99)
# The fewest runs a percentile says something over: p90 of 2 runs is their larger one, p99 of
# 10 their largest (which max already gives). A group with fewer shows '-', and a column no
# group of a table reaches is left out.
MIN_RUNS = {50: 1, 90: 10, 99: 100}
MAX_FAILURES_LISTED = 10


@dataclass(frozen=True)
class Spread:
    """A metric over `n` runs: its PERCENTILES and its largest value."""

    n: int
    percentiles: tuple[float, ...]
    max: float

    def cells(self, shown: Sequence[int]) -> list[str]:
        """The shown percentiles ('-' where there are too few runs for one) and the max."""
        return [_num(v) if self.n >= MIN_RUNS[p] else "-" for p, v in zip(PERCENTILES, self.percentiles)
                if p in shown] + [_num(self.max)]


@dataclass(frozen=True)
class Group:
    """The runs that share one value of one column."""

    value: Any
    runs: int
    ok: int
    passed: int
    spread: dict[str, Spread | None]  # metric -> its spread over the runs that ended; None: no values

    @property
    def pass_rate(self) -> float:
        return self.passed / self.runs if self.runs else math.nan


def spread(rows: Sequence[Row], metric: str) -> Spread | None:
    values = np.array([r[metric] for r in rows if r.get("status") == "ok" and isinstance(r.get(metric), (int, float))
                       and not isinstance(r.get(metric), bool)], dtype=float)
    values = values[np.isfinite(values)]
    if len(values) == 0:
        return None
    return Spread(len(values), tuple(float(v) for v in np.percentile(values, PERCENTILES)), float(values.max()))


def group(rows: Sequence[Row], value: Any, metrics: Sequence[str]) -> Group:
    return Group(value, len(rows), sum(r.get("status") == "ok" for r in rows), sum(bool(r.get("pass")) for r in rows),
                 {m: spread(rows, m) for m in metrics})


def varied(plan: Plan, rows: Sequence[Row]) -> list[str]:
    """The parameter columns that take more than one value in these rows."""
    return [c for c in plan.columns if len({value_key(r.get(c)) for r in rows}) > 1]


def value_key(v: Any) -> Any:
    """A column's value as something hashable (a list value as its text)."""
    return repr(v) if isinstance(v, (list, dict)) else v


def by_value(plan: Plan, rows: Sequence[Row], column: str) -> list[Group]:
    """One Group per value of `column`, in the campaign's order of values."""
    ordered = sorted(rows, key=lambda r: r["case"])
    buckets: dict[Any, list[Row]] = {}
    shown: dict[Any, Any] = {}
    for r in ordered:
        k = value_key(r.get(column))
        buckets.setdefault(k, []).append(r)
        shown.setdefault(k, r.get(column))
    return [group(b, shown[k], plan.campaign.summary_metrics) for k, b in buckets.items()]


def _num(x: float) -> str:
    return f"{x:.4g}"


def _cell_text(value: Any) -> str:
    """A value as a Markdown table cell: on one line, its `|` escaped (a variant may be named anything)."""
    return " ".join(str(value).split()).replace("|", "\\|")


def _table(title: str, groups: Iterable[Group], metrics: Sequence[str]) -> list[str]:
    groups = list(groups)
    head = [title, "runs", "ok", "pass"]
    shown: dict[str, list[int]] = {}
    for m in metrics:
        most = max((s.n for g in groups if (s := g.spread[m]) is not None), default=0)
        shown[m] = [p for p in PERCENTILES if most >= MIN_RUNS[p]] or [PERCENTILES[0]]
        head += [f"{m} p{p}" for p in shown[m]] + [f"{m} max"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for g in groups:
        cells = [_cell_text(g.value), str(g.runs), str(g.ok), f"{g.passed} ({g.pass_rate:.0%})" if g.runs else "0"]
        for m in metrics:
            s = g.spread[m]
            cells += s.cells(shown[m]) if s is not None else ["-"] * (len(shown[m]) + 1)
        lines.append("| " + " | ".join(cells) + " |")
    return lines


def summary_text(plan: Plan, rows: Sequence[Row]) -> str:
    """summary.md's content."""
    camp = plan.campaign
    metrics = camp.summary_metrics
    status = {s: sum(r.get("status") == s for r in rows) for s in ("ok", "failed", "timeout")}
    passed = sum(bool(r.get("pass")) for r in rows)
    lines = [f"# Sweep: {camp.name or camp.source}", "",
             f"Campaign `{camp.source}`: {len(rows)} runs of {len(plan.cases)} cases "
             f"({status['ok']} ok, {status['failed']} failed, {status['timeout']} timed out); "
             f"{passed} passed ({passed / len(rows):.1%})." if rows else
             f"Campaign `{camp.source}`: no runs yet of {len(plan.cases)} cases.",
             "", "Pass: " + " and ".join(f"`{c.text}`" for c in camp.run.criteria) + " (and the run ended: status ok).",
             "", f"Percentiles are over the runs that ended (status ok); metrics: {', '.join(metrics)}. "
             + "; ".join(f"p{p} is given over {n} runs or more" for p, n in MIN_RUNS.items() if n > 1)
             + " ('-' for fewer; a column no row reaches is left out).", ""]
    lines += _table("all runs", [group(rows, "all", metrics)], metrics)
    for column in varied(plan, rows):
        lines += ["", f"## By {column}", ""]
        lines += _table(column, by_value(plan, rows, column), metrics)
    bad = [r for r in sorted(rows, key=lambda r: r["case"]) if r.get("status") != "ok"]
    if bad:
        lines += ["", "## Runs that did not end", ""]
        for r in bad[:MAX_FAILURES_LISTED]:
            label = ", ".join(f"{c}={r.get(c)}" for c in plan.columns)
            lines.append(f"- case {r['case']} ({label}): {r['status']}: {r.get('error', '')}")
        if len(bad) > MAX_FAILURES_LISTED:
            lines.append(f"- and {len(bad) - MAX_FAILURES_LISTED} more (the table's `error` column)")
    return "\n".join(lines) + "\n"
