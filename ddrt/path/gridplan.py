"""Reading a grid planner's plan: its cell, its axes, its straight runs and where it turns.

A grid plan (every step one cell along an axis or a diagonal of one grid) is exact: its
staircase is no noise. A staircase that a straight line crosses cell by cell (one kind of step
never twice in a row, runs of the other differing by at most one, as a line's staircase steps:
`straight_runs`) is that line to a robot, so its cells are put onto the line before the fit
(`straightened`; the corridor is still measured from the cells). Fitted to the cells
themselves, the curve wiggled within them, and every wiggle was a turn slowed for at the grid
turn speed (turnspeed.py). A run of diagonals then a run along an axis is no line's staircase:
it is two runs and a 45 degree turn, left as it is.

Corners are read from the straightened cells, not from a scale set by a noise estimate: the
direction either side of a cell is the line through the cells within GRID_CORNER_CELLS of it
(and half that): six cells, so each half-scale side holds three cells even along a diagonal
(a side of two cells reads no direction: a 135 degree corner read so is no corner, and the fit
bends it to a 9 mm radius, crawled at the turn speed). Turns of 90 degrees and more turn in
place: at their cell's centre between straight runs, where two staircases' lines meet (within
the cell) between staircases; a leg that runs straight into a corner is held along its run.
Within a corridor of GRID_BLEND_CORRIDOR_M or more (half a 4 cm cell, or the path's own
tolerance), 90 degree corners are blended instead (only 135 and 180 degrees turn in place):
such a corner's radius can reach 3.4 corridors, and from 2 cm on that was faster than
stopping to turn in place on the fuzzed plans (python -m bench.grid_plans: from 3 cm cells,
257 plans faster and 16 slower; from 4 cm, 234 and 6).
45 degree steps are smoothed (condition.py) and blended (turnspeed.py). A bend the fit still
makes tighter than GRID_TIGHT_CELLS cells of radius while turning GRID_TIGHT_TURN_DEG or more
there (where the corridor blends 90 degree corners, one cell), or tighter than one cell at
all, is turned in place too (`tight_bends`): that tight a bend is crawled at the profile's
yaw rate and lateral acceleration, while a turn in place is a stop and about half a second;
a smaller bend is cheaper driven than stopped for. Over the fuzzed plans five cells is what
measured best.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from ddrt.path.corners import CornerPin, find_corners
from ddrt.path.geometry import Geometry

__all__ = ["GRID_PIVOT_DEG", "GridReading", "blends_square_corners", "coordinate_quantum", "corner_pin", "grid_axis",
           "grid_corners", "read_grid", "steps_back", "straight_runs", "straightened", "tight_bends"]

GRID_PIVOT_DEG = 67.5  # in a grid plan, turns of 90 degrees and more (90, 135, 180) pivot
GRID_BLEND_CORRIDOR_M = 0.02  # within a corridor this wide (half a 4 cm cell) 90 degree corners are blended
GRID_BLEND_PIVOT_DEG = 112.5  # there, turns of 135 and 180 degrees still pivot
GRID_CORNER_CELLS = 6.0  # a grid plan's corner scale: each half-scale side holds 3 cells even diagonally
GRID_CORNER_APART_CELLS = 2.0  # a grid plan's corners at least this far apart (cells)
GRID_TIGHT_CELLS = 5.0  # a grid plan's fit bending tighter than this radius (cells) turns in place there
GRID_TIGHT_TURN_DEG = 40.0  # if it turns by this much within that radius (or bends tighter than one cell)
STRAIGHT_MARGIN_CELLS = 0.49  # a run of cells is straight when one line passes this close to each (< half a cell)
STRAIGHT_MIN_STEPS = 3  # runs of fewer steps are left as they are (a corner's own cells)
GRID_ROUNDING_CELLS = 0.05  # coordinates rounded to at most this much of a cell still read as a grid plan
GRID_HAIR_CELLS = 0.05  # margin on bounds a grid's points lie exactly on (the nearest other distances are 0.17 cells off)
MEET_CELLS = 0.4  # two runs' lines meeting this close to their shared cell (along the axes) meet there
_LINE_ANGLES = np.radians(np.linspace(-40.0, 40.0, 321))  # lines tried about a run's chord (0.25 degree steps)
_FINE_ANGLES = np.radians(np.linspace(-0.25, 0.25, 101))  # and then about the best of those


_QUANTA = sorted((base * 10.0 ** -d for d in range(10) for base in (1.0, 0.0254, 0.3048)), reverse=True)  # m, in, ft


def coordinate_quantum(p: np.ndarray) -> float:
    """The step the points' coordinates were rounded to when they were written (a power of ten
    of a metre, an inch or a foot: a planner writes its cell centres to so many decimals), the
    coarsest every coordinate is a multiple of; 0.0 if none is (floats as computed)."""
    for q in _QUANTA:
        r = p / q
        if np.all(np.abs(r - np.round(r)) <= 1e-6):
            return q
    return 0.0


@dataclass(frozen=True)
class GridReading:
    """A grid plan read as its grid: each point's cell (integer indices along the grid's axes)
    and the grid that puts the cells nearest to the points (least squares): its cell, the
    direction of its first axis and the centre of cell (0, 0)."""

    cell: float
    axis: float
    origin: np.ndarray
    index: np.ndarray  # (n, 2) integers

    def points(self) -> np.ndarray:
        """The cells' centres: the points as planned, without the rounding they were written with."""
        c, s = math.cos(self.axis), math.sin(self.axis)
        return self.origin + self.cell * (self.index @ np.array([[c, s], [-s, c]]))


