"""`ddrt sim` scales linearly: windowed cross-track distances equal a brute-force search, the
telemetry is streamed (same CSV text) and the run holds no per-tick rows unless asked."""

from __future__ import annotations

import csv
import io
import math
import os
import subprocess
import sys
import tracemalloc

import numpy as np
import pytest

from ddrt.config import load_config
from ddrt.core.wrap import wrap_angle
from ddrt.path.spec import resolve_path
from ddrt.simrun.metrics import (WINDOW, PolylineDistance, TrackingAccumulator, path_polyline, tracking_metrics,
                                 wrap_angles)
from ddrt.simrun.runner import SIM_COLUMNS, SimResult, TelemetryStream, format_rows, run_sim, write_outputs
from tests.support.repo import REPO

SCENARIOS = REPO / "configs" / "scenarios"
COL = {name: i for i, name in enumerate(SIM_COLUMNS)}


# ------------------------------------------------------------------ brute-force references


def brute_polyline(path, step: float = 0.001) -> np.ndarray:
    """The polyline as it was built before: path.at at every step, one point at a time."""
    n = max(2, int(math.ceil(path.length / step)) + 1)
    pts = np.empty((n, 2))
    for i, s in enumerate(np.linspace(0.0, path.length, n)):
        p = path.at(float(s))
        pts[i] = p.x, p.y
    return pts


def brute_windowed(poly: np.ndarray, xy: np.ndarray, near: np.ndarray, window: int = WINDOW) -> np.ndarray:
    """Point by point: the nearest of all segments within `window` of the point's index."""
    nseg = len(poly) - 1
    out = np.empty(len(xy))
    for m, (p, k) in enumerate(zip(xy, near)):
        lo, hi = max(int(k) - window, 0), min(int(k) + window, nseg - 1)
        a = poly[lo:hi + 1]
        ab = poly[lo + 1:hi + 2] - a
        len2 = np.einsum("ij,ij->i", ab, ab)
        ap = p - a
        t = np.clip(np.einsum("ij,ij->i", ap, ab) / np.where(len2 > 0.0, len2, 1.0), 0.0, 1.0)
        diff = ap - t[:, None] * ab
        out[m] = math.sqrt(np.einsum("ij,ij->i", diff, diff).min())
    return out


def brute_metrics(path, rows: np.ndarray) -> dict[str, float]:
    """metrics.json's tracking figures from all rows at once, as summarise computed them before."""
    poly = brute_polyline(path)
    near = np.clip(np.round(rows[:, COL["sigma"]] / (path.length / (len(poly) - 1))).astype(int), 0, len(poly) - 2)
    d_true = brute_windowed(poly, rows[:, [COL["x"], COL["y"]]], near)
    d_est = brute_windowed(poly, rows[:, [COL["x_est"], COL["y_est"]]], near)
    heading = np.array([wrap_angle(a - b) for a, b in zip(rows[:, COL["theta_ref"]], rows[:, COL["theta"]])])
    end = path.at(path.length)
    return {
        "rms_cross_track_m": float(np.sqrt(np.mean(d_true ** 2))),
        "max_cross_track_m": float(d_true.max()),
        "rms_tracking_m": float(np.sqrt(np.mean(d_est ** 2))),
        "max_tracking_m": float(d_est.max()),
        "rms_heading_err_rad": float(np.sqrt(np.mean(heading ** 2))),
        "final_pos_err_m": float(math.hypot(rows[-1, COL["x"]] - end.x, rows[-1, COL["y"]] - end.y)),
        "saturated_fraction": float(np.mean(rows[:, COL["saturated"]])),
        "rms_velocity_err_mps": float(np.sqrt(np.mean((rows[:, COL["v_ref"]] - rows[:, COL["v"]]) ** 2))),
    }


