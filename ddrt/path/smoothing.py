"""The smoothing spline through one leg of samples: a P-spline that stays within a tolerance
of every point (ddrt/path/condition.py decides what a leg is: the points between two corners).

Each leg is a uniform cubic B-spline in the distance u the points stand for along the curve
(their chord length, averaged over a few noise sigmas where the noise is larger than a share
of the spacing: ddrt/path/noise.py; a grid plan's plain chord length), knots at the median
point spacing, fitted by penalised least squares (a P-spline):

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
1. the noise is given (ddrt/path/noise.py: local cubic residuals; a grid plan's staircase,
   `staircase_noise`: the residuals of a light fit of 3 cells);
2. per leg, the largest l on a sqrt(2) ladder whose RMS lateral residual stays within
   1.1 sigma (the discrepancy principle: remove the noise, keep the curve; the shape bias
   that remains is a fraction of the noise), over the leg's points but those where a pin is
   meant to pull the curve off them (`EndPin.settle`);
3. the tolerance is then enforced point by point: wherever a point lies farther than
   `tolerance` from the curve, the penalty is lowered four-fold around it and the leg is
   fitted again, until every point is within tolerance; never below the smoothing at which
   the noise would show in the curvature (noise.chase_floor: the fit would follow the noise;
   where the noise sets no such floor, an exact export, the point's weight is raised instead).
   A tolerance no such curve can meet is refused (`ToleranceUnmet`, naming the point and
   how far the curve passes).

A leg's ends may be pinned (`EndPin`): held at a point (a corner, a cusp) and, given a slope,
on a tangent there. The interface is one request (`FitRequest`) and one result (`FittedLeg`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from ddrt.errors import DdrtError
from ddrt.path.geometry import GeometryOptions, Piece, line_piece, polyline_geometry
from ddrt.path.noise import arc_parameter, chase_floor

__all__ = ["CurveStops", "EndPin", "FitError", "FitRequest", "FittedLeg", "ToleranceUnmet", "along_axes",
           "chord_length", "fit_leg", "staircase_noise"]

DISCREPANCY = 1.1  # RMS lateral residual allowed, in estimated noise sigmas
MAX_SMOOTHING_M = 4.0  # longest smoothing length tried
MAX_SMOOTHING_KNOTS = 40.0  # and at most this many knots (beyond, the normal equations lose precision)
_FIX_WEIGHT = 1e6  # weight (relative to the largest) of a leg end fixed at a corner
CUSP_SWING = 0.25 * math.pi  # rad: a heading turning this much within an eighth of a knot stops and reverses
SEARCH_POINTS = 4000  # a longer leg chooses its smoothing on windows of this many points


class FitError(DdrtError, ValueError):
    """The leg cannot be fitted (no length, a singular system, a tolerance no curve meets)."""


class ToleranceUnmet(FitError):
    """No smooth curve stays within the tolerance of point `index` (counted among the fitted
    points: a closed loop's wrap points first), at (x, y): the closest passes `deviation` m away."""

    def __init__(self, index: int, x: float, y: float, deviation: float, tolerance: float) -> None:
        super().__init__(f"point {index} ({x:.6g}, {y:.6g}) is {deviation * 1000:.3g} mm from the closest "
                         f"smooth curve, beyond the tolerance {tolerance:g} m")
        self.index, self.x, self.y, self.deviation = index, x, y, deviation


class CurveStops(DdrtError):
    """The fitted curve stops (zero speed) at `index`: a u value, or a point's index in its leg."""

    def __init__(self, index: float) -> None:
        super().__init__(index)
        self.index = index


@dataclass(frozen=True, slots=True)
class EndPin:
    """A fitted polyline's start or end held at `point`, with dr/du = `slope` there (u the
    points' chord length: |slope| is the pace of the points' progress per chord, about 1);
    `slope` None: the point only, the tangent free (a corner; or a cusp's sample, where no
    tangent is shared: the run then meets the other at one point, ddrt/path/reversal.py).
    `settle`: the length (of chord) near the pin over which the curve is meant to leave the
    points (a reversal's corner midway between its legs): left out of the smoothing's choice,
    which is about the noise."""

    point: np.ndarray
    slope: np.ndarray | None = None
    settle: float = 0.0


@dataclass(frozen=True)
class FitRequest:
    """One leg to smooth: its points and what the curve must keep to."""

    points: np.ndarray  # (n, 2) the leg's points, first to last
    tolerance: float  # m: the largest distance of a point from the curve
    noise: float  # m: the points' lateral noise (1 sigma), which the smoothing removes
    knot: float  # m of chord: the knot spacing (rounded to a whole number of intervals)
    options: GeometryOptions  # the sample step; a short leg's corners, as waypoints'
    start: EndPin | None = None  # the first point held (at a corner, a cusp) and its tangent, if given
    end: EndPin | None = None  # the same for the last point
    wrap: tuple[np.ndarray, np.ndarray] | None = None  # a closed loop's points before and after it
    cell_axis: float | None = None  # a grid plan's axis: the corridor is each point's cell
    cells: np.ndarray | None = None  # a grid plan's cell centres when `points` are their straightened stand-ins


@dataclass
class FittedLeg:
    """The leg's reference: its pieces and, per point, where its foot lies and how far off it is."""

    pieces: list[Piece]
    theta0: float  # heading at the start
    theta1: float  # and at the end
    sigma: np.ndarray  # progress (from the leg's start) of each of its points' feet
    dev: np.ndarray  # distance of each point from the reference
    smoothing_m: float | None = None  # the smoothing length chosen (None: a straight or waypoint leg)
    fits: int = 0  # systems solved


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
            raise FitError("the smoothing system is singular")
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


def chord_length(p: np.ndarray) -> np.ndarray:
    """The chord length u at each point: the spline's parameter."""
    return np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(p, axis=0).T))))



