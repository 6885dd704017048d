"""Path files and their units: a room-sized path written in mm, cm or inches (or with its v column
swapped for a coordinate) is refused or warned about, never built into an hour's run; the same
path in metres, or with its unit stated, loads and converts to the same metres."""

from __future__ import annotations

import math
from pathlib import Path as FsPath

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ddrt.cli import main
from ddrt.config.sections import PathsConfig
from ddrt.path import PathError, SpeedLimits, load_path
from ddrt.path.units import UNITS, UnitError, check_plausible, check_speeds, csv_columns
from tests.support.repo import SIM_YAML

LIM = SpeedLimits()
PATHS = PathsConfig()
WRONG = {"mm": 1000.0, "cm": 100.0, "in": 1.0 / 0.0254}  # numbers per metre
SOURCES = ("csv", "points", "file")
FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@st.composite
def room_paths(draw: st.DrawFn) -> list[tuple[float, float]]:
    """A polyline 0.5 to 15 m across (its bounding box's longer side) that lies within that
    distance of the origin on each axis: a walk of 1 to 4 legs turning at most 90 degrees,
    so that it never turns back on itself (how such points are conditioned is not this file's
    subject)."""
    size = round(draw(st.floats(0.5, 15.0)), 3)
    legs = draw(st.lists(st.tuples(st.floats(0.3, 1.0), st.floats(-90.0, 90.0)), min_size=1, max_size=4))
    heading = draw(st.floats(-180.0, 180.0))
    raw = [(0.0, 0.0)]
    for length, turn in legs:
        heading += turn
        raw.append((raw[-1][0] + length * math.cos(math.radians(heading)),
                    raw[-1][1] + length * math.sin(math.radians(heading))))
    xs, ys = [p[0] for p in raw], [p[1] for p in raw]
    side = max(max(xs) - min(xs), max(ys) - min(ys))
    corner = (draw(st.floats(-1.0, 0.0)) * size, draw(st.floats(-1.0, 0.0)) * size)
    # To the micrometre, as a file would hold them (a number below 1e-12 is refused as such).
    return [(round(corner[0] + (x - min(xs)) / side * size, 6), round(corner[1] + (y - min(ys)) / side * size, 6))
            for x, y in raw]


def _rows(pts: list[tuple[float, float]], per_m: float, speeds: list[float] | None,
          swap: str | None = None) -> list[tuple[float, ...]]:
    """The waypoints as written: coordinates times `per_m`, with a speed column when `speeds`;
    `swap` 'x' or 'y' writes that coordinate in the v column and the speed in its place."""
    rows: list[tuple[float, ...]] = []
    for j, (x, y) in enumerate(pts):
        x, y = x * per_m, y * per_m
        if speeds is None:
            rows.append((x, y))
        elif swap == "x":
            rows.append((speeds[j], y, x))
        elif swap == "y":
            rows.append((x, speeds[j], y))
        else:
            rows.append((x, y, speeds[j]))
    return rows


def _write_csv(path: FsPath, header: str, rows: list[tuple[float, ...]]) -> FsPath:
    path.write_text(header + "\n" + "".join(",".join(repr(c) for c in r) + "\n" for r in rows))
    return path


def _load(tmp: FsPath, source: str, rows: list[tuple[float, ...]], header: str | None = None,
          units: str | None = None):
    """Load the rows as a CSV (header `header`, default x,y[,v]), an inline points: spec or a
    file: spec naming that CSV, with `units:` in the two specs when given."""
    header = header or ("x,y,v" if len(rows[0]) == 3 else "x,y")
    if source == "csv":
        return load_path(_write_csv(tmp / "p.csv", header, rows), LIM, paths=PATHS)
    extra = {"units": units} if units else {}
    if source == "points":
        return load_path({"points": [list(r) for r in rows], **extra}, LIM, paths=PATHS, where="inline")
    _write_csv(tmp / "w.csv", header, rows)
    (tmp / "p.yaml").write_text(yaml.safe_dump({"file": "w.csv", **extra}))
    return load_path(tmp / "p.yaml", LIM, paths=PATHS)


