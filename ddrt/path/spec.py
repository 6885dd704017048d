"""Loading a path: a CSV of waypoints, a YAML spec (an analytic shape, inline points or a CSV
file), or the same spec as a mapping (from a config or the control socket). Errors name the
file, line or key.
"""

from __future__ import annotations

import csv
import io
import math
import os
from dataclasses import replace
from pathlib import Path as FsPath
from typing import TYPE_CHECKING, Any, Callable, Mapping

import numpy as np
import yaml

from ddrt.path.geometry import (
    TWO_PI, Curve, _arc, _Geometry, _line, _Options, _parametric, _polyline,
)
from ddrt.path.profile import SpeedLimits
from ddrt.path.sampled import Path

if TYPE_CHECKING:
    from ddrt.config import Config

YAML_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)  # libyaml when present

__all__ = ["PathError", "load_path", "resolve_path", "speed_limits"]


class PathError(ValueError):
    """A path file or spec is malformed; the message names the file, line or key, and the problem."""




_LIMIT_KEYS = ("accel", "decel", "lateral_accel", "omega_max", "alpha_max")
_COMMON = {"shape", "speed", "start", "start_pose", "pivot_radius", "corner_pivot_deg", "blend_max",
           "name", "description", *_LIMIT_KEYS}
_SHAPE_KEYS = {
    "line": {"heading_deg", "length", "origin"},
    "circle": {"radius", "direction", "center", "laps"},
    "rectangle": {"width", "height", "direction", "laps"},
    "ellipse": {"a", "b", "direction", "center", "laps"},
    "figure_eight": {"width", "height", "size", "center", "laps"},
    "s_curve": {"length", "offset"},
}
_MISSING = object()


class _Spec:
    """A YAML mapping with typed getters whose errors name the file and key."""

    def __init__(self, mapping: Mapping[str, Any], where: str) -> None:
        self.m = mapping
        self.where = where

    def fail(self, key: str, problem: str) -> PathError:
        return PathError(f"{self.where}: key '{key}': {problem}")

    def num(self, key: str, default: Any = _MISSING, *, positive: bool = False, nonneg: bool = False) -> float:
        if key not in self.m:
            if default is _MISSING:
                raise self.fail(key, "missing")
            return default
        return _number(self.m[key], lambda p: self.fail(key, p), positive=positive, nonneg=nonneg)

    def vec(self, key: str, size: int | tuple[int, ...], default: Any = _MISSING) -> tuple[float, ...]:
        if key not in self.m:
            if default is _MISSING:
                raise self.fail(key, "missing")
            return default
        raw = self.m[key]
        sizes = (size,) if isinstance(size, int) else size
        if not isinstance(raw, (list, tuple)) or len(raw) not in sizes:
            raise self.fail(key, f"expected a list of {' or '.join(map(str, sizes))} numbers, got {raw!r}")
        return tuple(_number(v, lambda p: self.fail(key, p)) for v in raw)

    def choice(self, key: str, options: tuple[str, ...], default: str) -> str:
        raw = self.m.get(key, default)
        if not isinstance(raw, str) or raw.lower() not in options:
            raise self.fail(key, f"expected one of {', '.join(options)}, got {raw!r}")
        return raw.lower()


def _number(raw: Any, fail: Callable[[str], PathError], *, positive: bool = False, nonneg: bool = False) -> float:
    if isinstance(raw, bool) or not isinstance(raw, (int, float, str)):
        raise fail(f"expected a number, got {raw!r}")
    try:
        value = float(raw)
    except ValueError:
        raise fail(f"not a number: {raw!r}") from None
    if not math.isfinite(value):
        raise fail(f"must be finite, got {raw!r}")
    if positive and value <= 0.0:
        raise fail(f"must be > 0, got {raw!r}")
    if nonneg and value < 0.0:
        raise fail(f"must be >= 0, got {raw!r}")
    return value


def _merge_points(rows: list[tuple[float, float, float]]) -> list[tuple[float, float, float]]:
    """Drop consecutive duplicates (keeping the lower speed cap)."""
    out: list[tuple[float, float, float]] = []
    for x, y, v in rows:
        if out and math.hypot(x - out[-1][0], y - out[-1][1]) < 1e-9:
            out[-1] = (out[-1][0], out[-1][1], min(out[-1][2], v))
        else:
            out.append((x, y, v))
    return out


