"""Joining two smoothed runs at a cusp: one point and one heading estimated from both runs'
samples (`estimate_cusp`), each run then fitted ending there; and, where the runs meet on two
headings, bending both onto one (`bend_end`, `bend_start`).

The shared cusp. At a real cusp the robot stops and drives on the other way with the heading
it had: the runs meet at one point with one tangent line, and both lie behind the point
along it (the motion reverses). So near the cusp, in a frame with x along the tangent
(towards the cusp) and y across it, both runs' points are y = c0 + c1 x + (each run's own)
a2 x^2 + ... + ad x^d for x <= 0, d = 1, 2 or 3: a linear least-squares fit with the offset
c0 and slope c1 shared. The frame is turned by the fitted slope and moved by the fitted
offset (three passes, leaving both about nil); the point keeps the recorded cusp sample's
place along the tangent (the along-track noise is as large either way, and it bends nothing).

Which window (the points within `w` of the cusp sample along each run) and which degree:
every window on a sqrt(2) ladder, from the shortest that holds CUSP_MIN_SIDE points on each
side besides the cusp sample to CUSP_WINDOW_MAX_M (and half of either run), is fitted with
each degree; a fit counts if it keeps at least 3 degrees of freedom and its residual RMS
(per degree of freedom) stays within (CUSP_DISCREPANCY + 1 / sqrt(2 dof)) times the runs'
noise (1 / sqrt(2 dof): the scatter of an RMS over dof terms, else chance alone refuses a
short window). Of the fits that count, the one chosen is the one whose tangent line is surest
where the runs bend onto it: the smallest variance, per unit noise, of its offset
CUSP_BLEND_M behind the cusp ((X^T X)^-1 of the shared offset and slope). None if no fit
counts, or either run has too few points.

Each run is then fitted with its end held at that point and its end tangent on that heading
(smoothing.EndPin), so the runs meet on one heading, and the cusp sample's distance from the
point counts in the reported deviation like any other point's. The assembly (reversal.py) shares
no cusp whose point lies farther than the tolerance from the cusp sample.

Where a cusp is not shared (a run is waypoints or has too few points, no window's fit
matches the noise, or a pinned fit cannot keep its points within the tolerance) the runs
still meet at one point, held by both fits: the cusp sample (or the previous run's end), the
tangents free (reversal.py). Only if no fit can hold that point is a run fitted free and moved
onto the previous run's end, the move added to its deviation.

Bending. Where the two runs' tangents at the cusp differ (each fitted on its own end), a
smoothing spline's end tangent being the least certain part of its fit, on 1-2 mm of noise
they come out 3-5 degrees apart, which would be a turn in place at the cusp (a stop, a yaw
acceleration spike, time). When both runs are smoothed samples (a waypoint's corner is the
user's, never ours) and the headings differ by at most CUSP_BLEND_MAX_RAD, each run's end is
bent to the mean heading: a lateral offset e(d) = tan(beta) d (1 - d / l)^2 over the last `l`
metres (d from the cusp), zero with zero slope at d = l, zero at the cusp, with slope
tan(beta) there (beta = half the difference, opposite on each side). It moves the curve by
at most 4/27 l tan|beta| and adds a curvature of at most 4 tan|beta| / l at the cusp, where
the robot is at rest. It is used only when that offset, added to the run's deviation, keeps
it within its tolerance; otherwise the turn in place stays.
"""

from __future__ import annotations

import math

import numpy as np

from dataclasses import dataclass

from ddrt.path.geometry import Piece

__all__ = ["CUSP_BLEND_MAX_RAD", "CUSP_BLEND_M", "SharedCusp", "blend_offset", "bend_end", "bend_start",
           "estimate_cusp"]

# Larger differences are a turn the user meant (or data that cannot say): turned in place.
CUSP_BLEND_MAX_RAD = math.radians(12.0)
# The length over which each side is bent (at most half the piece).
CUSP_BLEND_M = 0.25


def blend_length(piece: Piece) -> float:
    return min(CUSP_BLEND_M, 0.5 * piece.length)


def blend_offset(length: float, beta: float) -> float:
    """The largest lateral move (m) of bending a run's end by `beta` rad over `length` m."""
    return 4.0 / 27.0 * length * abs(math.tan(beta))


def _bend(pc: Piece, d: np.ndarray, sign: float, beta: float, length: float) -> None:
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


def bend_end(pc: Piece, beta: float, length: float) -> None:
    """Turn the piece's last tangent by beta (rad), its end point fixed."""
    _bend(pc, pc.s[-1] - pc.s, -1.0, beta, length)


def bend_start(pc: Piece, beta: float, length: float) -> None:
    """Turn the piece's first tangent by beta (rad), its start point fixed."""
    _bend(pc, pc.s - pc.s[0], 1.0, beta, length)


# ------------------------------------------------------------------------ the shared cusp

CUSP_DISCREPANCY = 1.1  # residual RMS allowed, in noise sigmas (as condition.DISCREPANCY)
CUSP_MIN_SIDE = 5  # points each run needs in the window besides the cusp sample
CUSP_WINDOW_MAX_M = 0.6  # longest window tried (and at most half of either run)


