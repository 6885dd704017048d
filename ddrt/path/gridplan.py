"""Reading a grid planner's plan: its cell, its axes, and where it turns.

A grid plan (every step one cell along an axis or a diagonal of one grid) is exact: its
staircase is no noise, so its corners are read from the cells, not from a scale set by a
noise estimate. The direction either side of a cell is the line through the cells within
GRID_CORNER_CELLS of it (and half that): six cells, so each half-scale side holds three cells
even along a diagonal (a side of two cells reads no direction: a 135 degree corner read so
is no corner, and the fit bends it to a 9 mm radius, crawled at the turn speed). Turns of 90
degrees and more turn in place at their cell's centre, a leg that runs straight into one held
along its run; staircases and 45 degree steps are smoothed (condition.py). A bend the fit
still makes tighter than GRID_TIGHT_CELLS cells of radius while turning GRID_TIGHT_TURN_DEG or
more there, or tighter than one cell at all, is turned in place too (`tight_bends`; a smaller
wiggle is cheaper driven than stopped for, and the sharp turns of a plan's 45 degree steps
stay smoothed): at the turn speed's bounded yaw acceleration any smoothed turn takes at least
sqrt(4 |turn| / accel) seconds (2.1 s for 90 degrees) and a bend that tight is taken well
below the asked speed, while a turn in place is a stop and about half a second. Five cells
is what measured fastest over the fuzzed plans (lab/path_inputs.py grid_fuzz_plan,
seeds 11-14, 150 each, within 1.3 x length / speed + 3 s): 1 cell 525 of 600, 5 cells 558,
8 cells 545 (wider bends turned in place stop more often than they save); 5 cells where the
bend turns 40 degrees or more, 553 (the turns of 10-15 degrees that the plain rule stopped for
belong to 45 degree steps, which are driven).
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from ddrt.path.corners import CornerPin, find_corners
from ddrt.path.geometry import Geometry

__all__ = ["GRID_PIVOT_DEG", "corner_pin", "grid_axis", "grid_cell", "grid_corners", "steps_back", "tight_bends"]

GRID_PIVOT_DEG = 67.5  # in a grid plan, turns of 90 degrees and more (90, 135, 180) pivot
GRID_CORNER_CELLS = 6.0  # a grid plan's corner scale: each half-scale side holds 3 cells even diagonally
GRID_CORNER_APART_CELLS = 2.0  # a grid plan's corners at least this far apart (cells)
GRID_TIGHT_CELLS = 5.0  # a grid plan's fit bending tighter than this radius (cells) turns in place there
GRID_TIGHT_TURN_DEG = 40.0  # if it turns by this much within that radius (or bends tighter than one cell)


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


def grid_corners(p: np.ndarray, u: np.ndarray, cell: float, threshold: float) -> tuple[float, list[tuple[int, float]]]:
    """(corner scale, corners (index, turn)) of a grid plan: turns by more than `threshold` and
    GRID_PIVOT_DEG, read over GRID_CORNER_CELLS cells and half that, GRID_CORNER_APART_CELLS apart."""
    scale = GRID_CORNER_CELLS * cell
    turn = max(threshold, math.radians(GRID_PIVOT_DEG))
    return scale, find_corners(p, u, scale, turn, apart=GRID_CORNER_APART_CELLS * cell)


def steps_back(p: np.ndarray) -> list[int]:
    """Points of a grid plan where it steps back the way it came (turned in place)."""
    d = np.diff(p, axis=0)
    seg = np.hypot(d[:, 0], d[:, 1])
    back = np.einsum("ij,ij->i", d[1:], d[:-1]) < -0.999 * seg[1:] * seg[:-1]
    return (np.flatnonzero(back) + 1).tolist()


def tight_bends(geo: Geometry, sig: np.ndarray | None, cell: float, corners: Sequence[int]) -> list[int]:
    """A grid plan's points nearest to where the fit bends tighter than GRID_TIGHT_CELLS cells of
    radius by GRID_TIGHT_TURN_DEG or more, or tighter than one cell at all (the sharpest point of
    each such bend; not already a corner; a small wiggle is cheaper driven than stopped for): a turn that sharp is
    slower driven than turned in place (turnspeed.py slows it well below the asked speed)."""
    s0 = 0.0
    found: list[int] = []
    assert sig is not None  # each point's progress on the reference
    for pc in geo.pieces:
        if not pc.pivot and len(pc.kappa):
            k = np.abs(pc.kappa)
            over = k > 1.0 / (GRID_TIGHT_CELLS * cell)
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