def csv_writer_text(rows: np.ndarray) -> str:
    """telemetry.csv as write_outputs wrote it before: csv.writer, f"{v:.9g}" per value."""
    fh = io.StringIO(newline="")
    w = csv.writer(fh)
    w.writerow(SIM_COLUMNS)
    for r in rows.tolist():
        w.writerow([f"{v:.9g}" for v in r])
    return fh.getvalue()


def _assert_metrics_equal(got: dict, want: dict) -> None:
    for k, v in want.items():
        assert got[k] == pytest.approx(v, rel=1e-12, abs=1e-15), k


# ------------------------------------------------------------------ the distance search


def _figure8(n: int = 6000, laps: float = 2.0) -> np.ndarray:
    u = np.linspace(0.0, 2.0 * math.pi * laps, n)
    return np.c_[0.6 * np.sin(u), 0.3 * np.sin(2.0 * u)]


def _with_pivots(poly: np.ndarray, every: int = 700, length: int = 150) -> np.ndarray:
    """Insert runs of `length` copies of a vertex every `every` points (turns in place)."""
    parts = []
    for i in range(0, len(poly), every):
        seg = poly[i:i + every]
        parts.append(seg)
        parts.append(np.repeat(seg[-1:], length, axis=0))
    return np.concatenate(parts)


def _hairpin(n: int = 3000) -> np.ndarray:
    """Out 1.5 m along x and back 8 mm beside itself: the window holds both legs."""
    out = np.c_[np.linspace(0.0, 1.5, n), np.zeros(n)]
    back = np.c_[np.linspace(1.5, 0.0, n), np.full(n, 0.008)]
    return np.concatenate([out, back[1:]])


@pytest.mark.parametrize("shape", ["figure8", "pivots", "hairpin", "tiny"])
def test_windowed_distance_equals_brute_force(shape: str) -> None:
    poly = {"figure8": _figure8, "pivots": lambda: _with_pivots(_figure8()), "hairpin": _hairpin,
            "tiny": lambda: np.array([[0.0, 0.0], [0.001, 0.0], [0.001, 0.0], [0.002, 0.001]])}[shape]()
    rng = np.random.default_rng(11)
    nseg = len(poly) - 1
    m = 3000
    near = rng.integers(0, nseg, m)
    # Mostly close to the progress point (as in a run), some far off, some at the crossing.
    foot = poly[np.clip(near + rng.integers(-3, 4, m), 0, nseg)]
    scale = rng.choice([1e-5, 1e-4, 1e-3, 1e-2, 0.1, 1.0], m, p=[0.3, 0.3, 0.2, 0.1, 0.05, 0.05])
    xy = foot + rng.normal(size=(m, 2)) * scale[:, None]
    xy[:50] = rng.normal(size=(50, 2)) * 1e-4  # the figure-eight's crossing is at the origin
    xy[50:60] = poly[near[50:60]]  # exactly on a vertex
    pd = PolylineDistance(poly)
    got = pd(xy, near)
    want = brute_windowed(poly, xy, near)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15)
    if shape in ("figure8", "pivots"):
        # Points within a millimetre of their progress need no whole-window search.
        close = scale <= 1e-4
        close[:60] = False
        assert pd.fallbacks < 0.3 * m
        pd2 = PolylineDistance(poly)
        pd2(xy[close], near[close])
        assert pd2.fallbacks == 0


def test_polyline_is_the_same_as_sampling_path_at() -> None:
    for name in ("figure8_fast.yaml", "rectangle.yaml", "waypoints_sparse.yaml"):
        path = resolve_path(load_config(SCENARIOS / name))
        assert np.array_equal(path_polyline(path), brute_polyline(path)), name


def test_wrap_angles_is_wrap_angle() -> None:
    a = np.r_[np.linspace(-20.0, 20.0, 4001), math.pi, -math.pi, 3 * math.pi, 0.0, -0.0, 1e-300]
    assert np.array_equal(wrap_angles(a), np.array([wrap_angle(float(v)) for v in a]))


