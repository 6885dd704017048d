"""Tracking metrics of a run, accumulated chunk by chunk as the telemetry comes (numpy is fine here).

The cross-track distance of a tick is the distance from the robot to the path's dense
polyline (`path_polyline`, 1 mm) within `WINDOW` segments either side of the run's progress
(the telemetry's `sigma`): a robot at a figure-eight's crossing is measured against its own
branch, not the one it is crossing. The search costs O(1) per tick, so a run's metrics are
linear in ticks plus path samples:

- The polyline is cut into blocks of `BLOCK` segments, each inside a bounding disk. Every
  tick searches exactly the segments of the block that holds its progress and of the two
  blocks beside it (`3 * BLOCK` segments).
- Each block knows its *clearance*: how close the disks of the other blocks that a window
  can reach come to its own disk. A tick whose distance is below the clearance minus its
  distance from its block's disk cannot be nearer to any other segment of its window, so the
  local answer is the windowed one, exactly.
- A tick that this cannot certify (the robot far from the path, the start of a run that
  begins off the path, a turn in place where many samples sit on one point, a path that
  comes back near itself within the window) is searched over its whole window, as
  `distances_to_polyline` always did: at most 2 * WINDOW + 1 segments per tick, never the
  whole path.

Running sums and maxima replace the arrays, so nothing grows with the run's length.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ddrt.path import Path
from ddrt.path.sampled import distances_to_polyline

__all__ = ["BLOCK", "GROUP", "STEP_M", "WINDOW", "PolylineDistance", "TrackingAccumulator", "distances_to_polyline",
           "path_polyline", "tracking_metrics", "wrap_angles"]

STEP_M = 0.001  # polyline spacing (m)
WINDOW = 400  # segments searched either side of the run's progress
BLOCK = 4  # segments per fine block of the local search
GROUP = 8  # fine blocks per coarse block
_BATCH = 1024  # points per vectorised batch of the local searches (bounds their memory)
_FALLBACK_CHUNK = 64  # points per vectorised batch of the whole-window search (bounds its memory)


def path_polyline(path: Path, step: float = STEP_M) -> np.ndarray:
    """Dense (N, 2) polyline of the path's geometry (pivots collapse to their corner point).

    The same points as `path.at(s)` at N evenly spaced s (same arithmetic, vectorised)."""
    n = max(2, int(math.ceil(path.length / step)) + 1)
    s = np.linspace(0.0, path.length, n)
    s = np.clip(s, 0.0, path.length)
    arr = path.arrays()
    sig, xs, ys = arr["sigma"], arr["x"], arr["y"]
    # Path.geometry's own arithmetic, vectorised: the same points as path.at(s) for each s.
    i = np.clip(np.searchsorted(sig, s, side="right") - 1, 0, len(sig) - 2)
    s0 = sig[i]
    f = (s - s0) / (sig[i + 1] - s0)
    pts = np.empty((n, 2))
    pts[:, 0] = xs[i] + f * (xs[i + 1] - xs[i])
    pts[:, 1] = ys[i] + f * (ys[i + 1] - ys[i])
    return pts


def wrap_angles(a: np.ndarray) -> np.ndarray:
    """`ddrt.core.wrap.wrap_angle` elementwise (same operations, so the same values)."""
    w = np.fmod(np.asarray(a, dtype=float) + math.pi, 2.0 * math.pi)
    w = np.where(w <= 0.0, w + 2.0 * math.pi, w)
    return w - math.pi


def _disks(a: np.ndarray, b: np.ndarray, size: int) -> tuple[np.ndarray, np.ndarray]:
    """Bounding disks (centres (nb, 2), radii (nb,)) of consecutive blocks of `size` segments a->b."""
    nseg = len(a)
    starts = np.arange(0, nseg, size)
    lo = np.minimum.reduceat(np.minimum(a, b), starts, axis=0)
    hi = np.maximum.reduceat(np.maximum(a, b), starts, axis=0)
    c = 0.5 * (lo + hi)
    cs = np.repeat(c, np.diff(np.append(starts, nseg)), axis=0)
    far = np.maximum(np.hypot(*(a - cs).T), np.hypot(*(b - cs).T))
    # Radii rounded up, so every segment lies inside its disk despite rounding.
    return c, np.maximum.reduceat(far, starts) * (1.0 + 1e-9) + 1e-12


def _clearance(c: np.ndarray, r: np.ndarray, lo: int, hi: int) -> np.ndarray:
    """Per block, a lower bound of the distance from its disk to the disks lo..hi blocks away."""
    nb = len(c)
    clear = np.full(nb, np.inf)
    for o in range(lo, min(hi, nb - 1) + 1):
        gap = np.hypot(*(c[o:] - c[:-o]).T) - r[o:] - r[:-o]
        np.minimum(clear[:-o], gap, out=clear[:-o])
        np.minimum(clear[o:], gap, out=clear[o:])
    return clear


class PolylineDistance:
    """Distance of points to a polyline within `window` segments of a given index, O(1) per point.

    A turn in place puts many samples on one point: each run of zero-length segments is
    searched as one (the same geometry, so the same distances), and the searches below work
    on that compressed polyline, each restricted to the segments of the point's window.

    Two levels of blocks: fine ones of `block` segments and coarse ones of `group` fine blocks.
    A point whose index lies in fine block b (coarse block C) is first measured against fine
    blocks b - 1..b + 1; that is its windowed distance when it is below both
    - the fine clearance of b (every other fine block of coarse blocks C - 1..C + 1), less
      the point's distance from b's disk, and
    - the coarse clearance of C (the coarse blocks 2 or more away that a window reaches),
      less the point's distance from C's disk.
    Else it is measured against coarse blocks C - 1..C + 1 under the coarse clearance alone,
    and at last against its whole window (`distances_to_polyline`, at most 2 * window + 1
    segments)."""

    def __init__(self, poly: np.ndarray, window: int = WINDOW, block: int = BLOCK, group: int = GROUP) -> None:
        if block < 1 or group < 2 or 2 * block * group > window:
            raise ValueError(f"block={block}, group={group}: need block >= 1, group >= 2 and "
                             f"2 * block * group <= window ({window})")
        self.poly = np.asarray(poly, dtype=float)
        self.window = int(window)
        a = self.poly[:-1]
        b = self.poly[1:]
        ab = b - a
        len2 = np.einsum("ij,ij->i", ab, ab)
        self.nseg = len(a)
        # Keep the first segment of every run of zero-length ones; _map: segment -> kept one.
        zero = len2 == 0.0
        keep = ~zero
        keep[1:] |= zero[1:] & ~zero[:-1]
        keep[0] = True
        self._compressed = not keep.all()
        self._map = np.cumsum(keep) - 1
        if self._compressed:
            a, b, ab, len2 = a[keep], b[keep], ab[keep], len2[keep]
        self._a, self._ab = a, ab
        self._len2 = np.where(len2 > 0.0, len2, 1.0)
        self._n = len(a)
        self._fine = block
        self._coarse = block * group
        self._cf, self._rf = _disks(a, b, self._fine)
        self._cc, self._rc = _disks(a, b, self._coarse)
        # Fine: every fine block of the coarse blocks beside (at most 2 * group - 1 away).
        self._clear_f = _clearance(self._cf, self._rf, 2, 2 * group - 1)
        # Coarse: every coarse block a window can reach (compression only shortens it), from 2 away.
        self._clear_c = _clearance(self._cc, self._rc, 2, window // self._coarse + 2)
        self.fallbacks = 0  # points measured against their whole window (benchmarks, tests)

    def _local(self, xy: np.ndarray, kc: np.ndarray, lo: np.ndarray | None, hi: np.ndarray | None,
               size: int) -> np.ndarray:
        """Distance to the (compressed) blocks of `size` beside each point's, within [lo, hi]."""
        blk = kc // size
        idx = np.clip(blk[:, None] * size + np.arange(-size, 2 * size)[None, :], 0, self._n - 1)
        sa = self._a[idx]
        sab = self._ab[idx]
        ap = xy[:, None, :] - sa
        t = np.clip(np.einsum("mij,mij->mi", ap, sab) / self._len2[idx], 0.0, 1.0)
        diff = ap - t[:, :, None] * sab
        d2 = np.einsum("mij,mij->mi", diff, diff)
        if lo is not None and hi is not None:
            d2[(idx < lo[:, None]) | (idx > hi[:, None])] = np.inf
        return np.sqrt(d2.min(axis=1))

    @staticmethod
    def _margin(clear: np.ndarray, c: np.ndarray, r: np.ndarray, xy: np.ndarray) -> np.ndarray:
        """clearance less the point's distance from its block's disk (a lower bound elsewhere)."""
        return clear - np.maximum(np.hypot(*(xy - c).T) - r, 0.0)

    def __call__(self, xy: np.ndarray, near: np.ndarray) -> np.ndarray:
        """Distance of each point of `xy` (M, 2) to the segments within `window` of `near` (M,)."""
        xy = np.asarray(xy, dtype=float).reshape(-1, 2)
        near = np.clip(np.asarray(near, dtype=np.int64).reshape(-1), 0, self.nseg - 1)
        out = np.empty(len(xy))
        for i in range(0, len(xy), _BATCH):  # batches bound the temporaries' memory
            out[i:i + _BATCH] = self._batch(xy[i:i + _BATCH], near[i:i + _BATCH])
        return out

    def _batch(self, xy: np.ndarray, near: np.ndarray) -> np.ndarray:
        m = self._map
        kc = m[near]
        lo = hi = None
        if self._compressed:
            lo = m[np.maximum(near - self.window, 0)]
            hi = m[np.minimum(near + self.window, self.nseg - 1)]
        d = self._local(xy, kc, lo, hi, self._fine)
        bf = kc // self._fine
        bc = kc // self._coarse
        coarse_ok = self._margin(self._clear_c[bc], self._cc[bc], self._rc[bc], xy)
        bound = np.minimum(self._margin(self._clear_f[bf], self._cf[bf], self._rf[bf], xy), coarse_ok)
        bad = np.flatnonzero(bound < d * (1.0 + 1e-9) + 1e-12)
        if len(bad):
            d2 = self._local(xy[bad], kc[bad], None if lo is None else lo[bad], None if hi is None else hi[bad],
                             self._coarse)
            d[bad] = d2
            worse = bad[coarse_ok[bad] < d2 * (1.0 + 1e-9) + 1e-12]
            if len(worse):
                self.fallbacks += len(worse)
                d[worse] = distances_to_polyline(self.poly, xy[worse], near[worse], window=self.window,
                                                 chunk=_FALLBACK_CHUNK)
        return d