# --------------------------------------------------------------------------- legs


def _short(p: np.ndarray, tol: float, opt: GeometryOptions, centres: np.ndarray | None = None) -> FittedLeg:
    """Few points (or a leg shorter than three knots): a straight line from the first to the
    last if every point (or its cell's centre, `centres`) is within `tol` of it, else straight
    segments through them all (as waypoints)."""
    c = p if centres is None else centres
    d = p[-1] - p[0]
    length = float(math.hypot(d[0], d[1]))
    if length > 0.0:
        t = np.clip(((c - p[0]) @ d) / (length * length), 0.0, 1.0)
        dev = np.hypot(*(c - (p[0] + t[:, None] * d)).T)
        if np.all(dev <= tol):
            heading = math.atan2(d[1], d[0])
            return FittedLeg([line_piece(float(p[0, 0]), float(p[0, 1]), heading, length, opt.step)], heading,
                             heading, t * length, dev)
    keep = np.concatenate(([True], np.hypot(*np.diff(p, axis=0).T) > 1e-9))
    q = p[keep]
    if len(q) < 2:
        raise FitError("a leg of the path has no length")
    geo = polyline_geometry([(float(a), float(b)) for a, b in q], [0.0] * len(q), opt)
    enter = np.asarray(geo.cap_sigma)[::2]
    sig = np.interp(np.cumsum(keep) - 1, np.arange(len(q)), enter)
    seg = np.diff(q, axis=0)
    th0 = math.atan2(seg[0, 1], seg[0, 0])
    th1 = float(geo.pieces[-1].theta[-1])
    return FittedLeg(geo.pieces, th0, th1, sig, np.hypot(*(c - p).T))


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
        raise CurveStops(float(uf[int(np.argmin(speed))]))
    # A heading that swings by more than CUSP_SWING within an eighth of a knot is a cusp the
    # speed test missed (the curve nearly stops and turns back).
    swing = np.abs(np.arctan2(dx[:-1] * dy[1:] - dy[:-1] * dx[1:], dx[:-1] * dx[1:] + dy[:-1] * dy[1:]))
    if swing.size and float(swing.max()) > CUSP_SWING:
        raise CurveStops(float(uf[int(np.argmax(swing))]))
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



def _choose_smoothing(q: np.ndarray, u: np.ndarray, w: np.ndarray, fixed: np.ndarray, knot: float,
                      noise: float, slopes: tuple[np.ndarray | None, np.ndarray | None] = (None, None)
                      ) -> tuple[float, int]:
    """The largest smoothing length on a sqrt(2) ladder whose RMS lateral residual (over the
    points not `fixed`) is within DISCREPANCY noise sigmas (bisection); a long leg takes the
    smallest over three windows (the choice is about the noise, which a window shows as well
    as the whole). `slopes`: the leg's held end tangents (a leg short enough to be chosen whole)."""
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
        except FitError:  # smoothing so heavy the system is ill-conditioned: too heavy
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


