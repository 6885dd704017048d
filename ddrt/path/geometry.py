"""Path geometry: lines, arcs, turn-in-place pivots, curvature-continuous blends, smooth
parametric curves, and polylines through waypoints, each sampled densely along progress.

The choices that shape the motion (pivots at sharp corners, raised-cosine blends at gentle
ones, uniform arc-length sampling) are described in ddrt/path/sampled.py's docstring.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from ddrt.core.wrap import wrap_angle

TWO_PI = 2.0 * math.pi


@dataclass(slots=True)
class Piece:
    """Samples of one piece, both end points included; `s` is progress from the piece's start."""

    s: np.ndarray
    x: np.ndarray
    y: np.ndarray
    theta: np.ndarray
    kappa: np.ndarray
    pivot: bool = False
    turn: float = 0.0
    reverse: bool = False  # driven backwards: theta is the robot's heading (tangent + pi), kappa its curvature

    @property
    def length(self) -> float:
        return float(self.s[-1])


def reversed_piece(pc: Piece) -> Piece:
    """The same samples driven backwards: the robot faces away from the direction of travel
    (theta + pi), and its curvature d(theta)/d(forward distance) changes sign (forward
    distance shrinks as progress grows), so omega = v kappa holds for the negative v."""
    if pc.pivot:
        return Piece(pc.s, pc.x, pc.y, pc.theta + math.pi, pc.kappa, True, pc.turn)
    return Piece(pc.s, pc.x, pc.y, pc.theta + math.pi, -pc.kappa, False, 0.0, True)


def _count(length: float, step: float) -> int:
    """Number of intervals: at least 2 so every piece has an interior sample (u > 0 there)."""
    return max(2, int(math.ceil(length / step - 1e-9)))


def line_piece(x0: float, y0: float, heading: float, length: float, step: float) -> Piece:
    n = _count(length, step)
    s = np.linspace(0.0, length, n + 1)
    c, sn = math.cos(heading), math.sin(heading)
    return Piece(s, x0 + c * s, y0 + sn * s, np.full(n + 1, heading), np.zeros(n + 1))


def arc_piece(x0: float, y0: float, heading: float, radius: float, sweep: float, step: float) -> Piece:
    """Arc of `radius` turning by `sweep` (rad, positive = left) from pose (x0, y0, heading)."""
    length = radius * abs(sweep)
    n = _count(length, step)
    s = np.linspace(0.0, length, n + 1)
    k = math.copysign(1.0 / radius, sweep)
    th = heading + k * s
    # Centre to the left for a left turn: c = p + (1/k) * normal.
    cx, cy = x0 - math.sin(heading) / k, y0 + math.cos(heading) / k
    x = cx + np.sin(th) / k
    y = cy - np.cos(th) / k
    x[0], y[0] = x0, y0
    return Piece(s, x, y, th, np.full(n + 1, k))


def pivot_piece(x: float, y: float, theta0: float, dtheta: float, b: float, step: float) -> Piece:
    length = b * abs(dtheta)
    n = _count(length, step)
    s = np.linspace(0.0, length, n + 1)
    th = theta0 + np.linspace(0.0, dtheta, n + 1)
    return Piece(s, np.full(n + 1, x), np.full(n + 1, y), th, np.zeros(n + 1), True, math.copysign(1.0, dtheta))


_SUB = 16  # sub-steps per sample when integrating a blend's position


def _blend_unit_chord(phi: float) -> float:
    """Length of the chord of a unit-length raised-cosine blend turning by phi."""
    u = np.linspace(0.0, 1.0, 4001)
    th = phi * (u - np.sin(TWO_PI * u) / TWO_PI)
    cx, cy = np.trapezoid(np.cos(th), u), np.trapezoid(np.sin(th), u)
    return math.hypot(cx, cy)


def _blend(x0: float, y0: float, heading: float, phi: float, length: float, step: float) -> Piece:
    """Curvature-continuous corner: kappa rises and falls as a raised cosine, total turn phi."""
    n = _count(length, step)
    m = n * _SUB
    sf = np.linspace(0.0, length, m + 1)
    w = sf / length
    th = heading + phi * (w - np.sin(TWO_PI * w) / TWO_PI)
    dx = np.concatenate(([0.0], np.cumsum(0.5 * (np.cos(th[1:]) + np.cos(th[:-1])) * np.diff(sf))))
    dy = np.concatenate(([0.0], np.cumsum(0.5 * (np.sin(th[1:]) + np.sin(th[:-1])) * np.diff(sf))))
    sel = slice(None, None, _SUB)
    kap = (phi / length) * (1.0 - np.cos(TWO_PI * w[sel]))
    return Piece(sf[sel], x0 + dx[sel], y0 + dy[sel], th[sel], kap)


Curve = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


