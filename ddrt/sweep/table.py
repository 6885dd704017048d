"""The campaign's table: one row per run, in case order, as Parquet (pyarrow) and CSV.

Column types are fixed by what a column is, not by which rows happen to be there (a metric
is a float column even when every run so far failed), so two tables of the same campaign
compare equal whatever finished first. Parquet keeps the types for analysis (pandas, polars,
DuckDB); the CSV is for a spreadsheet or a quick look.
"""

from __future__ import annotations

import json
import os
from pathlib import Path as FsPath
from typing import Any, Iterable, Sequence

from ddrt.sweep.cases import Plan
from ddrt.sweep.columns import BOOL_METRICS, CASE_COLUMNS, TEXT_METRICS, WALL_COLUMNS

PARQUET = "results.parquet"
CSV = "results.csv"
_INT_METRICS = ("ticks", "estimator.gyro_rejects", "estimator.encoder_rejects")

Row = dict[str, Any]


def columns(plan: Plan) -> list[str]:
    """Every column, in order: which case, its parameters, how it went, its metrics."""
    kept = plan.campaign.run.metrics
    return list(CASE_COLUMNS) + list(plan.columns) + ["status", "error", "pass"] + list(kept) + list(TEXT_METRICS) \
        + ["path_warnings", "wall_s"]


def _int64(v: int) -> bool:
    """Whether a whole number fits the table's int64 columns."""
    return -2**63 <= v < 2**63


def _param_type(values: Sequence[Any]) -> str:
    seen = [v for v in values if v is not None]
    if seen and all(isinstance(v, bool) for v in seen):
        return "bool"
    if seen and all(isinstance(v, int) and not isinstance(v, bool) for v in seen):
        # A whole number beyond int64 (a config's name: or description: takes any value) is
        # kept as its text rather than failing the table after every run has finished.
        return "int" if all(_int64(v) for v in seen) else "text"
    if seen and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in seen):
        return "float"
    return "text"


def _column_type(name: str, plan: Plan, values: Sequence[Any]) -> str:
    if name in ("case", "path_warnings") or name in _INT_METRICS:
        return "int"
    if name in ("pass",) or name in BOOL_METRICS:
        return "bool"
    if name in ("case_id", "status", "error") or name in TEXT_METRICS:
        return "text"
    if name in plan.columns:
        return _param_type(values)
    return "float"


def value_kinds(plan: Plan) -> dict[str, str]:
    """The type of every column that is not a parameter (those depend on the campaign's values)."""
    return {name: _column_type(name, plan, []) for name in columns(plan)
            if name not in plan.columns and name not in CASE_COLUMNS}


def fits(value: Any, kind: str) -> bool:
    """Whether `value` can be a cell of a column of `kind` (None always can)."""
    if value is None:
        return True
    if kind == "bool":
        return isinstance(value, bool)
    if kind == "text":
        return isinstance(value, str)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return False
    return kind == "float" or (isinstance(value, int) and _int64(value))


def _cell(value: Any, kind: str) -> Any:
    if value is None:
        return None
    if kind == "text":
        return value if isinstance(value, str) else json.dumps(value)
    if kind == "float":
        return float(value)
    return value


def arrow_table(plan: Plan, rows: Iterable[Row]) -> Any:
    """The rows (any order) as a pyarrow Table sorted by case."""
    import pyarrow as pa

    types = {"int": pa.int64(), "float": pa.float64(), "bool": pa.bool_(), "text": pa.string()}
    ordered = sorted(rows, key=lambda r: r["case"])
    arrays, fields = [], []
    for name in columns(plan):
        values = [r.get(name) for r in ordered]
        kind = _column_type(name, plan, values)
        arrays.append(pa.array([_cell(v, kind) for v in values], type=types[kind]))
        fields.append(pa.field(name, types[kind]))
    return pa.Table.from_arrays(arrays, schema=pa.schema(fields))


def write_table(plan: Plan, rows: Iterable[Row], out: FsPath) -> Any:
    """DIR/results.parquet and DIR/results.csv, each replaced whole (never half-written)."""
    import pyarrow.csv as pacsv
    import pyarrow.parquet as pq

    table = arrow_table(plan, rows)
    for name, write in ((PARQUET, pq.write_table), (CSV, pacsv.write_csv)):
        tmp = out / (name + ".tmp")
        write(table, str(tmp))
        os.replace(tmp, out / name)
    return table


def read_table(path: str | FsPath) -> Any:
    import pyarrow.parquet as pq

    return pq.read_table(str(path))


def without_wall_time(table: Any) -> Any:
    """The table less the columns that depend on the machine's speed (to compare two runs)."""
    return table.drop_columns([c for c in WALL_COLUMNS if c in table.column_names])