def along_axes(ex: np.ndarray | float, ey: np.ndarray | float, axis: float) -> np.ndarray | float:
    """The length of the offset (ex, ey) measured along a grid's axes (at `axis`): the larger
    of its two components there, as a grid plan's corridor is measured (arrays or floats)."""
    c, s = math.cos(axis), math.sin(axis)
    return np.maximum(np.abs(c * ex + s * ey), np.abs(c * ey - s * ex))


def _cell_distance(sp: _Spline, q: np.ndarray, uf: np.ndarray, axis: float) -> np.ndarray:
    """How far each point's foot on the curve lies from the point along the grid's axes (the
    larger of the two): at most half a cell while the curve crosses the point's own cell."""
    x, y = sp.eval(uf)
    return along_axes(q[:, 0] - x, q[:, 1] - y, axis)


def _settling(req: FitRequest, u: np.ndarray) -> np.ndarray:
    """Points within a pin's `settle` of its end, where the curve is meant to leave them."""
    out = np.zeros(len(u), dtype=bool)
    if req.start is not None and req.start.settle > 0.0:
        out |= u - u[0] < req.start.settle
    if req.end is not None and req.end.settle > 0.0:
        out |= u[-1] - u < req.end.settle
    return out


def fit_leg(req: FitRequest) -> FittedLeg:
    """One leg between corners (or the path's ends): the smoothing spline of the module doc.

    A pinned end (`req.start`, `req.end`) is held at its point; its slope, when given, is dr/du
    (u the points' chord length) held there: the heading and pace of a cusp shared with the
    next run (ddrt/path/cusp.py).

    `req.cell_axis`: a grid plan's axis direction; the corridor is then each point's cell (the
    distance is taken along the grid's axes, at the point's foot), not a disc round it.
    `req.cells`: the cells' own centres, where the points fitted are moved off them (a
    staircase put onto its line, ddrt/path/gridplan.py): the corridor is measured from these.

    `req.wrap`: a closed loop's points before its start and after its end (the loop's own, taken
    round), fitted with it so its ends are smoothed as well as its middle; the reference
    still runs from the first point's foot to the last one's.

    Raises CurveStops (the curve stops and turns back at that point of the leg), ToleranceUnmet
    or FitError."""
    p, tol, knot, opt, wrap, cell_axis = req.points, req.tolerance, req.knot, req.options, req.wrap, req.cell_axis
    fix0 = None if req.start is None else req.start.point
    fix1 = None if req.end is None else req.end.point
    q = p.copy()
    if fix0 is not None:
        q[0] = fix0
    if fix1 is not None:
        q[-1] = fix1
    centres = q if req.cells is None else np.concatenate((q[:1], req.cells[1:-1], q[-1:]))  # the ends as held
    if len(q) < 4 or float(np.sum(np.hypot(*np.diff(q, axis=0).T))) < 3.0 * knot:
        return _short(q, tol, opt, centres)
    core = slice(0, len(q))
    if wrap is not None:
        core = slice(len(wrap[0]), len(wrap[0]) + len(q))
        q = np.concatenate((wrap[0], q, wrap[1]))
        centres = np.concatenate((wrap[0], centres, wrap[1]))
    u = chord_length(q) if cell_axis is not None else arc_parameter(q, req.noise)
    h = np.diff(u)
    w = 0.5 * (np.concatenate((h, [0.0])) + np.concatenate(([0.0], h)))
    fixed = np.zeros(len(q), dtype=bool)  # not checked against the tolerance
    fixed[core.start] = fix0 is not None
    fixed[core.stop - 1] = fix1 is not None
    w[fixed] = _FIX_WEIGHT * float(w.max())
    fixed[:core.start] = True
    fixed[core.stop:] = True
    held = (req.start.slope if req.start is not None and wrap is None else None,
            req.end.slope if req.end is not None and wrap is None else None)
    choice = fixed | _settling(req, u)
    ell, fits = _choose_smoothing(q, u, w, choice if not choice.all() else fixed, knot, req.noise, held)
    fit = _LegFit(q, u, w, knot, held)
    nrow = fit.nc - 3
    kn = fit.spline.knot
    # The tolerance may lower the smoothing round a point that is out, but not so far that the
    # curve follows the noise (noise.chase_floor; a grid plan's staircase is not noise).
    floor = 0.0 if cell_axis is not None else chase_floor(req.noise, float(u[-1]) / max(len(u) - 1, 1))
    ell_min = max(0.5 * kn, min(floor, ell))
    lam = np.full(nrow, fit.lam(ell))
    lam_min = fit.lam(ell_min)
    reach = int(math.ceil(ell / kn)) + 3
    for _ in range(60):
        sp = fit.solve(lam)
        fits += 1
        d, uf = _project(sp, q, u)
        dev = np.abs(d) if cell_axis is None else _cell_distance(sp, centres, uf, cell_axis)
        bad = (dev > tol) & ~fixed
        if not bad.any():
            break
        rows = np.zeros(nrow + 1)
        jb = fit.j[bad]
        np.add.at(rows, np.clip(jb - reach, 0, nrow), 1.0)
        np.add.at(rows, np.clip(jb + reach + 1, 0, nrow), -1.0)
        near = np.cumsum(rows)[:nrow] > 0
        if np.all(lam[near] <= lam_min * (1.0 + 1e-9)):
            # Smoothing as low as it goes: where the noise does not set that floor, let the
            # points that are still out pull harder.
            if ell_min > 0.5 * kn * (1.0 + 1e-9) or np.all(fit.w[bad] >= 256.0 * w[bad]):
                break
            fit.set_weights(np.where(bad, fit.w * 4.0, fit.w))
        else:
            lam[near] = np.maximum(lam[near] * 0.25, lam_min)
    if np.any((dev > tol) & ~fixed):
        i = int(np.argmax(np.where(fixed, -1.0, dev)))
        raise ToleranceUnmet(i, float(centres[i, 0]), float(centres[i, 1]), float(dev[i]), tol)
    ua, ub = float(u[core.start]), float(u[core.stop - 1])
    try:
        piece, s_of_u = _sample_piece(sp, opt.step, fix0, fix1, ua, ub)
    except CurveStops as exc:
        raise CurveStops(int(np.clip(np.searchsorted(u, exc.index), core.start, core.stop - 1)) - core.start) from None
    sig = s_of_u(np.clip(uf[core], ua, ub))
    return FittedLeg([piece], float(piece.theta[0]), float(piece.theta[-1]), sig, dev[core], ell, fits)


