"""The length unit of a polyline's coordinates, and whether points given without one look like metres.

Path files are in metres. A file in millimetres, centimetres or inches reads as a path
hundreds or thousands of metres across that would still load and drive for an hour, so a
polyline that says nothing about its unit is held against the robot's workspace
(`paths.workspace_m`): beyond it the file is refused, naming the units that would make it
room-sized; beyond WARN_FRACTION of it (15 m of the default 50 m), a warning. The warning's
bound sits below 0.5 m written in inches (19.7 "m"), so no room-sized path in mm, cm or
inches loads unremarked, and above a 15 m lab floor in metres, which loads without one. A
unit given explicitly (a CSV header such as `x_mm,y_mm`, a YAML spec's `units: mm`, or
`units: m` / `x_m,y_m` for a path that really is that large) is taken as meant and converted
to metres.
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass
from typing import Sequence

from ddrt.errors import DdrtError

__all__ = ["UNITS", "UnitError", "CsvColumns", "csv_columns", "check_plausible", "check_speeds"]

# Metres per unit, for every unit a path's coordinates may be written in.
UNITS: dict[str, float] = {"m": 1.0, "cm": 0.01, "mm": 0.001, "in": 0.0254, "ft": 0.3048}
UNIT_NAMES = {"m": "metres", "cm": "centimetres", "mm": "millimetres", "in": "inches", "ft": "feet"}
# A path that is room-sized in some unit: this many metres across, or fewer (and more than a hand's width).
ROOM_MIN_M, ROOM_MAX_M = 0.2, 20.0
# A speed column with values above both of these holds no speeds (coordinates, or mm/s); a cap
# merely above the limit is clamped to it, with a note.
SPEED_COLUMN_FACTOR = 20.0
SPEED_COLUMN_MIN_MPS = 10.0
# Points reaching beyond this fraction of paths.workspace_m (and not beyond it) are warned about.
WARN_FRACTION = 0.3


class UnitError(DdrtError, ValueError):
    """The points' unit is wrong or unstated in a way that would drive a path nobody meant."""


@dataclass(frozen=True)
class CsvColumns:
    """What a CSV header says: each column's role ('x', 'y', 'v') in order, and the metres
    per unit of x and y (None: not stated, so metres by default and checked for plausibility)."""

    roles: tuple[str, ...]
    scale: float | None

    @property
    def has_v(self) -> bool:
        return "v" in self.roles


def csv_columns(header: Sequence[str]) -> CsvColumns | str:
    """The header's columns, or a message saying what a header must be. x and y are named,
    in any order, plain or with one unit suffix for both (x_mm,y_mm); v, if present, is m/s."""
    roles: list[str] = []
    units: set[str | None] = set()
    for cell in header:
        name, _, unit = cell.lower().partition("_")
        if name in ("x", "y") and (not unit or unit in UNITS):
            roles.append(name)
            units.add(unit or None)
        elif cell.lower() == "v":
            roles.append("v")
        else:
            return f"unknown column {cell!r}" + _header_hint(header, cell)
    if sorted(roles) not in (["x", "y"], ["v", "x", "y"]):
        return "columns x and y are required once each, and v at most once"
    if len(units) != 1:
        return "x and y must be in the same unit"
    unit = units.pop()
    return CsvColumns(tuple(roles), None if unit is None else UNITS[unit])


def _is_number(cell: str) -> bool:
    try:
        float(cell)
    except ValueError:
        return False
    return True


def _header_hint(header: Sequence[str], cell: str) -> str:
    """Why a header a person wrote may name no known column: the usual slips, said outright
    (a file without a header, another separator, a trailing comma), else nothing."""
    given = [c for c in header if c]
    if given and all(_is_number(c) for c in given):
        return " (the first line holds numbers: the file needs a header line first, such as x,y or x_mm,y_mm)"
    for sep, name in ((";", "semicolons"), ("\t", "tabs"), (" ", "spaces")):
        if len(header) == 1 and sep in cell.strip():
            return f" (the columns look separated by {name}: separate them by commas, as in x,y)"
    if cell == "":
        return " (an empty column name: a trailing comma?)"
    return ""


ROOM_TYPICAL_M = 3.0  # the size of a lab's floor, for ordering the candidate units


def _room_sized(span_m: float) -> list[str]:
    """The units (other than metres) that make a span room-sized, the most likely first."""
    fits = [u for u, f in UNITS.items() if u != "m" and ROOM_MIN_M <= span_m * f <= ROOM_MAX_M]
    return sorted(fits, key=lambda u: abs(math.log(span_m * UNITS[u] / ROOM_TYPICAL_M)))


def check_plausible(xy: Sequence[tuple[float, float]], where: str, workspace_m: float,
                    warnings: list[str]) -> None:
    """Refuse (UnitError) points without a stated unit that span more than `workspace_m`;
    note in `warnings` those that span more than WARN_FRACTION of it. Each message names the span,
    the units that would make the points room-sized, and how to state the unit."""
    if len(xy) < 2:
        return
    xs = [p[0] for p in xy]
    ys = [p[1] for p in xy]
    reach = max(max(map(abs, xs)), max(map(abs, ys)))
    span = max(max(xs) - min(xs), max(ys) - min(ys), reach)
    if span <= WARN_FRACTION * workspace_m:
        return
    spacing = statistics.median(math.hypot(b[0] - a[0], b[1] - a[1]) for a, b in zip(xy, xy[1:]))
    likely = _room_sized(span)
    guess = (" or ".join(f"{UNIT_NAMES[u]} (then {span * UNITS[u]:.3g} m)" for u in likely)
             if likely else "a unit other than metres")
    detail = (f"the points reach {span:.6g} m (median spacing {spacing:.4g} m), "
              f"beyond {'' if span > workspace_m else f'{WARN_FRACTION:g} of '}paths.workspace_m = {workspace_m:g} m: "
              f"likely in {guess}")
    fix = ("state the unit: a CSV header such as x_mm,y_mm (or x_cm, x_in), or `units: mm` in a YAML spec; "
           "if the path really is this large, x_m,y_m or `units: m` (or raise paths.workspace_m)")
    if span > workspace_m:
        raise UnitError(f"{where}: {detail}; {fix}")
    warnings.append(f"{where}: {detail}? If so, {fix}")


def check_speeds(speeds: Sequence[float], v_max: float, where: str) -> None:
    """A speed column far above the speed limit holds no speeds in m/s: coordinates in the
    wrong column, or mm/s."""
    finite = [abs(v) for v in speeds if math.isfinite(v)]
    if not finite:
        return
    top = max(finite)
    bound = max(SPEED_COLUMN_FACTOR * v_max, SPEED_COLUMN_MIN_MPS)
    if top > bound:
        raise UnitError(f"{where}: column 'v' reaches {top:.6g}, which is no speed in m/s for this robot (more "
                        f"than {bound:g} m/s, the larger of {SPEED_COLUMN_FACTOR:g}x the speed limit {v_max:g} m/s "
                        f"and {SPEED_COLUMN_MIN_MPS:g} m/s): are the columns swapped, or the speeds in mm/s? "
                        f"v is a speed cap in m/s")
