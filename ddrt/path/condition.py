"""Conditioning a polyline: the points people hand over are usually samples of a curve.

A CSV or `points:` list arrives as a polyline. Three kinds are told apart (`classify`):

- **waypoints**: points far apart (median spacing at least `paths.waypoint_spacing_m`,
  0.25 m), or `tolerance` 0. Straight segments through them, a turn in place at corners
  sharper than `corner_pivot_deg` and a curvature-continuous blend at gentler ones: the
  geometry of `polyline_geometry` (ddrt/path/geometry.py), unchanged.
- **grid**: a grid planner's plan cell by cell (every step one cell along an axis or a
  diagonal of a common grid, a cell below the waypoint spacing). The plan says which cells
  are free, not that the robot must zig-zag through their centres: it is smoothed like
  samples with a tolerance of half a cell (or the path's own `tolerance:`) measured along
  the grid's axes, so the corridor is each point's cell, and only turns sharper than 90
  degrees (135, 180) become turns in place; 45 and 90 degree steps are smoothed within the
  cells. A 90 degree step (at an obstacle's corner) still bends within about 1.7 cells, too
  tight to take at speed, so each turn of the reference gets one speed cap that bounds the
  RMS of v^2 dkappa/ds over it (ddrt/path/turnspeed.py).
- **samples**: anything denser. The points are samples of a curve with noise (a recording,
  a planner's output, an exported curve). The reference is a smoothing spline through them
  that stays within `tolerance` (`paths.tolerance_m`, 10 mm) of every point; genuine corners
  (the direction turns by more than `corner_pivot_deg` within a few tolerances of one point,
  at two scales) become turns in place between separately fitted legs.

The smoothing spline through each leg, its choice of smoothing and how it keeps every point
within the tolerance are ddrt/path/smoothing.py's; this module decides what the legs are
(where the corners are, whether a loop closes) and joins them.

The reported deviation (`Conditioning.deviation_m`) is the largest distance from an input
point to the reference (for a grid plan, along the grid's axes: at most half a cell while
the reference crosses every planned cell).

Reversals: in samples a corner that turns by 150 degrees or more is a cusp (the recording
drove back the way it came). Unless its points are marked as reached in reverse
(reversal.py), it is refused naming the line; a turn in place there is a different motion,
which the file would have to say (split it into two paths there).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from ddrt.path.geometry import Geometry, GeometryOptions, Piece, pivot_piece, polyline_geometry
from ddrt.path.smoothing import (
    CurveStops, EndPin, FitError, FitRequest, ToleranceUnmet, chord_length, estimate_noise, fit_leg,
)
from ddrt.path.turnspeed import turn_caps

__all__ = ["ConditionOptions", "Conditioning", "ConditionError", "classify", "condition_polyline", "knot_spacing",
           "point_noise"]

WAYPOINTS, SAMPLES, GRID = "waypoints", "samples", "grid"
REVERSAL_DEG = 150.0  # a corner this sharp in samples is a cusp: the path reverses
GRID_PIVOT_DEG = 112.5  # in a grid plan, turns sharper than 90 degrees (135, 180) pivot
GRID_TOLERANCE_CELLS = 0.5  # a grid plan's tolerance, in cells: the robot stays in the planned cells
NOISE_FLOOR_M = 2e-5  # below this the points are exact (an export): smooth to this level


class ConditionError(ValueError):
    """The polyline cannot be conditioned; the message names the point (line or key)."""


@dataclass(frozen=True, slots=True)
class ConditionOptions:
    tolerance: float = 0.01  # m; 0: every point is a waypoint (no conditioning)
    waypoint_spacing: float = 0.25  # m; median spacing at or above: waypoints
    tolerance_given: bool = False  # the path set its own tolerance (a grid keeps it)


@dataclass(frozen=True, slots=True)
class Corner:
    index: int  # input point (after merging duplicates)
    turn: float  # rad, + left
    x: float
    y: float


@dataclass
class Conditioning:
    """What conditioning did to a polyline (Path.conditioning; None for analytic shapes)."""

    mode: str  # waypoints | samples | grid
    tolerance_m: float
    points: np.ndarray  # (n, 2) the input points (consecutive duplicates merged)
    names: Sequence[str]  # where each point came from ("line 7", "key 'points[3]'")
    deviation_m: float = 0.0  # largest distance of an input point from the reference
    worst: int = 0  # that point's index
    noise_m: float = 0.0  # estimated noise of the points (1 sigma, lateral)
    grid_cell_m: float | None = None
    smoothing_m: tuple[float, ...] = ()  # smoothing length of each fitted leg
    corners: tuple[Corner, ...] = ()  # corners that became turns in place
    point_sigma: np.ndarray | None = None  # progress of each point's foot on the reference
    spacing_m: float = 0.0  # median distance between consecutive points
    iterations: int = 0  # fits solved in total
    extra: dict = field(default_factory=dict)

    def summary(self) -> str:
        if self.mode == WAYPOINTS:
            return f"{len(self.points)} points as waypoints (median spacing {self.spacing_m * 1000:.0f} mm)"
        kind = (f"a grid plan ({self.grid_cell_m * 1000:.0f} mm cells)" if self.mode == GRID
                else "samples of a curve")
        return (f"{len(self.points)} points as {kind}: smoothed within {self.tolerance_m * 1000:.1f} mm "
                f"(largest deviation {self.deviation_m * 1000:.1f} mm at {self.names[self.worst]}; "
                f"noise ~{self.noise_m * 1000:.2f} mm), {len(self.corners)} corner(s) turned in place")


# --------------------------------------------------------------------------- classification


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def grid_cell(p: np.ndarray) -> float | None:
    """The cell of a grid plan given cell by cell (every step one cell along an axis or a
    diagonal of one grid, which may be rotated), else None."""
    d = np.diff(p, axis=0)
    if len(d) < 3:
        return None
    length = np.hypot(d[:, 0], d[:, 1])
    c = float(length.min())
    if not c > 0.0:
        return None
    tol = 1e-3 * c
    axis = np.abs(length - c) <= tol
    diag = np.abs(length - c * math.sqrt(2.0)) <= tol
    if not np.all(axis | diag):
        return None
    ang = np.arctan2(d[:, 1], d[:, 0])
    k = (ang - ang[0]) / (0.25 * math.pi)
    kr = np.round(k)
    if np.max(np.abs(k - kr)) > 1e-3:
        return None
    # Steps an odd number of eighths of a turn apart are of the other kind (axis vs diagonal).
    parity = (kr.astype(np.int64) % 2) == 1
    if not np.array_equal(parity, axis != axis[0]):
        return None
    return c


def grid_axis(p: np.ndarray) -> float:
    """The direction of a grid plan's first axis (its steps are along it, across it or diagonal)."""
    d = p[1] - p[0]
    ang = math.atan2(d[1], d[0])
    diagonal = abs(math.hypot(d[0], d[1]) - float(np.min(np.hypot(*np.diff(p, axis=0).T)))) > 1e-6 * math.hypot(*d)
    return ang - 0.25 * math.pi if diagonal else ang


