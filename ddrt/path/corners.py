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
degree turn in place and a 20 mm radius hook. A turn whose points stray farther than the
tolerance from the two lines (a tight bend wider than the tolerance) is no corner: it is
fitted smooth.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["CornerPin", "corner_scale", "find_corners", "line_turns", "refine_corner"]

# The direction either side of a corner may be misread by noise by this much (1 sigma, rad).
CORNER_NOISE_RAD = math.radians(5.0)
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
               side_error: float = math.inf) -> np.ndarray:
    """Turn at each point between the lines through the points within `scale` before it and
    after it; NaN where a side is shorter than a quarter of the scale (near the ends) or its
    direction is less sure than `side_error` (rad; sigma sqrt(12 / m) / L for m points over L):
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
    return turn


def find_corners(p: np.ndarray, u: np.ndarray, scale: float, threshold: float,
                 noise: float = 0.0) -> list[tuple[int, float]]:
    """(index, turn) of corners: points where the direction turns by more than `threshold`
    at both `scale` and half of it, one per `scale` of length (the sharpest), measured only
    where the noise leaves each side's direction sure to a quarter of the threshold."""
    t1 = line_turns(p, u, scale, noise, 0.25 * threshold)
    t2 = line_turns(p, u, 0.5 * scale, noise, 0.25 * threshold)
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


class CornerPin:
    """Where a corner is, the directions of travel into it and out of it (None: free), and the
    length either side over which the legs leave their points to meet there (`settle`: a
    reversal's corner lies midway between its legs, off both)."""

    def __init__(self, point: np.ndarray, into: np.ndarray | None = None, out: np.ndarray | None = None,
                 settle: float = 0.0) -> None:
        self.point, self.into, self.out, self.settle = point, into, out, settle


def _side_line(p: np.ndarray, sel: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Centroid and unit direction (along the points' order) of the points `sel`."""
    q = p[sel]
    if len(q) < 3:
        return None
    c = q.mean(axis=0)
    _, _, vt = np.linalg.svd(q - c, full_matrices=False)
    d = vt[0]
    return c, (d if float((q[-1] - q[0]) @ d) >= 0.0 else -d)


def _ray_distance(q: np.ndarray, x: np.ndarray, into: np.ndarray, out: np.ndarray) -> np.ndarray:
    """Distance of the points q from the corner polyline: the ray arriving at x along `into`
    and the one leaving it along `out`."""
    def ray(d: np.ndarray, sign: float) -> np.ndarray:
        r = q - x
        t = np.maximum(sign * (r @ d), 0.0)
        return np.hypot(*(r - sign * t[:, None] * d[None, :]).T)

    return np.minimum(ray(into, -1.0), ray(out, 1.0))


def refine_corner(p: np.ndarray, u: np.ndarray, k: int, scale: float, tol: float,
                  reach: tuple[float, float] = (-math.inf, math.inf)) -> CornerPin | None:
    """The corner at point k, from lines fitted to the points either side clear of the turn
    itself (from half a scale to PARALLEL_REACH scales away, within `reach`, the u range up to
    the neighbouring corners; the points within a scale where a side has too few), so the turn
    in place is all of the turn: where they meet, or midway between them where they are nearly
    parallel (a reversal, a narrow U-turn). None where that is no clean corner: the point is
    farther than `tol` from the corner's own point, or the points round it farther than `tol`
    from the two lines meeting there (a tight bend wider than the tolerance, which the legs
    would have to hook round: it is fitted smooth instead)."""
    lo, hi = max(u[k] - PARALLEL_REACH * scale, reach[0]), min(u[k] + PARALLEL_REACH * scale, reach[1])
    before = (_side_line(p, np.flatnonzero((u >= lo) & (u <= u[k] - 0.5 * scale)))
              or _side_line(p, np.flatnonzero((u >= u[k] - scale) & (u < u[k]))))
    after = (_side_line(p, np.flatnonzero((u >= u[k] + 0.5 * scale) & (u <= hi)))
             or _side_line(p, np.flatnonzero((u > u[k]) & (u <= u[k] + scale))))
    if before is None or after is None:
        return CornerPin(p[k].copy())
    (c1, d1), (c2, d2) = before, after
    den = d1[0] * d2[1] - d1[1] * d2[0]
    parallel = abs(den) < math.sin(math.radians(10.0))
    if not parallel:
        r = c2 - c1
        x = c1 + (r[0] * d2[1] - r[1] * d2[0]) / den * d1
    else:
        x = 0.5 * (c1 + d1 * float((p[k] - c1) @ d1) + c2 + d2 * float((p[k] - c2) @ d2))
    if not np.all(np.isfinite(x)) or math.hypot(*(x - p[k])) > tol:
        return None
    zone = np.flatnonzero(np.abs(u - u[k]) <= 0.5 * scale)
    if float(np.max(_ray_distance(p[zone], x, d1, d2))) > tol:
        return None
    return CornerPin(x, d1, d2, scale if parallel else 0.0)
