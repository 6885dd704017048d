"""One case, run where it lands (a Dask worker, or this process), as `ddrt sim` runs it.

`run_case` never raises: a run that fails or outlives `run.timeout_s` becomes a row with its
error, so one bad case cannot stop a campaign. A row depends only on the case (its config,
path and seed) apart from its wall-time columns, whichever process ran it.
"""

from __future__ import annotations

import logging
import time
from typing import Any, Callable

from ddrt.errors import DdrtError
from ddrt.path import Path
from ddrt.simrun.runner import json_ready, run_sim
from ddrt.sweep.campaign import RunSettings
from ddrt.sweep.cases import Case
from ddrt.sweep.columns import TEXT_METRICS, flatten
from ddrt.sweep.criteria import passes

Row = dict[str, Any]


class RunTimedOut(DdrtError):
    """Raised from the run's progress hook once the case has used its wall-time budget."""


def blank_row(case: Case, settings: RunSettings, status: str, error: str = "") -> Row:
    """Every column of a row, the metrics empty: what a run that did not finish leaves."""
    row: Row = {"case": case.index, "case_id": case.case_id, **case.params,
                "status": status, "error": error, "pass": False}
    row.update({name: None for name in settings.metrics + TEXT_METRICS})
    row["path_warnings"] = None
    row["wall_s"] = None
    return row


def _deadline(timeout_s: float | None, t0: float) -> Callable[[float, float], None] | None:
    if timeout_s is None:
        return None

    def check(t_sim: float, expected: float) -> None:
        if time.perf_counter() - t0 > timeout_s:
            raise RunTimedOut(f"ran longer than run.timeout_s = {timeout_s:g} s of wall time "
                              f"({t_sim:.1f} of the {expected:.1f} simulated seconds expected done)")

    return check


def run_case(case: Case, path: Path, settings: RunSettings) -> Row:
    """Run one case to its end (or `duration_s`) and return its row."""
    t0 = time.perf_counter()
    logger = logging.getLogger("ddrt")
    level = logger.level
    logger.setLevel(logging.CRITICAL)  # a run that faults logs it; the fault is in the row
    try:
        result = run_sim(case.config, path, duration=settings.duration_s, seed=case.seed,
                         progress=_deadline(settings.timeout_s, t0))
    except RunTimedOut as exc:
        row = blank_row(case, settings, "timeout", str(exc))
    except Exception as exc:  # noqa: BLE001 - any failure of one run is that run's row
        row = blank_row(case, settings, "failed", f"{type(exc).__name__}: {' '.join(str(exc).split())}")
    else:
        row = blank_row(case, settings, "ok")
        metrics = json_ready(flatten(result.metrics))
        row.update({name: metrics.get(name) for name in settings.metrics + TEXT_METRICS})
        row["pass"] = passes(row, settings.criteria)
    finally:
        logger.setLevel(level)
    row["path_warnings"] = len(path.warnings)
    row["wall_s"] = time.perf_counter() - t0
    return row
