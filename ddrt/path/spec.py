"""Loading a path: a CSV of waypoints, a YAML spec (an analytic shape, inline points or a CSV
file), or the same spec as a mapping (from a config or the control socket). Errors name the
file, line or key.

A spec is built by the config's walker (one dataclass per kind, ddrt/path/shapes.py) from
the same YAML reader as a config. Its own limits can only lower the config's: a larger value
is clamped and reported in `path.warnings`. The config's paths: section sets the sampling
and bounds the work (samples, waypoints, extent, duration), checked before allocating.
"""

from __future__ import annotations

import csv
import io
import math
import os
from dataclasses import replace
from pathlib import Path as FsPath
from typing import TYPE_CHECKING, Any, Callable, Mapping, Sequence

import numpy as np

from ddrt.config.schema import ConfigError, build
from ddrt.config.sections import PathsConfig
from ddrt.config.yamlio import read_text, read_yaml, shorten
from ddrt.path.condition import (
    WAYPOINTS, ConditionError, ConditionOptions, Conditioning, classify, condition_polyline, point_noise,
)
from ddrt.core.wrap import wrap_angle
from ddrt.path.cusp import (
    CUSP_BLEND_MAX_RAD, SharedCusp, bend_end, bend_start, blend_length, blend_offset, estimate_cusp,
)
from ddrt.path.geometry import Geometry, GeometryOptions, Piece, pivot_piece, reversed_piece
from ddrt.path.profile import SpeedLimits
from ddrt.path.sampled import Path
from ddrt.path.shapes import (
    KINDS, LIMIT_KEYS, SHAPES, FileSpec, PathCommon, PointsSpec, RectangleSpec, polyline_samples,
)
from ddrt.path.smoothing import EndPin

if TYPE_CHECKING:
    from ddrt.config import Config

__all__ = ["PathError", "load_path", "path_source", "read_points_csv", "resolve_path", "speed_limits"]


class PathError(ValueError):
    """A path file or spec is malformed; the message names the file, line or key, and the problem."""


# Minimum length of a path (m): shorter, it is a point the robot cannot follow.
MIN_PATH_LENGTH_M = 0.001
# At a cusp whose two headings differ by more than this the robot turns in place there.
CUSP_TURN_TOL_RAD = 1e-4

# The config key each path limit lowers (the config has one acceleration, for braking too).
_CONFIG_KEY = {"speed": "limits.v_max", "accel": "limits.accel", "decel": "limits.accel",
               "lateral_accel": "limits.lateral_accel", "omega_max": "limits.omega_max",
               "alpha_max": "limits.alpha_max"}


def _path_error(exc: ConfigError, where: str) -> PathError:
    """The walker's "key: problem" as the path loader's "where: key 'key': problem"."""
    key, sep, problem = str(exc).partition(": ")
    return PathError(f"{where}: key '{key}': {problem}" if sep else f"{where}: {exc}")


def _number(raw: Any, fail: Callable[[str], PathError], *, positive: bool = False, nonneg: bool = False) -> float:
    """A CSV cell as a number. (A side validator that stays: CSV cells are text, which the
    walker rightly refuses for a YAML number.)"""
    if isinstance(raw, bool) or not isinstance(raw, (int, float, str)):
        raise fail(f"expected a number, got {shorten(raw)}")
    try:
        value = float(raw)
    except (ValueError, OverflowError):
        raise fail(f"not a number: {shorten(raw)}") from None
    if not math.isfinite(value):
        raise fail(f"must be finite, got {shorten(raw)}")
    if positive and value <= 0.0:
        raise fail(f"must be > 0, got {shorten(raw)}")
    if nonneg and value < 0.0:
        raise fail(f"must be >= 0, got {shorten(raw)}")
    return value


def _merge_points(rows: list[tuple[float, float, float]],
                  names: list[str]) -> tuple[list[tuple[float, float, float]], list[str]]:
    """Drop consecutive duplicates (keeping the lower speed cap); the names of the kept ones."""
    out: list[tuple[float, float, float]] = []
    kept: list[str] = []
    for (x, y, v), name in zip(rows, names):
        if out and math.hypot(x - out[-1][0], y - out[-1][1]) < 1e-9:
            # The lower cap; the direction the robot reaches the point in is the first one's.
            out[-1] = (out[-1][0], out[-1][1], math.copysign(min(abs(out[-1][2]), abs(v)), out[-1][2]))
        else:
            out.append((x, y, v))
            kept.append(name)
    return out, kept


