"""Paths: geometry against analytic shapes, the speed profile's limits, pivots, loading errors."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import yaml

from ddrt.path import Path, PathError, SpeedLimits, load_path
from ddrt.path.report import pivot_runs
from tests.support.repo import REPO

CONFIGS = REPO / "configs" / "paths"
EXAMPLES = sorted(p.name for p in CONFIGS.iterdir() if p.suffix in (".yaml", ".csv"))
LIM = SpeedLimits()


def _load(name: str, limits: SpeedLimits = LIM) -> Path:
    return load_path(CONFIGS / name, limits)


def _effective_limits(name: str) -> tuple[SpeedLimits, float]:
    """The limits and speed cap a config file asks for (read back from its YAML)."""
    if not name.endswith(".yaml"):
        return LIM, LIM.v_max
    data = yaml.safe_load((CONFIGS / name).read_text())
    over = {k: data[k] for k in ("accel", "decel", "lateral_accel", "omega_max", "alpha_max") if k in data}
    return replace(LIM, **over), min(LIM.v_max, data.get("speed", LIM.v_max))


# ---------------------------------------------------------------------------------------------
# Geometry


def test_seed_circle_matches_the_analytic_circle() -> None:
    path = _load("seed_circle.yaml")
    r = 0.3
    assert path.length == pytest.approx(2 * math.pi * r, rel=1e-12)
    assert path.start_pose == (0.0, 0.0, 0.0)
    rng = np.random.default_rng(1)
    worst = 0.0
    for s in np.concatenate((rng.uniform(0.0, path.length, 2000), [0.0, path.length])):
        p = path.at(float(s))
        phi = s / r  # clockwise from the top of a circle centred at (0, -0.3)
        ex, ey = r * math.sin(phi), -r + r * math.cos(phi)
        worst = max(worst, math.hypot(p.x - ex, p.y - ey))
        assert p.theta == pytest.approx(-phi, abs=1e-9)
        assert p.kappa == pytest.approx(-1.0 / r, rel=1e-12)
        assert math.hypot(p.x, p.y + r) == pytest.approx(r, abs=5e-6)
    assert worst < 5e-6  # 0.005 mm: far below the 0.05 mm the seed's errors are read at


def test_ellipse_perimeter_and_points() -> None:
    a, b = 1.0, 0.6
    path = _load("seed_ellipse.yaml")
    h = ((a - b) / (a + b)) ** 2
    perimeter = math.pi * (a + b) * (1 + 3 * h / (10 + math.sqrt(4 - 3 * h)))  # Ramanujan II, ~1e-10
    assert path.length == pytest.approx(perimeter, rel=1e-4)
    arr = path.arrays()
    on = (arr["x"] / a) ** 2 + ((arr["y"] - b) / b) ** 2
    assert np.max(np.abs(on - 1.0)) < 1e-6
    # Uniform arc-length spacing: chord lengths all equal to the step (2 mm) within 1e-6.
    chords = np.hypot(np.diff(arr["x"]), np.diff(arr["y"]))
    assert np.ptp(chords) < 1e-6
    # Curvature of an ellipse at the end of its minor axis is b / a^2 (ccw: positive).
    assert path.at(0.0).kappa == pytest.approx(b / a**2, rel=1e-6)
    assert path.at(path.length / 4).kappa == pytest.approx(a / b**2, rel=1e-3)
    assert path.start_pose == (0.0, -0.1, 0.0)  # the file's start pose, 100 mm off the path


def test_line_heading_and_end() -> None:
    path = _load("seed_line45.yaml")
    arr = path.arrays()
    assert np.allclose(arr["theta"], math.pi / 4, atol=1e-12)
    end = path.at(path.length)
    assert (end.x, end.y) == pytest.approx((math.sqrt(0.5), math.sqrt(0.5)), abs=1e-12)
    assert path.distance_to(0.5, 0.5) == pytest.approx(0.0, abs=1e-12)
    assert path.distance_to(0.0, 1.0) == pytest.approx(math.sqrt(0.5), abs=1e-9)
    assert path.distance_to(-0.3, -0.4) == pytest.approx(0.5, abs=1e-9)  # beyond the start: to the end point


def test_figure_eight_crosses_itself_at_its_centre() -> None:
    path = _load("figure8_slow.yaml")
    arr = path.arrays()
    d = np.hypot(arr["x"], arr["y"])
    near = np.flatnonzero(d < 1e-9)
    sig = arr["sigma"][near]
    # Start, half-way and end: three passes through the origin, with different headings.
    assert sig[0] == 0.0 and sig[-1] == pytest.approx(path.length)
    mid = path.at(path.length / 2)
    assert math.hypot(mid.x, mid.y) < 1e-6
    assert abs(math.sin(mid.theta - path.at(0.0).theta)) > 0.5


def test_circle_direction_and_center_options() -> None:
    ccw = load_path({"shape": "circle", "radius": 0.4, "direction": "ccw", "speed": 0.3}, LIM)
    arr = ccw.arrays()
    assert np.allclose(np.hypot(arr["x"], arr["y"] - 0.4), 0.4, atol=1e-12)
    assert np.all(arr["kappa"] > 0)
    moved = load_path({"shape": "circle", "radius": 0.2, "direction": "cw", "center": [1.0, 2.0]}, LIM)
    assert moved.start_pose == pytest.approx((1.0, 2.2, 0.0))
    laps = load_path({"shape": "circle", "radius": 0.2, "laps": 2}, LIM)
    assert laps.length == pytest.approx(2 * 2 * math.pi * 0.2)
    assert laps.at(laps.length).theta == pytest.approx(4 * math.pi)


# ---------------------------------------------------------------------------------------------
# Profile


@pytest.mark.parametrize("name", EXAMPLES)
def test_profile_respects_every_limit(name: str) -> None:
    path = _load(name)
    lim, v_cap = _effective_limits(name)
    arr = path.arrays()
    v, w, k, t = arr["v"], arr["omega"], arr["kappa"], arr["t"]
    a, al, piv = arr["a"], arr["alpha"], arr["seg_pivot"]
    tol = 1e-9
    assert v[0] == 0.0 and v[-1] == 0.0 and w[0] == 0.0 and w[-1] == 0.0
    assert np.all(np.diff(t) > 0.0)
    assert np.all(v >= 0.0) and np.all(v <= v_cap + tol)
    assert np.all(v * v * np.abs(k) <= lim.lateral_accel * (1 + 1e-9))
    assert np.all(np.abs(w) <= lim.omega_max * (1 + 1e-9))
    assert np.all(a <= lim.accel * (1 + 1e-9)) and np.all(a >= -lim.decel_eff * (1 + 1e-9))
    assert np.all(np.abs(al) <= lim.alpha_max * (1 + 1e-6))
    # a and alpha are the profile's own derivatives over each interval.
    dt = np.diff(t)
    drive = ~piv
    assert np.allclose(a[drive], (np.diff(v) / dt)[drive], rtol=1e-6, atol=1e-12)
    assert np.allclose(al, np.diff(w) / dt, rtol=1e-6, atol=1e-12)
    assert np.allclose(w[~arr["pivot_sample"]], (v * k)[~arr["pivot_sample"]], atol=1e-12)
    # The path is driven: something moves, and the duration is the last sample's time.
    assert v.max() > 0.0 and path.duration == t[-1]


def test_binding_limits_are_reached_but_not_exceeded() -> None:
    lim = SpeedLimits(v_max=1.0, accel=2.0, lateral_accel=0.3, omega_max=0.9, alpha_max=3.0)
    path = _load("figure8_fast.yaml", lim)
    arr = path.arrays()
    lat = arr["v"] ** 2 * np.abs(arr["kappa"])
    assert 0.29 < lat.max() <= 0.3 * (1 + 1e-9)
    assert 0.85 < np.abs(arr["omega"]).max() <= 0.9 * (1 + 1e-9)
    assert 2.0 < np.abs(arr["alpha"]).max() <= 3.0 * (1 + 1e-6)


def test_seed_circle_timing() -> None:
    path = _load("seed_circle.yaml")
    v_max = 0.0314159265
    arr = path.arrays()
    t, v, w = arr["t"], arr["v"], arr["omega"]
    full = np.flatnonzero(v >= v_max * (1 - 1e-9))
    sample_dt = 0.002 / v_max  # samples are 2 mm apart: the ramp ends within one of them
    assert t[full[0]] == pytest.approx(20.0, abs=sample_dt)
    assert t[full[-1]] == pytest.approx(60.0, abs=sample_dt)
    assert path.duration == pytest.approx(80.0, abs=0.05)
    assert w[full] == pytest.approx(-v_max / 0.3, rel=1e-9)  # -0.1047 rad/s
    assert path.at_time(10.0).v == pytest.approx(0.5 * v_max, rel=1e-3)
    assert path.at_time(10.0).a == pytest.approx(0.00157079633, rel=1e-6)
    assert path.at_time(70.0).v == pytest.approx(0.5 * v_max, rel=1e-3)


def test_square_pivots_follow_the_seed_schedule() -> None:
    path = _load("seed_square.yaml")
    runs = pivot_runs(path)
    assert len(runs) == 3
    arr = path.arrays()
    for first, last in runs:
        assert np.all(arr["v"][first:last + 1] == 0.0)
        assert arr["theta"][last] - arr["theta"][first] == pytest.approx(math.pi / 2, abs=1e-12)
        assert np.ptp(arr["x"][first:last + 1]) < 1e-12 and np.ptp(arr["y"][first:last + 1]) < 1e-12
        w = arr["omega"][first:last + 1]
        assert w.max() == pytest.approx(0.0785, rel=1e-9) and w.min() == 0.0
        dt = arr["t"][last] - arr["t"][first]
        assert dt == pytest.approx(math.pi / 2 / 0.0785 + 10.0, abs=0.05)  # trapezoid, 10 s ramps
    # Sides: 1 m at 25 mm/s with 10 s ramps = 50 s each, plus three 30 s turns.
    assert path.duration == pytest.approx(4 * 50.0 + 3 * (math.pi / 2 / 0.0785 + 10.0), abs=0.2)


def test_rectangle_pivots_turn_by_the_corner_angle_cw() -> None:
    path = load_path({"shape": "rectangle", "width": 1.2, "height": 0.8, "direction": "cw", "speed": 0.25}, LIM)
    arr = path.arrays()
    runs = pivot_runs(path)
    corners = [(1.2, 0.0), (1.2, -0.8), (0.0, -0.8)]
    assert len(runs) == 3
    for (first, last), (cx, cy) in zip(runs, corners):
        assert (arr["x"][first], arr["y"][first]) == pytest.approx((cx, cy), abs=1e-12)
        assert arr["theta"][last] - arr["theta"][first] == pytest.approx(-math.pi / 2, abs=1e-12)
        assert arr["sigma"][last] - arr["sigma"][first] == pytest.approx(0.1 * math.pi / 2)
        assert arr["omega"][first + 1:last].max() < 0.0  # turning right, never stopping inside
        assert arr["omega"][first:last + 1].min() == pytest.approx(-LIM.omega_max)
    assert path.length == pytest.approx(2 * (1.2 + 0.8) + 3 * 0.1 * math.pi / 2)


def test_sparse_waypoints_pivot_at_sharp_corners_and_blend_gentle_ones() -> None:
    path = _load("waypoints_sparse.csv")
    wps = np.loadtxt(CONFIGS / "waypoints_sparse.csv", delimiter=",", skiprows=3)
    assert len(wps) == 8
    arr = path.arrays()
    assert (arr["x"][0], arr["y"][0]) == (0.0, 0.0)
    assert (arr["x"][-1], arr["y"][-1]) == pytest.approx((0.0, 0.9), abs=1e-9)
    runs = pivot_runs(path)
    # Sharp corners: (1.8, 0.2) turns +90 deg, (1.8, 0.8) turns +71.57 deg.
    assert len(runs) == 2
    turns = [arr["theta"][last] - arr["theta"][first] for first, last in runs]
    assert turns == pytest.approx([math.pi / 2, math.atan2(0.2, -0.6) - math.pi / 2], abs=1e-9)
    for first, last in runs:
        assert np.all(arr["v"][first:last + 1] == 0.0)
        assert np.abs(arr["omega"][first + 1:last]).min() > 0.0
    # Gentle corners: heading changes in small steps (no jump), the path stays near the corner.
    dth = np.abs(np.diff(arr["theta"]))[~arr["seg_pivot"]]
    assert dth.max() < 0.05
    for x, y in wps[:, :2]:
        assert path.distance_to(x, y) < 0.02
    # Per-point caps: 0.25 m/s at (1.8, 0.2), 0.3 m/s elsewhere.
    assert arr["v"].max() == pytest.approx(0.3)
    assert path.duration > path.length / 0.3


def test_at_time_and_at_agree() -> None:
    path = _load("waypoints_sparse.csv")
    arr = path.arrays()
    assert np.all(np.diff(arr["t"]) > 0.0) and np.all(np.diff(arr["sigma"]) > 0.0)
    rng = np.random.default_rng(3)
    for s in rng.uniform(0.0, path.length, 500):
        p = path.at(float(s))
        q = path.at_time(p.t)
        assert q.sigma == pytest.approx(p.sigma, abs=1e-9)
        for f in ("x", "y", "theta", "v", "omega", "a", "alpha", "t"):
            assert getattr(q, f) == pytest.approx(getattr(p, f), abs=1e-7), f
        assert q.pivot == p.pivot
    # Between samples the profile has constant acceleration: sigma(t) is quadratic, v(t) linear.
    p0, p1 = path.at_time(1.0), path.at_time(1.001)
    assert p1.sigma - p0.sigma == pytest.approx(0.001 * 0.5 * (p0.v + p1.v), rel=1e-6)
    assert path.at_time(-5.0).sigma == 0.0 and path.at_time(1e9).sigma == path.length
    assert path.at(-1.0).sigma == 0.0 and path.at(1e9).v == 0.0


def test_speed_caps_and_overrides() -> None:
    spec = {"points": [[0, 0], [1, 0], [2, 0.0, 0.1], [3, 0]], "speed": 0.5}
    path = load_path(spec, LIM)
    assert path.at(0.5).v == pytest.approx(0.5)  # the path's speed
    assert path.at(2.0).v == pytest.approx(0.1, rel=1e-6)  # the point's own cap
    assert path.at(1.5).v == pytest.approx(0.3, rel=1e-3)  # interpolated between caps
    lim = SpeedLimits(v_max=0.2)
    assert load_path(spec, lim).at(0.5).v == pytest.approx(0.2)  # min(speed, v_max)
    slow = load_path({"shape": "line", "length": 1.0, "accel": 0.1, "decel": 0.05}, lim)
    arr = slow.arrays()
    assert arr["a"].max() == pytest.approx(0.1) and arr["a"].min() == pytest.approx(-0.05)


def test_duplicate_points_are_merged_and_start_pose_is_read(tmp_path) -> None:
    f = tmp_path / "dups.csv"
    f.write_text("x,y\n0,0\n0,0\n1,0\n1,0\n1,1\n")
    path = load_path(f, LIM)
    assert path.length == pytest.approx(2.0 + 0.1 * math.pi / 2)
    assert path.start_pose == (0.0, 0.0, 0.0)
    y = tmp_path / "wrap.yaml"
    y.write_text("file: dups.csv\nspeed: 0.2\nstart: [0.0, -0.05, 0.1]\n")
    wrapped = load_path(y, LIM)  # relative file name: resolved next to the YAML
    assert wrapped.start_pose == (0.0, -0.05, 0.1)
    assert max(wrapped.v) == pytest.approx(0.2)


# ---------------------------------------------------------------------------------------------
# Bad input


BAD_CSV = [
    ("missing_header.csv", "0,0\n1,0\n", "line 1", "header"),
    ("non_numeric.csv", "x,y\n0,0\n1,abc\n", "line 3", "not a number"),
    ("nan.csv", "x,y\n0,0\nnan,1\n", "line 3", "finite"),
    ("inf.csv", "x,y\n0,0\n1,inf\n", "line 3", "finite"),
    ("zero_speed.csv", "x,y,v\n0,0,0.2\n1,0,0\n", "line 3", "nonzero"),  # negative: reverse (test_reverse.py)
    ("columns.csv", "x,y\n0,0\n1,0,3\n", "line 3", "columns"),
    ("one_point.csv", "x,y\n# comment\n0.5,0.5\n0.5,0.5\n", "fewer than 2", "distinct"),
    ("empty.csv", "", "line 1", "header"),
]


@pytest.mark.parametrize("fname,text,where,problem", BAD_CSV)
def test_bad_csv_names_file_line_and_problem(tmp_path, fname, text, where, problem) -> None:
    f = tmp_path / fname
    f.write_text(text)
    with pytest.raises(PathError) as exc:
        load_path(f, LIM)
    msg = str(exc.value)
    assert fname in msg and where in msg and problem in msg
    assert isinstance(exc.value, ValueError)


BAD_YAML = [
    ("unknown_shape.yaml", "shape: hexagon\nspeed: 0.2\n", "key 'shape'", "unknown shape"),
    ("missing_key.yaml", "shape: circle\nspeed: 0.2\n", "key 'radius'", "missing"),
    ("negative.yaml", "shape: circle\nradius: -0.3\n", "key 'radius'", ">= 0.001 m"),
    ("bad_speed.yaml", "shape: line\nlength: 1\nspeed: -1\n", "key 'speed'", "> 0"),
    ("nan.yaml", "shape: ellipse\na: .nan\nb: 0.5\n", "key 'a'", "finite"),
    ("direction.yaml", "shape: circle\nradius: 0.3\ndirection: left\n", "key 'direction'", "cw"),
    # a reversal always turns in place: no threshold blends a 180 degree corner
    ("pivot_deg.yaml", "points: [[0, 0], [1, 0], [0, 0.01]]\ncorner_pivot_deg: 180\n", "key 'corner_pivot_deg'", "< 180 deg"),
    ("unknown_key.yaml", "shape: circle\nradius: 0.3\nradiuss: 2\n", "key 'radiuss'", "unknown key"),
    ("not_mapping.yaml", "- 1\n- 2\n", "top level", "mapping"),
    ("empty.yaml", "", "no path in it", "expected a mapping at the top level with one of shape:"),
    ("comments.yaml", "# a path, some day\n", "no path in it", "only comments"),
    ("syntax.yaml", "shape: circle\nradius: [0.3\n", "line", "invalid YAML"),
    ("bad_point.yaml", "points: [[0, 0], [1, x]]\n", "key 'points[1][1]'", "expected a number"),
    ("bad_start.yaml", "shape: circle\nradius: 0.3\nstart: [1, 2]\n", "key 'start'", "theta"),
    ("no_kind.yaml", "speed: 0.3\n", "exactly one of", "shape"),
    ("missing_file.yaml", "file: nowhere.csv\n", "nowhere.csv", "cannot read"),
]


@pytest.mark.parametrize("fname,text,where,problem", BAD_YAML)
def test_bad_yaml_names_file_key_and_problem(tmp_path, fname, text, where, problem) -> None:
    f = tmp_path / fname
    f.write_text(text)
    with pytest.raises(PathError) as exc:
        load_path(f, LIM)
    msg = str(exc.value)
    assert fname in msg and where in msg and problem in msg, msg


def test_bad_source_type_and_mapping_errors(tmp_path) -> None:
    with pytest.raises(PathError, match="unknown path file type"):
        load_path(tmp_path / "path.txt", LIM)
    with pytest.raises(PathError, match=r"<mapping>: key 'laps'"):
        load_path({"shape": "rectangle", "width": 1, "height": 1, "laps": 1.5}, LIM)
    with pytest.raises(ValueError, match="SpeedLimits.accel"):
        SpeedLimits(accel=0.0)
