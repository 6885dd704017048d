"""Corners of a polyline of samples: where the direction turns by more than a threshold within
a short stretch, at two scales (a smooth bend turns half as much at half the scale; a corner
as much), so a tight bend is not one.

The direction either side of a point is the least-squares line of the points within `scale`
of it along the curve (x(u), y(u) fitted in the distance u the points stand for), not the
chord to a point there: a chord shares the point's own noise between its two sides and reads
a point displaced by the noise as a corner. The scale (`corner_scale`) is a few tolerances,
and never so short that the noise of the points within it can make a turn of the threshold:
a line through m points spanning L misreads the direction by about sigma sqrt(12 / m) / L.

A corner found is placed where the lines through its sides meet, each line fitted clear of
the turn itself, and its legs are held on those lines there (`CornerPin.into`, `.out`), so
the turn in place is the whole turn. Where the lines are nearly parallel (an unmarked
reversal, or a U-turn narrower than the scale) the corner lies midway between them. A leg
fitted with its end tangent free, to a corner placed on lines through the turn itself, bent
its last few centimetres round the rest of the turn: a 2 cm wide recorded U-turn became a 102
degree turn in place and a 20 mm radius hook. Where its legs lie farther apart than the
tolerance, a midpoint would pull each leg off its points: the corner is then a cap across the
legs' ends, a quarter turn onto it and one off it (each leg on its own line). A turn whose
points stray farther than the tolerance from the two lines and the cap (a tight bend wider
than the tolerance) is no corner: it is fitted smooth.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["CornerPin", "corner_scale", "find_corners", "line_turns", "refine_corner"]

# The direction either side of a corner may be misread by noise by this much (1 sigma, rad).
CORNER_NOISE_RAD = math.radians(5.0)
CORNER_SIGMAS = 3.0  # a corner's turn must exceed the threshold by this many of its noise sigmas
CAP_TOLERANCES = 3.0  # a reversal whose legs lie farther apart than this is a U-turn, fitted smooth
PARALLEL_REACH = 3.0  # a reversal's side lines reach this many corner scales back
_CHUNK = 2048  # windows evaluated together (sums relative to the chunk's first point)


def corner_scale(tol: float, noise: float, spacing: float) -> float:
    """The stretch over which a corner turns: a few tolerances, three spacings, and long enough
    that the noise misreads each half-scale side's direction by at most CORNER_NOISE_RAD."""
    side = (noise * math.sqrt(12.0 * max(spacing, 1e-12)) / CORNER_NOISE_RAD) ** (2.0 / 3.0)
    return max(5.0 * tol, 20.0 * noise, 3.0 * spacing, 2.0 * side)