def _residual_share(ell_over_knot: float) -> float:
    """RMS share of white noise a Whittaker smoother of this length leaves in the residuals."""
    w = np.linspace(0.0, math.pi, 2001)[1:]
    g = ell_over_knot ** 6 * (2.0 * np.sin(0.5 * w)) ** 6
    return float(np.sqrt(np.mean((g / (1.0 + g)) ** 2)))


def staircase_noise(p: np.ndarray, knot: float) -> float:
    """A grid plan's zig-zag about the curve it stands for, as a noise level (1 sigma): the
    residuals of a light fit (3 cells), scaled by the share of white noise it leaves (on three
    windows of a long plan); 0 for too few points. The smoothing removes that much. (Recordings
    have ddrt/path/noise.py: a staircase is not white noise, and its steps are the cells.)"""
    if len(p) > SEARCH_POINTS:
        starts = np.linspace(0, len(p) - SEARCH_POINTS, 3).astype(int).tolist()
        return float(np.median([staircase_noise(p[a:a + SEARCH_POINTS], knot) for a in starts]))
    u = chord_length(p)
    if len(p) < 8 or u[-1] < 6.0 * knot:
        return 0.0
    h = np.diff(u)
    w = 0.5 * (np.concatenate((h, [0.0])) + np.concatenate(([0.0], h)))
    fit = _LegFit(p, u, w, knot)
    sp = fit.solve(np.full(fit.nc - 3, fit.lam(3.0 * fit.spline.knot)))
    d, _ = _project(sp, p, u)
    return float(1.4826 * np.median(np.abs(d)) / _residual_share(3.0))