def classify(p: np.ndarray, copt: ConditionOptions) -> tuple[str, float, float | None]:
    """(mode, tolerance, grid cell) for the distinct points p (n, 2)."""
    if len(p) < 4 or copt.tolerance <= 0.0:
        return WAYPOINTS, copt.tolerance, None
    cell = grid_cell(p)
    if cell is not None and cell < copt.waypoint_spacing:
        tol = copt.tolerance if copt.tolerance_given else max(copt.tolerance, GRID_TOLERANCE_CELLS * cell)
        return GRID, tol, cell
    spacing = float(np.median(np.hypot(*np.diff(p, axis=0).T)))
    if spacing >= copt.waypoint_spacing:
        return WAYPOINTS, copt.tolerance, None
    return SAMPLES, copt.tolerance, None


# --------------------------------------------------------------------------- corners


def _turns(p: np.ndarray, u: np.ndarray, scale: float) -> np.ndarray:
    """Turn at each point between the chords from u - scale to it and from it to u + scale
    (NaN where a chord would be shorter than a quarter of the scale: near the ends)."""
    total = u[-1]
    ua, ub = np.clip(u - scale, 0.0, total), np.clip(u + scale, 0.0, total)
    ax, ay = np.interp(ua, u, p[:, 0]), np.interp(ua, u, p[:, 1])
    bx, by = np.interp(ub, u, p[:, 0]), np.interp(ub, u, p[:, 1])
    ix, iy = p[:, 0] - ax, p[:, 1] - ay
    ox, oy = bx - p[:, 0], by - p[:, 1]
    turn = _wrap(np.arctan2(oy, ox) - np.arctan2(iy, ix))
    short = (np.hypot(ix, iy) < 0.25 * scale) | (np.hypot(ox, oy) < 0.25 * scale)
    turn[short] = np.nan
    return turn