def _read_csv(filename: str) -> tuple[list[tuple[float, float, float]], bool]:
    """Waypoints (x, y, v cap or inf) from a CSV with header x,y or x,y,v; second item: has v."""
    try:
        with open(filename, newline="", encoding="utf-8") as fh:
            text = fh.read()
    except OSError as exc:
        raise PathError(f"{filename}: cannot read: {exc.strerror or exc}") from None
    rows: list[tuple[float, float, float]] = []
    header: list[str] | None = None
    for lineno, fields_ in enumerate(csv.reader(io.StringIO(text)), start=1):
        cells = [c.strip() for c in fields_]
        if not cells or all(c == "" for c in cells) or cells[0].startswith("#"):
            continue
        if header is None:
            header = [c.lower() for c in cells]
            if header not in (["x", "y"], ["x", "y", "v"]):
                raise PathError(f"{filename}: line {lineno}: header must be 'x,y' or 'x,y,v', got {','.join(cells)!r}")
            continue
        if len(cells) != len(header):
            raise PathError(f"{filename}: line {lineno}: expected {len(header)} columns, got {len(cells)}")
        vals = []
        for name, cell in zip(header, cells):
            vals.append(_number(cell, lambda p, n=name: PathError(f"{filename}: line {lineno}: column '{n}': {p}")))
        v = math.inf
        if len(vals) == 3:
            v = vals[2]
            if v <= 0.0:
                raise PathError(f"{filename}: line {lineno}: column 'v': speed must be > 0, got {cells[2]!r}")
        rows.append((vals[0], vals[1], v))
    if header is None:
        raise PathError(f"{filename}: line 1: missing header 'x,y' or 'x,y,v' (file is empty)")
    return rows, len(header) == 3


def _waypoint_geometry(rows: list[tuple[float, float, float]], has_v: bool, where: str, opt: _Options) -> _Geometry:
    pts = _merge_points(rows)
    if len(pts) < 2:
        raise PathError(f"{where}: fewer than 2 distinct points ({len(pts)})")
    caps = [p[2] for p in pts] if has_v else None
    return _polyline([(p[0], p[1]) for p in pts], caps, opt)


def _closed_param(spec: _Spec, r: Curve, dr: Curve, ddr: Curve, laps: float, opt: _Options) -> _Geometry:
    try:
        return _Geometry([_parametric(r, dr, ddr, 0.0, TWO_PI * laps, opt.step)])
    except ValueError as exc:
        raise PathError(f"{spec.where}: {exc}") from None


def _shape_geometry(spec: _Spec, shape: str, opt: _Options) -> _Geometry:
    if shape == "line":
        origin = spec.vec("origin", 2, default=None)
        if origin is None:
            start = spec.m.get("start")
            origin = spec.vec("start", 2) if isinstance(start, (list, tuple)) and len(start) == 2 else (0.0, 0.0)
        heading = math.radians(spec.num("heading_deg", 0.0))
        return _Geometry([_line(origin[0], origin[1], heading, spec.num("length", positive=True), opt.step)])
    if shape == "circle":
        radius = spec.num("radius", positive=True)
        sign = 1.0 if spec.choice("direction", ("cw", "ccw"), "ccw") == "ccw" else -1.0
        laps = spec.num("laps", 1.0, positive=True)
        cx, cy = spec.vec("center", 2, default=(0.0, sign * radius))
        # Start where the heading is +x: bottom of a ccw circle, top of a cw one.
        return _Geometry([_arc(cx, cy - sign * radius, 0.0, radius, sign * TWO_PI * laps, opt.step)])
    if shape == "rectangle":
        w, h = spec.num("width", positive=True), spec.num("height", positive=True)
        sign = 1.0 if spec.choice("direction", ("cw", "ccw"), "ccw") == "ccw" else -1.0
        laps = spec.num("laps", 1.0, positive=True)
        if laps != int(laps):
            raise spec.fail("laps", f"a rectangle needs a whole number of laps, got {laps!r}")
        corners = [(w, 0.0), (w, sign * h), (0.0, sign * h), (0.0, 0.0)]
        return _polyline([(0.0, 0.0)] + corners * int(laps), None, opt)
    if shape == "ellipse":
        a, b = spec.num("a", positive=True), spec.num("b", positive=True)
        sign = 1.0 if spec.choice("direction", ("cw", "ccw"), "ccw") == "ccw" else -1.0
        laps = spec.num("laps", 1.0, positive=True)
        cx, cy = spec.vec("center", 2, default=(0.0, sign * b))
        # Starts at the end of the y semi-axis heading +x: (cx, cy - sign b).
        return _closed_param(
            spec,
            lambda u: (cx + a * np.sin(u), cy - sign * b * np.cos(u)),
            lambda u: (a * np.cos(u), sign * b * np.sin(u)),
            lambda u: (-a * np.sin(u), sign * b * np.cos(u)),
            laps, opt)
    if shape == "figure_eight":
        if "size" in spec.m and ("width" in spec.m or "height" in spec.m):
            raise spec.fail("size", "give either size or width/height, not both")
        if "size" in spec.m:
            w = spec.num("size", positive=True)
            h = 0.5 * w
        else:
            w, h = spec.num("width", positive=True), spec.num("height", positive=True)
        laps = spec.num("laps", 1.0, positive=True)
        cx, cy = spec.vec("center", 2, default=(0.0, 0.0))
        # Gerono's lemniscate: x = (w/2) sin u, y = (h/2) sin 2u; crosses itself at the centre.
        hw, hh = 0.5 * w, 0.5 * h
        return _closed_param(
            spec,
            lambda u: (cx + hw * np.sin(u), cy + hh * np.sin(2.0 * u)),
            lambda u: (hw * np.cos(u), 2.0 * hh * np.cos(2.0 * u)),
            lambda u: (-hw * np.sin(u), -4.0 * hh * np.sin(2.0 * u)),
            laps, opt)
    if shape == "s_curve":
        length, offset = spec.num("length", positive=True), spec.num("offset")
        k = math.pi / length
        # y = (offset/2)(1 - cos(pi x / length)): heading 0 at both ends, lateral shift `offset`.
        piece = _parametric(
            lambda u: (u, 0.5 * offset * (1.0 - np.cos(k * u))),
            lambda u: (np.ones_like(u), 0.5 * offset * k * np.sin(k * u)),
            lambda u: (np.zeros_like(u), 0.5 * offset * k * k * np.cos(k * u)),
            0.0, length, opt.step)
        return _Geometry([piece])
    raise spec.fail("shape", f"unknown shape {shape!r} (known: {', '.join(sorted(_SHAPE_KEYS))})")


