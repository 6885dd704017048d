"""The path spec's schema: one frozen dataclass per kind of path, built by the config's walker
(`ddrt.config.schema.build`), so a path's errors come from the same code as a config's. Each key
declares its unit, bounds and meaning (`setting`), as a config key does; docs/reference/paths.md
is written from them.

Each kind knows how many samples it will have (`samples(opt)`, checked against
paths.max_samples before anything is allocated) and builds its geometry (`geometry(opt)`).
Units: metres, radians, except `heading_deg` and `corner_pivot_deg` (degrees).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar, Literal

import numpy as np

from ddrt.config.schema import ConfigError, Section, field_items, setting
from ddrt.config.sections import MAX_TOLERANCE_M, MIN_PATH_SIZE_M
from ddrt.path.geometry import (
    TWO_PI, Curve, Geometry, GeometryOptions, arc_piece, line_piece, parametric_piece, polyline_geometry,
)

LIMIT_KEYS = ("accel", "decel", "lateral_accel", "omega_max", "alpha_max")


def _pivot_samples(opt: GeometryOptions, turn: float) -> float:
    return max(2.0, opt.pivot_radius * abs(turn) / opt.step)


@dataclass(frozen=True, kw_only=True)
class PathCommon(Section):
    """Keys every kind of path takes: its own (lower) limits, sampling options, start pose."""

    speed: float | None = setting(
        None, unit="m/s", gt=0, doc="Top speed along the path; above `limits.v_max` it is clamped to it.")
    accel: float | None = setting(
        None, unit="m/s^2", gt=0, doc="Forward acceleration; above `limits.accel` it is clamped to it.")
    decel: float | None = setting(
        None, unit="m/s^2", gt=0, doc="Braking; above `limits.accel` (which bounds both) it is clamped to it.")
    lateral_accel: float | None = setting(
        None, unit="m/s^2", gt=0, doc="Centripetal acceleration in curves; at most `limits.lateral_accel`.")
    omega_max: float | None = setting(None, unit="rad/s", gt=0, doc="Yaw rate; at most `limits.omega_max`.")
    alpha_max: float | None = setting(
        None, unit="rad/s^2", gt=0, doc="Yaw acceleration; at most `limits.alpha_max`.")
    pivot_radius: float | None = setting(
        None, unit="m", ge=MIN_PATH_SIZE_M, doc="Replaces `paths.pivot_radius_m` for this path.")
    corner_pivot_deg: float | None = setting(
        None, unit="deg", ge=0, lt=180, doc="Replaces `paths.corner_pivot_deg` for this path.")
    blend_max: float | None = setting(
        None, unit="m", ge=MIN_PATH_SIZE_M, doc="Replaces `paths.blend_max_m` for this path.")
    start_pose: tuple[float, float, float] | None = setting(
        None, unit="[m, m, rad]", doc="Where the robot starts, `[x, y, theta]`; wins over `start`.")
    start: tuple[float, ...] | None = setting(
        None, unit="[m, m, rad]", doc="`[x, y, theta]`, the robot's start pose; a line also takes `[x, y]`, its origin.")
    name: str | None = setting(None, doc="Short label of the path; not interpreted.")
    description: str | None = setting(None, doc="Free text; not interpreted.")
    reverse: bool = setting(
        False,
        doc="The whole path driven backwards (for `points` and `file`: as if every point's `v` were negated).")

    START_SIZES: ClassVar[tuple[int, ...]] = (3,)
    SIZE_KEY: ClassVar[str] = "length"  # the key a too-large path is blamed on

    def validate(self, where: str) -> None:
        if self.start is not None and len(self.start) not in self.START_SIZES:
            shown = "[x, y] (the line's origin) or " if 2 in self.START_SIZES else ""
            raise ConfigError(f"start: expected {shown}[x, y, theta] (theta in rad), got {list(self.start)}")

    def pose(self) -> tuple[float, float, float] | None:
        """The robot's start pose the spec gives, if any (start_pose wins over start)."""
        if self.start_pose is not None:
            return self.start_pose
        if self.start is not None and len(self.start) == 3:
            return (self.start[0], self.start[1], self.start[2])
        return None

    def positions(self) -> list[tuple[str, tuple[float, ...]]]:
        """(key, (x, y, ...)) of every position the spec names, for the workspace bound."""
        return [(f.name, v) for f, v in field_items(self)
                if f.name in ("start_pose", "start", "center", "origin") and v is not None]

    def blame(self) -> str:
        """The key to name when the path is too large: laps when there are several."""
        laps = next((v for f, v in field_items(self) if f.name == "laps"), 1.0)
        return "laps" if laps > 1.0 else self.SIZE_KEY

    # Each kind: samples(opt) -> float (an estimate, never below the real count by much) and
    # geometry(opt) -> Geometry.


