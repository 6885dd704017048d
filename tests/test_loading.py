"""Loading never tracebacks, paths never loosen the config, and a path's work is bounded:
the shared YAML reader (ddrt/config/yamlio.py), the paths: section, the limit clamp from
every source (files, CSV, inline points and shapes over the control socket)."""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ddrt.cli import main
from ddrt.config import ConfigError, PathsConfig, load_config
from ddrt.config.yamlio import load_yaml_text
from ddrt.loop import LoopState
from ddrt.path import PathError, SpeedLimits, load_path
from ddrt.path.spec import resolve_path, speed_limits
from tests.support.repo import REPO, SIM_YAML

PATHS = REPO / "configs" / "paths"


def _config(tmp_path: Path, text: str, name: str = "cfg.yaml") -> Path:
    """A config that extends configs/sim.yaml with `text`."""
    p = tmp_path / name
    p.write_text(f"extends: {SIM_YAML}\n{text}", encoding="utf-8")
    return p


def _sim(argv: list[str], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    code = main(["sim", *argv, "--duration", "0.01", "--quiet", "--out", str(tmp_path / "out")])
    return code, capsys.readouterr().err


# --------------------------------------------------------------------------- the YAML reader


@pytest.mark.parametrize(("text", "needle"), [
    ("a: 1\nb: 2\na: 3\n", "f.yaml: line 3: a: duplicate key (first given on line 1)"),
    ("x:\n  k: 1\n  j: 2\n  'k': 3\n", "f.yaml: line 4: x.k: duplicate key (first given on line 2)"),
    ("l:\n  - {p: 1, p: 2}\n", "f.yaml: line 2: l[0].p: duplicate key"),
    ("1: a\n", "f.yaml: line 1: key '1' is not text"),
    ("m:\n  null: a\n", "f.yaml: line 2: m: key 'null' is not text"),
    ("? [a, b]\n: 1\n", "key a sequence is not text"),
    ("a: &x [*x]\n", "an alias that contains itself"),
    ("a: " + "[" * 70 + "]" * 70 + "\n", "nested deeper than 64 levels"),
    ("a: &a [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]\nb: &b [*a, *a, *a, *a, *a, *a, *a, *a, *a, *a]\n"
     "c: &c [*b, *b, *b, *b, *b, *b, *b, *b, *b, *b]\nd: &d [*c, *c, *c, *c, *c, *c, *c, *c, *c, *c]\n"
     "e: &e [*d, *d, *d, *d, *d, *d, *d, *d, *d, *d]\nf: [*e, *e, *e, *e, *e, *e, *e, *e, *e, *e, *e]\n",
     "more than 200000 values"),
    ("a: " + "7" * 5000 + "\n", "f.yaml: line 1: a: a number of 5000 digits"),
    ("a: [1,\n", "f.yaml: line 2, column 1: invalid YAML"),
    ("a: b\x01\n", "f.yaml: line 1: invalid YAML: control characters are not allowed"),
])
def test_reader_refuses_what_yaml_would_accept_or_crash_on(text: str, needle: str) -> None:
    with pytest.raises(ConfigError) as info:
        load_yaml_text(text, "f.yaml", ConfigError)
    assert needle in str(info.value)
    assert "\n" not in str(info.value)


def test_reader_reads_numbers_as_people_write_them() -> None:
    data = load_yaml_text("a: 1e-3\nb: 1e308\nc: 1.0e308\nd: 2.5E+4\ne: 0x68\nf: 1_000\ng: .5\nh: 1e3x\n",
                          "f.yaml", ConfigError)
    assert data == {"a": 0.001, "b": 1e308, "c": 1e308, "d": 25000.0, "e": 104, "f": 1000, "g": 0.5, "h": "1e3x"}
    assert isinstance(data["b"], float)
    merged = load_yaml_text("base: &b {x: 1, y: 2}\nm:\n  <<: *b\n  x: 3\n", "f.yaml", ConfigError)
    assert merged["m"] == {"x": 3, "y": 2}  # a merge key's keys may be overridden: no duplicate


def test_config_duplicate_key_names_file_line_and_key(tmp_path: Path) -> None:
    p = _config(tmp_path, "controller:\n  rate_hz: 200\n  inner: {kp: 20, ki: 100}\n  rate_hz: 100\n")
    with pytest.raises(ConfigError, match=r"cfg\.yaml: line 5: controller\.rate_hz: duplicate key \(first given on line 3\)"):
        load_config(p)


def test_config_not_utf8_names_file_and_byte_offset(tmp_path: Path) -> None:
    p = tmp_path / "latin.yaml"
    p.write_bytes(f"extends: {SIM_YAML}\nname: caf\xe9\n".encode("latin-1"))
    offset = len(f"extends: {SIM_YAML}\nname: caf".encode())
    with pytest.raises(ConfigError, match=rf"latin\.yaml: not UTF-8 text: byte {offset} \(0xe9\)"):
        load_config(p)


def test_exponent_floats_are_numbers_in_a_config(tmp_path: Path) -> None:
    cfg = load_config(_config(tmp_path, "controller: {inner: {kp: 2e1, ki: 1.0e2}}\nestimator: {gyro_bias_walk: 1e-5}\n"))
    assert cfg.controller.inner.kp == 20.0 and cfg.controller.inner.ki == 100.0
    assert cfg.estimator.gyro_bias_walk == 1e-5


@pytest.mark.parametrize(("text", "needle"), [
    ("limits: {v_max: 1e400}\n", "limits.v_max: must be finite"),
    ("robot: {r_L: 1e300}\n", "robot.r_L: out of range, got 1e+300"),
    ("estimator: {gyro_bias_walk: 1e-13}\n", "estimator.gyro_bias_walk: out of range, got 1e-13"),
    ("robot: {m_p: " + "9" * 400 + "}\n", "robot.m_p: too large for a number, got a 400-digit integer"),
    ("sim: {seed: " + "9" * 30 + "}\n", "sim.seed: out of range"),
    ("sensors: []\n", "sensors: expected a mapping, got []"),
    ("path: 5\n", "path: expected a path file name or a path mapping, got 5"),
    ("hal: {imu: {gyro_range_dps: 500}}\n", "hal.imu.gyro_range_dps: no longer a key: use sensors.gyro_range_dps"),
    ("start: [1e5, 0, 0]\n", "start: (100000, 0) is beyond paths.max_extent_m"),
    ("paths: {sample_step_m: 0}\n", "paths.sample_step_m: must be > 0"),
    ("daemon: {socket: " + "x" * 5000 + "}\nrobot: {m_p: x}\n", "robot.m_p: expected a number, got 'x'"),
])
def test_odd_config_values_name_the_key(tmp_path: Path, text: str, needle: str) -> None:
    with pytest.raises(ConfigError) as info:
        load_config(_config(tmp_path, text))
    assert str(info.value).startswith(f"{tmp_path / 'cfg.yaml'}: ")
    assert needle in str(info.value)
    assert len(str(info.value)) < 400  # values are shown shortened, never whole


# --------------------------------------------------------------------------- ddrt sim: one line


def _cases(tmp_path: Path) -> dict[str, list[str]]:
    big = SIM_YAML.read_text(encoding="utf-8").replace("  m_p: 0.75", "  m_p: " + "9" * 400, 1)
    (tmp_path / "big.yaml").write_text(big, encoding="utf-8")
    files = {
        "coords.yaml": "points: [[0, 0], [1e308, 0]]\n",
        "tiny.yaml": "shape: circle\nradius: 1e-300\n",
        "laps.yaml": "shape: circle\nradius: 0.5\nlaps: 1e12\n",
        "rect.yaml": "shape: rectangle\nwidth: 1\nheight: 1\nlaps: 1e12\n",
        "huge_rect.yaml": "shape: rectangle\nwidth: 1e6\nheight: 1e6\n",
        "small.yaml": "shape: circle\nradius: 1e-6\n",
        "slow.yaml": "shape: line\nlength: 1\nspeed: 1e-9\n",
    }
    for name, text in files.items():
        (tmp_path / name).write_text(text, encoding="utf-8")
    return {
        "path: 5": [str(_config(tmp_path, "path: 5\n", "p5.yaml"))],
        "400-digit robot.m_p": [str(tmp_path / "big.yaml")],
        "coordinates of 1e308": [str(SIM_YAML), "--path", str(tmp_path / "coords.yaml")],
        "radius 1e-300": [str(SIM_YAML), "--path", str(tmp_path / "tiny.yaml")],
        "laps 1e12": [str(SIM_YAML), "--path", str(tmp_path / "laps.yaml")],
        "rectangle laps 1e12": [str(SIM_YAML), "--path", str(tmp_path / "rect.yaml")],
        "rectangle 1e6 wide": [str(SIM_YAML), "--path", str(tmp_path / "huge_rect.yaml")],
        "radius 1e-6": [str(SIM_YAML), "--path", str(tmp_path / "small.yaml")],
        "speed 1e-9": [str(SIM_YAML), "--path", str(tmp_path / "slow.yaml")],
    }


EXPECTED = {
    "path: 5": "p5.yaml: path: expected a path file name",
    "400-digit robot.m_p": "big.yaml: robot.m_p: too large",
    "coordinates of 1e308": "coords.yaml: key 'points[1][0]': out of range, got 1e+308 (a number is 0 or "
                            "between 1e-12 and 1e+12 in magnitude)",
    "radius 1e-300": "tiny.yaml: key 'radius': out of range, got 1e-300",
    "radius 1e-6": "small.yaml: key 'radius': must be >= 0.001 m, got 1e-06",
    "laps 1e12": "laps.yaml: key 'laps': the path would have about 1.57e+15 samples",
    "rectangle laps 1e12": "rect.yaml: key 'laps': 1e+12 laps make 4e+12 corners, more than paths.max_points",
    "rectangle 1e6 wide": "huge_rect.yaml: key 'width': the path would have about 2e+09 samples",
    "speed 1e-9": "slow.yaml: the path takes 1e+09 s at its limits, longer than paths.max_duration_s",
}


@pytest.mark.parametrize("case", sorted(EXPECTED))
def test_sim_gives_one_line_not_a_traceback(case: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, err = _sim(_cases(tmp_path)[case], tmp_path, capsys)
    assert code == 2
    assert err.count("\n") == 1 and err.startswith("ddrt: error: ") and "Traceback" not in err
    assert EXPECTED[case] in err, err


def test_plot_without_matplotlib_says_how_to_install_it(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # import matplotlib now fails
    code = main(["sim", str(SIM_YAML), "--plot", "--duration", "0.01", "--quiet", "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert code == 2 and "pip install 'ddrt[plot]'" in err and err.count("\n") == 1
    assert not (tmp_path / "telemetry.csv").exists()  # refused before the run, not after it


def test_sim_refuses_a_config_that_drives_real_devices(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, err = _sim([str(REPO / "configs" / "robot.yaml"), "--path", str(PATHS / "circle_1m.yaml")], tmp_path, capsys)
    assert code == 2 and "hal.imu.bus: sim" in err and err.count("\n") == 1


# --------------------------------------------------------------------------- paths: the budget


def test_sample_budget_is_checked_before_allocating_and_names_key_and_budget() -> None:
    paths = PathsConfig(max_samples=10_000)
    ok = load_path({"shape": "circle", "radius": 0.5, "laps": 5}, paths=paths)  # 7854 samples
    assert len(ok.sigma) <= 10_000
    with pytest.raises(PathError, match=r"key 'laps': the path would have about 1.57e\+04 samples .* "
                                        r"paths.max_samples = 10000"):
        load_path({"shape": "circle", "radius": 0.5, "laps": 10}, paths=paths)
    for spec, key in [({"shape": "line", "length": 30}, "length"),
                      ({"shape": "ellipse", "a": 5, "b": 3}, "a"),
                      ({"shape": "figure_eight", "size": 10}, "size"),
                      ({"shape": "s_curve", "length": 10, "offset": 10}, "length"),
                      ({"shape": "rectangle", "width": 5, "height": 5, "laps": 2}, "laps"),
                      ({"points": [[0, 0], [30, 0]]}, "points")]:
        with pytest.raises(PathError, match=rf"key '{key}': the path would have about .* paths.max_samples = 10000"):
            load_path(spec, paths=paths)


def test_many_laps_of_a_closed_curve_keep_one_lap_of_arc_length_table() -> None:
    one = load_path({"shape": "figure_eight", "width": 1.2, "height": 0.6})
    many = load_path({"shape": "figure_eight", "width": 1.2, "height": 0.6, "laps": 40})
    assert many.length == pytest.approx(40 * one.length, rel=1e-9)
    assert many.at(many.length / 40 * 7.5).x == pytest.approx(one.at(one.length / 2).x, abs=1e-6)


def test_sample_step_and_pivot_defaults_come_from_the_paths_section(tmp_path: Path) -> None:
    base = load_config(_config(tmp_path, "", "base.yaml"))
    coarse = load_config(_config(tmp_path, "paths: {sample_step_m: 0.01, pivot_radius_m: 0.2}\n", "coarse.yaml"))
    rect = str(PATHS / "rectangle.yaml")
    fine_path, coarse_path = resolve_path(base, rect), resolve_path(coarse, rect)
    assert len(coarse_path.sigma) < len(fine_path.sigma) / 4
    assert coarse_path.pivot_radius == 0.2 and fine_path.pivot_radius == 0.1
    assert max(np.diff(coarse_path.sigma)) == pytest.approx(0.01, rel=0.05)


def test_csv_beyond_max_points_is_refused_at_the_line(tmp_path: Path) -> None:
    f = tmp_path / "many.csv"
    f.write_text("x,y\n" + "".join(f"{0.1 * i},0\n" for i in range(30)))
    with pytest.raises(PathError, match=r"many\.csv: line 22: more than paths.max_points = 20 waypoints"):
        load_path(f, paths=PathsConfig(max_points=20))
    assert len(load_path(f, paths=PathsConfig(max_points=30)).sigma) > 100
    with pytest.raises(PathError, match=r"key 'points': 30 points, more than paths.max_points = 20"):
        load_path({"points": [[0.1 * i, 0] for i in range(30)]}, paths=PathsConfig(max_points=20))


@pytest.mark.parametrize(("text", "needle"), [
    ("x,y\n0,0\n1,\x000\n", "line 3: column 'y': not a number"),
    ("x,y\n0,0\n\"1,0\n", "line 3: expected 2 columns, got 1"),
    ("x,y\n0,0\n1," + "2" * 200_000 + "\n", "line 3: not CSV: field larger than field limit"),
    ("x,y\n0,0\n1e400,0\n", "line 3: column 'x': must be finite"),
    ("x,y\n0,0\n" + "1" * 500 + ",0\n", "line 3: column 'x': must be finite"),
    ("x,y\n0,0\n20000,0\n", "line 3: (20000, 0) is beyond paths.max_extent_m"),
])
def test_bad_csv_cells_name_the_line(tmp_path: Path, text: str, needle: str) -> None:
    f = tmp_path / "bad.csv"
    f.write_text(text)
    with pytest.raises(PathError) as info:
        load_path(f)
    assert "bad.csv" in str(info.value) and needle in str(info.value), str(info.value)


def test_a_path_beyond_the_workspace_is_refused() -> None:
    with pytest.raises(PathError, match=r"the path reaches 20000 m from the origin, beyond paths.max_extent_m"):
        load_path({"shape": "circle", "radius": 10_000, "center": [0, 10_000]},
                  paths=PathsConfig(sample_step_m=1.0, pivot_radius_m=0.1))
    with pytest.raises(PathError, match=r"key 'center': .* is beyond paths.max_extent_m"):
        load_path({"shape": "circle", "radius": 1, "center": [1e9, 0]})


def test_profile_that_cannot_move_is_a_clear_error() -> None:
    from ddrt.path.profile import speed_profile

    # A curvature whose speed cap squares to zero: the passes cannot leave the start.
    with pytest.raises(ValueError, match="the speed profile cannot move"):
        speed_profile([0.0, 1e-3, 2e-3], [1e300, 1e300, 1e300], [False, False], [0.0, 0.0],
                      np.full(3, 1.0), SpeedLimits(), 0.1)


# --------------------------------------------------------------------------- paths never loosen the config

CFG_LIMITS = SpeedLimits(v_max=0.5, accel=0.4, lateral_accel=0.6, omega_max=1.5, alpha_max=5.0)


def _assert_within(path: Any, lim: SpeedLimits) -> None:
    arr = path.arrays()
    assert path.limits.accel <= lim.accel and path.limits.decel_eff <= lim.decel_eff
    assert path.limits.omega_max <= lim.omega_max and path.limits.alpha_max <= lim.alpha_max
    assert path.limits.lateral_accel <= lim.lateral_accel
    assert arr["v"].max() <= lim.v_max * (1 + 1e-9)
    assert np.abs(arr["omega"]).max() <= lim.omega_max * (1 + 1e-9)
    assert arr["a"].max() <= lim.accel * (1 + 1e-9) and arr["a"].min() >= -lim.decel_eff * (1 + 1e-9)


LOOSE = {"speed": 3.0, "accel": 9.0, "decel": 9.0, "lateral_accel": 9.0, "omega_max": 50.0, "alpha_max": 500.0}


def test_yaml_path_limits_above_the_configs_are_clamped_and_reported(tmp_path: Path) -> None:
    f = tmp_path / "loose.yaml"
    f.write_text("shape: rectangle\nwidth: 1\nheight: 1\n" + "".join(f"{k}: {v}\n" for k, v in LOOSE.items()))
    path = load_path(f, CFG_LIMITS)
    _assert_within(path, CFG_LIMITS)
    assert len(path.warnings) == len(LOOSE)
    assert f"{f}: key 'omega_max': 50 is above the config's 1.5 (limits.omega_max); clamped to it" in path.warnings
    assert any("key 'decel': 9 is above the config's 0.4 (limits.accel)" in w for w in path.warnings)
    # Lower values are the path's to choose, and are kept without a word.
    low = load_path({"shape": "line", "length": 1, "accel": 0.1, "omega_max": 0.5, "speed": 0.2}, CFG_LIMITS)
    assert low.warnings == [] and low.limits.accel == 0.1 and low.limits.omega_max == 0.5
    assert max(low.v) == pytest.approx(0.2)


def test_csv_and_point_speeds_above_v_max_are_clamped_and_reported(tmp_path: Path) -> None:
    f = tmp_path / "fast.csv"
    f.write_text("x,y,v\n0,0,0.3\n1,0,2.0\n2,0,0.4\n2,1,3.0\n")
    path = load_path(f, CFG_LIMITS)
    _assert_within(path, CFG_LIMITS)
    assert path.warnings == [f"{f}: 2 point speed(s) (column or third value v) up to 3 are above the config's 0.5 (limits.v_max); clamped to it"]
    spec = {"points": [[0, 0, 0.3], [1, 0, 2.0], [2, 0]], "speed": 0.4}
    inline = load_path(spec, CFG_LIMITS)
    _assert_within(inline, CFG_LIMITS)
    assert len(inline.warnings) == 1 and "key 'points'" in inline.warnings[0]
    assert max(inline.v) <= 0.4  # the path's own speed caps its points too


def test_config_path_mapping_is_clamped_to_the_configs_limits(tmp_path: Path) -> None:
    cfg = load_config(_config(tmp_path, "limits: {omega_max: 1.0, accel: 0.3}\n"
                                        "path: {shape: circle, radius: 0.3, omega_max: 3.0, accel: 2.0}\n"))
    path = resolve_path(cfg)
    _assert_within(path, speed_limits(cfg))
    assert any(w.startswith(f"{cfg.source}: path: key 'omega_max'") for w in path.warnings), path.warnings


def test_the_gyro_margin_holds_for_every_path(tmp_path: Path) -> None:
    """limits.omega_max <= 0.8 x the gyro's range, and no path turns faster than it."""
    cfg = load_config(_config(tmp_path, "limits: {omega_max: 3.4}\n"))
    gyro = math.radians(cfg.sensors.gyro_range_dps)
    path = load_path({"shape": "rectangle", "width": 1, "height": 1, "omega_max": 10.0, "alpha_max": 100.0},
                     speed_limits(cfg), paths=cfg.paths)
    assert np.abs(path.arrays()["omega"]).max() <= 0.8 * gyro


class _FakeLoop:
    state = LoopState.IDLE
    path = None

    def __init__(self) -> None:
        self.followed: list[Any] = []

    def follow(self, path: Any, pose: Any = None, built: Any = None) -> None:
        self.followed.append((path, pose))
        self.state = LoopState.FOLLOWING


@pytest.fixture
def daemon(tmp_path: Path) -> Any:
    from ddrt.service.daemon import Daemon

    d = Daemon(str(_config(tmp_path, "limits: {v_max: 0.5, accel: 0.4, omega_max: 1.5, alpha_max: 5.0}\n"
                                     "paths: {max_points: 50}\n")))
    d.loop = _FakeLoop()  # type: ignore[assignment]
    return d


def test_socket_shape_limits_are_clamped_and_the_reply_says_so(daemon: Any) -> None:
    reply = daemon.handle({"cmd": "follow", "shape": "circle", "radius": 0.5, "id": 7, "pose": [0, 0, 0], **LOOSE})
    assert reply["ok"] is True
    path, pose = daemon.loop.followed[-1]
    assert pose == (0.0, 0.0, 0.0)
    _assert_within(path, speed_limits(daemon.cfg))
    assert len(reply["warnings"]) == len(LOOSE)
    assert any("request: key 'alpha_max': 500 is above the config's 5 (limits.alpha_max)" in w for w in reply["warnings"])


def test_socket_points_limits_are_clamped_and_the_reply_says_so(daemon: Any) -> None:
    reply = daemon.handle({"cmd": "follow", "points": [[0, 0], [1, 0, 9.0], [1, 1]], "accel": 5.0, "omega_max": 20})
    assert reply["ok"] is True
    path, _ = daemon.loop.followed[-1]
    _assert_within(path, speed_limits(daemon.cfg))
    assert len(reply["warnings"]) == 3  # accel, omega_max and the point's v
    assert max(path.v) <= 0.3  # the default speed of inline points


def test_socket_paths_obey_the_configs_budget(daemon: Any) -> None:
    reply = daemon.handle({"cmd": "follow", "points": [[0.01 * i, 0] for i in range(60)]})
    assert reply["ok"] is False and "more than paths.max_points = 50" in reply["error"]
    reply = daemon.handle({"cmd": "follow", "shape": "circle", "radius": 0.5, "laps": 1e9})
    assert reply["ok"] is False and "paths.max_samples" in reply["error"] and "key 'laps'" in reply["error"]
    reply = daemon.handle({"cmd": "follow", "shape": "circle", "radius": 0.5, "bogus": 1})
    assert reply["ok"] is False and "key 'bogus': unknown key" in reply["error"]
    assert daemon.loop.followed == []