def read_grid(p: np.ndarray) -> GridReading | None:
    """A grid plan given cell by cell (every step one cell along an axis or a diagonal of one
    grid, which may be rotated), read as its grid; None for other points. Each step may be off
    by the error its coordinates' rounding puts in it (`coordinate_quantum`: up to sqrt(2)
    quanta, a quantum of up to GRID_ROUNDING_CELLS of a cell: the millimetre from 2 cm cells),
    so a plan written to a few decimals on a rotated grid still reads as one, and the
    grid is fitted to every point, so no one step's rounding tilts or stretches it. Each point
    lies within one quantum of its cell's centre (a rounded plan's within half of one and the
    fit's error, at most 0.83 quanta over 20000 fuzzed plans of 4-8 points): points the grid
    would move further, a recording's or a densified arc's, are not its cells."""
    d = np.diff(p, axis=0)
    if len(d) < 3:
        return None
    length = np.hypot(d[:, 0], d[:, 1])
    c = float(length.min())
    if not c > 0.0:
        return None
    if not np.all((np.abs(length - c) <= 0.16 * c) | (np.abs(length - c * math.sqrt(2.0)) <= 0.16 * c)):
        return None  # beyond any rounding allowed for (2 slacks, at most 0.155 c): a recording, at once
    q = coordinate_quantum(p)
    # Rounding finer than GRID_ROUNDING_CELLS of a cell is allowed for; coarser, a point's offset
    # of one quantum may be meant (a recording's legs 1 mm apart at 1 cm spacing, written in mm).
    # The cell is at most the shortest step and the rounding it may be short by.
    rounding = q if q <= GRID_ROUNDING_CELLS * (c + 1.01 * math.sqrt(2.0) * q) else 0.0
    slack = max(1e-3 * c, 1.01 * math.sqrt(2.0) * rounding)
    along = np.abs(length - c) <= 2.0 * slack  # c itself may be short by one slack
    diag = np.abs(length - c * math.sqrt(2.0)) <= 2.0 * slack
    if not np.all(along | diag) or np.any(along & diag):
        return None
    ang = np.arctan2(d[:, 1], d[:, 0]) - np.where(along, 0.0, 0.25 * math.pi)  # each step's axis
    mean = 0.25 * math.atan2(float(np.mean(np.sin(4.0 * ang))), float(np.mean(np.cos(4.0 * ang))))
    first = mean + 0.5 * math.pi * round((float(ang[0]) - mean) / (0.5 * math.pi))  # the axis nearest the first step
    k = (np.arctan2(d[:, 1], d[:, 0]) - first) / (0.25 * math.pi)
    kr = np.round(k)
    if np.max(np.abs(k - kr)) > max(1e-3, 2.0 * slack / c / (0.25 * math.pi)):
        return None
    # Steps an odd number of eighths of a turn from the axis are diagonal, the others along it.
    if not np.array_equal((kr.astype(np.int64) % 2) == 1, diag):
        return None
    cs, sn = math.cos(first), math.sin(first)
    cell_steps = float(np.median(np.where(along, length, length / math.sqrt(2.0))))
    steps = np.round((d @ np.array([[cs, -sn], [sn, cs]])) / cell_steps)
    index = np.vstack(([0, 0], np.cumsum(steps, axis=0))).astype(np.int64)
    # p = origin + a * index + b * index rotated a quarter turn, in least squares (a similarity).
    i, j = index[:, 0].astype(float), index[:, 1].astype(float)
    ones, zeros = np.ones_like(i), np.zeros_like(i)
    m = np.vstack((np.column_stack((ones, zeros, i, -j)), np.column_stack((zeros, ones, j, i))))
    sol = np.linalg.lstsq(m, np.concatenate((p[:, 0], p[:, 1])), rcond=None)[0]
    cell, axis = float(math.hypot(sol[2], sol[3])), float(math.atan2(sol[3], sol[2]))
    grid = GridReading(cell, axis, sol[:2].copy(), index)
    if np.max(np.abs(grid.points() - p)) > max(1e-3 * c, rounding):  # the steps add up to no one grid
        return None
    return grid