def _direction(value: str) -> float:
    return 1.0 if value == "ccw" else -1.0


@dataclass(frozen=True, kw_only=True)
class LineSpec(PathCommon):
    """`shape: line`: a straight segment."""

    length: float = setting(unit="m", ge=MIN_PATH_SIZE_M, doc="The segment's length.")
    heading_deg: float = setting(0.0, unit="deg", doc="Its direction from +x, counter-clockwise.")
    origin: tuple[float, float] | None = setting(
        None, unit="[m, m]", doc="Where it starts; default: `start`'s x, y, else the origin.")

    START_SIZES: ClassVar[tuple[int, ...]] = (2, 3)

    def samples(self, opt: GeometryOptions) -> float:
        return self.length / opt.step

    def geometry(self, opt: GeometryOptions) -> Geometry:
        origin = self.origin
        if origin is None:
            origin = (self.start[0], self.start[1]) if self.start is not None and len(self.start) == 2 else (0.0, 0.0)
        return Geometry([line_piece(origin[0], origin[1], math.radians(self.heading_deg), self.length, opt.step)])


@dataclass(frozen=True, kw_only=True)
class CircleSpec(PathCommon):
    """`shape: circle`, started heading +x."""

    radius: float = setting(unit="m", ge=MIN_PATH_SIZE_M, doc="The circle's radius.")
    direction: Literal["cw", "ccw"] = setting("ccw", doc="`ccw` (counter-clockwise, turning left) or `cw`.")
    center: tuple[float, float] | None = setting(
        None, unit="[m, m]", doc="The centre; default: the start at the origin heading +x.")
    laps: float = setting(1.0, gt=0, doc="How many times the path goes round.")

    SIZE_KEY: ClassVar[str] = "radius"

    def samples(self, opt: GeometryOptions) -> float:
        return TWO_PI * self.radius * self.laps / opt.step

    def geometry(self, opt: GeometryOptions) -> Geometry:
        sign = _direction(self.direction)
        cx, cy = self.center if self.center is not None else (0.0, sign * self.radius)
        # Start where the heading is +x: bottom of a ccw circle, top of a cw one.
        return Geometry([arc_piece(cx, cy - sign * self.radius, 0.0, self.radius, sign * TWO_PI * self.laps, opt.step)])


@dataclass(frozen=True, kw_only=True)
class RectangleSpec(PathCommon):
    """`shape: rectangle` from the origin heading +x, a turn in place at each corner."""

    width: float = setting(unit="m", ge=MIN_PATH_SIZE_M, doc="Its side along x.")
    height: float = setting(unit="m", ge=MIN_PATH_SIZE_M, doc="Its side along y.")
    direction: Literal["cw", "ccw"] = setting("ccw", doc="`ccw` (counter-clockwise, turning left) or `cw`.")
    laps: float = setting(1.0, ge=1, doc="How many times the path goes round: a whole number.")

    SIZE_KEY: ClassVar[str] = "width"

    def validate(self, where: str) -> None:
        super().validate(where)
        if self.laps != int(self.laps):
            raise ConfigError(f"laps: a rectangle needs a whole number of laps, got {self.laps!r}")

    def corners(self) -> float:
        return 4.0 * self.laps + 1.0

    def samples(self, opt: GeometryOptions) -> float:
        per_lap = 2.0 * (self.width + self.height) / opt.step + 4.0 * _pivot_samples(opt, 0.5 * math.pi)
        return self.laps * per_lap

    def geometry(self, opt: GeometryOptions) -> Geometry:
        w, h, sign = self.width, self.height, _direction(self.direction)
        corners = [(w, 0.0), (w, sign * h), (0.0, sign * h), (0.0, 0.0)]
        return polyline_geometry([(0.0, 0.0)] + corners * int(self.laps), None, opt)


def _curve_length(dr: Curve, u1: float) -> float:
    """Arc length of a smooth curve over u in [0, u1] (a coarse estimate, for the budget)."""
    u = np.linspace(0.0, u1, 2001)
    dx, dy = dr(u)
    return float(np.trapezoid(np.hypot(dx, dy), u))


