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
from dataclasses import dataclass, replace
from pathlib import Path as FsPath
from typing import TYPE_CHECKING, Any, Callable, Mapping, Sequence

import numpy as np

from ddrt.config.filekind import PATH, not_a
from ddrt.errors import DdrtError
from ddrt.config.schema import ConfigError, build, field_items
from ddrt.config.sections import PathsConfig
from ddrt.config.yamlio import read_text, read_yaml, shorten
from ddrt.path.condition import WAYPOINTS, ConditionError, ConditionOptions, Conditioning, classify, condition_polyline
from ddrt.path.geometry import Geometry, GeometryOptions, reversed_piece
from ddrt.path.profile import SpeedLimits
from ddrt.path.reversal import Point, direction_runs, reversing_geometry
from ddrt.path.sampled import Path
from ddrt.path.shapes import (
    KINDS, LIMIT_KEYS, SHAPES, FileSpec, PathCommon, PointsSpec, RectangleSpec, polyline_samples,
)
from ddrt.path.smoothing import EndPin
from ddrt.path.units import UNITS, CsvColumns, UnitError, check_plausible, check_speeds, csv_columns

if TYPE_CHECKING:
    from ddrt.config import Config

__all__ = ["PathError", "config_path_error", "load_path", "path_source", "read_points_csv", "resolve_path", "speed_limits"]


class PathError(DdrtError, ValueError):
    """A path file or spec is malformed; the message names the file, line or key, and the problem."""


# Minimum length of a path (m): shorter, it is a point the robot cannot follow.
MIN_PATH_LENGTH_M = 0.001

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


CSV_BYTES_PER_POINT = 128  # a CSV line "x,y,v" with full-precision floats and room to spare
CSV_HEADER_BYTES = 65536  # the header, comments and blank lines


@dataclass
class CsvPoints:
    """A CSV's waypoints (x, y in metres, v cap in m/s or inf), whether it has a v column,
    each waypoint's line ("line 7"), and whether its header stated the unit (x_mm, x_m, ...)."""

    rows: list[tuple[float, float, float]]
    has_v: bool
    lines: list[str]
    unit_stated: bool  # by the header or the spec's units:


def read_points_csv(filename: str, paths: PathsConfig, units: str | None = None) -> CsvPoints:
    """The waypoints of a CSV whose header names x, y and optionally v (see units.csv_columns),
    in the header's unit, else in `units` (a YAML spec's `units:`), else in metres."""
    # At most ~128 bytes a waypoint: the file cannot be larger than its waypoints need.
    by_points = CSV_BYTES_PER_POINT * paths.max_points + CSV_HEADER_BYTES
    if by_points < paths.max_file_bytes:
        limit, limit_from = by_points, (f"paths.max_points = {paths.max_points} waypoints of at most "
                                        f"{CSV_BYTES_PER_POINT} bytes each")
    else:
        limit, limit_from = paths.max_file_bytes, "paths.max_file_bytes"
    text = read_text(filename, PathError, limit=limit, limit_from=limit_from)
    rows: list[tuple[float, float, float]] = []
    lines: list[str] = []
    header: list[str] | None = None
    columns = CsvColumns(("x", "y"), None)
    scale = 1.0
    lineno = 0
    reader = csv.reader(io.StringIO(text))
    try:
        for lineno, fields_ in enumerate(reader, start=1):
            cells = [c.strip() for c in fields_]
            if not cells or all(c == "" for c in cells) or cells[0].startswith("#"):
                continue
            if header is None:
                header = [c.lower() for c in cells]
                parsed = csv_columns(header)
                if isinstance(parsed, str):
                    raise PathError(f"{filename}: line {lineno}: header must name the columns x,y or x,y,v "
                                    f"(in metres and m/s; x_mm,y_mm, x_cm,y_cm or x_in,y_in for other units), "
                                    f"got {shorten(','.join(cells))}: {parsed}")
                columns = parsed
                if units is not None and columns.scale not in (None, UNITS[units]):
                    raise PathError(f"{filename}: line {lineno}: the header's unit ({shorten(','.join(cells))}) "
                                    f"is not the spec's units: {units}")
                scale = columns.scale if columns.scale is not None else UNITS[units or "m"]
                continue
            if len(cells) != len(header):
                raise PathError(f"{filename}: line {lineno}: expected {len(header)} columns, got {len(cells)}")
            if len(rows) >= paths.max_points:
                raise PathError(f"{filename}: line {lineno}: more than paths.max_points = "
                                f"{paths.max_points} waypoints")
            vals = {role: _number(cell, lambda p, n=name: PathError(f"{filename}: line {lineno}: column '{n}': {p}"))
                    for role, name, cell in zip(columns.roles, header, cells)}
            x, y, v = vals["x"] * scale, vals["y"] * scale, vals.get("v", math.inf)
            if v == 0.0:
                raise PathError(f"{filename}: line {lineno}: column 'v': speed must be nonzero (> 0 forward, "
                                f"< 0 reaching this point in reverse), got {shorten(cells[columns.roles.index('v')])}")
            if max(abs(x), abs(y)) > paths.max_extent_m:
                raise PathError(f"{filename}: line {lineno}: ({x:.6g}, {y:.6g}) is beyond "
                                f"paths.max_extent_m = {paths.max_extent_m:g} m from the origin")
            rows.append((x, y, v))
            lines.append(f"line {lineno}")
    except csv.Error as exc:  # a NUL byte, an unterminated quote, a field over the size limit
        raise PathError(f"{filename}: line {reader.line_num or lineno}: not CSV: {exc}") from None
    if header is None:
        raise PathError(f"{filename}: line 1: missing header 'x,y' or 'x,y,v' (file is empty)")
    return CsvPoints(rows, columns.has_v, lines, columns.scale is not None or units is not None)