def test_tracking_metrics_in_chunks_equal_all_at_once() -> None:
    path = resolve_path(load_config(SCENARIOS / "figure8_fast.yaml"))
    rng = np.random.default_rng(5)
    sig = np.sort(rng.uniform(0.0, path.length, 5000))
    pts = np.array([[path.at(s).x, path.at(s).y] for s in sig])
    true_xy = pts + rng.normal(size=pts.shape) * 2e-4
    est_xy = pts + rng.normal(size=pts.shape) * 1e-4
    head = rng.normal(size=len(sig)) * 1e-3
    sat = (rng.uniform(size=len(sig)) < 0.1).astype(float)
    whole = tracking_metrics(path, true_xy, est_xy, head, sat, sig)
    acc = TrackingAccumulator(path)
    for i in range(0, len(sig), 333):
        acc.add(true_xy[i:i + 333], est_xy[i:i + 333], head[i:i + 333], sat[i:i + 333], sig[i:i + 333])
    _assert_metrics_equal(acc.result(), whole)
    poly = brute_polyline(path)
    near = np.clip(np.round(sig / (path.length / (len(poly) - 1))).astype(int), 0, len(poly) - 2)
    assert whole["max_cross_track_m"] == pytest.approx(brute_windowed(poly, true_xy, near).max(), rel=1e-12)


# ------------------------------------------------------------------ runs


@pytest.mark.parametrize("name, duration", [("figure8_fast.yaml", None), ("rectangle.yaml", None),
                                            ("seed_square.yaml", 30.0)])
def test_run_metrics_equal_brute_force(name: str, duration: float | None) -> None:
    """The figure-eight (its crossing), the rectangle (turns in place) and the seed's square
    (it starts 50 mm off the path: the whole-window fallback)."""
    cfg = load_config(SCENARIOS / name)
    path = resolve_path(cfg)
    r = run_sim(cfg, path, duration=duration, keep_rows=True, chunk_rows=1000)
    assert r.table is not None and len(r.table) == r.metrics["ticks"] > 1000
    _assert_metrics_equal(r.metrics, brute_metrics(path, r.table))
    if name == "seed_square.yaml":
        assert r.extra["metrics_fallback_points"] > 0


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(p.name for p in SCENARIOS.glob("*.yaml")))
def test_every_scenario_metrics_equal_brute_force(name: str) -> None:
    cfg = load_config(SCENARIOS / name)
    path = resolve_path(cfg)
    r = run_sim(cfg, path, keep_rows=True)
    _assert_metrics_equal(r.metrics, brute_metrics(path, r.table))


def test_streamed_csv_is_the_csv_writer_text_and_rows_are_not_kept(tmp_path) -> None:
    cfg = load_config(SCENARIOS / "s_curve.yaml")
    path = resolve_path(cfg)
    kept = run_sim(cfg, path, seed=2, keep_rows=True, telemetry=tmp_path / "a" / "telemetry.csv", chunk_rows=300)
    streamed = run_sim(cfg, path, seed=2, telemetry=tmp_path / "b" / "telemetry.csv")
    assert streamed.table is None  # the default with a file: rows are not held
    assert kept.metrics["ticks"] % 300 != 0  # a partial last chunk too
    text = (tmp_path / "a" / "telemetry.csv").read_bytes().decode()
    assert text == csv_writer_text(kept.table)
    assert (tmp_path / "b" / "telemetry.csv").read_bytes().decode() == text  # chunking changes nothing
    for k in ("rms_cross_track_m", "max_cross_track_m", "rms_tracking_m", "rms_heading_err_rad", "ticks"):
        assert streamed.metrics[k] == pytest.approx(kept.metrics[k], rel=1e-12)
    # Read back on demand from the file, at the file's precision.
    np.testing.assert_allclose(streamed.column("x"), kept.column("x"), rtol=1e-8, atol=1e-12)
    # write_outputs leaves a streamed file alone and writes the kept rows the same way.
    write_outputs(streamed, tmp_path / "b")
    write_outputs(SimResult(metrics=kept.metrics, path=path, table=kept.table), tmp_path / "c")
    assert (tmp_path / "b" / "telemetry.csv").read_bytes().decode() == text
    assert (tmp_path / "c" / "telemetry.csv").read_bytes().decode() == text