class TrackingAccumulator:
    """`tracking_metrics` fed in chunks: running sums and maxima, nothing kept per tick."""

    def __init__(self, path: Path, step: float = STEP_M) -> None:
        self.path = path
        self.poly = path_polyline(path, step)
        self.distance = PolylineDistance(self.poly)
        self._h = path.length / (len(self.poly) - 1) if path.length > 0.0 else 1.0
        self.n = 0
        self._sq_true = self._sq_est = self._sq_head = 0.0
        self._max_true = self._max_est = -math.inf
        self._sat = 0.0
        self._last_true: tuple[float, float] | None = None

    def distances(self, xy: np.ndarray, sigma: np.ndarray | None) -> np.ndarray:
        """Cross-track distances of `xy` at progress `sigma` (None: to the whole polyline, O(M N))."""
        if sigma is None:
            return distances_to_polyline(self.poly, xy, chunk=_FALLBACK_CHUNK)
        near = np.clip(np.round(np.asarray(sigma) / self._h).astype(int), 0, len(self.poly) - 2)
        return self.distance(xy, near)

    def add(self, true_xy: np.ndarray, est_xy: np.ndarray, heading_err: np.ndarray, saturated: np.ndarray,
            sigma: np.ndarray | None = None) -> None:
        m = len(true_xy)
        if m == 0:
            return
        d_true = self.distances(true_xy, sigma)
        d_est = self.distances(est_xy, sigma)
        self.n += m
        self._sq_true += float(np.dot(d_true, d_true))
        self._sq_est += float(np.dot(d_est, d_est))
        self._max_true = float(np.maximum(self._max_true, d_true.max()))  # NaN propagates, as in d.max()
        self._max_est = float(np.maximum(self._max_est, d_est.max()))
        h = np.asarray(heading_err, dtype=float)
        self._sq_head += float(np.dot(h, h))
        self._sat += float(np.sum(saturated))
        self._last_true = (float(true_xy[-1, 0]), float(true_xy[-1, 1]))

    def result(self) -> dict[str, float]:
        if self.n == 0 or self._last_true is None:
            return {"rms_cross_track_m": float("nan"), "max_cross_track_m": float("nan"),
                    "rms_tracking_m": float("nan"), "max_tracking_m": float("nan"),
                    "rms_heading_err_rad": float("nan"), "final_pos_err_m": float("nan"),
                    "saturated_fraction": 0.0}
        end = self.path.at(self.path.length)
        n = self.n
        return {
            "rms_cross_track_m": math.sqrt(self._sq_true / n),
            "max_cross_track_m": self._max_true,
            "rms_tracking_m": math.sqrt(self._sq_est / n),
            "max_tracking_m": self._max_est,
            "rms_heading_err_rad": math.sqrt(self._sq_head / n),
            "final_pos_err_m": float(math.hypot(self._last_true[0] - end.x, self._last_true[1] - end.y)),
            "saturated_fraction": self._sat / n,
        }