def _check_units(rows: list[tuple[float, float, float]], stated: bool, has_v: bool, v_max: float, where: str,
                 paths: PathsConfig, notes: list[str]) -> None:
    """A polyline that states no unit must look like metres; a v column must hold speeds."""
    try:
        if has_v:
            check_speeds([r[2] for r in rows], v_max, where)
        if not stated:
            check_plausible([(r[0], r[1]) for r in rows], where, paths.workspace_m, notes)
    except UnitError as exc:
        raise PathError(str(exc)) from None


def _condition_options(paths: PathsConfig, tolerance: float | str | None) -> ConditionOptions:
    """The config's tolerance, the path's own first; `auto` as None (set from the noise)."""
    tol = paths.tolerance_m if tolerance is None else tolerance
    return ConditionOptions(None if tol == "auto" else float(tol), paths.waypoint_spacing_m, tolerance is not None)


def _waypoint_geometry(rows: list[tuple[float, float, float]], has_v: bool, where: str, opt: GeometryOptions,
                       paths: PathsConfig, names: list[str], tolerance: float | str | None = None,
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
    runs = direction_runs(pts)
    if len(runs) > 1 or runs[0][2] < 0.0:
        def fit_run(sub: list[Point], sub_names: list[str], pins: Sequence[tuple[EndPin | None, EndPin | None]],
                    pooled: float | None) -> tuple[Geometry, Conditioning]:
            return _waypoint_geometry(sub, has_v, where, opt, paths, sub_names, tolerance, budget_where, pins, pooled)

        return reversing_geometry(pts, kept, runs, _condition_options(paths, tolerance), opt, fit_run)
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
    given = {f.name: value for f, value in field_items(spec)}
    for key in ("speed", *LIMIT_KEYS):
        asked = given[key]
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
        notes.append(f"{where}: {len(over)} point speed(s) (column or third value v) up to {max(over):g} are above the config's "
                     f"{v_max:g} (limits.v_max); clamped to it")


def _spec(m: Any, where: str, paths: PathsConfig) -> PathCommon:
    """The mapping as its kind's dataclass, via the config walker; errors name the key."""
    if m is None:
        raise PathError(f"{where}: no path in it (empty, or only comments): expected a mapping at the top level "
                        "with one of shape:, points: or file:")
    if not isinstance(m, Mapping):
        raise PathError(f"{where}: expected a mapping at the top level (shape:, points: or file:), got {shorten(m)}")
    kinds = [k for k in ("shape", "points", "file") if k in m]
    other = not_a(m, PATH, where, "a path file") if not kinds else None
    if other is not None:
        raise PathError(other)
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
        scale = UNITS[spec.units or "m"]
        for j, item in enumerate(spec.points):
            x, y = item[0] * scale, item[1] * scale  # the workspace bound is in metres, whatever the unit
            try:
                paths.check_pose((x, y), f"points[{j}]")
            except ConfigError as exc:
                raise _path_error(exc, where) from None
            rows.append((x, y, item[2] if len(item) == 3 else math.inf))
        has_v = any(len(item) == 3 for item in spec.points)
        _check_units(rows, spec.units is not None, has_v, limits.v_max, f"{where}: key 'points'", paths, notes)
        if spec.reverse:
            rows = [(x, y, -v) for x, y, v in rows]
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
            csvp = read_points_csv(fname, paths, spec.units)
            rows, has_v, lines = csvp.rows, csvp.has_v, csvp.lines
            _check_units(rows, csvp.unit_stated, has_v, limits.v_max, fname, paths, notes)
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
    # A drive of no length (a nanometre or less: between two turns in place at one point, where a reversal's runs
    # meet) is no motion, and its samples share one progress, which no profile can take.
    driven = [pc for pc in geo.pieces if pc.pivot or pc.length > 1e-9]
    if driven and len(driven) < len(geo.pieces):
        geo.pieces = driven
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
    path.warnings = [*lim.notes, *notes]
    if cond is not None and cond.mode != WAYPOINTS:
        path.notes = [f"{where}: {cond.summary()}"]
    elif cond is not None and cond.note:
        path.notes = [f"{where}: {cond.note}"]
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
        csvp = read_points_csv(fname, paths)
        rows, has_v, lines = csvp.rows, csvp.has_v, csvp.lines
        notes: list[str] = []
        _check_units(rows, csvp.unit_stated, has_v, limits.v_max, fname, paths, notes)
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
    """The path named on the command line, else the config's `path:` entry (its errors name
    the config file and the key)."""
    source, kwargs = path_source(cfg, path_arg)
    try:
        return load_path(source, speed_limits(cfg), **kwargs)
    except PathError as exc:
        if path_arg is not None:
            raise
        raise PathError(config_path_error(cfg, str(exc))) from None


def config_path_error(cfg: "Config", message: str) -> str:
    """`message` (about the config's `path:`) naming the config file and the key, and where a
    relative file name was looked for."""
    where = f"{cfg.source}: path"
    text = message if message.startswith(where) else f"{where}: {message}"
    if (isinstance(cfg.path, str) and "cannot read" in message
            and FsPath(cfg.path).is_relative_to(cfg.base_dir)):
        text += f" (a relative path: resolved against the config's directory, {cfg.base_dir})"
    return text


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