def read_points_csv(filename: str,
                    paths: PathsConfig) -> tuple[list[tuple[float, float, float]], bool, list[str]]:
    """Waypoints (x, y, v cap or inf) from a CSV with header x,y or x,y,v; second item: has v;
    third: each waypoint's line ("line 7")."""
    # At most ~128 bytes a waypoint: the file cannot be larger than its waypoints need.
    text = read_text(filename, PathError, limit=128 * paths.max_points + 65536)
    rows: list[tuple[float, float, float]] = []
    lines: list[str] = []
    header: list[str] | None = None
    lineno = 0
    reader = csv.reader(io.StringIO(text))
    try:
        for lineno, fields_ in enumerate(reader, start=1):
            cells = [c.strip() for c in fields_]
            if not cells or all(c == "" for c in cells) or cells[0].startswith("#"):
                continue
            if header is None:
                header = [c.lower() for c in cells]
                if header not in (["x", "y"], ["x", "y", "v"]):
                    raise PathError(f"{filename}: line {lineno}: header must be 'x,y' or 'x,y,v', "
                                    f"got {shorten(','.join(cells))}")
                continue
            if len(cells) != len(header):
                raise PathError(f"{filename}: line {lineno}: expected {len(header)} columns, got {len(cells)}")
            if len(rows) >= paths.max_points:
                raise PathError(f"{filename}: line {lineno}: more than paths.max_points = "
                                f"{paths.max_points} waypoints")
            vals = []
            for name, cell in zip(header, cells):
                vals.append(_number(cell, lambda p, n=name: PathError(f"{filename}: line {lineno}: column '{n}': {p}")))
            v = math.inf
            if len(vals) == 3:
                v = vals[2]
                if v == 0.0:
                    raise PathError(f"{filename}: line {lineno}: column 'v': speed must be nonzero (> 0 forward, "
                                    f"< 0 reaching this point in reverse), got {shorten(cells[2])}")
            if max(abs(vals[0]), abs(vals[1])) > paths.max_extent_m:
                raise PathError(f"{filename}: line {lineno}: ({vals[0]:.6g}, {vals[1]:.6g}) is beyond "
                                f"paths.max_extent_m = {paths.max_extent_m:g} m from the origin")
            rows.append((vals[0], vals[1], v))
            lines.append(f"line {lineno}")
    except csv.Error as exc:  # a NUL byte, an unterminated quote, a field over the size limit
        raise PathError(f"{filename}: line {reader.line_num or lineno}: not CSV: {exc}") from None
    if header is None:
        raise PathError(f"{filename}: line 1: missing header 'x,y' or 'x,y,v' (file is empty)")
    return rows, len(header) == 3, lines


def _condition_options(paths: PathsConfig, tolerance: float | None) -> ConditionOptions:
    return ConditionOptions(paths.tolerance_m if tolerance is None else tolerance, paths.waypoint_spacing_m,
                            tolerance is not None)