def grid_axis(p: np.ndarray) -> float:
    """The direction of a grid plan's first axis (its steps are along it, across it or
    diagonal): the one nearest its first step."""
    found = read_grid(p)
    assert found is not None, "grid_axis of points that are no grid plan"
    return found.axis


def blends_square_corners(corridor: float) -> bool:
    """Whether a grid plan smoothed within `corridor` (its tolerance: half a cell, or the path's
    own) blends its 90 degree corners: a blended corner's radius is at most 3.4 corridors, and
    from 2 cm on (4 cm cells) that is faster than stopping to turn in place on the fuzzed plans
    (python -m bench.grid_plans; within 1 cm, every 2 cm cell, it was slower on the whole)."""
    return corridor >= GRID_BLEND_CORRIDOR_M * (1.0 - 1e-3)  # a cell read from rounded points


def grid_corners(p: np.ndarray, u: np.ndarray, cell: float, threshold: float,
                 corridor: float) -> tuple[float, list[tuple[int, float]]]:
    """(corner scale, corners (index, turn)) of a grid plan smoothed within `corridor`: turns by
    more than `threshold` and GRID_PIVOT_DEG (GRID_BLEND_PIVOT_DEG where the corridor blends 90
    degree corners), read over GRID_CORNER_CELLS cells and half that, GRID_CORNER_APART_CELLS apart."""
    # A grid's points lie whole cells (and diagonals) apart, exactly on these bounds: a hair over
    # the scale and under the spacing keeps a point six cells off inside the window and corners
    # two cells apart both, whatever the last bits of the coordinates (else they pick the corners).
    scale = (GRID_CORNER_CELLS + GRID_HAIR_CELLS) * cell
    turn = max(threshold, math.radians(GRID_BLEND_PIVOT_DEG if blends_square_corners(corridor) else GRID_PIVOT_DEG))
    return scale, find_corners(p, u, scale, turn, apart=(GRID_CORNER_APART_CELLS - GRID_HAIR_CELLS) * cell)


def steps_back(p: np.ndarray) -> list[int]:
    """Points of a grid plan where it steps back the way it came (turned in place)."""
    d = np.diff(p, axis=0)
    seg = np.hypot(d[:, 0], d[:, 1])
    back = np.einsum("ij,ij->i", d[1:], d[:-1]) < -0.999 * seg[1:] * seg[:-1]
    return (np.flatnonzero(back) + 1).tolist()


def tight_bends(geo: Geometry, sig: np.ndarray | None, cell: float, corridor: float, corners: Sequence[int]) -> list[int]:
    """A grid plan's points nearest to where the fit bends tighter than GRID_TIGHT_CELLS cells of
    radius by GRID_TIGHT_TURN_DEG or more (where the corridor blends 90 degree corners, one
    cell), or tighter than one cell at all (the sharpest point of
    each such bend; not already a corner; a small wiggle is cheaper driven than stopped for): a turn that sharp is
    slower driven than turned in place (turnspeed.py slows it well below the asked speed)."""
    s0 = 0.0
    found: list[int] = []
    assert sig is not None  # each point's progress on the reference
    for pc in geo.pieces:
        if not pc.pivot and len(pc.kappa):
            k = np.abs(pc.kappa)
            over = k > 1.0 / ((1.0 if blends_square_corners(corridor) else GRID_TIGHT_CELLS) * cell)
            edges = np.flatnonzero(np.diff(over.astype(np.int8))) + 1
            for a, b in zip(np.concatenate(([0], edges)).tolist(), np.concatenate((edges, [len(k)])).tolist()):
                turn = abs(float(np.sum(pc.kappa[a:b - 1] * np.diff(pc.s[a:b])))) if b - a > 1 else 0.0
                if over[a] and (turn >= math.radians(GRID_TIGHT_TURN_DEG) or k[a:b].max() > 1.0 / cell):
                    at = s0 + float(pc.s[a + int(np.argmax(k[a:b]))])
                    i = int(np.argmin(np.abs(sig - at)))
                    if 0 < i < len(sig) - 1 and i not in corners and i not in found:
                        found.append(i)
        s0 += pc.length
    return found