def _from_mapping(m: Any, limits: SpeedLimits, where: str, base_dir: str | None, opt: _Options) -> Path:
    if not isinstance(m, Mapping):
        raise PathError(f"{where}: expected a mapping at the top level, got {type(m).__name__}")
    spec = _Spec(m, where)
    kinds = [k for k in ("shape", "points", "file") if k in m]
    if len(kinds) != 1:
        raise PathError(f"{where}: exactly one of keys 'shape', 'points', 'file' is required, got {kinds or 'none'}")
    kind = kinds[0]
    if kind == "shape":
        shape = m["shape"]
        if not isinstance(shape, str) or shape not in _SHAPE_KEYS:
            raise spec.fail("shape", f"unknown shape {shape!r} (known: {', '.join(sorted(_SHAPE_KEYS))})")
        allowed = _COMMON | _SHAPE_KEYS[shape]
    else:
        allowed = _COMMON | {kind}
    unknown = sorted(str(k) for k in m if k not in allowed)
    if unknown:
        raise spec.fail(unknown[0], f"unknown key (allowed here: {', '.join(sorted(allowed))})")
    overrides = {k: spec.num(k, positive=True) for k in _LIMIT_KEYS if k in m}
    try:
        lim = replace(limits, **overrides)
    except ValueError as exc:
        raise PathError(f"{where}: {exc}") from None
    opt = replace(
        opt,
        pivot_radius=spec.num("pivot_radius", opt.pivot_radius, positive=True),
        corner_pivot_deg=spec.num("corner_pivot_deg", opt.corner_pivot_deg, nonneg=True),
        blend_max=spec.num("blend_max", opt.blend_max, positive=True),
    )
    v_cap = spec.num("speed", lim.v_max, positive=True)
    if kind == "shape":
        geo = _shape_geometry(spec, m["shape"], opt)
    elif kind == "points":
        raw = m["points"]
        if not isinstance(raw, (list, tuple)):
            raise spec.fail("points", f"expected a list of [x, y] or [x, y, v], got {raw!r}")
        rows = []
        has_v = False
        for j, item in enumerate(raw):
            key = f"points[{j}]"
            if not isinstance(item, (list, tuple)) or len(item) not in (2, 3):
                raise spec.fail(key, f"expected [x, y] or [x, y, v], got {item!r}")
            vals = [_number(c, lambda p, k=key: spec.fail(k, p)) for c in item]
            v = math.inf
            if len(vals) == 3:
                has_v = True
                v = vals[2]
                if v <= 0.0:
                    raise spec.fail(key, f"speed must be > 0, got {item[2]!r}")
            rows.append((vals[0], vals[1], v))
        geo = _waypoint_geometry(rows, has_v, f"{where}: key 'points'", opt)
        if has_v and geo.cap_value is not None:
            geo.cap_value = np.minimum(geo.cap_value, v_cap)
    else:
        fname = m["file"]
        if not isinstance(fname, str) or not fname.lower().endswith(".csv"):
            raise spec.fail("file", f"expected a .csv file name, got {fname!r}")
        if base_dir is not None and not os.path.isabs(fname):
            fname = os.path.join(base_dir, fname)
        try:
            rows, has_v = _read_csv(fname)
        except PathError as exc:
            raise spec.fail("file", str(exc)) from None
        geo = _waypoint_geometry(rows, has_v, fname, opt)
        if geo.cap_value is not None:
            geo.cap_value = np.minimum(geo.cap_value, v_cap)
    start = None
    for key in ("start_pose", "start"):
        raw = m.get(key)
        if isinstance(raw, (list, tuple)) and len(raw) == 3:
            start = spec.vec(key, 3)
        elif raw is not None and not (key == "start" and m.get("shape") == "line"):
            raise spec.fail(key, f"expected [x, y, theta] (theta in rad), got {raw!r}")
    return Path(geo, lim, v_cap=v_cap, pivot_radius=opt.pivot_radius, start_pose=start)