def _waypoint_geometry(rows: list[tuple[float, float, float]], has_v: bool, where: str, opt: GeometryOptions,
                       paths: PathsConfig, names: list[str], tolerance: float | None = None,
                       budget_where: str | None = None,
                       tries: Sequence[tuple[EndPin | None, EndPin | None]] = (),
                       noise: float | None = None) -> tuple[Geometry, Conditioning]:
    """A polyline's geometry: waypoints as they are, samples of a curve smoothed (condition.py).
    Errors about one point name `where` and the point's name; about the whole, `budget_where`.
    `tries`: a run's start and end pins (smoothing.EndPin: a cusp shared with the next run,
    or the point where the other run meets it), tried in order; if no fit can hold them
    within the tolerance, the run is fitted free (`Conditioning.extra["ends"]` says which
    pins were held, `extra["pinned"]` which ends). `noise`: the points' noise if known
    (condition_polyline)."""
    pts, kept = _merge_points(rows, names)
    runs = _direction_runs(pts)
    if len(runs) > 1 or runs[0][2] < 0.0:
        return _reversing_geometry(pts, kept, runs, has_v, where, opt, paths, tolerance, budget_where)
    whole = where if budget_where is None else budget_where
    if len(pts) < 2:
        only = f" (every point equals the one at {kept[0]})" if kept and len(rows) > 1 else ""
        raise PathError(f"{where}: {kept[0] + ': ' if kept else ''}fewer than 2 distinct points ({len(pts)}){only}")
    copt = _condition_options(paths, tolerance)
    xy = np.array([(p[0], p[1]) for p in pts], dtype=float)
    mode = classify(xy, copt)[0]
    if mode == WAYPOINTS:
        _check_samples(polyline_samples(pts, opt), whole, paths, opt)
    else:  # a smoothed curve is no longer than its points' polyline (and pivots are few)
        length = float(np.sum(np.hypot(*np.diff(xy, axis=0).T)))
        _check_samples(1.05 * length / opt.step + 2.0 * len(pts) ** 0.5, whole, paths, opt)
    caps = np.array([abs(p[2]) for p in pts]) if has_v else None  # the sign marks direction only
    for ends in tries if mode != WAYPOINTS else ():
        if ends[0] is None and ends[1] is None:
            continue
        try:
            geo, cond = condition_polyline(xy, caps, opt, copt, where, kept, ends, noise)
        except ConditionError:
            continue  # the pin is not within the tolerance of this run's points: the next, or free
        cond.extra["ends"] = ends
        cond.extra["pinned"] = (ends[0] is not None, ends[1] is not None)
        return geo, cond
    try:
        geo, cond = condition_polyline(xy, caps, opt, copt, where, kept, noise=noise)
    except ConditionError as exc:
        raise PathError(str(exc)) from None
    cond.extra["ends"] = (None, None)
    cond.extra["pinned"] = (False, False)
    return geo, cond


def _direction_runs(pts: list[tuple[float, float, float]]) -> list[tuple[int, int, float]]:
    """(first point, last point, direction) of each run of segments driven one way. The segment
    to point k is driven in reverse when point k's v is negative (the robot reaches it backwards)."""
    dirs = [-1.0 if pts[k][2] < 0.0 else 1.0 for k in range(1, len(pts))] or [1.0]
    runs: list[tuple[int, int, float]] = []
    a = 0
    for k in range(1, len(dirs) + 1):
        if k == len(dirs) or dirs[k] != dirs[a]:
            runs.append((a, k, dirs[a]))
            a = k
    return runs


def _reversing_geometry(pts: list[tuple[float, float, float]], names: list[str], runs: list[tuple[int, int, float]],
                        has_v: bool, where: str, opt: GeometryOptions, paths: PathsConfig, tolerance: float | None,
                        budget_where: str | None) -> tuple[Geometry, Conditioning]:
    """A polyline with runs driven in reverse: each run read as its own polyline (so a reversal
    inside a run is still refused naming its point), its pieces turned round, joined at each
    cusp. Where both runs are smoothed samples the cusp is estimated once from both runs'
    points and each run fitted ending there on its heading (ddrt/path/cusp.py); otherwise a
    turn in place joins them where the headings differ. The runs are one recording, with one
    noise: each is smoothed for the noise pooled over all (a short run's own estimate is
    unsure, and too low a one leaves noise in its curvature). Speed caps are |v|."""
    shared, noise, tols = _shared_cusps(pts, runs, paths, tolerance)
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
        geo, cond = _waypoint_geometry(sub, has_v, where, opt, paths, names[a:b + 1], tolerance, budget_where, tries,
                                       noise)
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


# A run needs this many points for its own noise estimate to count in the pooled one.
NOISE_POOL_MIN_POINTS = 8


def _shared_cusps(pts: list[tuple[float, float, float]], runs: list[tuple[int, int, float]], paths: PathsConfig,
                  tolerance: float | None) -> tuple[list[SharedCusp | None], float | None, list[float]]:
    """Each cusp's point and heading from the points of both runs that meet there, where both
    are smoothed samples (ddrt/path/cusp.py; None where either is waypoints or too short, or
    the estimated point is farther than the tolerance from the cusp sample), the noise pooled
    over the smoothed runs (the RMS of their estimates, weighted by their points; None if no
    run has enough points for one), and each run's tolerance."""
    copt = _condition_options(paths, tolerance)
    xys = [np.array([(p[0], p[1]) for p in pts[a:b + 1]], dtype=float) for a, b, _ in runs]
    found = [point_noise(xy, copt) if len(xy) >= 4 else (WAYPOINTS, 0.0) for xy in xys]
    tols = [classify(xy, copt)[1] for xy in xys]
    pool = [(len(xy), nz) for xy, (mode, nz) in zip(xys, found)
            if mode != WAYPOINTS and len(xy) >= NOISE_POOL_MIN_POINTS]
    noise = (math.sqrt(sum(n * nz * nz for n, nz in pool) / sum(n for n, _ in pool))) if pool else None
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