def _unit_remark(warnings: list[str]) -> bool:
    """A warning that the points look like another unit, or that the speed column is no speed."""
    return any("paths.workspace_m" in w or "limits.v_max" in w for w in warnings)


# ---------------------------------------------------------------------------------------------
# The fuzz


@FUZZ
@given(pts=room_paths(), unit=st.sampled_from(sorted(WRONG)), source=st.sampled_from(SOURCES),
       v=st.sampled_from(["none", "v", "swap x", "swap y"]),
       speeds=st.lists(st.floats(0.05, 1.0), min_size=8, max_size=8))
def test_a_room_path_in_the_wrong_units_is_refused_or_warned_about(tmp_path, pts, unit, source, v, speeds) -> None:
    rows = _rows(pts, WRONG[unit], None if v == "none" else speeds[:len(pts)],
                 v.split()[1] if v.startswith("swap") else None)
    try:
        path = _load(tmp_path, source, rows)
    except PathError as exc:
        assert "Traceback" not in str(exc)
        return
    assert _unit_remark(path.warnings), (unit, v, rows, path.warnings)
    assert path.duration < PATHS.max_duration_s


@FUZZ
@given(pts=room_paths(), source=st.sampled_from(SOURCES), with_v=st.booleans(),
       speeds=st.lists(st.floats(0.05, 1.0), min_size=8, max_size=8))
def test_a_room_path_in_metres_loads_without_a_unit_warning(tmp_path, pts, source, with_v, speeds) -> None:
    rows = _rows(pts, 1.0, speeds[:len(pts)] if with_v else None)
    path = _load(tmp_path, source, rows)
    assert not _unit_remark(path.warnings), path.warnings
    assert path.duration < PATHS.max_duration_s


@FUZZ
@given(pts=room_paths(), unit=st.sampled_from(["mm", "cm", "in", "ft", "m"]), source=st.sampled_from(SOURCES),
       order=st.permutations(["x", "y", "v"]), speeds=st.lists(st.floats(0.05, 1.0), min_size=8, max_size=8))
def test_a_path_with_its_unit_stated_converts_to_the_same_metres(tmp_path, pts, unit, source, order, speeds) -> None:
    """Stated by the CSV header (columns in any order) or by the spec's units:, the path is
    the one written in metres."""
    (tmp_path / "m").mkdir(exist_ok=True)
    metres = _load(tmp_path / "m", source, _rows(pts, 1.0, speeds[:len(pts)]))
    per = 1.0 / UNITS[unit]
    written = [dict(zip("xyv", (x * per, y * per, s))) for (x, y), s in zip(pts, speeds)]
    rows = [tuple(w[c] for c in order) for w in written]
    if source == "points":  # inline points are [x, y, v] in that order; the unit is the spec's
        path = _load(tmp_path, source, [(w["x"], w["y"], w["v"]) for w in written], units=unit)
    else:
        header = ",".join(c if c == "v" else f"{c}_{unit}" for c in order)
        path = _load(tmp_path, source, rows, header=header)
    assert not _unit_remark(path.warnings)
    assert path.length == pytest.approx(metres.length, rel=1e-9, abs=1e-9)
    assert path.duration == pytest.approx(metres.duration, rel=1e-6)
    for s in (0.0, 0.5 * path.length, path.length):
        a, b = path.at(s), metres.at(s)
        assert (a.x, a.y) == pytest.approx((b.x, b.y), abs=1e-7)


# ---------------------------------------------------------------------------------------------
# The rules one by one


def test_the_issue_s_millimetre_csv_is_refused_naming_the_file_and_millimetres(tmp_path) -> None:
    f = _write_csv(tmp_path / "mm.csv", "x,y", [(0, 0), (1000, 0), (1000, 1000), (0, 1000)])
    with pytest.raises(PathError) as exc:
        load_path(f, LIM, paths=PATHS)
    text = str(exc.value)
    assert str(f) in text and "millimetres (then 1 m)" in text and "x_mm,y_mm" in text