def _run_direction(p: np.ndarray, sel: np.ndarray) -> np.ndarray | None:
    """The unit direction of the cells `sel` where they run straight (every step the same, at
    least two steps); None for a staircase or a shorter side."""
    d = np.diff(p[sel], axis=0)
    if len(d) < 2 or not np.allclose(d, d[0], rtol=0.0, atol=1e-9 * float(np.abs(d[0]).max())):
        return None
    return d[0] / float(np.hypot(*d[0]))


def corner_pin(p: np.ndarray, u: np.ndarray, k: int, scale: float) -> CornerPin:
    """A grid corner at its cell's centre; a leg whose cells run straight into it (or out of it)
    for half the corner scale is held there along that run. Left free, such a leg's end hooks
    round the corner (the bench's 10 cm plan: 27 mm RMS from its staircase over the metre after
    its 98 degree corner, against 13 mm held); a staircase side is left free (held along its
    mean line, the leg bends harder than the corner does)."""
    before = np.flatnonzero((u >= u[k] - 0.5 * scale) & (u <= u[k]))
    after = np.flatnonzero((u >= u[k]) & (u <= u[k] + 0.5 * scale))
    into, out = _run_direction(p, before), _run_direction(p, after)
    if into is None or out is None:
        return CornerPin(p[k].copy())
    return CornerPin(p[k].copy(), into, out)



def _line_fit(g: np.ndarray, chord: np.ndarray | None = None) -> tuple[float, np.ndarray, float]:
    """(deviation, unit normal, offset) of the line nearest to every cell centre `g` (grid units)
    along the grid's axes: for a line of normal n through offset o, a centre c is |n.c - o| /
    (|n_x| + |n_y|) from it that way, so the best offset for a direction is the midrange, and
    the direction is searched within 40 degrees of the run's chord (`chord`, else g[-1] - g[0]).
    Only the extremes count, so `g` may be just the run's convex hull."""
    d = g[-1] - g[0] if chord is None else chord
    best = math.atan2(float(d[1]), float(d[0]))
    for angles in (_LINE_ANGLES, _FINE_ANGLES):
        phi = best + angles
        nx, ny = -np.sin(phi), np.cos(phi)
        o = nx[:, None] * g[None, :, 0] + ny[:, None] * g[None, :, 1]
        spread = 0.5 * (o.max(axis=1) - o.min(axis=1)) / (np.abs(nx) + np.abs(ny))
        k = int(np.argmin(np.round(spread, 12)))  # of directions equally near, the first (not the last bit's pick)
        best = float(phi[k])
    return float(spread[k]), np.array([nx[k], ny[k]]), 0.5 * float(o[k].max() + o[k].min())


def _hull(xy: list[list[float]], idx: list[int]) -> list[int]:
    """The indices among `idx` of the convex hull's corners of points `xy[idx]` (collinear
    points dropped): a run's line fit reads only its extremes, so a run grown a cell at a time
    refits over its few hull corners instead of every cell."""
    pts = sorted(set(idx), key=lambda k: xy[k])
    if len(pts) < 3:
        return pts

    def turns_left(o: int, a: int, b: int) -> bool:
        (ox, oy), (ax, ay), (bx, by) = xy[o], xy[a], xy[b]
        return (ax - ox) * (by - oy) - (ay - oy) * (bx - ox) > 0.0

    lower: list[int] = []
    upper: list[int] = []
    for k in pts:
        while len(lower) >= 2 and not turns_left(lower[-2], lower[-1], k):
            lower.pop()
        lower.append(k)
    for k in reversed(pts):
        while len(upper) >= 2 and not turns_left(upper[-2], upper[-1], k):
            upper.pop()
        upper.append(k)
    return lower[:-1] + upper[:-1]


