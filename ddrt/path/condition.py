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
  the grid's axes, so the corridor is each point's cell. A staircase that a straight line
  crosses cell by cell is fitted as that line (ddrt/path/gridplan.py `straightened`; the
  corridor still measured from the cells). Its corners are read from those cells (the
  staircase is exact, not noise): where the direction of the lines through six cells either
  side, and three, turns by more than GRID_PIVOT_DEG (90, 135 and 180 degree turns; within a
  corridor of 2 cm or more, 4 cm cells, 135 and 180 only, 90 degree corners blended), the plan turns in
  place at that cell (its centre, or where two staircases' lines meet within it); corners
  may lie two cells apart. 45 degree steps are smoothed within the cells. A turn the fit
  still bends tighter than five cells' radius by 40 degrees or more (one cell where 90 degree
  corners blend; or tighter than a cell at all) is turned in place at its sharpest point too:
  that tight a turn is crawled (a 135 degree corner bent to 9 mm doubles a whole plan's
  time), while a turn in place costs a stop and about half a second. Smoothed turns of 25
  degrees or more are blended, smaller ones taken gently (ddrt/path/turnspeed.py).
- **samples**: anything denser. The points are samples of a curve with noise (a recording,
  a planner's output, an exported curve). The reference is a smoothing spline through them
  that stays within the tolerance of every point; genuine corners (the direction turns by
  more than `corner_pivot_deg` within a few tolerances of one point, at two scales, and the
  points round it lie on the two sides: ddrt/path/corners.py) become turns in place between
  separately fitted legs, each held on its side's line at the corner.

The smoothing spline through each leg, its choice of smoothing and how it keeps every point
within the tolerance are ddrt/path/smoothing.py's; this module decides what the legs are
(where the corners are, whether a loop closes) and joins them.

The reported deviation (`Conditioning.deviation_m`) is the largest distance from an input
point to the reference (for a grid plan, along the grid's axes: at most half a cell while
the reference crosses every planned cell).

Reversals, one rule for every kind of input: a direction that turns back (by more than
`corner_pivot_deg`, up to 180 degrees, within a corner's scale) is a corner like any other,
a turn in place where the file does not mark it, for waypoints, samples and grid plans alike:
the robot keeps facing the way it travels. To drive back instead (a cusp: stop and reverse),
the file marks the points reached in reverse with a negative v (reversal.py). A reversal whose
legs lie apart (a narrow U-turn) turns in place midway between them, or, legs up to three
tolerances apart, turns a quarter onto the cap across their ends and a quarter off it; a
wider one is a U-turn, fitted smooth. A fit that still stops and turns back gets a corner there.

Tolerance: `paths.tolerance_m` (or the path's `tolerance:`) is a number or `auto` (the
default): the tolerance set from the points' estimated noise (ddrt/path/noise.py), never
below 10 mm, so a noisy recording is smoothed as its noise needs. A number is kept to: where
the curve cannot stay within it without following the noise, the path is refused with the
tolerance that would work.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Sequence, TypeVar

import numpy as np

from ddrt.errors import DdrtError
from ddrt.path.corners import CornerPin, corner_scale, find_corners, line_turns, refine_corner
from ddrt.path.geometry import Geometry, GeometryOptions, Piece, line_piece, pivot_piece, polyline_geometry
from ddrt.path.gridplan import (
    GRID_CORNER_APART_CELLS, GRID_HAIR_CELLS, GridReading, corner_pin, grid_axis, grid_corners, read_grid, steps_back,
    straightened, tight_bends,
)
from ddrt.path.noise import TOLERANCE_FLOOR_M, arc_parameter, auto_tolerance, estimate_noise
from ddrt.path.smoothing import (
    CurveStops, EndPin, FitError, FitRequest, FittedLeg, ToleranceUnmet, along_axes, chord_length, fit_leg,
    staircase_noise,
)
from ddrt.path.turnspeed import turn_caps

__all__ = ["ConditionOptions", "Conditioning", "ConditionError", "ascending", "classify", "condition_polyline",
           "knot_spacing", "point_noise", "run_tolerance"]

_T = TypeVar("_T")
WAYPOINTS, SAMPLES, GRID = "waypoints", "samples", "grid"
GRID_TOLERANCE_CELLS = 0.5  # a grid plan's tolerance, in cells: the robot stays in the planned cells
NOISE_FLOOR_M = 2e-5  # below this the points are exact (an export): smooth to this level


class ConditionError(DdrtError, ValueError):
    """The polyline cannot be conditioned; the message names the point (line or key)."""


@dataclass(frozen=True, slots=True)
class ConditionOptions:
    tolerance: float | None = None  # m; None: auto (from the points' noise); 0: every point is a waypoint
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
    points: np.ndarray  # (n, 2) the input points (consecutive duplicates merged; a grid plan's on its cells' centres)
    names: Sequence[str]  # where each point came from ("line 7", "key 'points[3]'")
    deviation_m: float = 0.0  # largest distance of one of those points from the reference
    worst: int = 0  # that point's index
    noise_m: float = 0.0  # estimated noise of the points (1 sigma, lateral)
    grid_cell_m: float | None = None
    smoothing_m: tuple[float, ...] = ()  # smoothing length of each fitted leg
    corners: tuple[Corner, ...] = ()  # corners that became turns in place
    blended: tuple[tuple[float, float], ...] = ()  # a grid plan's blended turns: (start, end) progress
    point_sigma: np.ndarray | None = None  # progress of each point's foot on the reference
    spacing_m: float = 0.0  # median distance between consecutive points
    iterations: int = 0  # fits solved in total
    auto: bool = False  # the tolerance was set from the noise (`auto`)
    note: str = ""  # why points that look like more were read as waypoints (`waypoints_note`)
    extra: dict = field(default_factory=dict)

    def summary(self) -> str:
        if self.mode == WAYPOINTS:
            return (f"{len(self.points)} points as waypoints (median spacing {self.spacing_m * 1000:.0f} mm)"
                    + (f"; {self.note}" if self.note else ""))
        kind = (f"a grid plan ({self.grid_cell_m * 1000:.0f} mm cells)" if self.mode == GRID
                else "samples of a curve")
        how = "auto, from the noise; " if self.auto else ""
        return (f"{len(self.points)} points as {kind}: smoothed within {self.tolerance_m * 1000:.1f} mm "
                f"({how}largest deviation {self.deviation_m * 1000:.1f} mm at {self.names[self.worst]}; "
                f"noise ~{self.noise_m * 1000:.2f} mm), {len(self.corners)} corner(s) turned in place"
                + (f", {len(self.blended)} turn(s) blended" if self.mode == GRID else ""))


# --------------------------------------------------------------------------- classification


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def classify(p: np.ndarray, copt: ConditionOptions) -> tuple[str, float | None, GridReading | None]:
    """(mode, tolerance, a grid plan's grid: gridplan.read_grid) for the distinct points p (n, 2).
    The tolerance is None where it is `auto` and the points are samples (`resolve_tolerance`
    sets it from their noise)."""
    if len(p) < 4 or copt.tolerance == 0.0:
        return WAYPOINTS, copt.tolerance, None
    grid = read_grid(p)
    if grid is not None and grid.cell < copt.waypoint_spacing:
        given = copt.tolerance_given and copt.tolerance is not None
        floor = TOLERANCE_FLOOR_M if copt.tolerance is None else copt.tolerance
        return GRID, copt.tolerance if given else max(floor, GRID_TOLERANCE_CELLS * grid.cell), grid
    spacing = float(np.median(np.hypot(*np.diff(p, axis=0).T)))
    if spacing >= copt.waypoint_spacing:
        return WAYPOINTS, copt.tolerance, None
    return SAMPLES, copt.tolerance, None


def waypoints_note(p: np.ndarray, copt: ConditionOptions, spacing: float) -> str:
    """What a user may not expect of points read as waypoints for their spacing alone: a path's
    own `tolerance:` that no fit uses, or a grid plan whose cells are that large (each step
    then a waypoint, a staircase's every step turned in place; a polygon drawn on a grid, with
    no staircase, is taken as meant); empty otherwise."""
    if len(p) < 4 or copt.tolerance == 0.0 or spacing < copt.waypoint_spacing:
        return ""
    what = []
    if copt.tolerance_given and copt.tolerance is not None:
        what.append(f"its tolerance ({copt.tolerance * 1000:g} mm) is not used")
    grid = read_grid(p)
    steps = np.diff(grid.index, axis=0) if grid is not None else np.zeros((0, 2))
    jogs = np.all(steps[:-2] == steps[2:], axis=1) & np.any(steps[1:-1] != steps[:-2], axis=1)
    if np.any(jogs):  # a single step between two alike: a staircase, not a drawn polygon
        what.append("a grid plan of cells this large is driven cell by cell, a staircase's every step a corner")
    if not what:
        return ""
    return (f"{'; '.join(what)} (points {spacing:.3g} m apart, paths.waypoint_spacing_m = {copt.waypoint_spacing:g} m "
            f"or more, are waypoints, driven through exactly; to smooth them, raise paths.waypoint_spacing_m "
            f"above {spacing:.3g} m)")


def resolve_tolerance(tol: float | None, noise: float, n: int) -> float:
    """A classified tolerance, `auto` (None) set from the noise of n points (noise.auto_tolerance)."""
    return auto_tolerance(noise, n) if tol is None else tol


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
        t = line_turns(ext, ue, sc)[0][len(pre)]
        if not np.isfinite(t) or abs(t) > threshold:
            return None
    return pre, post



def _cap_turns(geo: Geometry, info: Conditioning) -> None:
    """A grid plan's gentle turns at a bounded yaw acceleration, its sharp ones blended
    (ddrt/path/turnspeed.py), merged with the points' own caps."""
    caps = turn_caps(geo.pieces)
    ts, tv = caps.sigma, caps.cap
    info.blended = caps.blended
    if geo.cap_sigma is not None and geo.cap_value is not None:
        tv = np.minimum(tv, np.interp(ts, geo.cap_sigma, geo.cap_value))
    geo.cap_sigma, geo.cap_value = ts, tv


def knot_spacing(spacing: float, tol: float, cell: float | None) -> float:
    """The spline's knot spacing: the points' spacing, but no closer than half the tolerance
    (finer detail than that is noise to be removed, and denser knots only cost time); a grid
    plan's cell."""
    return cell if cell is not None else max(spacing, 0.5 * tol, 1e-4)


def _noise(p: np.ndarray, cell: float | None = None) -> float:
    """The points' noise (noise.estimate_noise; a grid plan's, its staircase's), at least
    NOISE_FLOOR_M."""
    if cell is not None:
        try:
            return max(staircase_noise(p, cell), NOISE_FLOOR_M)
        except FitError as exc:
            raise ConditionError(str(exc)) from None
    return max(estimate_noise(p), NOISE_FLOOR_M)


def _as_planned(p: np.ndarray, grid: GridReading | None) -> np.ndarray:
    """A grid plan's points as the centres of the cells it was read as (gridplan.read_grid: the
    rounding they were written with taken off, so a plan reads the same on any grid, rounded
    or not); other points as they are."""
    return p if grid is None else grid.points()


def point_noise(pts: np.ndarray, copt: ConditionOptions) -> tuple[str, float]:
    """(mode, estimated lateral noise) of a polyline of distinct points, as condition_polyline
    finds them (for a cusp's estimate from two runs' points, ddrt/path/cusp.py)."""
    p = np.asarray(pts, dtype=float)
    mode, _, grid = classify(p, copt)
    if mode == WAYPOINTS:
        return mode, 0.0
    return mode, _noise(_as_planned(p, grid), None if grid is None else grid.cell)


def run_tolerance(pts: np.ndarray, copt: ConditionOptions, noise: float | None) -> float:
    """The tolerance condition_polyline would hold these points to (`auto` from `noise`, else
    from their own estimate); the floor for waypoints, which no fit holds to anything."""
    p = np.asarray(pts, dtype=float)
    mode, tol, grid = classify(p, copt)
    if mode == WAYPOINTS:
        return TOLERANCE_FLOOR_M if not tol else tol
    if noise is None:
        return resolve_tolerance(tol, _noise(_as_planned(p, grid), None if grid is None else grid.cell), len(p))
    return resolve_tolerance(tol, max(noise, NOISE_FLOOR_M), len(p))


@dataclass
class _Plan:
    """What the legs are fitted to: the points, their noise and tolerance, and the corners."""

    p: np.ndarray
    mode: str
    tol: float
    noise: float
    knot: float
    scale: float
    corners: list[tuple[int, float]]
    pins: list[tuple[EndPin | None, EndPin | None]]  # each leg's start and end
    wrap: tuple[np.ndarray, np.ndarray] | None
    axis: float | None
    opt: GeometryOptions
    fit_p: np.ndarray  # what the legs are fitted to: p, or a grid plan's straight runs put onto their lines


def _leg_pins(ends: tuple[EndPin | None, EndPin | None],
              corners: list[CornerPin]) -> list[tuple[EndPin | None, EndPin | None]]:
    """Each leg's start and end pins: the polyline's own ends, else a corner's point, with the
    side lines' directions as the legs' tangents there where the corner gives them (samples'
    corners, corners.py; a grid corner's straight runs, gridplan.py)."""
    starts: list[EndPin | None] = [ends[0]]
    stops: list[EndPin | None] = []
    for c in corners:
        held = c.into is not None and c.out is not None
        stops.append(EndPin(c.point, c.into if held else None, c.settle))
        starts.append(EndPin(c.point if c.cap is None or not held else c.cap, c.out if held else None, c.settle))
    stops.append(ends[1])
    return list(zip(starts, stops))


def ascending(items: Sequence[_T], key: Callable[[_T], int]) -> list[_T]:
    """The items whose key exceeds every key kept before it: corners in order along the points,
    no two at one point. A reversal's corner moves to its tip (corners.refine_corner), which
    may lie past the next corner found; each is compared with the last one kept, not with the
    one before it in the list, which may itself have been dropped."""
    out: list[_T] = []
    for item in items:
        if not out or key(item) > key(out[-1]):
            out.append(item)
    return out


def _fit_points(p: np.ndarray, grid: GridReading | None) -> tuple[np.ndarray, float | None]:
    """(the points the legs are fitted to, a grid plan's axis): a grid plan's staircases put on
    their lines (gridplan.straightened), read once for every replan of the same points `p` (on
    their cells' centres; the axis is read from them)."""
    if grid is None:
        return p, None
    axis = grid_axis(p)
    return straightened(p, grid.cell, axis), axis


def _plan(p: np.ndarray, mode: str, tol: float, cell: float | None, noise: float, opt: GeometryOptions,
          ends: tuple[EndPin | None, EndPin | None], forced: Sequence[int], fitted: tuple[np.ndarray, float | None]
          ) -> _Plan:
    """Where the corners are (along the distance the points stand for, corners.py; `forced`:
    points where a fit stopped and turned back, corners whatever their sides say), each leg's
    ends, and whether the polyline closes on itself. `fitted`: `_fit_points`."""
    u = chord_length(p) if mode == GRID else arc_parameter(p, noise)
    fit_p, axis = fitted
    spacing = float(np.median(np.diff(u)))
    knot = knot_spacing(spacing, tol, cell)
    threshold = math.radians(opt.corner_pivot_deg)
    if mode == GRID:
        assert cell is not None
        scale, corners = grid_corners(fit_p, u, cell, threshold, tol)
    else:
        scale = corner_scale(tol, noise, spacing)
        corners = find_corners(p, u, scale, threshold, noise)
    # Within a corner scale of an end pinned with a shared tangent the points were found smooth
    # by the cusp's own fit (ddrt/path/cusp.py): a turn found there is the end's short chord on noise.
    held0 = ends[0] is not None and ends[0].slope is not None
    held1 = ends[1] is not None and ends[1].slope is not None
    corners = [(k, t) for k, t in corners if not (held0 and u[k] < scale) and not (held1 and u[-1] - u[k] < scale)]
    if mode == GRID and forced:
        # Where a grid plan steps back, that cell is the corner: a turn read over windows that
        # straddle it is the same corner a cell or so early, and both kept leave a leg of one
        # step between them (a turn in place of a few degrees, or none, as the last bits fall).
        assert cell is not None
        near = (GRID_CORNER_APART_CELLS - GRID_HAIR_CELLS) * cell
        corners = [(k, t) for k, t in corners if all(k == f or abs(u[k] - u[f]) >= near for f in forced)]
    corners = sorted(corners + [(k, math.pi) for k in forced if all(k != c for c, _ in corners)])
    mids = [0.5 * (u[a] + u[b]) for (a, _), (b, _) in zip(corners[:-1], corners[1:])]
    bounds = list(zip([-math.inf, *mids], [*mids, math.inf]))
    if mode == GRID:  # a grid plan turns at a cell's centre: its corner is that point
        refined = [((k, t), (k, corner_pin(fit_p, u, k, scale))) for k, t in corners]
    else:
        refined = [((k, t), refine_corner(p, u, k, scale, tol, bounds[i])) for i, (k, t) in enumerate(corners)]
    # A forced corner (the fit turned back there) stays at its point whatever its sides say.
    refined = [((k, t), (k, CornerPin(p[k].copy()))) if pin is None and k in forced else ((at, t), (at, pin))
               for (k, t), (at, pin) in refined]
    kept = [((at, t), pin) for (_, t), (at, pin) in refined if pin is not None and 0 < at < len(p) - 1]
    kept = ascending(kept, key=lambda c: c[0][0])
    corners = [c for c, _ in kept]
    found = [pin for _, pin in kept]
    pinned = ends[0] is not None or ends[1] is not None
    wrap = _loop_wrap(p, knot, scale, threshold, tol, spacing) if not corners and not pinned else None
    pins = _leg_pins(ends, found)
    return _Plan(p, mode, tol, noise, knot, scale, corners, pins, wrap, axis, opt, fit_p)


class _LegStops(DdrtError):
    """A leg's fit stops and turns back at point `index` (of the whole polyline)."""

    def __init__(self, index: int) -> None:
        super().__init__(index)
        self.index = index


class _LegUnmet(DdrtError):
    """A leg's ToleranceUnmet, with the leg's first point (its index counts from there)."""

    def __init__(self, cause: ToleranceUnmet, first: int) -> None:
        super().__init__(str(cause))
        self.cause, self.first = cause, first


def _fit(plan: _Plan, j: int, a: int, b: int, where: str, names: Sequence[str]) -> FittedLeg:
    """Leg j (points a..b) of the plan, its ends held on the corners' side lines if it can be (else
    at the corners' points only); its failures as ConditionErrors naming the point."""
    start, end = plan.pins[j]
    loose = (_point_only(start, j > 0), _point_only(end, j < len(plan.pins) - 1))
    tries = [(start, end)] + ([loose] if loose[0] is not start or loose[1] is not end else [])
    for n, (s0, s1) in enumerate(tries):
        try:
            return fit_leg(FitRequest(plan.fit_p[a:b + 1], plan.tol, plan.noise, plan.knot, plan.opt, s0, s1,
                                      plan.wrap, plan.axis, None if plan.fit_p is plan.p else plan.p[a:b + 1]))
        except CurveStops as exc:
            first = len(plan.wrap[0]) if plan.wrap is not None else 0
            raise _LegStops(a + min(max(int(exc.index) - first, 0), b - a)) from None
        except ToleranceUnmet as exc:
            if n == len(tries) - 1:
                raise _LegUnmet(exc, a) from None
        except FitError as exc:
            raise ConditionError(f"{where}: {names[a]}: the points from here cannot be smoothed: {exc}") from None
    raise AssertionError("unreachable")


def _point_only(pin: EndPin | None, at_corner: bool) -> EndPin | None:
    """A corner's pin without its tangent (the polyline's own ends are kept as given)."""
    return EndPin(pin.point, None, pin.settle) if at_corner and pin is not None and pin.slope is not None else pin


def _assemble(plan: _Plan, caps: np.ndarray | None, info: Conditioning, where: str,
              names: Sequence[str]) -> Geometry:
    """Fit each leg and join them with a turn in place at each corner (any angle up to 180
    degrees: an unmarked reversal is a corner too); fills `info` with the points' progress,
    deviations and the corners kept."""
    p, opt = plan.p, plan.opt
    cuts = [0] + [k for k, _ in plan.corners] + [len(p) - 1]
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
        leg = _fit(plan, j, a, b, where, names)
        info.iterations += leg.fits
        if leg.smoothing_m is not None:
            ells.append(leg.smoothing_m)
        theta0 = leg.theta0
        if heading is not None:
            x1, x2 = _corner_ends(plan, j)
            joint, theta0, turns = _joint(x1, x2, heading, leg.theta0, opt)
            for turn, x, y in turns:
                kept.append(Corner(a, turn, x, y))
            for pc in joint:
                if caps is not None:
                    cap_s.append(sigma)
                    cap_v.append(float(caps[a]))
                pieces.append(pc)
                sigma += pc.length
        for pc in leg.pieces:  # keep theta continuous across legs
            shift = theta0 - leg.theta0
            if shift:
                pc.theta = pc.theta + shift
            pieces.append(pc)
            if pc.pivot:  # a short leg's own corner, driven as waypoints (smoothing._short)
                near = a + int(np.argmin(np.hypot(p[a:b + 1, 0] - pc.x[0], p[a:b + 1, 1] - pc.y[0])))
                kept.append(Corner(near, float(pc.theta[-1] - pc.theta[0]), float(pc.x[0]), float(pc.y[0])))
        heading = theta0 + (leg.theta1 - leg.theta0)
        sl = slice(a, b + 1)
        sig_pts[sl] = sigma + leg.sigma
        devs[sl] = np.maximum(devs[sl], leg.dev)
        for k, (x1, x2) in ((a, _corner_ends(plan, j)), (b, _corner_ends(plan, j + 1))):
            if x1 is not None and x2 is not None:  # a corner's own point against the corner
                devs[k] = max(devs[k], _segment_distance(p[k], x1, x2, plan.axis))
        if caps is not None:
            cap_s.extend((sigma + leg.sigma).tolist())
            cap_v.extend(caps[sl].tolist())
        sigma += sum(pc.length for pc in leg.pieces)
    geo = Geometry(pieces)
    if caps is not None:
        geo.cap_sigma = np.maximum.accumulate(np.asarray(cap_s))
        geo.cap_value = np.asarray(cap_v)
    info.deviation_m = float(devs.max())
    info.worst = int(np.argmax(devs))
    info.corners = tuple(kept)
    info.smoothing_m = tuple(ells)
    info.point_sigma = sig_pts
    return geo


def _corner_ends(plan: _Plan, j: int) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Where leg j - 1 ends and leg j starts (one point, or a reversal's cap across its legs);
    None for the polyline's own ends (and for pins the fit was given from outside)."""
    if j == 0 or j == len(plan.pins):
        return None, None
    end, start = plan.pins[j - 1][1], plan.pins[j][0]
    return (None if end is None else end.point), (None if start is None else start.point)


def _segment_distance(q: np.ndarray, x1: np.ndarray, x2: np.ndarray, axis: float | None = None) -> float:
    """From q to its foot on the segment x1-x2; for a grid plan (`axis`), along the grid's axes
    (the larger of the two), as its corridor is measured."""
    d = x2 - x1
    n2 = float(d @ d)
    t = min(max(float((q - x1) @ d) / n2, 0.0), 1.0) if n2 > 0.0 else 0.0
    e = q - x1 - t * d
    return float(math.hypot(*e)) if axis is None else float(along_axes(e[0], e[1], axis))


def _joint(x1: np.ndarray | None, x2: np.ndarray | None, heading: float, theta0: float,
           opt: GeometryOptions) -> tuple[list[Piece], float, list[tuple[float, float, float]]]:
    """The pieces from one leg's end (at x1, facing `heading`) to the next leg's start (at x2,
    facing theta0): a turn in place, or, where a reversal's legs lie farther apart than that
    can bridge (a cap, corners.py), a turn onto the cap, the cap, and a turn onto the leg. Also
    the next leg's heading kept continuous, and each turn (rad, x, y)."""
    assert x1 is not None and x2 is not None
    pieces: list[Piece] = []
    turns: list[tuple[float, float, float]] = []
    gap = x2 - x1
    length = float(math.hypot(*gap))
    if length > 1e-9:
        across = heading + float(_wrap(np.array(math.atan2(gap[1], gap[0]) - heading)))
        pieces, heading, turns = _pivot(x1, heading, across, opt)
        pieces.append(line_piece(float(x1[0]), float(x1[1]), heading, length, opt.step))
    final = heading + float(_wrap(np.array(theta0 - heading)))
    more, final, more_turns = _pivot(x2, heading, final, opt)
    return pieces + more, final, turns + more_turns


def _pivot(x: np.ndarray, heading: float, to: float,
           opt: GeometryOptions) -> tuple[list[Piece], float, list[tuple[float, float, float]]]:
    """A turn in place at x from `heading` to `to` (nothing for a turn below 1e-9 rad)."""
    turn = to - heading
    if abs(turn) <= 1e-9:
        return [], heading, []
    return ([pivot_piece(float(x[0]), float(x[1]), heading, turn, opt.pivot_radius, opt.step)], to,
            [(turn, float(x[0]), float(x[1]))])


def _needed(deviation: float) -> float:
    """A tolerance that holds a deviation, rounded up to half a millimetre."""
    return math.ceil(1.05 * deviation / 5e-4) * 5e-4


def _unmet(exc: ToleranceUnmet, plan: _Plan, a: int, where: str, names: Sequence[str]) -> ConditionError:
    """A number the points cannot be held to without following their noise, and what would do."""
    k = a + min(max(exc.index - (len(plan.wrap[0]) if plan.wrap is not None else 0), 0), len(names) - 1 - a)
    return ConditionError(
        f"{where}: {names[k]}: the reference cannot stay within {plan.tol:g} m of the point "
        f"({exc.x:.6g}, {exc.y:.6g}) without following the points' noise (~{plan.noise * 1000:.3g} mm): "
        f"the closest smooth curve passes {exc.deviation * 1000:.3g} mm away; a tolerance of "
        f"{_needed(exc.deviation):g} m would work (raise paths.tolerance_m or the path's tolerance:, "
        "or set it to auto)")


AUTO_RETRIES = 3  # `auto` widens itself this many times where a point is still out (an outlier)
MAX_REPLANS = 8  # fits of the whole polyline: widened tolerances and reversals found by the fit


def _turns_back(where: str, name: str) -> ConditionError:
    return ConditionError(f"{where}: {name}: the points turn back on themselves here and no turn in place "
                          "fits them: mark the points reached in reverse (a negative v) or split the path here")


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
    mode, given, grid = classify(p, copt)
    cell = None if grid is None else grid.cell
    p = _as_planned(p, grid)
    if mode == WAYPOINTS:
        geo, info = _waypoints(p, caps, opt, names, spacing, TOLERANCE_FLOOR_M if given is None else given)
        info.note = waypoints_note(p, copt, spacing)
        return geo, info
    nz = _noise(p, cell) if noise is None else max(noise, NOISE_FLOOR_M)
    tol = resolve_tolerance(given, nz, len(p))
    forced = steps_back(p) if mode == GRID else []
    tight: list[int] = []  # a grid plan's points where the fit bent too tight (gridplan.tight_bends): turned in place
    widened = 0
    fitted = _fit_points(p, grid)
    for attempt in range(MAX_REPLANS):
        info = Conditioning(mode, tol, p, names, noise_m=nz, grid_cell_m=cell, spacing_m=spacing,
                            auto=given is None and mode == SAMPLES)
        plan = _plan(p, mode, tol, cell, nz, opt, ends, forced + tight, fitted)
        info.extra["closed_loop"] = plan.wrap is not None
        try:
            geo = _assemble(plan, caps, info, where, names)
            more = tight_bends(geo, info.point_sigma, cell, tol, [k for k, _ in plan.corners]) if cell is not None else []
            if not more or attempt == MAX_REPLANS - 1:
                break
            tight.extend(more)
        except _LegStops as exc:
            if exc.index in forced or exc.index in (0, len(p) - 1):
                raise _turns_back(where, names[exc.index]) from None
            forced.append(exc.index)  # an unmarked reversal the corners missed: turned in place
        except _LegUnmet as exc:
            if given is not None or widened == AUTO_RETRIES:
                raise _unmet(exc.cause, plan, exc.first, where, names) from None
            tol = _needed(exc.cause.deviation)
            widened += 1
    else:
        raise _turns_back(where, names[forced[-1]])
    if mode == GRID:
        _cap_turns(geo, info)
    info.extra["corner_scale_m"] = plan.scale
    return geo, info


def _waypoints(p: np.ndarray, caps: np.ndarray | None, opt: GeometryOptions, names: Sequence[str],
               spacing: float, tol: float) -> tuple[Geometry, Conditioning]:
    """Straight segments through the points, corners turned in place or blended (geometry.py)."""
    info = Conditioning(WAYPOINTS, tol, p, names, spacing_m=spacing)
    geo = polyline_geometry([(float(a), float(b)) for a, b in p], None if caps is None else caps.tolist(), opt)
    if len(p) > 2:
        d = np.diff(p, axis=0)
        turn = _wrap(np.diff(np.arctan2(d[:, 1], d[:, 0])))
        sharp = np.abs(turn) > math.radians(opt.corner_pivot_deg)
        info.corners = tuple(Corner(int(i) + 1, float(turn[i]), float(p[i + 1, 0]), float(p[i + 1, 1]))
                             for i in np.flatnonzero(sharp))
        # Counted for the report from a degree on: collinear points written to a few decimals
        # meet at a few hundredths of a degree, blended but no turn to a reader.
        info.extra["blends"] = int(np.sum(~sharp & (np.abs(turn) >= math.radians(1.0))))
    return geo, info
