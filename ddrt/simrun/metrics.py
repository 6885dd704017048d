"""Tracking metrics of a finished run, computed offline from the telemetry (numpy is fine here)."""

from __future__ import annotations

import math

import numpy as np

from ddrt.path import Path
from ddrt.path.sampled import distances_to_polyline

__all__ = ["distances_to_polyline", "path_polyline", "tracking_metrics"]


def path_polyline(path: Path, step: float = 0.001) -> np.ndarray:
    """Dense (N, 2) polyline of the path's geometry (pivots collapse to their corner point)."""
    n = max(2, int(math.ceil(path.length / step)) + 1)
    s = np.linspace(0.0, path.length, n)
    # The path is linear between its samples (Path.geometry), as np.interp is: the same
    # points as path.at(s) for each s, without a Python call per millimetre.
    arr = path.arrays()
    return np.column_stack((np.interp(s, arr["sigma"], arr["x"]), np.interp(s, arr["sigma"], arr["y"])))


def tracking_metrics(path: Path, true_xy: np.ndarray, est_xy: np.ndarray, heading_err: np.ndarray,
                     saturated: np.ndarray, sigma: np.ndarray | None = None) -> dict[str, float]:
    """RMS/max cross-track (true and estimated pose), heading, end error, saturation."""
    if len(true_xy) == 0:
        return {"rms_cross_track_m": float("nan"), "max_cross_track_m": float("nan"),
                "rms_tracking_m": float("nan"), "max_tracking_m": float("nan"),
                "rms_heading_err_rad": float("nan"), "final_pos_err_m": float("nan"),
                "saturated_fraction": 0.0}
    step = 0.001
    poly = path_polyline(path, step)
    near = None
    if sigma is not None:
        near = np.clip(np.round(sigma / (path.length / (len(poly) - 1))).astype(int), 0, len(poly) - 2)
    d_true = distances_to_polyline(poly, true_xy, near)
    d_est = distances_to_polyline(poly, est_xy, near)
    end = path.at(path.length)
    final = float(math.hypot(true_xy[-1, 0] - end.x, true_xy[-1, 1] - end.y))
    return {
        "rms_cross_track_m": float(np.sqrt(np.mean(d_true ** 2))),
        "max_cross_track_m": float(d_true.max()),
        "rms_tracking_m": float(np.sqrt(np.mean(d_est ** 2))),
        "max_tracking_m": float(d_est.max()),
        "rms_heading_err_rad": float(np.sqrt(np.mean(heading_err ** 2))),
        "final_pos_err_m": final,
        "saturated_fraction": float(np.mean(saturated)),
    }
