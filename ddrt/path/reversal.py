"""A polyline that reverses: runs driven one way each, joined at the cusps between them.

A point reached in reverse (a negative `v`) makes the segment to it a reversing one; each run
of segments driven one way is read as its own polyline (by the loader, spec.py, so a reversal
inside a run is still refused naming its point), turned round when driven backwards, and the
runs are joined at each cusp: at the point and heading both runs' samples share
(ddrt/path/cusp.py) where both are smoothed samples, else with a turn in place where the
headings differ.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Callable, Sequence

import numpy as np

from ddrt.core.wrap import wrap_angle
from ddrt.path.condition import WAYPOINTS, ConditionOptions, Conditioning, point_noise, run_tolerance
from ddrt.path.cusp import (
    CUSP_BLEND_MAX_RAD, SharedCusp, bend_end, bend_start, blend_length, blend_offset, estimate_cusp,
)
from ddrt.path.geometry import Geometry, GeometryOptions, Piece, pivot_piece, reversed_piece
from ddrt.path.smoothing import EndPin

__all__ = ["Point", "Run", "RunFitter", "direction_runs", "reversing_geometry"]

Point = tuple[float, float, float]  # x, y and the speed cap v (negative: reached in reverse)
Run = tuple[int, int, float]  # first point, last point, direction (+1 forward, -1 reverse)
# Reads one run's points (x, y, |v|) with their names as a polyline, trying the start and end
# pins given in order, with the noise pooled over the runs (spec.py's reader).
RunFitter = Callable[[list[Point], list[str], Sequence[tuple[EndPin | None, EndPin | None]], float | None],
                     tuple[Geometry, Conditioning]]

# At a cusp whose two headings differ by more than this the robot turns in place there.
CUSP_TURN_TOL_RAD = 1e-4
# A run needs this many points for its own noise estimate to count in the pooled one.
NOISE_POOL_MIN_POINTS = 8


def direction_runs(pts: list[Point]) -> list[Run]:
    """(first point, last point, direction) of each run of segments driven one way. The segment
    to point k is driven in reverse when point k's v is negative (the robot reaches it backwards)."""
    dirs = [-1.0 if pts[k][2] < 0.0 else 1.0 for k in range(1, len(pts))] or [1.0]
    runs: list[Run] = []
    a = 0
    for k in range(1, len(dirs) + 1):
        if k == len(dirs) or dirs[k] != dirs[a]:
            runs.append((a, k, dirs[a]))
            a = k
    return runs


def reversing_geometry(pts: list[Point], names: list[str], runs: list[Run], copt: ConditionOptions,
                       opt: GeometryOptions, fit_run: RunFitter) -> tuple[Geometry, Conditioning]:
    """A polyline with runs driven in reverse: each run read as its own polyline (so a reversal
    inside a run is still refused naming its point), its pieces turned round, joined at each
    cusp. Where both runs are smoothed samples the cusp is estimated once from both runs'
    points and each run fitted ending there on its heading (ddrt/path/cusp.py); otherwise a
    turn in place joins them where the headings differ. The runs are one recording, with one
    noise: each is smoothed for the noise pooled over all (a short run's own estimate is
    unsure, and too low a one leaves noise in its curvature). Speed caps are |v|.

    `fit_run` reads one run (the loader's polyline reader, spec.py), trying the pins given."""
    shared, noise, tols = _shared_cusps(pts, runs, copt)
    pieces: list[Piece] = []
    cap_s: list[np.ndarray] = []
    cap_v: list[np.ndarray] = []
    conds: list[tuple[int, Conditioning]] = []
    sigma = 0.0
    held = 0
    for r, (a, b, d) in enumerate(runs):
        sub = [(x, y, abs(v)) for x, y, v in pts[a:b + 1]]
        before = shared[r - 1] if r > 0 else None
        after = shared[r] if r < len(shared) else None
        # The start meets the previous run's end: at the shared cusp on its heading when that run
        # ended there, else at that end's point (within the tolerance of this run's first point);
        # the end at the shared cusp, else at the cusp sample itself. Only if no fit holds them
        # is the run fitted free and moved onto the previous end (below).
        starts: list[EndPin | None] = [None]
        ends_: list[EndPin | None] = [None]
        if r > 0:
            prev_end = np.array([pieces[-1].x[-1], pieces[-1].y[-1]], dtype=float)
            last = conds[-1][1].extra.get("ends", (None, None))[1]
            starts = []
            if before is not None and last is not None and last.slope is not None:
                starts.append(EndPin(before.point, -before.pace_out * before.direction))
            if math.hypot(*(prev_end - np.array(pts[a][:2]))) <= tols[r]:
                starts.append(EndPin(prev_end))
        if r < len(runs) - 1:
            ends_ = ([] if after is None else [EndPin(after.point, after.pace_in * after.direction)])
            ends_.append(EndPin(np.array(pts[b][:2], dtype=float)))
        tries = [(s0, s1) for s0 in starts for s1 in ends_]
        geo, cond = fit_run(sub, names[a:b + 1], tries, noise)
        run = [reversed_piece(pc) for pc in geo.pieces] if d < 0.0 else geo.pieces
        if pieces:
            got_end = conds[-1][1].extra.get("ends", (None, None))[1]
            got_start = cond.extra.get("ends", (None, None))[0]
            if got_end is not None and got_end.slope is not None and got_start is not None and got_start.slope is not None:
                held += 1
            # A smoothed run need not end exactly on its last point: the next one is moved onto
            # it (by less than the tolerance), so the two meet at one cusp.
            dx, dy = float(pieces[-1].x[-1] - run[0].x[0]), float(pieces[-1].y[-1] - run[0].y[0])
            if dx or dy:
                for pc in run:
                    pc.x, pc.y = pc.x + dx, pc.y + dy
                cond.deviation_m += math.hypot(dx, dy)
            turn = wrap_angle(float(run[0].theta[0]) - float(pieces[-1].theta[-1]))
            if abs(turn) > CUSP_TURN_TOL_RAD and _blend_cusp(pieces[-1], run[0], turn, conds[-1][1], cond):
                turn = 0.0
            if abs(turn) > CUSP_TURN_TOL_RAD:
                pieces.append(pivot_piece(float(run[0].x[0]), float(run[0].y[0]), float(pieces[-1].theta[-1]), turn,
                                     opt.pivot_radius, opt.step))
                sigma += pieces[-1].length
        if geo.cap_sigma is not None and geo.cap_value is not None:
            cap_s.append(sigma + geo.cap_sigma)
            cap_v.append(geo.cap_value)
        pieces += run
        sigma += sum(pc.length for pc in run)
        conds.append((a, cond))
    out = Geometry(pieces)
    if cap_s:
        out.cap_sigma = np.maximum.accumulate(np.concatenate(cap_s))
        out.cap_value = np.concatenate(cap_v)
    joined = _joined_conditioning(pts, names, conds, [a for a, _, _ in runs[1:]])
    joined.extra["cusps_shared"] = held
    return out, joined