def test_format_rows_matches_csv_writer_on_edge_values() -> None:
    rng = np.random.default_rng(3)
    rows = rng.normal(size=(50, len(SIM_COLUMNS))) * 10.0 ** rng.integers(-30, 30, size=(50, len(SIM_COLUMNS)))
    rows[:, 3] = 0.0  # constant columns are formatted once
    rows[:, 4] = -0.0
    rows[:, 5] = 7.0
    rows[::7, 6] = -0.0  # 0.0 and -0.0 in one column differ in text
    rows[1, 7:12] = [np.nan, np.inf, -np.inf, 5e-324, 1e308]
    rows[:, 12] = np.nan
    want = csv_writer_text(rows)
    assert ",".join(SIM_COLUMNS) + "\r\n" + format_rows(rows) == want


# ------------------------------------------------------------------ memory


def _synthetic_rows(path, n: int, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    arr = path.arrays()
    sig = np.linspace(0.0, path.length, n)
    rows = rng.normal(size=(n, len(SIM_COLUMNS)))
    rows[:, COL["t"]] = np.arange(n) * 0.005
    rows[:, COL["sigma"]] = sig
    for c, k in (("x", "x"), ("y", "y"), ("x_est", "x"), ("y_est", "y")):
        rows[:, COL[c]] = np.interp(sig, arr["sigma"], arr[k]) + rng.normal(size=n) * 1e-4
    return rows


def _stream_peak(path, rows: np.ndarray, csv_path) -> int:
    """tracemalloc peak of streaming `rows` through a TelemetryStream, a chunk at a time."""
    tracemalloc.start()
    try:
        stream = TelemetryStream(path, csv_path, keep=False, chunk=1024)
        for i in range(0, len(rows), 1024):
            part = rows[i:i + 1024]
            stream.buf[:len(part)] = part
            stream.n = len(part)
            stream.flush()
        stream.close()
        return tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()


def test_streaming_memory_does_not_grow_with_rows(tmp_path) -> None:
    """Eight times the rows (80 s against 10 s at 200 Hz) need no more memory: the buffer,
    one chunk's text and the metrics' sums are all a run holds."""
    path = resolve_path(load_config(SCENARIOS / "figure8_fast.yaml"))
    short = _synthetic_rows(path, 2048)
    long = np.concatenate([short] * 8)  # 16 384 rows: 4.7 MB as an array, ~20 MB as tuples
    p_short = _stream_peak(path, short, tmp_path / "short.csv")
    p_long = _stream_peak(path, long, tmp_path / "long.csv")
    assert p_long < 1.5 * p_short + 0.5e6, (p_short, p_long)
    assert p_long < 4.7e6  # less than the rows themselves
    assert (tmp_path / "long.csv").read_text().count("\n") == len(long) + 1


@pytest.mark.slow
def test_ddrt_sim_peak_memory_does_not_grow_with_run_length(tmp_path) -> None:
    """Peak RSS of `ddrt sim` on the seed's square (290 s simulated) against 20 s of it, each
    in a fresh process: the long run may not hold its rows (58 000 of them)."""
    code = ("import resource, sys; from ddrt.cli import main; main(sys.argv[1:]); "
            "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)")
    env = dict(os.environ, PYTHONPATH=str(REPO))

    def peak_kb(*extra: str) -> int:
        p = subprocess.run([sys.executable, "-c", code, "sim", str(SCENARIOS / "seed_square.yaml"), "--quiet",
                            "--out", str(tmp_path / f"out{len(extra)}"), *extra],
                           cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
        return int(p.stdout.strip().splitlines()[-1])

    short = peak_kb("--duration", "20")
    long = peak_kb()
    assert long < short + 25 * 1024, (short, long)