def load_path(source: str | os.PathLike[str] | Mapping[str, Any], limits: SpeedLimits | None = None, *,
              base_dir: str | None = None, sample_step_m: float = 0.002, pivot_radius: float = 0.1,
              corner_pivot_deg: float = 30.0, blend_max_m: float = 0.15) -> Path:
    """Load a path from a .csv / .yaml / .yml file or a mapping (see the module docstring).

    Relative `file:` entries resolve against `base_dir`, which defaults to the YAML file's folder.
    """
    limits = SpeedLimits() if limits is None else limits
    if not (sample_step_m > 0.0 and pivot_radius > 0.0 and blend_max_m > 0.0 and corner_pivot_deg >= 0.0):
        raise ValueError("load_path: sample_step_m, pivot_radius, blend_max_m must be > 0, corner_pivot_deg >= 0")
    opt = _Options(sample_step_m, pivot_radius, corner_pivot_deg, blend_max_m)
    if isinstance(source, Mapping):
        return _from_mapping(source, limits, "<mapping>", base_dir, opt)
    fname = os.fspath(source)
    low = fname.lower()
    if low.endswith(".csv"):
        rows, has_v = _read_csv(fname)
        return Path(_waypoint_geometry(rows, has_v, fname, opt), limits, v_cap=limits.v_max, pivot_radius=pivot_radius)
    if low.endswith((".yaml", ".yml")):
        try:
            with open(fname, encoding="utf-8") as fh:
                data = yaml.load(fh, Loader=YAML_LOADER)
        except OSError as exc:
            raise PathError(f"{fname}: cannot read: {exc.strerror or exc}") from None
        except yaml.YAMLError as exc:
            mark = getattr(exc, "problem_mark", None)
            line = f"line {mark.line + 1}: " if mark is not None else ""
            raise PathError(f"{fname}: {line}invalid YAML: {getattr(exc, 'problem', exc)}") from None
        return _from_mapping(data, limits, fname, base_dir if base_dir is not None else os.path.dirname(fname), opt)
    raise PathError(f"{fname}: unknown path file type (expected .csv, .yaml or .yml)")


def speed_limits(cfg: "Config") -> SpeedLimits:
    lim = cfg.limits
    return SpeedLimits(v_max=lim.v_max, accel=lim.accel, lateral_accel=lim.lateral_accel,
                       omega_max=lim.omega_max, alpha_max=lim.alpha_max)


def resolve_path(cfg: "Config", path_arg: str | None = None) -> Path:
    """The path named on the command line, else the config's `path:` entry."""
    limits = speed_limits(cfg)
    if path_arg is not None:
        return load_path(path_arg, limits)
    if cfg.path is None:
        raise ValueError(f"{cfg.source}: path: missing; give one in the config or with --path")
    source = cfg.path
    if isinstance(source, str) and not FsPath(source).is_absolute():
        source = str(FsPath(cfg.base_dir) / source)
    return load_path(source, limits, base_dir=cfg.base_dir)