@dataclass(frozen=True, kw_only=True)
class EllipseSpec(PathCommon):
    """`shape: ellipse`, started at the end of its y semi-axis heading +x."""

    a: float = setting(unit="m", ge=MIN_PATH_SIZE_M, doc="The semi-axis along x.")
    b: float = setting(unit="m", ge=MIN_PATH_SIZE_M, doc="The semi-axis along y.")
    direction: Literal["cw", "ccw"] = setting("ccw", doc="`ccw` (counter-clockwise, turning left) or `cw`.")
    center: tuple[float, float] | None = setting(
        None, unit="[m, m]", doc="The centre; default: the start at the origin heading +x.")
    laps: float = setting(1.0, gt=0, doc="How many times the path goes round.")

    SIZE_KEY: ClassVar[str] = "a"

    def _curve(self) -> tuple[Curve, Curve, Curve]:
        a, b, sign = self.a, self.b, _direction(self.direction)
        cx, cy = self.center if self.center is not None else (0.0, sign * b)
        # Starts at the end of the y semi-axis heading +x: (cx, cy - sign b).
        return (lambda u: (cx + a * np.sin(u), cy - sign * b * np.cos(u)),
                lambda u: (a * np.cos(u), sign * b * np.sin(u)),
                lambda u: (-a * np.sin(u), sign * b * np.cos(u)))

    def samples(self, opt: GeometryOptions) -> float:
        a, b = self.a, self.b
        h = ((a - b) / (a + b)) ** 2 if a + b < math.inf else 0.0
        perimeter = math.pi * (a + b) * (1.0 + 3.0 * h / (10.0 + math.sqrt(4.0 - 3.0 * h)))  # Ramanujan
        return perimeter * self.laps / opt.step

    def geometry(self, opt: GeometryOptions) -> Geometry:
        r, dr, ddr = self._curve()
        return Geometry([parametric_piece(r, dr, ddr, 0.0, TWO_PI * self.laps, opt.step, period=TWO_PI)])


@dataclass(frozen=True, kw_only=True)
class FigureEightSpec(PathCommon):
    """`shape: figure_eight`: Gerono's lemniscate, crossing itself at its centre."""

    width: float | None = setting(None, unit="m", ge=MIN_PATH_SIZE_M, doc="Its extent along x (or give `size`).")
    height: float | None = setting(None, unit="m", ge=MIN_PATH_SIZE_M, doc="Its extent along y (or give `size`).")
    size: float | None = setting(
        None, unit="m", ge=MIN_PATH_SIZE_M, doc="Instead of width and height: width = size, height = size / 2.")
    center: tuple[float, float] = setting((0.0, 0.0), unit="[m, m]", doc="Where it crosses itself.")
    laps: float = setting(1.0, gt=0, doc="How many times the path goes round.")

    SIZE_KEY: ClassVar[str] = "width"

    def validate(self, where: str) -> None:
        super().validate(where)
        if self.size is not None and (self.width is not None or self.height is not None):
            raise ConfigError("size: give either size or width/height, not both")
        if self.size is None:
            for key, value in (("width", self.width), ("height", self.height)):
                if value is None:
                    raise ConfigError(f"{key}: missing (required, or give size)")

    def _curve(self) -> tuple[Curve, Curve, Curve]:
        w = self.size if self.size is not None else self.width
        h = 0.5 * self.size if self.size is not None else self.height
        assert w is not None and h is not None  # validate() saw to it
        cx, cy = self.center
        hw, hh = 0.5 * w, 0.5 * h
        # Gerono's lemniscate: x = (w/2) sin u, y = (h/2) sin 2u; crosses itself at the centre.
        return (lambda u: (cx + hw * np.sin(u), cy + hh * np.sin(2.0 * u)),
                lambda u: (hw * np.cos(u), 2.0 * hh * np.cos(2.0 * u)),
                lambda u: (-hw * np.sin(u), -4.0 * hh * np.sin(2.0 * u)))

    def blame(self) -> str:
        return "laps" if self.laps > 1.0 else ("size" if self.size is not None else "width")

    def samples(self, opt: GeometryOptions) -> float:
        with np.errstate(over="ignore", invalid="ignore"):
            lap = _curve_length(self._curve()[1], TWO_PI)
        return lap * self.laps / opt.step if math.isfinite(lap) else math.inf

    def geometry(self, opt: GeometryOptions) -> Geometry:
        r, dr, ddr = self._curve()
        return Geometry([parametric_piece(r, dr, ddr, 0.0, TWO_PI * self.laps, opt.step, period=TWO_PI)])