@dataclass(frozen=True, slots=True)
class SharedCusp:
    """Where two runs meet at a cusp, estimated from both runs' points."""

    point: np.ndarray  # (2,)
    heading: float  # the arriving run's direction of travel there (rad); the leaving run's + pi
    pace_in: float  # progress along the tangent per chord length of the arriving run's points
    pace_out: float  # and of the leaving run's
    window_m: float
    rms_m: float  # residual RMS of the fit (per degree of freedom)

    @property
    def direction(self) -> np.ndarray:
        return np.array([math.cos(self.heading), math.sin(self.heading)])


def _chord_from_cusp(p: np.ndarray) -> np.ndarray:
    """Chord length from p[0] along the points."""
    return np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(p, axis=0).T))))


def _fit_window(a: np.ndarray, b: np.ndarray, degree: int) -> tuple[np.ndarray, np.ndarray, float, np.ndarray] | None:
    """(point, unit tangent towards the cusp, residual RMS per degree of freedom, (X^T X)^-1 of
    the shared offset and slope) of the shared fit with each run's own terms x^2 .. x^degree;
    a[0] = b[0] is the cusp sample, a and b lead away from it along each run."""
    c = a[0]
    pts = np.concatenate((a, b[1:]))
    side_b = np.concatenate((np.zeros(len(a)), np.ones(len(b) - 1)))
    t = c - pts[1:].mean(axis=0)
    norm = math.hypot(*t)
    if not norm > 0.0:
        return None
    t = t / norm
    o = c.copy()
    rss = 0.0
    design = np.zeros((0, 0))
    for _ in range(3):
        n = np.array([-t[1], t[0]])
        x = (pts - o) @ t
        y = (pts - o) @ n
        cols = [np.ones_like(x), x]
        for k in range(2, degree + 1):
            cols += [(1.0 - side_b) * x ** k, side_b * x ** k]
        design = np.column_stack(cols)
        coef, *_ = np.linalg.lstsq(design, y, rcond=None)
        if not np.all(np.isfinite(coef)):
            return None
        rss = float(np.sum((design @ coef - y) ** 2))
        o = o + coef[0] * n
        t = t + coef[1] * n
        t = t / math.hypot(*t)
    dof = len(pts) - design.shape[1]
    try:
        cov = np.linalg.inv(design.T @ design)[:2, :2]
    except np.linalg.LinAlgError:
        return None
    return o, t, math.sqrt(rss / dof), cov


def _pace(p: np.ndarray, point: np.ndarray, t: np.ndarray) -> float:
    """Progress away from the cusp along -t per chord length of the points p (p[0] the cusp)."""
    u = _chord_from_cusp(p)
    x = (point - p) @ t
    den = float(u @ u)
    return float(np.clip((x @ u) / den, 0.5, 1.0)) if den > 0.0 else 1.0


def estimate_cusp(arrive: np.ndarray, leave: np.ndarray, noise: float) -> SharedCusp | None:
    """The cusp shared by a run arriving at arrive[-1] and one leaving from leave[0] (the same
    sample), from both runs' points (module docstring); None when either run has too few
    points near the cusp, or no window's fit matches the noise."""
    a = np.asarray(arrive, dtype=float)[::-1]
    b = np.asarray(leave, dtype=float)
    if len(a) < CUSP_MIN_SIDE + 1 or len(b) < CUSP_MIN_SIDE + 1 or not np.array_equal(a[0], b[0]):
        return None
    ua, ub = _chord_from_cusp(a), _chord_from_cusp(b)
    top = min(CUSP_WINDOW_MAX_M, 0.5 * float(ua[-1]), 0.5 * float(ub[-1]))
    # The shortest window that holds the points a fit needs on both sides.
    start = max(float(ua[CUSP_MIN_SIDE]), float(ub[CUSP_MIN_SIDE]))
    best: SharedCusp | None = None
    best_var = math.inf
    w = start
    while w <= top * (1.0 + 1e-9):
        sa, sb = a[ua <= w], b[ub <= w]
        for degree in (1, 2, 3):
            got = _fit_window(sa, sb, degree)
            if got is None:
                continue
            point, t, rms, cov = got
            # A residual RMS over k degrees of freedom scatters by about 1 / sqrt(2 k) of sigma:
            # a short window's is allowed that much more (else chance alone refuses it).
            dof = len(sa) + len(sb) - 1 - (2 * degree)
            if dof < 3 or rms > (CUSP_DISCREPANCY + 1.0 / math.sqrt(2.0 * dof)) * noise:
                continue
            # Of the fits the noise allows, the one whose tangent line is surest where the
            # runs bend onto it (the variance of its offset CUSP_BLEND_M behind the cusp).
            var = float(cov[0, 0] - 2.0 * CUSP_BLEND_M * cov[0, 1] + CUSP_BLEND_M ** 2 * cov[1, 1])
            if var < best_var:
                best_var = var
                best = SharedCusp(point, math.atan2(t[1], t[0]), _pace(sa, point, t), _pace(sb, point, t), w, rms)
        w *= math.sqrt(2.0)
    return best