def tracking_metrics(path: Path, true_xy: np.ndarray, est_xy: np.ndarray, heading_err: np.ndarray,
                     saturated: np.ndarray, sigma: np.ndarray | None = None) -> dict[str, Any]:
    """RMS/max cross-track (true and estimated pose), heading, end error, saturation, in one go.

    With `sigma` (the run's progress per tick) linear in ticks; without it every point is
    measured against the whole polyline (quadratic: for short arrays only)."""
    acc = TrackingAccumulator(path)
    acc.add(np.asarray(true_xy, dtype=float).reshape(-1, 2), np.asarray(est_xy, dtype=float).reshape(-1, 2),
            heading_err, saturated, sigma)
    return acc.result()


def cross_track(px: np.ndarray, py: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Distance of each point of a run (in order) to the polyline (px, py): a window of 800
    segments follows the nearest one, so a long run costs its length, not length x path."""
    out = np.empty(len(xy))
    i0 = 0
    for k, (x, y) in enumerate(xy):
        lo, hi = max(0, i0 - 400), min(len(px) - 1, i0 + 400)
        ax, ay, bx, by = px[lo:hi], py[lo:hi], px[lo + 1:hi + 1], py[lo + 1:hi + 1]
        dx, dy = bx - ax, by - ay
        den = dx * dx + dy * dy
        u = np.clip(((x - ax) * dx + (y - ay) * dy) / np.where(den > 0, den, 1.0), 0.0, 1.0)
        d = np.hypot(ax + u * dx - x, ay + u * dy - y)
        j = int(np.argmin(d))
        out[k] = d[j]
        i0 = lo + j
    return out