@dataclass(frozen=True, kw_only=True)
class SCurveSpec(PathCommon):
    """`shape: s_curve`: along x, shifted sideways by `offset`, heading +x at both ends."""

    length: float = setting(unit="m", ge=MIN_PATH_SIZE_M, doc="Its extent along x.")
    offset: float = setting(unit="m", doc="The sideways shift from start to end (+: to the left).")

    def samples(self, opt: GeometryOptions) -> float:
        return (self.length + 2.0 * abs(self.offset)) / opt.step  # the arc is at most this long

    def geometry(self, opt: GeometryOptions) -> Geometry:
        length, offset = self.length, self.offset
        k = math.pi / length
        # y = (offset/2)(1 - cos(pi x / length)): heading 0 at both ends, lateral shift `offset`.
        return Geometry([parametric_piece(
            lambda u: (u, 0.5 * offset * (1.0 - np.cos(k * u))),
            lambda u: (np.ones_like(u), 0.5 * offset * k * np.sin(k * u)),
            lambda u: (np.zeros_like(u), 0.5 * offset * k * k * np.cos(k * u)),
            0.0, length, opt.step)])


TOLERANCE_DOC = ("Replaces `paths.tolerance_m` for this path: how close the reference stays to the points, "
                 "m, or `auto`; 0: every point a waypoint.")
UNITS_DOC = "The unit of the points' x and y; unstated: metres, checked against `paths.workspace_m`."


@dataclass(frozen=True, kw_only=True)
class PointsSpec(PathCommon):
    """`points:`: a polyline given inline."""

    points: tuple[tuple[float, ...], ...] = setting(
        doc="`[x, y]` or `[x, y, v]` each: v a speed cap (m/s), negative where the point is reached in reverse.")
    tolerance: float | Literal["auto"] | None = setting(None, unit="m", ge=0.0, le=MAX_TOLERANCE_M, doc=TOLERANCE_DOC)
    units: Literal["m", "cm", "mm", "in", "ft"] | None = setting(None, doc=UNITS_DOC)

    SIZE_KEY: ClassVar[str] = "points"

    def validate(self, where: str) -> None:
        super().validate(where)
        for j, item in enumerate(self.points):
            if len(item) not in (2, 3):
                raise ConfigError(f"points[{j}]: expected [x, y] or [x, y, v], got {list(item)}")
            if len(item) == 3 and (item[2] == 0.0 or item[2] != item[2]):
                raise ConfigError(f"points[{j}]: speed must be nonzero (> 0 forward, < 0 reaching this point "
                                  f"in reverse), got {item[2]!r}")


@dataclass(frozen=True, kw_only=True)
class FileSpec(PathCommon):
    """`file:`: a polyline in a CSV file."""

    file: str = setting(doc="A .csv of points (`x,y` or `x,y,v` rows), relative to the spec's folder.")
    tolerance: float | Literal["auto"] | None = setting(None, unit="m", ge=0.0, le=MAX_TOLERANCE_M, doc=TOLERANCE_DOC)
    units: Literal["m", "cm", "mm", "in", "ft"] | None = setting(
        None, doc="The unit of the file's x and y unless its header says; unstated: metres, checked.")

    SIZE_KEY: ClassVar[str] = "file"


SHAPES: dict[str, type[PathCommon]] = {
    "line": LineSpec, "circle": CircleSpec, "rectangle": RectangleSpec, "ellipse": EllipseSpec,
    "figure_eight": FigureEightSpec, "s_curve": SCurveSpec,
}
KINDS: dict[str, type[PathCommon]] = {"points": PointsSpec, "file": FileSpec}


def polyline_samples(pts: list[tuple[float, float, Any]], opt: GeometryOptions) -> float:
    """An upper estimate of the samples of a polyline through `pts` (every corner a pivot)."""
    total = 0.0
    for (x0, y0, _), (x1, y1, _) in zip(pts, pts[1:]):
        total += max(2.0, math.hypot(x1 - x0, y1 - y0) / opt.step)
    return total + max(0, len(pts) - 2) * _pivot_samples(opt, math.pi)