def _joined_conditioning(pts: list[tuple[float, float, float]], names: list[str],
                         conds: list[tuple[int, Conditioning]], cusps: list[int]) -> Conditioning:
    """One Conditioning for the runs of a reversing polyline (indices into all its points)."""
    first = next((c for _, c in conds if c.mode != WAYPOINTS), conds[0][1])
    worst_a, worst = max(conds, key=lambda ac: ac[1].deviation_m)
    corners = tuple(replace(k, index=k.index + a) for a, c in conds for k in c.corners)
    xy = np.array([(p[0], p[1]) for p in pts], dtype=float)
    seg = np.hypot(*np.diff(xy, axis=0).T)
    out = Conditioning(first.mode, first.tolerance_m, xy, names, deviation_m=worst.deviation_m,
                       worst=worst_a + worst.worst, noise_m=max(c.noise_m for _, c in conds),
                       grid_cell_m=first.grid_cell_m, smoothing_m=tuple(e for _, c in conds for e in c.smoothing_m),
                       corners=corners, spacing_m=float(np.median(seg)) if len(seg) else 0.0,
                       iterations=sum(c.iterations for _, c in conds))
    out.extra["cusps"] = [names[k] for k in cusps]
    return out


def _check_samples(estimate: float, where: str, paths: PathsConfig, opt: GeometryOptions) -> None:
    if not estimate <= paths.max_samples:
        raise PathError(f"{where}: the path would have about {estimate:.3g} samples at {opt.step:g} m "
                        f"(paths.sample_step_m), more than paths.max_samples = {paths.max_samples}")


def _options(spec: PathCommon, paths: PathsConfig) -> GeometryOptions:
    """Sampling options: the config's paths: section, with the spec's own keys first."""
    return GeometryOptions(
        paths.sample_step_m,
        paths.pivot_radius_m if spec.pivot_radius is None else spec.pivot_radius,
        paths.corner_pivot_deg if spec.corner_pivot_deg is None else spec.corner_pivot_deg,
        paths.blend_max_m if spec.blend_max is None else spec.blend_max,
    )


def _clamped_limits(spec: PathCommon, limits: SpeedLimits, where: str,
                    notes: list[str]) -> tuple[SpeedLimits, float]:
    """The path's limits, never above the config's: a larger value is clamped and noted."""
    allowed = {"speed": limits.v_max, "accel": limits.accel, "decel": limits.decel_eff,
               "lateral_accel": limits.lateral_accel, "omega_max": limits.omega_max,
               "alpha_max": limits.alpha_max}
    chosen: dict[str, float] = {}
    for key in ("speed", *LIMIT_KEYS):
        asked = getattr(spec, key)
        if asked is None:
            continue
        if asked > allowed[key]:
            notes.append(f"{where}: key '{key}': {asked:g} is above the config's {allowed[key]:g} "
                         f"({_CONFIG_KEY[key]}); clamped to it")
            asked = allowed[key]
        chosen[key] = asked
    v_cap = chosen.pop("speed", limits.v_max)
    return replace(limits, **chosen), v_cap


def _note_point_caps(caps: list[float], v_max: float, where: str, notes: list[str]) -> None:
    over = [abs(v) for v in caps if math.isfinite(v) and abs(v) > v_max]
    if over:
        notes.append(f"{where}: {len(over)} waypoint speed(s) up to {max(over):g} are above the config's "
                     f"{v_max:g} (limits.v_max); clamped to it")