def parametric_piece(r: Curve, dr: Curve, ddr: Curve, u0: float, u1: float, step: float,
                period: float | None = None) -> Piece:
    """Smooth curve r(u), u in [u0, u1], resampled at uniform arc length.

    A curve that repeats every `period` in u (a closed shape's laps) keeps its arc-length
    table for one period only, so many laps cost no more than one in the table.
    """
    span = u1 - u0
    one = span if period is None else min(span, period)
    fine = max(20001, int(50000 * one / TWO_PI) + 1)
    uf = np.linspace(u0, u0 + one, fine)
    dxf, dyf = dr(uf)
    speed = np.hypot(dxf, dyf)
    if np.any(speed <= 0.0):
        raise ValueError("curve has a cusp (zero speed)")
    sf = np.concatenate(([0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(uf))))
    lap = float(sf[-1])
    if period is None or span <= period:
        length = lap

        def s_of_u(u: np.ndarray) -> np.ndarray:
            return np.interp(u, uf, sf)

        def u_of_s(s: np.ndarray) -> np.ndarray:
            return np.interp(s, sf, uf)
    else:
        full, rest = divmod(span, period)
        length = full * lap + float(np.interp(u0 + rest, uf, sf))

        def s_of_u(u: np.ndarray) -> np.ndarray:
            k = np.floor((u - u0) / period)
            return k * lap + np.interp(u - k * period, uf, sf)

        def u_of_s(s: np.ndarray) -> np.ndarray:
            k = np.floor(s / lap)
            return k * period + np.interp(s - k * lap, sf, uf)
    n = _count(length, step)
    s = np.linspace(0.0, length, n + 1)
    u = u_of_s(s)
    # One Newton step on s(u) = s_target using the exact speed refines the inverse.
    dxu, dyu = dr(u)
    u = u - (s_of_u(u) - s) / np.hypot(dxu, dyu)
    u[0], u[-1] = u0, u1
    x, y = r(u)
    dx, dy = dr(u)
    ddx, ddy = ddr(u)
    th = np.unwrap(np.arctan2(dy, dx))
    kap = (dx * ddy - dy * ddx) / np.hypot(dx, dy) ** 3
    return Piece(s, x, y, th, kap)


@dataclass(slots=True)
class Geometry:
    """A path's pieces in driving order, and the speed caps its points set (progress, cap)."""

    pieces: list[Piece]
    cap_sigma: np.ndarray | None = None  # progress of waypoints with a speed cap
    cap_value: np.ndarray | None = None


@dataclass(frozen=True, slots=True)
class GeometryOptions:
    """How geometry is built: the sample step (m), the turn-in-place radius b (m), the corner
    sharper than which a polyline turns in place (deg) and the longest blend (m)."""

    step: float = 0.002
    pivot_radius: float = 0.1
    corner_pivot_deg: float = 30.0
    blend_max: float = 0.15


def polyline_geometry(pts: Sequence[tuple[float, float]], caps: Sequence[float] | None,
                      opt: GeometryOptions) -> Geometry:
    """Straight segments through the waypoints; pivots at sharp corners, blends at gentle ones."""
    p = [(float(a), float(b)) for a, b in pts]
    nseg = len(p) - 1
    seg_len = [math.hypot(p[i + 1][0] - p[i][0], p[i + 1][1] - p[i][1]) for i in range(nseg)]
    seg_dir = [math.atan2(p[i + 1][1] - p[i][1], p[i + 1][0] - p[i][0]) for i in range(nseg)]
    sharp = math.radians(opt.corner_pivot_deg)
    turn = [0.0] * len(p)
    tangent = [0.0] * len(p)  # tangent length consumed by a blend at each vertex
    for k in range(1, nseg):
        phi = wrap_angle(seg_dir[k] - seg_dir[k - 1])
        turn[k] = phi
        if 1e-9 < abs(phi) <= sharp:
            tangent[k] = min(opt.blend_max, 0.5 * seg_len[k - 1], 0.5 * seg_len[k])
    pieces: list[Piece] = []
    enter = [0.0] * len(p)
    leave = [0.0] * len(p)
    sigma = 0.0
    heading = seg_dir[0]
    for k in range(nseg):
        (ax, ay), (bx, by) = p[k], p[k + 1]
        c, sn = math.cos(seg_dir[k]), math.sin(seg_dir[k])
        x0, y0 = ax + c * tangent[k], ay + sn * tangent[k]
        straight = seg_len[k] - tangent[k] - tangent[k + 1]
        heading = heading + wrap_angle(seg_dir[k] - heading)  # keep theta continuous
        if straight > 1e-9:
            pieces.append(line_piece(x0, y0, heading, straight, opt.step))
            sigma += straight
        if k + 1 == nseg:
            enter[k + 1] = leave[k + 1] = sigma
            break
        phi = turn[k + 1]
        if abs(phi) > sharp:
            enter[k + 1] = sigma
            pieces.append(pivot_piece(bx, by, heading, phi, opt.pivot_radius, opt.step))
            sigma += pieces[-1].length
            leave[k + 1] = sigma
        elif tangent[k + 1] > 0.0:
            d = tangent[k + 1]
            length = 2.0 * d * math.cos(0.5 * phi) / _blend_unit_chord(phi)
            pieces.append(_blend(bx - c * d, by - sn * d, heading, phi, length, opt.step))
            enter[k + 1] = leave[k + 1] = sigma + 0.5 * length
            sigma += length
        else:
            enter[k + 1] = leave[k + 1] = sigma
        heading += phi
    geo = Geometry(pieces)
    if caps is not None:
        xs = np.array([v for pair in zip(enter, leave) for v in pair])
        geo.cap_sigma = xs
        geo.cap_value = np.repeat(np.asarray(caps, dtype=float), 2)
    return geo
