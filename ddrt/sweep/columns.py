"""What a campaign's table has in its rows: the metrics a run can keep, and the fixed columns.

The metrics are those of metrics.json (ddrt/simrun/runner.py), nested ones flattened with a
dot (`estimator.gyro_rejects`). They are listed here so a campaign's `metrics:` and `pass:`
are checked before anything runs; tests/test_sweep_campaign.py holds the list to a real run.
"""

from __future__ import annotations

from typing import Any, Mapping

# Every number (and the one yes/no) of metrics.json, in its order.
NUMERIC_METRICS = (
    "rms_cross_track_m", "max_cross_track_m", "rms_tracking_m", "max_tracking_m", "rms_heading_err_rad",
    "final_pos_err_m", "saturated_fraction", "completed", "ticks", "sim_duration_s", "path_length_m",
    "path_duration_s", "rms_velocity_err_mps", "estimator.gyro_rejects", "estimator.encoder_rejects",
    "realtime_factor",
)
# The yes/no among them.
BOOL_METRICS = ("completed",)
# Text that says how a run ended; every row has them.
TEXT_METRICS = ("state", "fault")
KNOWN_METRICS = NUMERIC_METRICS + TEXT_METRICS
# Columns that depend on the machine and its load, not on the case: left out when two tables
# are compared for determinism.
WALL_COLUMNS = ("wall_s", "realtime_factor")
# Every row: which case, how it went.
CASE_COLUMNS = ("case", "case_id")
STATUS_COLUMNS = ("status", "error", "pass", "path_warnings", "wall_s")
STATUSES = ("ok", "failed", "timeout")


def flatten(metrics: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    """metrics.json's mapping with nested mappings as dotted keys."""
    out: dict[str, Any] = {}
    for key, value in metrics.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(flatten(value, name + "."))
        else:
            out[name] = value
    return out