def _spec(m: Any, where: str, paths: PathsConfig) -> PathCommon:
    """The mapping as its kind's dataclass, via the config walker; errors name the key."""
    if not isinstance(m, Mapping):
        raise PathError(f"{where}: expected a mapping at the top level, got {type(m).__name__}")
    kinds = [k for k in ("shape", "points", "file") if k in m]
    if len(kinds) != 1:
        raise PathError(f"{where}: exactly one of keys 'shape', 'points', 'file' is required, got {kinds or 'none'}")
    kind = kinds[0]
    body = dict(m)
    if kind == "shape":
        shape = body.pop("shape")
        if not isinstance(shape, str) or shape not in SHAPES:
            raise PathError(f"{where}: key 'shape': unknown shape {shorten(shape)} (known: {', '.join(sorted(SHAPES))})")
        cls = SHAPES[shape]
    else:
        cls = KINDS[kind]
        raw = body[kind]
        if kind == "points" and isinstance(raw, (list, tuple)) and len(raw) > paths.max_points:
            raise PathError(f"{where}: key 'points': {len(raw)} points, more than paths.max_points = {paths.max_points}")
    try:
        spec = build(cls, body)
    except ConfigError as exc:
        raise _path_error(exc, where) from None
    if isinstance(spec, RectangleSpec) and spec.corners() > paths.max_points:
        raise PathError(f"{where}: key 'laps': {spec.laps:g} laps make {spec.corners():.3g} corners, more than "
                        f"paths.max_points = {paths.max_points}")
    for key, point in spec.positions():
        try:
            paths.check_pose(point, key)
        except ConfigError as exc:
            raise _path_error(exc, where) from None
    return spec


def _from_mapping(m: Any, limits: SpeedLimits, where: str, base_dir: str | None, paths: PathsConfig) -> Path:
    spec = _spec(m, where, paths)
    opt = _options(spec, paths)
    notes: list[str] = []
    lim, v_cap = _clamped_limits(spec, limits, where, notes)
    if isinstance(spec, PointsSpec):
        rows = []
        for j, item in enumerate(spec.points):
            try:
                paths.check_pose(item, f"points[{j}]")
            except ConfigError as exc:
                raise _path_error(exc, where) from None
            rows.append((item[0], item[1], item[2] if len(item) == 3 else math.inf))
        if spec.reverse:
            rows = [(x, y, -v) for x, y, v in rows]
        has_v = any(len(item) == 3 for item in spec.points)
        _note_point_caps([r[2] for r in rows], limits.v_max, f"{where}: key 'points'", notes)
        names = [f"key 'points[{j}]'" for j in range(len(rows))]
        geo, cond = _waypoint_geometry(rows, has_v, where, opt, paths, names, spec.tolerance,
                                        f"{where}: key 'points'")
    elif isinstance(spec, FileSpec):
        fname = spec.file
        if not fname.lower().endswith(".csv"):
            raise PathError(f"{where}: key 'file': expected a .csv file name, got {shorten(fname)}")
        if base_dir is not None and not os.path.isabs(fname):
            fname = os.path.join(base_dir, fname)
        try:
            rows, has_v, lines = read_points_csv(fname, paths)
            if spec.reverse:
                rows = [(x, y, -v) for x, y, v in rows]
            geo, cond = _waypoint_geometry(rows, has_v, fname, opt, paths, lines, spec.tolerance)
        except PathError as exc:
            raise PathError(f"{where}: key 'file': {exc}") from None
        _note_point_caps([r[2] for r in rows], limits.v_max, fname, notes)
    else:
        cond = None
        blame = spec.blame()
        _check_samples(spec.samples(opt), f"{where}: key '{blame}'", paths, opt)
        try:
            geo = spec.geometry(opt)
        except ValueError as exc:
            raise PathError(f"{where}: {exc}") from None
        if spec.reverse:
            geo.pieces = [reversed_piece(pc) for pc in geo.pieces]
    if geo.cap_value is not None:
        geo.cap_value = np.minimum(geo.cap_value, v_cap)
    return _finish(geo, lim, v_cap, opt, spec.pose(), where, paths, notes, cond)


def _finish(geo: Geometry, lim: SpeedLimits, v_cap: float, opt: GeometryOptions,
            start: tuple[float, float, float] | None, where: str, paths: PathsConfig, notes: list[str],
            cond: Conditioning | None = None) -> Path:
    """Check the sampled geometry against the bounds, then profile it into a Path."""
    count = sum(len(pc.s) for pc in geo.pieces) - max(0, len(geo.pieces) - 1)
    _check_samples(float(count), where, paths, opt)
    length = sum(pc.length for pc in geo.pieces)
    if not length >= MIN_PATH_LENGTH_M:
        raise PathError(f"{where}: the path is {length:.3g} m long, shorter than {MIN_PATH_LENGTH_M} m")
    extent = max(float(np.max(np.abs(np.concatenate((pc.x, pc.y))))) for pc in geo.pieces)
    if not extent <= paths.max_extent_m:
        raise PathError(f"{where}: the path reaches {extent:.6g} m from the origin, beyond "
                        f"paths.max_extent_m = {paths.max_extent_m:g} m")
    try:
        path = Path(geo, lim, v_cap=v_cap, pivot_radius=opt.pivot_radius, start_pose=start)
    except ValueError as exc:
        raise PathError(f"{where}: {exc}") from None
    if not path.duration <= paths.max_duration_s:
        raise PathError(f"{where}: the path takes {path.duration:.3g} s at its limits, longer than "
                        f"paths.max_duration_s = {paths.max_duration_s:g} s (a speed or acceleration too low?)")
    if cond is not None and cond.mode != WAYPOINTS:
        notes.append(f"{where}: {cond.summary()}")
    path.warnings = [*lim.notes, *notes]
    path.conditioning = cond
    return path