def test_the_header_s_unit_converts_and_the_spec_must_agree_with_it(tmp_path) -> None:
    metres = load_path(_write_csv(tmp_path / "m.csv", "x,y", [(0, 0), (1, 0), (1, 1)]), LIM, paths=PATHS)
    _write_csv(tmp_path / "w.csv", "x_mm,y_mm", [(0, 0), (1000, 0), (1000, 1000)])
    (tmp_path / "ok.yaml").write_text("file: w.csv\nunits: mm\n")
    assert load_path(tmp_path / "ok.yaml", LIM, paths=PATHS).length == pytest.approx(metres.length, rel=1e-12)
    (tmp_path / "bad.yaml").write_text("file: w.csv\nunits: cm\n")
    with pytest.raises(PathError, match=r"w\.csv: line 1: the header's unit \('x_mm,y_mm'\) is not the spec's units: cm"):
        load_path(tmp_path / "bad.yaml", LIM, paths=PATHS)


def test_a_large_path_that_states_metres_is_taken_as_meant(tmp_path) -> None:
    rows = [(0, 0), (60, 0), (60, 60)]
    with pytest.raises(PathError, match="beyond paths.workspace_m = 50 m"):
        load_path(_write_csv(tmp_path / "a.csv", "x,y", rows), LIM, paths=PATHS)
    path = load_path(_write_csv(tmp_path / "b.csv", "x_m,y_m", rows), LIM, paths=PATHS)
    end = path.at(path.length)
    assert (end.x, end.y) == pytest.approx((60.0, 60.0), abs=1e-6) and not _unit_remark(path.warnings)
    inline = load_path({"points": rows, "units": "m"}, LIM, paths=PATHS)
    assert inline.length == pytest.approx(path.length, rel=1e-12)


@pytest.mark.parametrize("header, why", [
    ("x_mm,y_cm", "same unit"), ("x,y,z", "unknown column 'z'"), ("x,x", "x and y are required once"),
    ("x_furlong,y_furlong", "unknown column"), ("x,y,v,v", "v at most once"),
])
def test_a_header_that_names_no_usable_columns_is_refused(tmp_path, header, why) -> None:
    rows = [tuple(float(j) for _ in header.split(",")) for j in range(3)]
    with pytest.raises(PathError, match=why):
        load_path(_write_csv(tmp_path / "h.csv", header, rows), LIM, paths=PATHS)


@pytest.mark.parametrize("text, hint", [
    ("0.0,0.0\n0.05,0\n0.1,0\n", "the first line holds numbers: the file needs a header line first"),
    ("1,2,\n3,4,\n", "the first line holds numbers"),
    ("x_mm;y_mm\n0;0\n500;0\n", "separated by semicolons"),
    ("x;y\n0,5;0\n1,5;0\n", "separated by semicolons"),
    ("x\ty\n0\t0\n1\t0\n", "separated by tabs"),
    ("x y\n0 0\n1 0\n", "separated by spaces"),
    ("x,y,\n0,0,\n1,0,\n", "an empty column name: a trailing comma?"),
])
def test_a_header_refused_for_a_usual_slip_says_which(tmp_path, text, hint) -> None:
    """A planner's export without a header, with another separator or a trailing comma is
    refused naming the file, the line and the slip, not only the column it could not read."""
    f = tmp_path / "plan.csv"
    f.write_text(text)
    with pytest.raises(PathError) as exc:
        load_path(f, LIM, paths=PATHS)
    msg = str(exc.value)
    assert "plan.csv: line 1: header must name the columns" in msg and hint in msg, msg


def test_a_header_with_an_unknown_name_gets_no_hint() -> None:
    assert csv_columns(["x", "y", "theta"]) == "unknown column 'theta'"
    assert csv_columns(["x (mm)", "y (mm)"]) == "unknown column 'x (mm)'"  # two columns: no other separator


