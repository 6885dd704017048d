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

The smoothing spline. Each leg is a uniform cubic B-spline in the input's chord length u
(knots at the median point spacing), fitted by penalised least squares (a P-spline):

    minimise  sum_i w_i |r(u_i) - p_i|^2 + sum_j lambda_j (third difference of the coefficients)_j^2

with w_i the arc length each point stands for. The third-difference penalty approximates
l^6 * integral |r'''|^2 du (lambda = l^6 / knot^5), so `l` is a smoothing length: features
shorter than l are removed, and the penalty bears on the rate of change of curvature, which
is what the yaw acceleration d(omega)/dt = v^2 d(kappa)/ds sees. A cubic B-spline is C2, so
the curvature is continuous. The normal equations are banded (half-bandwidth 3) and solved
by a banded LDL^T factorisation in plain Python floats (numpy has no banded solver; about
1 us per coefficient).

Choosing the smoothing (why not "as smooth as the tolerance allows": that would bend an
exact export of a figure-eight by the whole tolerance):
1. the noise is estimated from a light fit (l = 3 knots): sigma = 1.4826 MAD of the lateral
   residuals, divided by the share of white noise such a fit leaves;
2. per leg, the largest l on a sqrt(2) ladder whose RMS lateral residual stays within
   1.1 sigma (the discrepancy principle: remove the noise, keep the curve; the shape bias
   that remains is a fraction of the noise);
3. the tolerance is then enforced point by point: wherever a point lies farther than
   `tolerance` from the curve, the penalty is lowered four-fold around it (and, at the
   lowest smoothing, the point's weight raised) and the leg is fitted again, until every
   point is within tolerance. A tolerance no smooth curve can meet (far below the noise)
   is refused naming the point's line.

The reported deviation (`Conditioning.deviation_m`) is the largest distance from an input
point to the reference (for a grid plan, along the grid's axes: at most half a cell while
the reference crosses every planned cell).

Reversals: in samples a corner that turns by 150 degrees or more is a cusp (the recording
drove back the way it came). Unless its points are marked as reached in reverse (spec.py), it is refused naming the
line; a turn in place there is a different motion, which the file would have to say
(split it into two paths there).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from ddrt.path.geometry import Geometry, GeometryOptions, Piece, line_piece, pivot_piece, polyline_geometry
from ddrt.path.turnspeed import turn_caps

__all__ = ["ConditionOptions", "Conditioning", "ConditionError", "EndPin", "classify", "condition_polyline",
           "knot_spacing", "point_noise"]

WAYPOINTS, SAMPLES, GRID = "waypoints", "samples", "grid"
REVERSAL_DEG = 150.0  # a corner this sharp in samples is a cusp: the path reverses
GRID_PIVOT_DEG = 112.5  # in a grid plan, turns sharper than 90 degrees (135, 180) pivot
GRID_TOLERANCE_CELLS = 0.5  # a grid plan's tolerance, in cells: the robot stays in the planned cells
NOISE_FLOOR_M = 2e-5  # below this the points are exact (an export): smooth to this level
DISCREPANCY = 1.1  # RMS lateral residual allowed, in estimated noise sigmas
MAX_SMOOTHING_M = 4.0  # longest smoothing length tried
MAX_SMOOTHING_KNOTS = 40.0  # and at most this many knots (beyond, the normal equations lose precision)
_FIX_WEIGHT = 1e6  # weight (relative to the largest) of a leg end fixed at a corner


class ConditionError(ValueError):
    """The polyline cannot be conditioned; the message names the point (line or key)."""


class _Cusp(Exception):
    """The fitted curve stops (zero speed) at `index`: a u value, or a point's index in its leg."""

    def __init__(self, index: float) -> None:
        super().__init__(index)
        self.index = index


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


# --------------------------------------------------------------------------- the spline


def _basis(t: np.ndarray, der: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The four uniform cubic B-spline weights (or their t-derivatives) at local t in [0, 1]."""
    if der == 0:
        t2, t3 = t * t, t * t * t
        s = 1.0 - t
        return s * s * s / 6.0, (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0, (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0, t3 / 6.0
    if der == 1:
        t2 = t * t
        s = 1.0 - t
        return -0.5 * s * s, 1.5 * t2 - 2.0 * t, -1.5 * t2 + t + 0.5, 0.5 * t2
    if der == 2:
        return 1.0 - t, 3.0 * t - 2.0, 1.0 - 3.0 * t, t
    raise ValueError(der)


class _Spline:
    """A uniform cubic B-spline r(u), u in [0, length], with (nc, 2) coefficients."""

    def __init__(self, knot: float, n_int: int, length: float) -> None:
        self.knot = knot
        self.n_int = n_int
        self.length = length
        self.coef = np.zeros((n_int + 3, 2))

    def locate(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        q = np.asarray(u, dtype=float) / self.knot
        j = np.clip(np.floor(q), 0, self.n_int - 1).astype(np.intp)
        return j, q - j

    def eval(self, u: np.ndarray, der: int = 0) -> tuple[np.ndarray, np.ndarray]:
        j, t = self.locate(u)
        b = _basis(t, der)
        c = self.coef
        x = b[0] * c[j, 0] + b[1] * c[j + 1, 0] + b[2] * c[j + 2, 0] + b[3] * c[j + 3, 0]
        y = b[0] * c[j, 1] + b[1] * c[j + 1, 1] + b[2] * c[j + 2, 1] + b[3] * c[j + 3, 1]
        if der:
            scale = self.knot ** -der
            x, y = x * scale, y * scale
        return x, y


def _ldl_band3(d0: list[float], d1: list[float], d2: list[float], d3: list[float],
               bx: list[float], by: list[float]) -> tuple[list[float], list[float]]:
    """Solve A z = b (two right-hand sides) for symmetric positive definite A given by its
    diagonal d0 and super-diagonals d1, d2, d3 (each padded to len(d0)): banded LDL^T.

    Plain floats: numpy has no banded solver, and a Python loop over numpy scalars would be
    slower than one over floats."""
    n = len(d0)
    D = [0.0] * n
    l1 = [0.0] * n  # L[i+1, i]
    l2 = [0.0] * n  # L[i+2, i]
    l3 = [0.0] * n  # L[i+3, i]
    # Rolling values of the three previous columns: (D, l1, l2, l3) at i-1, i-2, i-3.
    Da = Db = Dc = 0.0
    a1 = a2 = a3 = 0.0  # column i-1: l1, l2, l3
    b2 = b3 = 0.0  # column i-2: l2, l3
    c3 = 0.0  # column i-3: l3
    for i in range(n):
        # Row i of L: L[i, i-1] = a1, L[i, i-2] = b2, L[i, i-3] = c3.
        di = d0[i] - a1 * a1 * Da - b2 * b2 * Db - c3 * c3 * Dc
        if not di > 0.0:
            raise ConditionError("the smoothing system is singular")
        v1 = d1[i] - a2 * a1 * Da - b3 * b2 * Db  # A[i+1, i] minus L[i+1, k] L[i, k] D_k
        v2 = d2[i] - a3 * a1 * Da
        n1, n2, n3 = v1 / di, v2 / di, d3[i] / di
        D[i], l1[i], l2[i], l3[i] = di, n1, n2, n3
        # Shift: column i becomes i-1, and so on.
        Dc, c3 = Db, b3
        Db, b2, b3 = Da, a2, a3
        Da, a1, a2, a3 = di, n1, n2, n3
    # Forward: L y = b.
    zx = [0.0] * n
    zy = [0.0] * n
    x1 = x2 = x3 = y1 = y2 = y3 = 0.0
    for i in range(n):
        k1 = l1[i - 1] if i >= 1 else 0.0
        k2 = l2[i - 2] if i >= 2 else 0.0
        k3 = l3[i - 3] if i >= 3 else 0.0
        xv = bx[i] - k1 * x1 - k2 * x2 - k3 * x3
        yv = by[i] - k1 * y1 - k2 * y2 - k3 * y3
        zx[i], zy[i] = xv, yv
        x3, x2, x1 = x2, x1, xv
        y3, y2, y1 = y2, y1, yv
    # Diagonal and backward: L^T z = D^-1 y.
    x1 = x2 = x3 = y1 = y2 = y3 = 0.0
    for i in range(n - 1, -1, -1):
        inv = 1.0 / D[i]
        k1, k2, k3 = l1[i], l2[i], l3[i]
        xv = zx[i] * inv - k1 * x1 - k2 * x2 - k3 * x3
        yv = zy[i] * inv - k1 * y1 - k2 * y2 - k3 * y3
        zx[i], zy[i] = xv, yv
        x3, x2, x1 = x2, x1, xv
        y3, y2, y1 = y2, y1, yv
    return zx, zy


_PEN = (1.0, -3.0, 3.0, -1.0)  # a third difference


class _LegFit:
    """Penalised least squares of one leg's points; the data part is assembled once."""

    def __init__(self, p: np.ndarray, u: np.ndarray, w: np.ndarray, knot: float,
                 slopes: tuple[np.ndarray | None, np.ndarray | None] = (None, None)) -> None:
        length = float(u[-1])
        n_int = max(1, int(math.ceil(length / knot - 1e-9)))
        self.spline = _Spline(length / n_int, n_int, length)
        self.p, self.u = p, u
        self.nc = n_int + 3
        self.j, self.t = self.spline.locate(u)
        self.b = _basis(self.t, 0)
        # dr/du held at the start and the end (a shared cusp's heading): a term as heavy as a
        # fixed point's, on (c[2] - c[0]) / 2h at u = 0 and (c[-1] - c[-3]) / 2h at u = length.
        self.slopes = slopes
        self.set_weights(w.copy())

    def set_weights(self, w: np.ndarray) -> None:
        self.w = w
        self._cache = self._data()

    def _data(self) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
        nc, j, b, w = self.nc, self.j, self.b, self.w
        diags = [np.zeros(nc) for _ in range(4)]
        for o in range(4):
            for a in range(4 - o):
                diags[o] += np.bincount(j + a, weights=w * b[a] * b[a + o], minlength=nc)[:nc]
        rx = np.zeros(nc)
        ry = np.zeros(nc)
        for a in range(4):
            rx += np.bincount(j + a, weights=w * b[a] * self.p[:, 0], minlength=nc)[:nc]
            ry += np.bincount(j + a, weights=w * b[a] * self.p[:, 1], minlength=nc)[:nc]
        h = self.spline.knot
        # As heavy as the fixed end point beside it (the largest weight): a slope error e moves
        # the curve by about h e.
        heavy = float(w.max()) * h * h
        g = 0.5 / h
        for i0, slope in ((0, self.slopes[0]), (nc - 3, self.slopes[1])):
            if slope is None:
                continue
            diags[0][i0] += heavy * g * g
            diags[0][i0 + 2] += heavy * g * g
            diags[2][i0] -= heavy * g * g
            rx[i0] -= heavy * g * slope[0]
            rx[i0 + 2] += heavy * g * slope[0]
            ry[i0] -= heavy * g * slope[1]
            ry[i0 + 2] += heavy * g * slope[1]
        return diags, rx, ry

    def solve(self, lam: np.ndarray) -> _Spline:
        """Fit with penalty weights lam (one per third difference, nc - 3)."""
        diags0, rx, ry = self._cache
        diags = [d.copy() for d in diags0]
        rows = np.arange(self.nc - 3)
        for o in range(4):
            for a in range(4 - o):
                diags[o] += np.bincount(rows + a, weights=lam * (_PEN[a] * _PEN[a + o]), minlength=self.nc)[:self.nc]
        zx, zy = _ldl_band3(diags[0].tolist(), diags[1].tolist(), diags[2].tolist(), diags[3].tolist(),
                            rx.tolist(), ry.tolist())
        self.spline.coef = np.column_stack((zx, zy))
        return self.spline

    def lam(self, ell: float) -> float:
        """Penalty weight of a smoothing length ell (see the module docstring)."""
        return ell ** 6 / self.spline.knot ** 5


def _project(sp: _Spline, p: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed lateral distance of each point from the curve (left +) and its foot's u."""
    uu = np.asarray(u, dtype=float).copy()
    for _ in range(3):
        x, y = sp.eval(uu)
        dx, dy = sp.eval(uu, 1)
        sp2 = dx * dx + dy * dy
        uu = np.clip(uu + ((p[:, 0] - x) * dx + (p[:, 1] - y) * dy) / np.where(sp2 > 0, sp2, 1.0), 0.0, sp.length)
    x, y = sp.eval(uu)
    dx, dy = sp.eval(uu, 1)
    ex, ey = p[:, 0] - x, p[:, 1] - y
    dist = np.hypot(ex, ey)
    sign = np.where(dx * ey - dy * ex >= 0.0, 1.0, -1.0)
    return sign * dist, uu


def _residual_share(ell_over_knot: float) -> float:
    """RMS share of white noise a Whittaker smoother of this length leaves in the residuals."""
    w = np.linspace(0.0, math.pi, 2001)[1:]
    g = ell_over_knot ** 6 * (2.0 * np.sin(0.5 * w)) ** 6
    return float(np.sqrt(np.mean((g / (1.0 + g)) ** 2)))


# --------------------------------------------------------------------------- corners


def _chord_param(p: np.ndarray) -> np.ndarray:
    return np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(p, axis=0).T))))


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


# --------------------------------------------------------------------------- legs


@dataclass
class _Leg:
    pieces: list[Piece]
    theta0: float
    theta1: float
    sigma: np.ndarray  # progress (from the leg's start) of each of its points' feet
    dev: np.ndarray  # distance of each point from the reference
    ell: float | None = None
    fits: int = 0


def _short(p: np.ndarray, tol: float, opt: GeometryOptions) -> _Leg:
    """Few points (or a leg shorter than three knots): a straight line from the first to the
    last if every point is within `tol` of it, else straight segments through them all (as
    waypoints)."""
    d = p[-1] - p[0]
    length = float(math.hypot(d[0], d[1]))
    if length > 0.0:
        t = np.clip(((p - p[0]) @ d) / (length * length), 0.0, 1.0)
        dev = np.hypot(*(p - (p[0] + t[:, None] * d)).T)
        if np.all(dev <= tol):
            heading = math.atan2(d[1], d[0])
            return _Leg([line_piece(float(p[0, 0]), float(p[0, 1]), heading, length, opt.step)], heading, heading,
                        t * length, dev)
    keep = np.concatenate(([True], np.hypot(*np.diff(p, axis=0).T) > 1e-9))
    q = p[keep]
    if len(q) < 2:
        raise ConditionError("a leg of the path has no length")
    geo = polyline_geometry([(float(a), float(b)) for a, b in q], [0.0] * len(q), opt)
    enter = np.asarray(geo.cap_sigma)[::2]
    sig = np.interp(np.cumsum(keep) - 1, np.arange(len(q)), enter)
    seg = np.diff(q, axis=0)
    th0 = math.atan2(seg[0, 1], seg[0, 0])
    th1 = float(geo.pieces[-1].theta[-1])
    return _Leg(geo.pieces, th0, th1, sig, np.zeros(len(p)))


def _sample_piece(sp: _Spline, step: float, start: np.ndarray | None, end: np.ndarray | None,
                  u0: float = 0.0, u1: float | None = None) -> tuple[Piece, Callable[[np.ndarray], np.ndarray]]:
    """The spline on [u0, u1] sampled every `step` of its own arc length; also the map from u
    to that arc length."""
    u1 = sp.length if u1 is None else u1
    m = max(64, int(math.ceil(8 * sp.n_int * (u1 - u0) / sp.length)))
    uf = np.linspace(u0, u1, m + 1)
    dx, dy = sp.eval(uf, 1)
    speed = np.hypot(dx, dy)
    if not np.all(speed > 1e-6 * float(np.max(speed))):
        raise _Cusp(float(uf[int(np.argmin(speed))]))
    sf = np.concatenate(([0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(uf))))
    total = float(sf[-1])
    n = max(2, int(math.ceil(total / step - 1e-9)))
    s = np.linspace(0.0, total, n + 1)
    u = np.interp(s, sf, uf)
    dx, dy = sp.eval(u, 1)
    u = np.clip(u - (np.interp(u, uf, sf) - s) / np.hypot(dx, dy), u0, u1)
    u[0], u[-1] = u0, u1
    x, y = sp.eval(u)
    dx, dy = sp.eval(u, 1)
    ddx, ddy = sp.eval(u, 2)
    sp2 = np.hypot(dx, dy)
    th = np.unwrap(np.arctan2(dy, dx))
    kap = (dx * ddy - dy * ddx) / sp2 ** 3
    if start is not None:
        x[0], y[0] = start
    if end is not None:
        x[-1], y[-1] = end
    return Piece(s, x, y, th, kap), (lambda uu: np.interp(uu, uf, sf))


SEARCH_POINTS = 4000  # a longer leg chooses its smoothing on windows of this many points


def _choose_smoothing(q: np.ndarray, u: np.ndarray, w: np.ndarray, fixed: np.ndarray, knot: float,
                      noise: float, slopes: tuple[np.ndarray | None, np.ndarray | None] = (None, None)
                      ) -> tuple[float, int]:
    """The largest smoothing length on a sqrt(2) ladder whose RMS lateral residual is within
    DISCREPANCY noise sigmas (bisection); a long leg takes the smallest over three windows
    (the choice is about the noise, which a window shows as well as the whole). `slopes`:
    the leg's held end tangents (a leg short enough to be chosen whole)."""
    n = len(q)
    if n > SEARCH_POINTS:
        starts = np.linspace(0, n - SEARCH_POINTS, 3).astype(int).tolist()
        best, fits = math.inf, 0
        for a in starts:
            sl = slice(a, a + SEARCH_POINTS)
            e, f = _choose_smoothing(q[sl], u[sl] - u[a], w[sl], fixed[sl], knot, noise)
            best, fits = min(best, e), fits + f
        return best, fits
    fit = _LegFit(q, u, w, knot, slopes)
    nrow = fit.nc - 3
    kn = fit.spline.knot
    ell_lo = 1.5 * kn
    fits = 0

    def rms_ok(ell: float) -> bool:
        nonlocal fits
        fits += 1
        try:
            sp = fit.solve(np.full(nrow, fit.lam(ell)))
        except ConditionError:  # smoothing so heavy the system is ill-conditioned: too heavy
            return False
        d, _ = _project(sp, q, u)
        return float(np.sqrt(np.mean(d[~fixed] ** 2))) <= DISCREPANCY * noise

    total = float(u[-1])
    ladder = [ell_lo * 2.0 ** (k / 2.0) for k in range(40)]
    ladder = [e for e in ladder if e <= max(ell_lo, min(MAX_SMOOTHING_M, total, MAX_SMOOTHING_KNOTS * kn))]
    lo, hi = 0, len(ladder) - 1
    if not rms_ok(ladder[lo]):
        return ell_lo, fits
    if rms_ok(ladder[hi]):
        return ladder[hi], fits
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if rms_ok(ladder[mid]):
            lo = mid
        else:
            hi = mid
    return ladder[lo], fits


def _cell_distance(sp: _Spline, q: np.ndarray, uf: np.ndarray, axis: float) -> np.ndarray:
    """How far each point's foot on the curve lies from the point along the grid's axes (the
    larger of the two): at most half a cell while the curve crosses the point's own cell."""
    x, y = sp.eval(uf)
    ex, ey = q[:, 0] - x, q[:, 1] - y
    c, s = math.cos(axis), math.sin(axis)
    return np.maximum(np.abs(c * ex + s * ey), np.abs(c * ey - s * ex))


def _fit_leg(p: np.ndarray, fix0: np.ndarray | None, fix1: np.ndarray | None, tol: float, noise: float,
             knot: float, opt: GeometryOptions, names: Sequence[str], offset: int, where: str,
             wrap: tuple[np.ndarray, np.ndarray] | None = None, cell_axis: float | None = None,
             slope0: np.ndarray | None = None, slope1: np.ndarray | None = None) -> _Leg:
    """One leg between corners (or the path's ends): the smoothing spline of the module doc.

    `slope0`, `slope1`: dr/du (u the points' chord length) held at a fixed start or end: the
    heading and pace of a cusp shared with the next run (ddrt/path/cusp.py).

    `cell_axis`: a grid plan's axis direction; the corridor is then each point's cell (the
    distance is taken along the grid's axes, at the point's foot), not a disc round it.

    `wrap`: a closed loop's points before its start and after its end (the loop's own, taken
    round), fitted with it so its ends are smoothed as well as its middle; the reference
    still runs from the first point's foot to the last one's."""
    q = p.copy()
    if fix0 is not None:
        q[0] = fix0
    if fix1 is not None:
        q[-1] = fix1
    if len(q) < 4 or float(np.sum(np.hypot(*np.diff(q, axis=0).T))) < 3.0 * knot:
        return _short(q, tol, opt)
    core = slice(0, len(q))
    if wrap is not None:
        core = slice(len(wrap[0]), len(wrap[0]) + len(q))
        q = np.concatenate((wrap[0], q, wrap[1]))
    u = _chord_param(q)
    h = np.diff(u)
    w = 0.5 * (np.concatenate((h, [0.0])) + np.concatenate(([0.0], h)))
    fixed = np.zeros(len(q), dtype=bool)  # not checked against the tolerance
    if fix0 is not None:
        fixed[0] = True
    if fix1 is not None:
        fixed[-1] = True
    w[fixed] = _FIX_WEIGHT * float(w.max())
    fixed[:core.start] = True
    fixed[core.stop:] = True
    held = (slope0 if fix0 is not None and wrap is None else None,
            slope1 if fix1 is not None and wrap is None else None)
    fit = _LegFit(q, u, w, knot, held)
    nrow = fit.nc - 3
    kn = fit.spline.knot
    ell_min = 0.5 * kn
    ell, fits = _choose_smoothing(q, u, w, fixed, knot, noise, held)
    lam = np.full(nrow, fit.lam(ell))
    lam_min = fit.lam(ell_min)
    reach = int(math.ceil(ell / kn)) + 3
    for _ in range(60):
        sp = fit.solve(lam)
        fits += 1
        d, uf = _project(sp, q, u)
        dev = np.abs(d) if cell_axis is None else _cell_distance(sp, q, uf, cell_axis)
        bad = (dev > tol) & ~fixed
        if not bad.any():
            break
        rows = np.zeros(nrow + 1)
        jb = fit.j[bad]
        np.add.at(rows, np.clip(jb - reach, 0, nrow), 1.0)
        np.add.at(rows, np.clip(jb + reach + 1, 0, nrow), -1.0)
        near = np.cumsum(rows)[:nrow] > 0
        if np.all(lam[near] <= lam_min * (1.0 + 1e-9)):
            # Smoothing as low as it goes: let the points that are still out pull harder.
            if np.all(fit.w[bad] >= 256.0 * w[bad]):
                break
            fit.set_weights(np.where(bad, fit.w * 4.0, fit.w))
        else:
            lam[near] = np.maximum(lam[near] * 0.25, lam_min)
    if np.any((dev > tol) & ~fixed):
        i = int(np.argmax(np.where(fixed, -1.0, dev)))
        raise ConditionError(
            f"{where}: {names[offset + i]}: the reference cannot stay within {tol:g} m of the point "
            f"({q[i, 0]:.6g}, {q[i, 1]:.6g}): the closest smooth curve passes {dev[i] * 1000:.3g} mm away "
            "(the points are noisier than the tolerance); raise paths.tolerance_m or the path's tolerance:")
    ua, ub = float(u[core.start]), float(u[core.stop - 1])
    try:
        piece, s_of_u = _sample_piece(sp, opt.step, fix0, fix1, ua, ub)
    except _Cusp as exc:
        raise _Cusp(int(np.clip(np.searchsorted(u, exc.index), core.start, core.stop - 1)) - core.start) from None
    sig = s_of_u(np.clip(uf[core], ua, ub))
    return _Leg([piece], float(piece.theta[0]), float(piece.theta[-1]), sig, dev[core], ell, fits)


def _estimate_noise(p: np.ndarray, knot: float) -> float:
    """Lateral noise of the points: residuals of a light fit, scaled by the share it leaves
    (on three windows of a long polyline)."""
    if len(p) > SEARCH_POINTS:
        starts = np.linspace(0, len(p) - SEARCH_POINTS, 3).astype(int).tolist()
        return float(np.median([_estimate_noise(p[a:a + SEARCH_POINTS], knot) for a in starts]))
    u = _chord_param(p)
    if len(p) < 8 or u[-1] < 6.0 * knot:
        return 0.0
    h = np.diff(u)
    w = 0.5 * (np.concatenate((h, [0.0])) + np.concatenate(([0.0], h)))
    fit = _LegFit(p, u, w, knot)
    sp = fit.solve(np.full(fit.nc - 3, fit.lam(3.0 * fit.spline.knot)))
    d, _ = _project(sp, p, u)
    return float(1.4826 * np.median(np.abs(d)) / _residual_share(3.0))


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
    u = _chord_param(body)
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
    ue = _chord_param(ext)
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


def point_noise(pts: np.ndarray, copt: ConditionOptions) -> tuple[str, float]:
    """(mode, estimated lateral noise) of a polyline of distinct points, as condition_polyline
    finds them (for a cusp's estimate from two runs' points, ddrt/path/cusp.py)."""
    p = np.asarray(pts, dtype=float)
    mode, tol, cell = classify(p, copt)
    if mode == WAYPOINTS:
        return mode, 0.0
    spacing = float(np.median(np.hypot(*np.diff(p, axis=0).T)))
    return mode, max(_estimate_noise(p, knot_spacing(spacing, tol, cell)), NOISE_FLOOR_M)


@dataclass(frozen=True, slots=True)
class EndPin:
    """A fitted polyline's start or end held at `point`, with dr/du = `slope` there (u the
    points' chord length: |slope| is the pace of the points' progress per chord, about 1);
    `slope` None: the point only, the tangent free (a cusp's sample, where no tangent is
    shared: the run then meets the other at one point, ddrt/path/spec.py)."""

    point: np.ndarray
    slope: np.ndarray | None = None


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
    u = _chord_param(p)
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
    noise = max(_estimate_noise(p, knot) if noise is None else noise, NOISE_FLOOR_M)
    axis = grid_axis(p) if mode == GRID else None
    info.noise_m = noise
    pinned = ends[0] is not None or ends[1] is not None
    wrap = _loop_wrap(p, knot, scale, threshold, tol, spacing) if not corners and not pinned else None
    info.extra["closed_loop"] = wrap is not None
    cuts = [0] + [k for k, _ in corners] + [len(p) - 1]
    fixes: list[np.ndarray | None] = ([None if ends[0] is None else ends[0].point]
                                      + [_refine_corner(p, u, k, scale, tol) for k, _ in corners]
                                      + [None if ends[1] is None else ends[1].point])
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
            leg = _fit_leg(p[a:b + 1], fixes[j], fixes[j + 1], tol, noise, knot, opt, names, a, where, wrap,
                           axis, ends[0].slope if j == 0 and ends[0] is not None else None,
                           ends[1].slope if j == len(cuts) - 2 and ends[1] is not None else None)
        except _Cusp as exc:
            k = a + exc.index
            raise ConditionError(f"{where}: {names[k]}: the points turn back on themselves here (the smoothed "
                                 "curve stops and reverses): mark the points reached in reverse (a negative v) "
                                 "or split the path here") from None
        except ConditionError as exc:
            if str(exc).startswith(where):
                raise
            raise ConditionError(f"{where}: {names[a]}: the points from here cannot be smoothed: {exc}") from None
        info.iterations += leg.fits
        if leg.ell is not None:
            ells.append(leg.ell)
        if heading is not None:
            turn = float(_wrap(np.array(leg.theta0 - heading)))
            if abs(turn) >= math.radians(REVERSAL_DEG) and mode == SAMPLES:
                raise ConditionError(
                    f"{where}: {names[a]}: the path reverses here (it turns {math.degrees(abs(turn)):.0f} degrees): "
                    "mark the points reached in reverse (a negative v) or split the path here")
            if abs(turn) > 1e-9:
                c = fixes[j]
                assert c is not None
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
        for k, c in ((a, fixes[j]), (b, fixes[j + 1])):  # a corner's own point against the corner
            if c is not None:
                devs[k] = max(devs[k], float(math.hypot(*(p[k] - c))))
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