def _wrap(a: np.ndarray) -> np.ndarray:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def _line_directions(p: np.ndarray, u: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Heading (rad) of the least-squares line x(u), y(u) through points lo[j]..hi[j] (inclusive;
    NaN with fewer than 3), from running sums taken chunk by chunk relative to each chunk's
    first point, so coordinates far from the origin lose no precision."""
    out = np.full(len(lo), np.nan)
    for c0 in range(0, len(lo), _CHUNK):
        sl = slice(c0, min(c0 + _CHUNK, len(lo)))
        a, b = lo[sl], hi[sl]
        base, top = int(a.min()), int(b.max())
        q = p[base:top + 1] - p[base]
        t = u[base:top + 1] - u[base]
        sums = [np.concatenate(([0.0], np.cumsum(v))) for v in (np.ones_like(t), t, t * t, q[:, 0], q[:, 1],
                                                               t * q[:, 0], t * q[:, 1])]
        i0, i1 = a - base, b - base + 1
        n, st, stt, sx, sy, stx, sty = (s[i1] - s[i0] for s in sums)
        with np.errstate(invalid="ignore", divide="ignore"):
            var = stt - st * st / n
            vx = (stx - st * sx / n) / var
            vy = (sty - st * sy / n) / var
            out[sl] = np.where((n >= 3) & (var > 0.0), np.arctan2(vy, vx), np.nan)
    return out


def line_turns(p: np.ndarray, u: np.ndarray, scale: float, noise: float = 0.0,
               side_error: float = math.inf) -> tuple[np.ndarray, np.ndarray]:
    """Turn at each point between the lines through the points within `scale` before it and
    after it, and how far the noise may have moved it (1 sigma: the sides' direction errors,
    sigma sqrt(12 / m) / L for m points over L, combined); NaN where a side is shorter than a
    quarter of the scale (near the ends) or its direction is less sure than `side_error` (rad):
    a short side near an end, read on noise, would turn any way."""
    idx = np.arange(len(p))
    lo = np.searchsorted(u, u - scale, side="left")
    hi = np.searchsorted(u, u + scale, side="right") - 1
    before = _line_directions(p, u, lo, idx)
    after = _line_directions(p, u, idx, hi)
    turn = _wrap(after - before)
    len_b, len_a = u - u[lo], u[hi] - u
    short = (len_b < 0.25 * scale) | (len_a < 0.25 * scale)
    with np.errstate(divide="ignore", invalid="ignore"):
        err_b = noise * np.sqrt(12.0 / (idx - lo + 1)) / len_b
        err_a = noise * np.sqrt(12.0 / (hi - idx + 1)) / len_a
    unsure = (err_b > side_error) | (err_a > side_error)
    turn[short | unsure | ~np.isfinite(turn)] = np.nan
    return turn, np.hypot(err_b, err_a)


def find_corners(p: np.ndarray, u: np.ndarray, scale: float, threshold: float,
                 noise: float = 0.0, apart: float | None = None) -> list[tuple[int, float]]:
    """(index, turn) of corners: points where the direction turns by more than `threshold`
    at both `scale` and half of it, one per `apart` of length (the sharpest; default `scale`:
    a grid plan's exact corners may lie closer), measured only
    where the noise leaves each side's direction sure to a quarter of the threshold, and by
    more than the threshold with CORNER_SIGMAS of the turn's own noise taken off (a bend of
    28 degrees read as 36 on 22 mm of noise is no corner)."""
    t1, e1 = line_turns(p, u, scale, noise, 0.25 * threshold)
    t2, e2 = line_turns(p, u, 0.5 * scale, noise, 0.25 * threshold)
    with np.errstate(invalid="ignore"):
        sure = np.minimum(np.abs(t1) - CORNER_SIGMAS * e1, np.abs(t2) - CORNER_SIGMAS * e2)
        score = np.where(np.sign(t1) == np.sign(t2), sure, 0.0)
    score = np.nan_to_num(score, nan=0.0)
    score[0] = score[-1] = 0.0
    cand = np.flatnonzero(score > threshold)
    if len(cand) == 0:
        return []
    # Equal turns (a grid plan's symmetric corners) are taken in order along the path, not in
    # the order their last bits happen to give.
    order = cand[np.argsort(-np.round(score[cand], 9), kind="stable")]
    gap = scale if apart is None else apart
    taken: list[int] = []
    for i in order.tolist():
        if all(abs(u[i] - u[k]) >= gap for k in taken):
            taken.append(i)
    taken.sort()
    return [(i, float(t2[i])) for i in taken]


class CornerPin:
    """Where a corner is, the directions of travel into it and out of it (None: free), the
    length either side over which the legs leave their points to meet there (`settle`: a narrow
    reversal's corner lies midway between its legs, off both), and, for a reversal whose legs
    lie farther apart than the tolerance, where the leg after it starts (`cap`: the robot turns
    onto the cap from `point` and off it at `cap`)."""

    def __init__(self, point: np.ndarray, into: np.ndarray | None = None, out: np.ndarray | None = None,
                 settle: float = 0.0, cap: np.ndarray | None = None) -> None:
        self.point, self.into, self.out, self.settle, self.cap = point, into, out, settle, cap


def _side_line(p: np.ndarray, sel: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Centroid and unit direction (along the points' order) of the points `sel`."""
    q = p[sel]
    if len(q) < 3:
        return None
    c = q.mean(axis=0)
    _, _, vt = np.linalg.svd(q - c, full_matrices=False)
    d = vt[0]
    return c, (d if float((q[-1] - q[0]) @ d) >= 0.0 else -d)


def _corner_distance(q: np.ndarray, x1: np.ndarray, x2: np.ndarray, into: np.ndarray,
                     out: np.ndarray) -> np.ndarray:
    """Distance of the points q from the corner's polyline: the ray arriving at x1 along `into`,
    the segment x1 - x2 (a reversal's cap across its legs; nothing where the lines meet), and
    the ray leaving x2 along `out`."""
    def ray(x: np.ndarray, d: np.ndarray, sign: float) -> np.ndarray:
        r = q - x
        t = np.maximum(sign * (r @ d), 0.0)
        return np.hypot(*(r - sign * t[:, None] * d[None, :]).T)

    cap = x2 - x1
    n2 = float(cap @ cap)
    t = np.clip(((q - x1) @ cap) / n2, 0.0, 1.0) if n2 > 0.0 else np.zeros(len(q))
    seg = np.hypot(*(q - x1 - t[:, None] * cap[None, :]).T)
    return np.minimum(np.minimum(ray(x1, into, -1.0), ray(x2, out, 1.0)), seg)


def _segment_gap(q: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> float:
    """Distance of the point q from the segment x1 - x2."""
    return float(_corner_distance(q[None, :], x1, x2, np.zeros(2), np.zeros(2))[0])


def _sides(p: np.ndarray, u: np.ndarray, k: int, scale: float, reach: tuple[float, float]
           ) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]] | None:
    """The lines either side of point k, fitted clear of the turn (from half a scale to
    PARALLEL_REACH scales away, within `reach`), or within a scale where a side has too few."""
    lo, hi = max(u[k] - PARALLEL_REACH * scale, reach[0]), min(u[k] + PARALLEL_REACH * scale, reach[1])
    before = (_side_line(p, np.flatnonzero((u >= lo) & (u <= u[k] - 0.5 * scale)))
              or _side_line(p, np.flatnonzero((u >= u[k] - scale) & (u < u[k]))))
    after = (_side_line(p, np.flatnonzero((u >= u[k] + 0.5 * scale) & (u <= hi)))
             or _side_line(p, np.flatnonzero((u > u[k]) & (u <= u[k] + scale))))
    return None if before is None or after is None else (before, after)


def _parallel(d1: np.ndarray, d2: np.ndarray) -> bool:
    return abs(float(d1[0] * d2[1] - d1[1] * d2[0])) < math.sin(math.radians(10.0))


def _tip(p: np.ndarray, u: np.ndarray, k: int, scale: float, d1: np.ndarray) -> int:
    """A reversal's tip: of the points within a scale of k, the one farthest along the arriving
    direction (the sharpest turn found may lie where the turn starts, not at its end)."""
    near = np.flatnonzero(np.abs(u - u[k]) <= scale)
    return int(near[np.argmax(p[near] @ d1)])


def refine_corner(p: np.ndarray, u: np.ndarray, k: int, scale: float, tol: float,
                  reach: tuple[float, float] = (-math.inf, math.inf)) -> tuple[int, CornerPin | None]:
    """The corner found at point k (and the point it is at: a reversal's tip), from lines fitted
    to the points either side clear of the turn (`_sides`), so the turn in place is all of the
    turn: where the lines meet; for a reversal (the lines nearly parallel) midway between them
    where its legs lie within the tolerance of each other, or a cap across them within
    CAP_TOLERANCES of it. None where that is no clean corner (fitted smooth instead): the corner lies farther
    than `tol` from the point, the points round it farther than `tol` from the lines meeting
    there, or a reversal's legs lie wider apart than a cap (a U-turn the robot can drive)."""
    sides = _sides(p, u, k, scale, reach)
    if sides is None:
        return k, CornerPin(p[k].copy())
    (c1, d1), (c2, d2) = sides
    if _parallel(d1, d2):
        k = _tip(p, u, k, scale, d1)
        sides = _sides(p, u, k, scale, reach) or sides
        (c1, d1), (c2, d2) = sides
    if not _parallel(d1, d2):
        r = c2 - c1
        den = float(d1[0] * d2[1] - d1[1] * d2[0])
        x1 = x2 = c1 + (r[0] * d2[1] - r[1] * d2[0]) / den * d1
    else:  # the legs' feet at the tip
        x1, x2 = c1 + d1 * float((p[k] - c1) @ d1), c2 + d2 * float((p[k] - c2) @ d2)
    width = float(math.hypot(*(x2 - x1)))
    zone = np.flatnonzero(np.abs(u - u[k]) <= 0.5 * scale)
    if (not np.all(np.isfinite(x1 + x2)) or width > CAP_TOLERANCES * tol or _segment_gap(p[k], x1, x2) > tol
            or float(np.max(_corner_distance(p[zone], x1, x2, d1, d2))) > tol):
        return k, None
    if width > tol:
        return k, CornerPin(x1, d1, d2, scale, x2)  # a cap: the legs stay on their lines
    return k, CornerPin(0.5 * (x1 + x2), d1, d2, scale if width > 0.0 else 0.0)