def _shared_cusps(pts: list[Point], runs: list[Run],
                  copt: ConditionOptions) -> tuple[list[SharedCusp | None], float | None, list[float]]:
    """Each cusp's point and heading from the points of both runs that meet there, where both
    are smoothed samples (ddrt/path/cusp.py; None where either is waypoints or too short, or
    the estimated point is farther than the tolerance from the cusp sample), the noise pooled
    over the smoothed runs (the RMS of their estimates, weighted by their points; None if no
    run has enough points for one), and each run's tolerance."""
    xys = [np.array([(p[0], p[1]) for p in pts[a:b + 1]], dtype=float) for a, b, _ in runs]
    found = [point_noise(xy, copt) if len(xy) >= 4 else (WAYPOINTS, 0.0) for xy in xys]
    pool = [(len(xy), nz) for xy, (mode, nz) in zip(xys, found)
            if mode != WAYPOINTS and len(xy) >= NOISE_POOL_MIN_POINTS]
    noise = (math.sqrt(sum(n * nz * nz for n, nz in pool) / sum(n for n, _ in pool))) if pool else None
    tols = [run_tolerance(xy, copt, noise) for xy in xys]
    out: list[SharedCusp | None] = []
    for r in range(len(runs) - 1):
        (ma, na), (mb, nb) = found[r], found[r + 1]
        cusp = (None if WAYPOINTS in (ma, mb)
                else estimate_cusp(xys[r], xys[r + 1], max(na, nb) if noise is None else noise))
        # The cusp sample is measured against the shared point, and a pinned point is not one the
        # fit can move: a point farther from it than the tolerance is no cusp the runs can share.
        if cusp is not None and math.hypot(*(cusp.point - xys[r][-1])) > min(tols[r], tols[r + 1]):
            cusp = None
        out.append(cusp)
    return out, noise, tols


def _blend_cusp(end: Piece, start: Piece, turn: float, before: Conditioning, after: Conditioning) -> bool:
    """Bend two smoothed runs onto one heading at their cusp when the difference is within what
    their points allow (ddrt/path/cusp.py); False (nothing changed) otherwise."""
    if before.mode == WAYPOINTS or after.mode == WAYPOINTS or abs(turn) > CUSP_BLEND_MAX_RAD:
        return False
    la, lb = blend_length(end), blend_length(start)
    ea, eb = blend_offset(la, 0.5 * turn), blend_offset(lb, 0.5 * turn)
    if before.deviation_m + ea > before.tolerance_m or after.deviation_m + eb > after.tolerance_m:
        return False
    bend_end(end, 0.5 * turn, la)
    bend_start(start, -0.5 * turn, lb)
    before.deviation_m += ea
    after.deviation_m += eb
    return True


def _joined_conditioning(pts: list[Point], names: list[str],
                         conds: list[tuple[int, Conditioning]], cusps: list[int]) -> Conditioning:
    """One Conditioning for the runs of a reversing polyline (indices into all its points)."""
    first = next((c for _, c in conds if c.mode != WAYPOINTS), conds[0][1])
    worst_a, worst = max(conds, key=lambda ac: ac[1].deviation_m)
    corners = tuple(replace(k, index=k.index + a) for a, c in conds for k in c.corners)
    xy = np.array([(p[0], p[1]) for p in pts], dtype=float)
    seg = np.hypot(*np.diff(xy, axis=0).T)
    # Each run's tolerance (`auto` sets one per run, from the pooled noise and its points).
    tol = max((c.tolerance_m for _, c in conds if c.mode != WAYPOINTS), default=first.tolerance_m)
    out = Conditioning(first.mode, tol, xy, names, deviation_m=worst.deviation_m, auto=first.auto,
                       worst=worst_a + worst.worst, noise_m=max(c.noise_m for _, c in conds),
                       grid_cell_m=first.grid_cell_m, smoothing_m=tuple(e for _, c in conds for e in c.smoothing_m),
                       corners=corners, spacing_m=float(np.median(seg)) if len(seg) else 0.0,
                       iterations=sum(c.iterations for _, c in conds))
    out.extra["cusps"] = [names[k] for k in cusps]
    return out