def test_csv_columns_reads_any_order_and_one_unit() -> None:
    cols = csv_columns(["v", "y_in", "x_in"])
    assert not isinstance(cols, str)
    assert cols.roles == ("v", "y", "x") and cols.scale == 0.0254 and cols.has_v
    plain = csv_columns(["X", "Y"])
    assert not isinstance(plain, str) and plain.scale is None and not plain.has_v


def test_the_warning_and_refusal_bounds_follow_paths_workspace_m() -> None:
    notes: list[str] = []
    check_plausible([(0.0, 0.0), (14.9, 0.0)], "w", 50.0, notes)
    assert notes == []
    check_plausible([(0.0, 0.0), (15.1, 0.0)], "w", 50.0, notes)
    assert len(notes) == 1 and "0.3 of paths.workspace_m = 50 m" in notes[0]
    with pytest.raises(UnitError, match="likely in"):
        check_plausible([(0.0, 0.0), (50.1, 0.0)], "w", 50.0, [])
    check_plausible([(0.0, 0.0), (50.1, 0.0)], "w", 200.0, notes)  # a larger workspace: not even a warning
    assert len(notes) == 1
    check_plausible([(0.0, 0.0), (60.1, 0.0)], "w", 200.0, notes)
    assert len(notes) == 2


def test_a_speed_column_beyond_any_speed_is_refused() -> None:
    check_speeds([0.5, 19.9, math.inf], 1.0, "w")
    with pytest.raises(UnitError, match="columns swapped"):
        check_speeds([0.5, 20.1], 1.0, "w")
    with pytest.raises(UnitError, match="10 m/s"):
        check_speeds([10.5], 0.1, "w")


def test_a_path_longer_than_max_duration_is_refused_naming_the_key(tmp_path) -> None:
    """The duration bound holds for a path whose unit is stated: 1 km at 0.2 m/s."""
    f = _write_csv(tmp_path / "long.csv", "x_m,y_m,v", [(0, 0, 0.2), (500, 0, 0.2), (500, 500, 0.2)])
    with pytest.raises(PathError, match=r"longer than paths.max_duration_s = 3600 s"):
        load_path(f, LIM, paths=PATHS)


# ---------------------------------------------------------------------------------------------
# The commands


def test_ddrt_sim_refuses_a_millimetre_path_before_simulating(tmp_path, capsys) -> None:
    f = _write_csv(tmp_path / "mm.csv", "x,y", [(0, 0), (1000, 0), (1000, 1000), (0, 1000)])
    out = tmp_path / "out"
    assert main(["sim", str(SIM_YAML), "--path", str(f), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("ddrt: error: ") and "mm.csv" in err and "millimetres" in err
    assert "Traceback" not in err and err.count("\n") == 1
    assert not (out / "telemetry.csv").exists()


def test_ddrt_path_prints_the_unit_warning_of_a_path_in_inches(tmp_path, capsys) -> None:
    """A 0.6 m path in inches reads 23.6 m across: loaded, with the warning naming inches."""
    f = _write_csv(tmp_path / "in.csv", "x,y", [(0, 0), (23.6, 0), (23.6, 10)])
    assert main(["path", str(f)]) == 0
    out = capsys.readouterr().out
    assert "warning" in out and "inches (then 0.599 m)" in out


def test_a_config_s_path_in_millimetres_is_refused_by_ddrt_sim(tmp_path, capsys) -> None:
    _write_csv(tmp_path / "mm.csv", "x,y", [(0, 0), (2000, 0)])
    text = SIM_YAML.read_text().replace("path: paths/figure8_slow.yaml", "path: mm.csv")
    (tmp_path / "c.yaml").write_text(text)
    assert main(["sim", str(tmp_path / "c.yaml"), "--out", str(tmp_path / "out"), "--quiet"]) == 2
    assert "millimetres" in capsys.readouterr().err