def load_path(source: str | os.PathLike[str] | Mapping[str, Any], limits: SpeedLimits | None = None, *,
              base_dir: str | None = None, paths: PathsConfig | None = None, where: str = "<mapping>") -> Path:
    """Load a path from a .csv / .yaml / .yml file or a mapping (see the module docstring).

    `limits` are the config's (speed_limits(cfg)): the path's own can only lower them (a
    larger value is clamped and noted in `path.warnings`). `paths` bounds the work and sets
    the sampling (paths: in the config; its defaults when None). Relative `file:` entries
    resolve against `base_dir`, which defaults to the YAML file's folder; `where` names a
    mapping in messages.
    """
    limits = SpeedLimits() if limits is None else limits
    paths = PathsConfig() if paths is None else paths
    if isinstance(source, Mapping):
        return _from_mapping(source, limits, where, base_dir, paths)
    if not isinstance(source, (str, os.PathLike)):
        raise PathError(f"{where}: expected a path file name or a path mapping, got {shorten(source)}")
    fname = os.fspath(source)
    low = fname.lower()
    if low.endswith(".csv"):
        rows, has_v, lines = read_points_csv(fname, paths)
        notes: list[str] = []
        _note_point_caps([r[2] for r in rows], limits.v_max, fname, notes)
        opt = GeometryOptions(paths.sample_step_m, paths.pivot_radius_m, paths.corner_pivot_deg, paths.blend_max_m)
        geo, cond = _waypoint_geometry(rows, has_v, fname, opt, paths, lines)
        return _finish(geo, limits, limits.v_max, opt, None, fname, paths, notes, cond)
    if low.endswith((".yaml", ".yml")):
        data = read_yaml(fname, PathError)
        return _from_mapping(data, limits, fname, base_dir if base_dir is not None else os.path.dirname(fname), paths)
    raise PathError(f"{fname}: unknown path file type (expected .csv, .yaml or .yml)")


def speed_limits(cfg: "Config") -> SpeedLimits:
    """The config's motion limits for the speed profile, with the robot's motor envelope.

    limits.v_max and limits.accel may be null (what the motors give); a value above what
    they give is noted (`SpeedLimits.notes`, which every path built with them reports)."""
    from ddrt.core.envelope import resolve_limits

    lim = cfg.limits
    res = resolve_limits(lim, cfg.robot, cfg.robot_motor)
    return SpeedLimits(v_max=res.profile_v_max, accel=math.inf if lim.accel is None else lim.accel,
                       lateral_accel=lim.lateral_accel, omega_max=lim.omega_max, alpha_max=lim.alpha_max,
                       envelope=res.envelope, notes=res.notes)


def resolve_path(cfg: "Config", path_arg: str | None = None) -> Path:
    """The path named on the command line, else the config's `path:` entry."""
    source, kwargs = path_source(cfg, path_arg)
    return load_path(source, speed_limits(cfg), **kwargs)


def path_source(cfg: "Config", path_arg: str | None = None) -> tuple[Any, dict[str, Any]]:
    """What resolve_path hands load_path besides the limits: (source, keyword arguments).
    For callers that load it elsewhere (the daemon's path worker)."""
    if path_arg is not None:
        return path_arg, {"paths": cfg.paths}
    if cfg.path is None:
        raise PathError(f"{cfg.source}: path: missing; give one in the config or with --path")
    source = cfg.path
    if isinstance(source, str) and not FsPath(source).is_absolute():
        source = str(FsPath(cfg.base_dir) / source)
    return source, {"base_dir": cfg.base_dir, "paths": cfg.paths, "where": f"{cfg.source}: path"}