def _onto(g: np.ndarray, n: np.ndarray, off: float) -> np.ndarray:
    """Each centre moved onto the line along a diagonal of its cell (the nearest point of the
    line along the grid's axes)."""
    lam = (off - g @ n) / (abs(n[0]) + abs(n[1]))
    return g + lam[:, None] * np.sign(n)[None, :]


def _advance(n: np.ndarray) -> np.ndarray:
    """The vector w whose dot product with a step between two centres is how far the step
    advances along the line of unit normal `n` once both centres are moved onto it (`_onto`):
    the advance does not depend on the line's offset and is linear in the step, so a run's steps
    all advance one way exactly when the corners of their hull do."""
    t = np.array([n[1], -n[0]])
    return t - n * float(np.sign(n) @ t) / (abs(n[0]) + abs(n[1]))


def _stepped(steps: list[tuple[int, int]]) -> bool:
    """Whether cells stepping `steps` (integer pairs) are a staircase with a whole run of the
    commoner step between two rarer ones (a single rarer step between two runs is a jog, not a
    slope)."""
    kinds = sorted(set(steps))
    return len(kinds) == 2 and min(steps.count(k) for k in kinds) >= 2


def _rare(steps: list[tuple[int, int]]) -> tuple[int, int] | None:
    """The rarer of a staircase's two kinds of step (`steps`: integer pairs): the one that never
    comes twice in a row, between runs of the other that differ by at most one (the first and
    last may be shorter); the less frequent where both would do. None for one kind of step or
    no staircase."""
    kinds = sorted(set(steps))
    if len(kinds) != 2:
        return None
    for rare in sorted(kinds, key=steps.count):
        runs: list[int] = [0]
        for k, st in enumerate(steps):
            if st != rare:
                runs[-1] += 1
            elif k > 0 and steps[k - 1] == rare:
                break  # two in a row
            else:
                runs.append(0)
        else:
            inner = runs[1:-1]
            if not inner or (max(inner) - min(inner) <= 1 and max(runs[0], runs[-1]) <= min(inner) + 1):
                return rare
    return None


@dataclass
class _RarerRuns:
    """`_rare`'s reading of a growing run for one candidate rarer step, a step at a time: the
    runs of the other step before, between and after its occurrences."""

    rare: tuple[int, int]
    first: int = 0  # steps before the first rare one
    last: int = 0  # steps since the last rare one
    inner_min: int = sys.maxsize
    inner_max: int = -1  # no run between two rare steps yet
    seen: bool = False
    prev: bool = False  # the last step was the rare one
    twice: bool = False  # it came twice in a row

    def add(self, step: tuple[int, int]) -> None:
        """Counts one more step of the run."""
        if step != self.rare:
            self.last += 1
            self.prev = False
            return
        self.twice |= self.prev
        if self.seen:
            self.inner_min = min(self.inner_min, self.last)
            self.inner_max = max(self.inner_max, self.last)
        else:
            self.first, self.seen = self.last, True
        self.last, self.prev = 0, True

    def holds(self) -> bool:
        """Whether the steps so far are a line's staircase with `rare` as its rarer step."""
        if self.twice:
            return False
        if self.inner_max < 0:
            return True
        return self.inner_max - self.inner_min <= 1 and max(self.first, self.last) <= self.inner_min + 1


@dataclass
class _StairWindow:
    """Whether a run's steps, given one at a time, step as a straight line's staircase does: one
    kind of step, or two where the rarer one never comes twice in a row and the runs of the
    other between them differ by at most one (the first and last may be shorter; `_rare`). A
    run of diagonals then a run along an axis (a planner's detour round a corner, or its choice
    among equally short plans) is not one, however near a line its cells lie: it is two runs and
    a 45 degree turn. Read as the run grows, so growing a run of n cells costs n steps, not n^2."""

    steps: list[tuple[int, int]] = field(default_factory=list)
    kinds: list[tuple[int, int]] = field(default_factory=list)
    readings: list[_RarerRuns] = field(default_factory=list)

    def add(self, step: tuple[int, int]) -> bool:
        """Adds a step; whether the steps so far are a staircase."""
        self.steps.append(step)
        if step not in self.kinds:
            self.kinds.append(step)
            if len(self.kinds) == 2:
                self.readings = [_RarerRuns(k) for k in self.kinds]
                for st in self.steps:
                    for r in self.readings:
                        r.add(st)
                return any(r.holds() for r in self.readings)
        if len(self.kinds) != 2:
            return len(self.kinds) == 1
        for r in self.readings:
            r.add(step)
        return any(r.holds() for r in self.readings)


