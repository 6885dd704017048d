"""The summary's figures, when matplotlib is installed (the `plot` extra): the error
distribution for each value of each axis (box plots), and for a campaign with two `axes:` a
heat map of the pass rate over them (everything else pooled in each cell) with each cell's
median error written in it.

matplotlib's object API (Figure, no pyplot), so drawing changes no global backend or state
of a program that calls this in its own process (a benchmark).
"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path as FsPath
from typing import Sequence

import numpy as np

from ddrt.sweep.cases import Plan
from ddrt.sweep.run import Row
from ddrt.sweep.summary import by_value, value_key, varied

FIGURES = "figures"
MAX_BOXES = 60  # beyond this many values a box plot is unreadable


def available() -> bool:
    return importlib.util.find_spec("matplotlib") is not None


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.+-]+", "_", name)


def _values(rows: Sequence[Row], metric: str) -> list[float]:
    out = [r.get(metric) for r in rows if r.get("status") == "ok"]
    return [float(v) for v in out if isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v)]


def _axes_of(plan: Plan, rows: Sequence[Row]) -> list[str]:
    """The swept columns worth a figure: every varied one but the noise seed."""
    return [c for c in varied(plan, rows) if c != "seed"]


def shown_as(metric: str) -> tuple[float, str]:
    """The scale and axis label a metric is drawn with: a length in metres (`*_m`) in mm, which
    reads without an offset at the sub-millimetre errors a sweep compares."""
    return (1000.0, f"{metric} (mm)") if metric.endswith("_m") else (1.0, metric)


def box_plot(plan: Plan, rows: Sequence[Row], column: str, metric: str, dest: FsPath) -> None:
    from matplotlib.figure import Figure

    groups = by_value(plan, rows, column)
    scale, label = shown_as(metric)
    data = [[scale * v for v in _values([r for r in rows if value_key(r.get(column)) == value_key(g.value)], metric)]
            for g in groups]
    fig = Figure(figsize=(max(5.0, 0.45 * len(groups) + 2.0), 4.0), layout="constrained")
    ax = fig.add_subplot()
    ax.boxplot([d if d else [np.nan] for d in data], showfliers=True)
    ax.set_xticks(range(1, len(groups) + 1), [str(g.value) for g in groups], rotation=45 if len(groups) > 8 else 0,
                  ha="right" if len(groups) > 8 else "center")
    ax.set_xlabel(column)
    ax.set_ylabel(label)
    ax.ticklabel_format(axis="y", useOffset=False)
    ax.set_title(f"{sum(map(len, data))} runs that ended", fontsize=10)
    ax.grid(True, axis="y", alpha=0.3)
    fig.savefig(dest, dpi=110)


def heat_map(plan: Plan, rows: Sequence[Row], x: str, y: str, metric: str, dest: FsPath) -> None:
    from matplotlib.figure import Figure

    xs = [g.value for g in by_value(plan, rows, x)]
    ys = [g.value for g in by_value(plan, rows, y)]
    rate = np.full((len(ys), len(xs)), np.nan)
    median = np.full_like(rate, np.nan)
    for i, yv in enumerate(ys):
        for j, xv in enumerate(xs):
            cell = [r for r in rows if value_key(r.get(x)) == value_key(xv) and value_key(r.get(y)) == value_key(yv)]
            if cell:
                rate[i, j] = sum(bool(r.get("pass")) for r in cell) / len(cell)
                vals = _values(cell, metric)
                median[i, j] = shown_as(metric)[0] * float(np.median(vals)) if vals else np.nan
    fig = Figure(figsize=(max(5.0, 0.8 * len(xs) + 2.5), max(3.5, 0.5 * len(ys) + 2.0)), layout="constrained")
    ax = fig.add_subplot()
    im = ax.imshow(rate, vmin=0.0, vmax=1.0, cmap="RdYlGn", origin="lower", aspect="auto")
    fig.colorbar(im, ax=ax, label="pass rate")
    ax.set_xticks(range(len(xs)), [str(v) for v in xs])
    ax.set_yticks(range(len(ys)), [str(v) for v in ys])
    ax.set_xlabel(x)
    ax.set_ylabel(y)
    ax.set_title(f"pass rate; in each cell the median {shown_as(metric)[1]}")
    for i in range(len(ys)):
        for j in range(len(xs)):
            if np.isfinite(median[i, j]):
                ax.text(j, i, f"{median[i, j]:.3g}", ha="center", va="center", fontsize=8)
    fig.savefig(dest, dpi=110)


def write_figures(plan: Plan, rows: Sequence[Row], out: FsPath) -> list[FsPath]:
    """Every figure the rows allow, into DIR/figures/; none without matplotlib or rows."""
    if not available() or not rows:
        return []
    folder = out / FIGURES
    folder.mkdir(exist_ok=True)
    metric = plan.campaign.summary_metrics[0]
    written: list[FsPath] = []
    columns = _axes_of(plan, rows)
    for column in columns:
        if len(by_value(plan, rows, column)) <= MAX_BOXES:
            dest = folder / f"{_safe(metric)}_by_{_safe(column)}.png"
            box_plot(plan, rows, column, metric, dest)
            written.append(dest)
    swept = [a.key for a in plan.campaign.axes if len(a.values) > 1]
    if len(swept) == 2:  # the other columns (seeds, variants, robots) pooled in each cell
        x, y = swept
        dest = folder / f"pass_rate_{_safe(x)}_x_{_safe(y)}.png"
        heat_map(plan, rows, x, y, metric, dest)
        written.append(dest)
    return written
