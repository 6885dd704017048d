"""Tracking metrics of a finished run, computed offline from the telemetry (numpy is fine here)."""

from __future__ import annotations

import math

import numpy as np

from ddrt.path import Path


def path_polyline(path: Path, step: float = 0.001) -> np.ndarray:
    """Dense (N, 2) polyline of the path's geometry (pivots collapse to their corner point)."""
    n = max(2, int(math.ceil(path.length / step)) + 1)
    s = np.linspace(0.0, path.length, n)
    # The path is linear between its samples (Path.geometry), as np.interp is: the same
    # points as path.at(s) for each s, without a Python call per millimetre.
    arr = path.arrays()
    return np.column_stack((np.interp(s, arr["sigma"], arr["x"]), np.interp(s, arr["sigma"], arr["y"])))


def distances_to_polyline(poly: np.ndarray, xy: np.ndarray, near_index: np.ndarray | None = None,
                          window: int = 400, chunk: int = 1024) -> np.ndarray:
    """Euclidean distance of each point in `xy` (M, 2) to the polyline `poly` (N, 2).

    With `near_index` (a polyline index near each point's closest point, e.g. from the
    run's progress), only `window` segments either side are searched: the same answer for a
    robot within that many samples of its progress, and linear instead of quadratic time.
    """
    a = poly[:-1]
    ab = poly[1:] - a
    len2 = np.einsum("ij,ij->i", ab, ab)
    len2 = np.where(len2 > 0.0, len2, 1.0)
    nseg = len(a)
    out = np.empty(len(xy))
    if near_index is None:
        offsets = None
    else:
        w = min(window, nseg)
        offsets = np.arange(-w, w + 1)
    for start in range(0, len(xy), chunk):
        p = xy[start:start + chunk]
        if offsets is None:
            idx = np.broadcast_to(np.arange(nseg), (len(p), nseg))
        else:
            idx = np.clip(near_index[start:start + chunk, None] + offsets[None, :], 0, nseg - 1)
        sa = a[idx]
        sab = ab[idx]
        ap = p[:, None, :] - sa
        t = np.clip(np.einsum("mij,mij->mi", ap, sab) / len2[idx], 0.0, 1.0)
        diff = ap - t[:, :, None] * sab
        d2 = np.einsum("mij,mij->mi", diff, diff)
        out[start:start + chunk] = np.sqrt(d2.min(axis=1))
    return out


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