def _raw_noise(p: np.ndarray) -> float:
    """A rough lateral noise level from the points alone (for the corner scale)."""
    if len(p) < 12:
        return 0.0
    a, m, b = p[:-2], p[1:-1], p[2:]
    c = b - a
    cl = np.hypot(c[:, 0], c[:, 1])
    e = (c[:, 0] * (m[:, 1] - a[:, 1]) - c[:, 1] * (m[:, 0] - a[:, 0])) / np.where(cl > 0, cl, 1.0)
    k = 9
    if len(e) <= k:
        return float(1.4826 * np.median(np.abs(e - np.median(e))) / math.sqrt(1.5))
    win = np.lib.stride_tricks.sliding_window_view(e, k)
    local = np.median(win, axis=1)
    r = e[k // 2: k // 2 + len(local)] - local
    return float(1.4826 * np.median(np.abs(r)) / math.sqrt(1.5))


def _find_corners(p: np.ndarray, u: np.ndarray, scale: float, threshold: float) -> list[tuple[int, float]]:
    """(index, turn) of corners: points where the direction turns by more than `threshold`
    at both `scale` and half of it (a smooth bend turns half as much at half the scale),
    one per `scale` of length (the sharpest)."""
    t1 = _turns(p, u, scale)
    t2 = _turns(p, u, 0.5 * scale)
    with np.errstate(invalid="ignore"):
        score = np.where(np.sign(t1) == np.sign(t2), np.minimum(np.abs(t1), np.abs(t2)), 0.0)
    score = np.nan_to_num(score, nan=0.0)
    score[0] = score[-1] = 0.0
    cand = np.flatnonzero(score > threshold)
    if len(cand) == 0:
        return []
    order = cand[np.argsort(-score[cand], kind="stable")]
    taken: list[int] = []
    for i in order.tolist():
        if all(abs(u[i] - u[k]) >= scale for k in taken):
            taken.append(i)
    taken.sort()
    return [(i, float(t2[i])) for i in taken]


def _refine_corner(p: np.ndarray, u: np.ndarray, k: int, scale: float, tol: float) -> np.ndarray:
    """The corner as the intersection of lines fitted to the points either side (noise on the
    corner's own point would bend both legs' ends); the point itself if that is off."""
    def line(sel: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        q = p[sel]
        if len(q) < 3:
            return None
        c = q.mean(axis=0)
        _, _, vt = np.linalg.svd(q - c, full_matrices=False)
        return c, vt[0]

    before = line(np.flatnonzero((u >= u[k] - scale) & (u < u[k])))
    after = line(np.flatnonzero((u > u[k]) & (u <= u[k] + scale)))
    if before is None or after is None:
        return p[k].copy()
    (c1, d1), (c2, d2) = before, after
    den = d1[0] * d2[1] - d1[1] * d2[0]
    if abs(den) < math.sin(math.radians(10.0)):
        return p[k].copy()
    r = c2 - c1
    t = (r[0] * d2[1] - r[1] * d2[0]) / den
    x = c1 + t * d1
    if not np.all(np.isfinite(x)) or math.hypot(*(x - p[k])) > tol:
        return p[k].copy()
    return x


# --------------------------------------------------------------------------- the whole polyline


def _loop_wrap(p: np.ndarray, knot: float, scale: float, threshold: float, tol: float,
               spacing: float) -> tuple[np.ndarray, np.ndarray] | None:
    """A closed loop whose end runs smoothly into its start (a lap of a recording): the points
    to fit before and after it, taken round the loop; else None."""
    n = len(p)
    gap = float(math.hypot(*(p[-1] - p[0])))
    if n < 12 or gap > max(tol, 1.5 * spacing):
        return None
    same = gap < 0.3 * spacing  # the last point repeats the first
    body = p[:-1] if same else p
    total = float(np.sum(np.hypot(*np.diff(body, axis=0).T))) + (float(math.hypot(*(body[-1] - body[0]))))
    reach = min(0.45 * total, max(2.0 * scale, 120.0 * knot), 2.0)
    u = chord_length(body)
    k_pre = len(body) - int(np.searchsorted(u, u[-1] - reach, side="left"))  # points within reach of the end
    k_post = int(np.searchsorted(u, reach, side="right"))
    k_pre = max(1, min(k_pre, len(body) - 1))
    k_post = max(1, min(k_post, len(body) - 1))
    pre = body[len(body) - k_pre:]
    post = body[:k_post] if not same else p[1:1 + k_post]
    if same:
        pre = p[n - 1 - k_pre:n - 1]
    # The junction must not be a corner (a rectangle recorded from one of its corners).
    ext = np.concatenate((pre, p[:k_post + 1]))
    ue = chord_length(ext)
    for sc in (scale, 0.5 * scale):
        t = _turns(ext, ue, sc)[len(pre)]
        if not np.isfinite(t) or abs(t) > threshold:
            return None
    return pre, post



def _cap_turns(geo: Geometry, info: Conditioning) -> None:
    """A grid plan's turns at a bounded yaw acceleration (ddrt/path/turnspeed.py), merged with
    the points' own caps."""
    ts, tv = turn_caps(geo.pieces)
    if geo.cap_sigma is not None and geo.cap_value is not None:
        tv = np.minimum(tv, np.interp(ts, geo.cap_sigma, geo.cap_value))
    geo.cap_sigma, geo.cap_value = ts, tv


def knot_spacing(spacing: float, tol: float, cell: float | None) -> float:
    """The spline's knot spacing: the points' spacing, but no closer than half the tolerance
    (finer detail than that is noise to be removed, and denser knots only cost time); a grid
    plan's cell."""
    return cell if cell is not None else max(spacing, 0.5 * tol, 1e-4)


def _noise(p: np.ndarray, knot: float) -> float:
    """The points' noise (smoothing.estimate_noise); its failure a ConditionError like the rest."""
    try:
        return estimate_noise(p, knot)
    except FitError as exc:
        raise ConditionError(str(exc)) from None


def point_noise(pts: np.ndarray, copt: ConditionOptions) -> tuple[str, float]:
    """(mode, estimated lateral noise) of a polyline of distinct points, as condition_polyline
    finds them (for a cusp's estimate from two runs' points, ddrt/path/cusp.py)."""
    p = np.asarray(pts, dtype=float)
    mode, tol, cell = classify(p, copt)
    if mode == WAYPOINTS:
        return mode, 0.0
    spacing = float(np.median(np.hypot(*np.diff(p, axis=0).T)))
    return mode, max(_noise(p, knot_spacing(spacing, tol, cell)), NOISE_FLOOR_M)


def condition_polyline(pts: np.ndarray, caps: np.ndarray | None, opt: GeometryOptions, copt: ConditionOptions,
                       where: str, names: Sequence[str],
                       ends: tuple[EndPin | None, EndPin | None] = (None, None),
                       noise: float | None = None) -> tuple[Geometry, Conditioning]:
    """The geometry of a polyline of distinct points (module docstring); caps per point or None.

    `noise`: the points' noise when it is known better than from these points alone (one run
    of a recording that reverses: the recording's, pooled over its runs); else estimated.

    `ends`: smoothed samples whose first or last leg starts or ends at a given point with a
    given tangent (a cusp shared with the run before or after it) or at a given point alone;
    ignored for waypoints. The point at that end is then measured against the pinned point
    for the deviation."""
    p = np.asarray(pts, dtype=float)
    seg = np.hypot(*np.diff(p, axis=0).T)
    spacing = float(np.median(seg)) if len(seg) else 0.0
    mode, tol, cell = classify(p, copt)
    info = Conditioning(mode, tol, p, names, grid_cell_m=cell, spacing_m=spacing)
    if mode == WAYPOINTS:
        geo = polyline_geometry([(float(a), float(b)) for a, b in p], None if caps is None else caps.tolist(), opt)
        if len(p) > 2:
            d = np.diff(p, axis=0)
            turn = _wrap(np.diff(np.arctan2(d[:, 1], d[:, 0])))
            sharp = np.abs(turn) > math.radians(opt.corner_pivot_deg)
            info.corners = tuple(Corner(int(i) + 1, float(turn[i]), float(p[i + 1, 0]), float(p[i + 1, 1]))
                                 for i in np.flatnonzero(sharp))
            info.extra["blends"] = int(np.sum(~sharp & (np.abs(turn) > 1e-9)))
        return geo, info
    u = chord_length(p)
    knot = knot_spacing(spacing, tol, cell)
    rough = _raw_noise(p)
    scale = max(5.0 * tol, 20.0 * rough, 3.0 * spacing)
    threshold = math.radians(opt.corner_pivot_deg)
    if mode == GRID:
        threshold = max(threshold, math.radians(GRID_PIVOT_DEG))
    corners = _find_corners(p, u, scale, threshold)
    # Within a corner scale of an end pinned with a shared tangent the points were found smooth
    # by the cusp's own fit (ddrt/path/cusp.py): a turn found there is the end's short chord on noise.
    held0 = ends[0] is not None and ends[0].slope is not None
    held1 = ends[1] is not None and ends[1].slope is not None
    corners = [(k, t) for k, t in corners if not (held0 and u[k] < scale) and not (held1 and u[-1] - u[k] < scale)]
    if mode == SAMPLES:
        for k, turn in corners:
            if abs(turn) >= math.radians(REVERSAL_DEG):
                raise ConditionError(
                    f"{where}: {names[k]}: the path reverses here (it turns {math.degrees(abs(turn)):.0f} degrees "
                    f"within {scale * 100:.0f} cm): mark the points reached in reverse (a negative v) or split the path here")
    else:
        d = np.diff(p, axis=0)
        back = np.flatnonzero(np.einsum("ij,ij->i", d[1:], d[:-1]) < -0.999 * seg[1:] * seg[:-1])
        if len(back):
            k = int(back[0]) + 1
            raise ConditionError(f"{where}: {names[k]}: the plan steps back the way it came (a reversal): "
                                 "mark the points reached in reverse (a negative v) or split the path here")
    noise = max(_noise(p, knot) if noise is None else noise, NOISE_FLOOR_M)
    axis = grid_axis(p) if mode == GRID else None
    info.noise_m = noise
    pinned = ends[0] is not None or ends[1] is not None
    wrap = _loop_wrap(p, knot, scale, threshold, tol, spacing) if not corners and not pinned else None
    info.extra["closed_loop"] = wrap is not None
    cuts = [0] + [k for k, _ in corners] + [len(p) - 1]
    # Each leg's ends: the polyline's own (pinned or free), else a corner (the point only).
    pins: list[EndPin | None] = [ends[0], *(EndPin(_refine_corner(p, u, k, scale, tol)) for k, _ in corners), ends[1]]
    pieces: list[Piece] = []
    sig_pts = np.zeros(len(p))
    devs = np.zeros(len(p))
    cap_s: list[float] = []
    cap_v: list[float] = []
    sigma = 0.0
    heading: float | None = None
    kept: list[Corner] = []
    ells: list[float] = []
    for j in range(len(cuts) - 1):
        a, b = cuts[j], cuts[j + 1]
        try:
            leg = fit_leg(FitRequest(p[a:b + 1], tol, noise, knot, opt, pins[j], pins[j + 1], wrap, axis))
        except CurveStops as exc:
            k = a + exc.index
            raise ConditionError(f"{where}: {names[k]}: the points turn back on themselves here (the smoothed "
                                 "curve stops and reverses): mark the points reached in reverse (a negative v) "
                                 "or split the path here") from None
        except ToleranceUnmet as exc:
            raise ConditionError(
                f"{where}: {names[a + exc.index]}: the reference cannot stay within {tol:g} m of the point "
                f"({exc.x:.6g}, {exc.y:.6g}): the closest smooth curve passes {exc.deviation * 1000:.3g} mm away "
                "(the points are noisier than the tolerance); raise paths.tolerance_m or the path's tolerance:"
            ) from None
        except FitError as exc:
            raise ConditionError(f"{where}: {names[a]}: the points from here cannot be smoothed: {exc}") from None
        info.iterations += leg.fits
        if leg.smoothing_m is not None:
            ells.append(leg.smoothing_m)
        if heading is not None:
            turn = float(_wrap(np.array(leg.theta0 - heading)))
            if abs(turn) >= math.radians(REVERSAL_DEG) and mode == SAMPLES:
                raise ConditionError(
                    f"{where}: {names[a]}: the path reverses here (it turns {math.degrees(abs(turn)):.0f} degrees): "
                    "mark the points reached in reverse (a negative v) or split the path here")
            if abs(turn) > 1e-9:
                corner = pins[j]
                assert corner is not None
                c = corner.point
                pieces.append(pivot_piece(float(c[0]), float(c[1]), heading, turn, opt.pivot_radius, opt.step))
                kept.append(Corner(a, turn, float(c[0]), float(c[1])))
                if caps is not None:
                    cap_s.append(sigma)
                    cap_v.append(float(caps[a]))
                sigma += pieces[-1].length
        theta0 = leg.theta0 if heading is None else heading + float(_wrap(np.array(leg.theta0 - heading)))
        for pc in leg.pieces:  # keep theta continuous across legs
            shift = theta0 - leg.theta0
            if shift:
                pc.theta = pc.theta + shift
            pieces.append(pc)
        heading = theta0 + (leg.theta1 - leg.theta0)
        sl = slice(a, b + 1)
        sig_pts[sl] = sigma + leg.sigma
        devs[sl] = np.maximum(devs[sl], leg.dev)
        for k, pin in ((a, pins[j]), (b, pins[j + 1])):  # a corner's own point against the corner
            if pin is not None:
                devs[k] = max(devs[k], float(math.hypot(*(p[k] - pin.point))))
        if caps is not None:
            cap_s.extend((sigma + leg.sigma).tolist())
            cap_v.extend(caps[sl].tolist())
        sigma += sum(pc.length for pc in leg.pieces)
    geo = Geometry(pieces)
    if caps is not None:
        cs = np.maximum.accumulate(np.asarray(cap_s))
        geo.cap_sigma = cs
        geo.cap_value = np.asarray(cap_v)
    if mode == GRID:
        _cap_turns(geo, info)
    info.deviation_m = float(devs.max())
    info.worst = int(np.argmax(devs))
    info.corners = tuple(kept)
    info.smoothing_m = tuple(ells)
    info.point_sigma = sig_pts
    info.extra["corner_scale_m"] = scale
    return geo, info