def straight_runs(g: np.ndarray, margin: float = STRAIGHT_MARGIN_CELLS) -> list[tuple[int, int, np.ndarray]]:
    """A grid plan's cells (grid units) cut, greedily from its start, into the longest runs one
    line passes within `margin` cells of (along the axes) while the cells advance along it: the
    staircases a planner leaves of a straight line. (first, last, the run's centres on that line)
    for runs of at least STRAIGHT_MIN_STEPS steps; consecutive runs share their end cell. A run
    grows a cell at a time reading a few points a cell, not the whole run: its line is refitted
    over its hull's corners and its advance along the line read at its steps' hull's corners
    (`_hull`, `_advance`); its cells are put onto the line once it stops growing."""
    out: list[tuple[int, int, np.ndarray]] = []
    d = np.diff(g, axis=0)
    plan_steps = [(int(a), int(b)) for a, b in np.round(d)]
    xy, dxy = g.tolist(), d.tolist()
    i, n = 0, len(g)
    while i < n - 1:
        j, line = i + 1, None
        window, hull, moves = _StairWindow(), [i, i + 1], [i]
        window.add(plan_steps[i])
        while j + 1 < n:
            if not window.add(plan_steps[j]):
                break
            hull, moves = _hull(xy, hull + [j + 1]), _hull(dxy, moves + [j])
            dev, nrm, off = _line_fit(g[hull], g[j + 1] - g[i])
            along = d[moves] @ _advance(nrm)
            if dev > margin or not (np.all(along > 0.0) or np.all(along < 0.0)):
                break
            j, line = j + 1, (nrm, off)
        a = i
        if line is not None:
            fit = _onto(g[i:j + 1], *line)
            # A rarer step at either end may be the first of a run of its own (a diagonal run
            # after a straight one): it is left to the cells between the runs.
            steps = plan_steps[i:j]
            rare = _rare(steps)
            while rare is not None and j - i > STRAIGHT_MIN_STEPS and steps[j - 1 - i] == rare:
                j -= 1
            a = 1 if i == 0 and rare is not None and steps[0] == rare else i  # the plan's start stays
            if j - a >= STRAIGHT_MIN_STEPS and _stepped(plan_steps[a:j]):
                out.append((a, j, fit[a - i:j - i + 1]))
        i = j
    return out


def _meet(a: np.ndarray, b: np.ndarray) -> np.ndarray | None:
    """Where the line through a[0], a[-1] meets the one through b[0], b[-1]; None if parallel."""
    da, db = a[-1] - a[0], b[-1] - b[0]
    den = float(da[0] * db[1] - da[1] * db[0])
    if abs(den) < 1e-9 * float(np.hypot(*da) * np.hypot(*db)):
        return None
    r = b[0] - a[0]
    return a[0] + float(r[0] * db[1] - r[1] * db[0]) / den * da


def straightened(p: np.ndarray, cell: float, axis: float) -> np.ndarray:
    """A grid plan's points with each straight run's cells (`straight_runs`) moved onto its
    line: what the smoothing is fitted to, so a staircase becomes the straight line it stands
    for (fitted to the cells themselves, it wiggles within them, and every wiggle is a turn
    slowed for, ddrt/path/turnspeed.py). A cell where two runs meet goes where their lines
    meet if that lies within the cell (a corner turned there leaves both legs on their lines),
    else midway between its places on both. The corridor is still measured from the cells."""
    c, s = math.cos(axis), math.sin(axis)
    rot = np.array([[c, -s], [s, c]])  # grid units -> the plan's frame
    g = ((p - p[0]) @ rot) / cell
    q = g.copy()
    runs = straight_runs(g)
    for a, b, on in runs:
        q[a + 1:b] = on[1:-1]
        q[a], q[b] = (on[0], on[-1]) if a > 0 else (g[a], on[-1])
    for (_, b0, on0), (a1, _, on1) in zip(runs[:-1], runs[1:]):
        if b0 == a1:
            x = _meet(on0, on1)
            q[a1] = x if x is not None and np.max(np.abs(x - g[a1])) <= MEET_CELLS else 0.5 * (on0[-1] + on1[0])
    q[0], q[-1] = g[0], g[-1]  # the plan's own ends stay
    return p[0] + cell * (q @ rot.T)
