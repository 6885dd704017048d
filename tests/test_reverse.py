"""Paths driven in reverse: cusps, negative speed end to end, marked and unmarked reversals.

The three-point turn is a CSV whose negative `v` marks the points reached backwards; the
parallel park is a YAML `points:` list of samples of a curve (smoothed) with negative speeds on
the reversing leg, which meets the forward leg in line (a cusp with no turn in place).
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest

from ddrt.config import load_config
from ddrt.path.report import pivot_runs
from ddrt.path.spec import PathError, load_path, speed_limits
from ddrt.simrun.runner import run_sim
from tests.support.repo import SIM_YAML
from tests.support.reverse_paths import THREE_POINT, parallel_park_points


@pytest.fixture(scope="module")
def cfg():
    return load_config(SIM_YAML)


def _run(cfg, path):
    r = run_sim(cfg, path, seed=1, keep_rows=True)
    return r, r.metrics


def _check_drive(path, r, m) -> None:
    assert m["completed"], m
    assert m["rms_cross_track_m"] < 3e-3 and m["final_pos_err_m"] < 3e-3, m
    assert m["saturated_fraction"] < 0.01, m
    sig, v_ref, v = r.column("sigma"), r.column("v_ref"), r.column("v")
    d = np.asarray(path.direction)
    piv = np.asarray(path.seg_pivot)
    i = np.clip(np.searchsorted(path.sigma, sig, side="right") - 1, 0, len(d) - 1)
    rev = (d[i] < 0) & ~piv[i]
    assert rev.sum() > 100  # it did drive backwards
    # Where the path says reverse the reference speed is never forward, and the robot drove backwards.
    assert np.all(v_ref[rev] <= 1e-9)
    assert np.mean(v[rev] < 0.0) > 0.9 and v[rev].min() < -0.15
    assert np.all(v_ref[(d[i] > 0) & ~piv[i]] >= -1e-9)
    for c in path.cusps:  # at rest at every cusp, in the profile and in the run
        assert path.at(c).v == 0.0
        near = np.abs(sig - c) < 2e-3
        assert near.any() and np.abs(v[near]).min() < 0.02


def test_a_three_point_turn_from_a_csv_is_driven_backwards_where_it_says(cfg, tmp_path) -> None:
    f = tmp_path / "three_point.csv"
    f.write_text(THREE_POINT)
    path = load_path(f, speed_limits(cfg), paths=cfg.paths)
    assert len(path.cusps) == 2
    assert min(path.v) < -0.2 and max(path.v) > 0.25
    r, m = _run(cfg, path)
    _check_drive(path, r, m)


def test_a_parallel_park_yaml_reverses_in_line_and_parks(cfg) -> None:
    path = load_path(parallel_park_points(), speed_limits(cfg), paths=cfg.paths)
    assert len(path.cusps) == 1
    # In line: at most the few degrees by which the two smoothed legs' end tangents differ.
    turned = sum(b - a for a, b, p in zip(path.sigma, path.sigma[1:], path.seg_pivot) if p) / path.pivot_radius
    assert turned < math.radians(5.0)
    i = path.index(path.cusps[0])
    assert abs(path.theta[i] - path.theta[0]) < 0.05  # the robot keeps facing +x
    r, m = _run(cfg, path)
    _check_drive(path, r, m)
    assert abs(r.column("x")[-1] - 0.4) < 3e-3 and abs(r.column("y")[-1] + 0.3) < 3e-3


def test_a_path_driven_in_reverse_matches_its_mirror_image_driven_forward(cfg) -> None:
    """A ccw circle driven backwards is (v, omega) -> (-v, -omega) of the cw circle driven
    forwards: the model differs only in its quadratic terms (m_x omega^2, m_x v omega), so the
    errors match closely."""
    base = {"shape": "circle", "radius": 0.4, "laps": 1.0, "speed": 0.4}
    back = load_path({**base, "direction": "ccw", "reverse": True}, speed_limits(cfg), paths=cfg.paths)
    fwd = load_path({**base, "direction": "cw"}, speed_limits(cfg), paths=cfg.paths)
    assert back.duration == pytest.approx(fwd.duration, rel=0.02)
    assert max(back.v) <= 0.0 and min(fwd.v) >= 0.0
    _, mb = _run(cfg, back)
    _, mf = _run(cfg, fwd)
    assert mb["completed"] and mf["completed"]
    for key in ("rms_cross_track_m", "rms_tracking_m"):
        assert abs(mb[key] - mf[key]) <= max(0.3 * mf[key], 3e-5), (key, mb[key], mf[key])


def test_an_unmarked_reversal_turns_in_place_and_a_marked_one_reverses(cfg, tmp_path) -> None:
    """One rule: unmarked, an out-and-back recording turns in place at the far end; marked with
    a negative v, the same points reverse at a cusp."""
    rows = ["x,y"] + [f"{0.01 * k:.3f},0" for k in range(0, 51)] + [f"{0.5 - 0.01 * k:.3f},0.001" for k in range(1, 40)]
    f = tmp_path / "out_and_back.csv"
    f.write_text("\n".join(rows) + "\n")
    path = load_path(f, speed_limits(cfg), paths=cfg.paths)
    assert not path.cusps and min(path.v) >= 0.0
    (corner,) = path.conditioning.corners
    assert abs(math.degrees(corner.turn)) == pytest.approx(180.0, abs=3.0) and abs(corner.x - 0.5) < 0.01
    marked = ["x,y,v"] + [r + ",0.3" for r in rows[1:52]] + [r + ",-0.3" for r in rows[52:]]
    f.write_text("\n".join(marked) + "\n")
    path = load_path(f, speed_limits(cfg), paths=cfg.paths)
    assert len(path.cusps) == 1 and min(path.v) < 0.0


def test_a_zero_speed_is_refused_naming_the_line(cfg, tmp_path) -> None:
    f = tmp_path / "z.csv"
    f.write_text("x,y,v\n0,0,0.2\n1,0,0\n")
    with pytest.raises(PathError, match=r"z.csv: line 3: column 'v': speed must be nonzero"):
        load_path(f, speed_limits(cfg), paths=cfg.paths)


def test_random_marked_reverse_paths_load_or_fail_cleanly(cfg) -> None:
    """Fuzz: random polylines with random runs marked reverse either load (signs and cusps as
    marked) or fail with a PathError; nothing else escapes."""
    rng = np.random.default_rng(13)
    lim = speed_limits(cfg)
    loaded = 0
    for trial in range(300):
        n = int(rng.integers(2, 9))
        pts = np.cumsum(rng.normal(0.0, 0.3, (n, 2)), axis=0)
        if rng.random() < 0.3:  # dense, noisy samples now and then
            t = np.linspace(0.0, 1.0, int(rng.integers(20, 120)))[:, None]
            pts = np.hstack([t, 0.2 * np.sin(3 * t)]) + rng.normal(0.0, 0.001, (len(t), 2))
        signs = np.where(rng.random(len(pts)) < 0.4, -1.0, 1.0)
        speeds = rng.uniform(0.05, 0.6, len(pts)) * signs
        spec = {"points": [[float(x), float(y), float(v)] for (x, y), v in zip(pts, speeds)]}
        if rng.random() < 0.2:
            spec["reverse"] = True
        try:
            path = load_path(spec, lim, paths=cfg.paths)
        except PathError as exc:
            assert "points" in str(exc) or "path" in str(exc), str(exc)
            continue
        loaded += 1
        a = path.arrays()
        d, piv, u = a["direction"], a["seg_pivot"], a["u"]
        v = a["v"]
        drive = ~piv
        assert np.all(v[:-1][drive & (d < 0)] <= 0.0) and np.all(v[:-1][drive & (d > 0)] >= 0.0)
        for c in path.cusps:
            assert path.at(c).v == 0.0
        assert np.all(np.isfinite(a["t"])) and math.isfinite(path.duration)
    assert loaded > 150


def test_ddrt_path_reports_the_cusps(cfg, tmp_path) -> None:
    from ddrt.path.report import path_report, report_text

    f = tmp_path / "three_point.csv"
    f.write_text(THREE_POINT)
    text = report_text(path_report(load_path(f, speed_limits(cfg), paths=cfg.paths), str(f)))
    assert "cusps: 2 (0.424 m driven in reverse)" in text and text.count("cusp at") == 2


# ---------------------------------------------------------------- the shared cusp estimate


def _runs_at_first_cusp(m, xy: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    k = int(np.flatnonzero(np.sign(v[1:]) != np.sign(v[:-1]))[0])  # v[k + 1] flips: point k is the cusp
    nxt = np.flatnonzero(np.sign(v[k + 2:]) != np.sign(v[k + 1:-1]))
    end = k + 1 + int(nxt[0]) if len(nxt) else len(v) - 1
    return xy[:k + 1], xy[k:end + 1]


def test_the_cusp_estimate_recovers_the_point_and_heading_from_noisy_runs() -> None:
    """Over 40 noisy recordings of a three-point turn (1.5 mm noise, 1 cm apart) the shared
    fit finds the cusp's point across the tangent and its heading to within what the noise
    allows."""
    from lab.cusp_inputs import three_point_turn
    from ddrt.path.cusp import estimate_cusp

    m = three_point_turn()
    i = int(np.flatnonzero(m.leg == 0)[-1])
    true_p = np.array([m.x[i], m.y[i]])
    true_h = float(m.theta[i])  # the first leg is forward: travel = heading
    rng = np.random.default_rng(5)
    lateral, heading = [], []
    for _ in range(40):
        xy, v = m.recording(rng, 0.3, noise=0.0015)
        arrive, leave = _runs_at_first_cusp(m, xy, v)
        est = estimate_cusp(arrive, leave, 0.0015)
        if est is None:  # no window's fit matched the noise: the loader falls back to the bend
            continue
        n = np.array([-math.sin(true_h), math.cos(true_h)])
        lateral.append(float((est.point - true_p) @ n))
        heading.append(math.remainder(est.heading - true_h, 2 * math.pi))
        assert 0.5 <= est.pace_in <= 1.0 and 0.5 <= est.pace_out <= 1.0
    assert len(lateral) >= 36
    assert np.sqrt(np.mean(np.square(lateral))) < 1.0e-3
    # Measured: 2.5 degrees RMS (a 0.54 m leg of 1 cm samples bends at the cusp; its windows are short).
    assert np.sqrt(np.mean(np.square(heading))) < math.radians(3.0)
    # Measured bias: 0.7 degrees (the curvature the cubic leaves within its window).
    assert abs(np.mean(heading)) < math.radians(1.5)


def test_a_recorded_three_point_turn_meets_at_each_cusp_without_a_shift(cfg) -> None:
    """Both cusps shared: the runs end and start on one point with one heading (no turn in
    place, no shift), and that point is the recorded cusp sample's within the tolerance."""
    from lab.cusp_inputs import three_point_turn

    m = three_point_turn()
    xy, v = m.recording(np.random.default_rng(11), 0.3, noise=0.0015)
    path = load_path({"points": [[float(a), float(b), float(c)] for (a, b), c in zip(xy, v)]},
                     speed_limits(cfg), paths=cfg.paths)
    assert len(path.cusps) == 2 and path.conditioning.extra["cusps_shared"] == 2
    assert not any(path.seg_pivot)
    a = path.arrays()
    for c in path.cusps:
        i = path.index(c)
        assert abs(math.remainder(a["theta"][i + 1] - a["theta"][i - 1], 2 * math.pi)) < 0.01
        k = int(np.argmin(np.hypot(xy[:, 0] - a["x"][i], xy[:, 1] - a["y"][i])))
        assert math.hypot(*(xy[k] - (a["x"][i], a["y"][i]))) <= path.conditioning.tolerance_m
    assert path.deviation_m <= path.conditioning.tolerance_m


def test_turns_in_place_meeting_at_one_point_load_without_a_drive_between(cfg, tmp_path) -> None:
    """Marked reversals 1 cm apart whose runs meet at one point put two turns in place there
    with a drive of no length between them: it is no motion and is left out (its samples share
    one progress, which the profile cannot take: the path was refused, after numpy warnings)."""
    f = tmp_path / "jog.csv"
    f.write_text("x,y,v\n0,0,0.01\n-0.01,0,0.01\n0.01,0,-0.3\n0.001,0,0.01\n0.01,0,0.3\n0.05,0,0.01\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        path = load_path(f, speed_limits(cfg), paths=cfg.paths)
    assert len(path.cusps) == 2 and np.all(np.isfinite(path.v)) and path.duration < 10.0
    assert len(pivot_runs(path)) == 1  # the two meet as one half turn
