"""Joining two smoothed runs at a cusp on one heading, instead of a needless turn in place.

At a real cusp (a three-point turn, a parking manoeuvre) the robot stops and drives on the
other way with the heading it had: both runs have the same tangent there. Each run of a
recording is smoothed on its own, and a smoothing spline's end tangent is the least certain
part of its fit: on 1-2 mm of noise the two ends came out 3-5 degrees apart, and the loader
turned that into a turn in place at every cusp (a stop, a yaw acceleration spike, time).

When both runs are smoothed samples (a waypoint's corner is the user's, never ours) and the
headings differ by at most CUSP_BLEND_MAX_RAD, each run's end is bent to the mean heading:
a lateral offset e(d) = tan(beta) d (1 - d / l)^2 over the last `l` metres (d from the cusp),
zero with zero slope at d = l, zero at the cusp, with slope tan(beta) there (beta = half the
difference, opposite on each side). It moves the curve by at most 4/27 l tan|beta| and adds a
curvature of at most 4 tan|beta| / l at the cusp, where the robot is at rest. It is used only
when that offset keeps the run within its tolerance; otherwise the turn in place stays.
"""

from __future__ import annotations

import math

import numpy as np

from ddrt.path.geometry import _Piece

__all__ = ["CUSP_BLEND_MAX_RAD", "CUSP_BLEND_M", "blend_offset", "bend_end", "bend_start"]

# Larger differences are a turn the user meant (or data that cannot say): turned in place.
CUSP_BLEND_MAX_RAD = math.radians(12.0)
# The length over which each side is bent (at most half the piece).
CUSP_BLEND_M = 0.25


def blend_length(piece: _Piece) -> float:
    return min(CUSP_BLEND_M, 0.5 * piece.length)


def blend_offset(length: float, beta: float) -> float:
    """The largest lateral move (m) of bending a run's end by `beta` rad over `length` m."""
    return 4.0 / 27.0 * length * abs(math.tan(beta))


def _bend(pc: _Piece, d: np.ndarray, sign: float, beta: float, length: float) -> None:
    """Offset the samples at distance d (from the cusp) along the travel normal; `sign` is ds/dd
    (-1 at a run's end, +1 at its start), so the tangent there turns by beta."""
    m = d < length
    if not m.any():
        return
    tb = math.tan(beta)
    dd = d[m]
    q = 1.0 - dd / length
    e = sign * tb * dd * q * q
    de = tb * q * (1.0 - 3.0 * dd / length)  # de/ds = sign * de/dd, and sign^2 = 1
    d2e = sign * tb * (6.0 * dd / length - 4.0) / length
    travel = pc.theta[m] + (math.pi if pc.reverse else 0.0)
    pc.x = pc.x.copy()
    pc.y = pc.y.copy()
    pc.theta = pc.theta.copy()
    pc.kappa = pc.kappa.copy()
    pc.x[m] -= e * np.sin(travel)
    pc.y[m] += e * np.cos(travel)
    pc.theta[m] += np.arctan(de)
    # kappa is the robot's curvature: the travel curvature's negative on a reversed piece.
    pc.kappa[m] += (-1.0 if pc.reverse else 1.0) * d2e


def bend_end(pc: _Piece, beta: float, length: float) -> None:
    """Turn the piece's last tangent by beta (rad), its end point fixed."""
    _bend(pc, pc.s[-1] - pc.s, -1.0, beta, length)


def bend_start(pc: _Piece, beta: float, length: float) -> None:
    """Turn the piece's first tangent by beta (rad), its start point fixed."""
    _bend(pc, pc.s - pc.s[0], 1.0, beta, length)
