"""The reported deviation (`Path.deviation_m`, `Conditioning.deviation_m`, what `ddrt path`
prints) held against an independent measurement: for every input point, the exact distance
to the polyline of the Path's own sampled x, y, by brute force over all its segments.

The deviation from the input is bounded and reported, so the reported
figure must be at least the true largest distance, and, where the conditioning says it
smoothed within a tolerance, at most that tolerance. The one allowance is for sampling: the
report measures against the spline, this check against the chords between its samples,
which sag by at most kappa ds^2 / 8 (taken twice, for curvature that varies within a step).

For a grid plan the deviation is measured along the grid's axes (condition.py: the corridor
is each point's cell), so the check there is the exact Chebyshev distance, in the grid's
frame, from the point (its cell's centre) to the reference: at most half a cell is the
reference crossing that cell.
"""

from __future__ import annotations

import math
import os
import re
import tempfile

import numpy as np
import pytest

from ddrt.config import load_config
from ddrt.path.report import path_report
from ddrt.path.spec import PathError, load_path, speed_limits
from lab import path_inputs as pg
from lab.cusp_inputs import random_manoeuvre
from tests.support.repo import SIM_YAML

CFG = load_config(SIM_YAML)
LIM = speed_limits(CFG)


# ------------------------------------------------------------------ the independent measure


def euclid_to_polyline(poly: np.ndarray, xy: np.ndarray, budget: int = 2_000_000) -> np.ndarray:
    """Exact distance of each point to the polyline, every segment tried (chunks of points)."""
    a = poly[:-1]
    ab = poly[1:] - a
    l2 = np.einsum("ij,ij->i", ab, ab)
    l2 = np.where(l2 > 0.0, l2, 1.0)
    out = np.empty(len(xy))
    step = max(1, budget // max(1, len(a)))
    for s in range(0, len(xy), step):
        ap = xy[s:s + step, None, :] - a[None]
        t = np.clip(np.einsum("mij,ij->mi", ap, ab) / l2, 0.0, 1.0)
        d = ap - t[:, :, None] * ab[None]
        out[s:s + step] = np.sqrt(np.einsum("mij,mij->mi", d, d).min(axis=1))
    return out


def chebyshev_to_polyline(poly: np.ndarray, xy: np.ndarray, axis: float, budget: int = 400_000) -> np.ndarray:
    """Exact smallest max(|dx|, |dy|) (in a frame turned by `axis`) from each point to the
    polyline: on a segment it is convex and piecewise linear in the segment's parameter, so
    its minimum is at an end or where dx or dy is nil or |dx| = |dy|."""
    c, s_ = math.cos(axis), math.sin(axis)
    rot = np.array([[c, s_], [-s_, c]])
    p, q = poly @ rot.T, xy @ rot.T
    a = p[:-1]
    ab = p[1:] - a
    bx, by = ab[None, :, 0], ab[None, :, 1]
    out = np.empty(len(q))
    step = max(1, budget // max(1, len(a)))
    for s in range(0, len(q), step):
        e = q[s:s + step, None, :] - a[None]
        ex, ey = e[..., 0], e[..., 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            cands = (np.zeros_like(ex), np.ones_like(ex), ex / bx, ey / by, (ex - ey) / (bx - by), (ex + ey) / (bx + by))
        best = np.full(ex.shape, np.inf)
        for t in cands:
            t = np.clip(np.nan_to_num(t, nan=0.0, posinf=0.0, neginf=0.0), 0.0, 1.0)
            best = np.minimum(best, np.maximum(np.abs(ex - t * bx), np.abs(ey - t * by)))
        out[s:s + step] = best.min(axis=1)
    return out


def sampling_allowance(a: dict[str, np.ndarray]) -> float:
    """How far the chords between the reference's samples may lie from the curve sampled."""
    ds = np.diff(a["sigma"])
    k = np.maximum(np.abs(a["kappa"][1:]), np.abs(a["kappa"][:-1]))
    return float(np.max(np.where(a["seg_pivot"], 0.0, 2.0 * k * ds * ds / 8.0), initial=0.0)) + 1e-9


def grid_frame(xy: np.ndarray) -> float:
    """The grid's axis, from the plan's own shortest step (an axis step, not a diagonal)."""
    d = np.diff(xy, axis=0)
    i = int(np.argmin(np.hypot(d[:, 0], d[:, 1])))
    return math.atan2(d[i, 1], d[i, 0]) % (0.5 * math.pi)


def true_deviation(path) -> np.ndarray:
    c = path.conditioning
    a = path.arrays()
    poly = np.column_stack((a["x"], a["y"]))
    if c.mode == "grid":
        return chebyshev_to_polyline(poly, c.points, grid_frame(c.points))
    return euclid_to_polyline(poly, c.points)


def assert_reported_bounds(path, what: str) -> float:
    """The reported deviation bounds the measured one, and is within the tolerance claimed;
    the report `ddrt path` prints says the same. Returns the measured largest distance."""
    c = path.conditioning
    assert c is not None and c.mode in ("samples", "grid"), (what, c and c.mode)
    d = true_deviation(path)
    eps = sampling_allowance(path.arrays())
    i = int(np.argmax(d))
    assert d[i] <= path.deviation_m + eps, (what, c.names[i], d[i], path.deviation_m, eps)
    # "smoothed within tolerance" (Conditioning.summary): the reference is in the corridor.
    assert path.deviation_m <= c.tolerance_m * (1.0 + 1e-9), (what, path.deviation_m, c.tolerance_m)
    assert d[i] <= c.tolerance_m + eps, (what, c.names[i], d[i], c.tolerance_m)
    r = path_report(path, what)
    assert r.deviation_m == path.deviation_m and r.tolerance_m == c.tolerance_m
    assert r.deviation_at in c.names
    return float(d[i])


def load_csv(xy: np.ndarray, v: np.ndarray | float, tolerance: float | None = None):
    """As `ddrt sim --path` loads a recording (the bench's CSV writer)."""
    with tempfile.TemporaryDirectory() as tmp:
        f = os.path.join(tmp, "p.csv")
        pg.write_csv(f, xy, v)
        src = f if tolerance is None else {"file": f, "tolerance": tolerance}
        return load_path(src, LIM, paths=CFG.paths)


# ------------------------------------------------------------------ the measure itself


def test_the_measures_are_exact_on_shapes_whose_distances_are_known() -> None:
    rng = np.random.default_rng(0)
    phi = np.linspace(0.0, 2.0 * math.pi, 4001)
    poly = np.column_stack((np.cos(phi), np.sin(phi)))  # unit circle, chords sag 3e-7 m
    r = rng.uniform(0.5, 1.5, 300)
    ang = rng.uniform(0.0, 2.0 * math.pi, 300)
    pts = np.column_stack((r * np.cos(ang), r * np.sin(ang)))
    got = euclid_to_polyline(poly, pts, budget=50_000)  # several chunks
    assert np.allclose(got, np.abs(r - 1.0), atol=1e-6)
    # Chebyshev to an L shape, against a dense sampling of it, and turned with its points.
    corner = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]])
    dense = pg.dense(corner, 1e-4)
    q = rng.uniform(-0.5, 1.5, (200, 2))
    brute = np.min(np.max(np.abs(q[:, None, :] - dense[None]), axis=2), axis=1)
    assert np.allclose(chebyshev_to_polyline(corner, q, 0.0), brute, atol=1e-4)
    turn = 0.3
    rot = np.array([[math.cos(turn), -math.sin(turn)], [math.sin(turn), math.cos(turn)]])
    assert np.allclose(chebyshev_to_polyline(corner @ rot.T, q @ rot.T, turn), brute, atol=1e-4)


def test_a_lowered_report_is_caught() -> None:
    """The check can fail: the same path with its deviation under-reported by 10 % is refused."""
    path = load_csv(*_recording(np.random.default_rng(3)))
    true = assert_reported_bounds(path, "recording")
    path.conditioning.deviation_m = 0.9 * true
    with pytest.raises(AssertionError):
        assert_reported_bounds(path, "lowered")


# ------------------------------------------------------------------ the inputs


def _recording(rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """A random smooth route (no reversal), recorded at 5-30 mm with 1-2 mm of noise."""
    s = np.arange(0.0, float(rng.uniform(2.0, 6.0)), 0.001)
    k = np.zeros_like(s)
    for _ in range(3):
        k += rng.uniform(0.3, 0.9) * np.sin(2.0 * math.pi * rng.uniform(0.1, 0.5) * s + rng.uniform(0, 2 * math.pi))
    th = np.concatenate(([0.0], np.cumsum(k[:-1] * 0.001)))
    x = np.concatenate(([0.0], np.cumsum(np.cos(th[:-1]) * 0.001)))
    y = np.concatenate(([0.0], np.cumsum(np.sin(th[:-1]) * 0.001)))
    at = [0.0]
    while at[-1] < s[-1]:
        at.append(at[-1] + float(rng.uniform(0.005, 0.030)))
    at_ = np.minimum(np.array(at), s[-1])
    xy = np.column_stack((np.interp(at_, s, x), np.interp(at_, s, y)))
    return xy + rng.normal(0.0, float(rng.uniform(0.001, 0.002)), xy.shape), 0.4


@pytest.mark.parametrize("name", list(pg.CASES))
def test_bench_section_9_inputs(name: str) -> None:
    case = pg.CASES[name]()
    if case.csv is not None:
        path = load_path(str(case.csv), LIM, paths=CFG.paths)
    else:
        path = load_csv(case.xy, case.speed if case.v is None else case.v)
    c = path.conditioning
    if case.kind == "waypoints":
        # Straight segments through the points: no deviation is claimed, none reported.
        assert c is None or c.mode == "waypoints"
        assert path.deviation_m == 0.0
        return
    assert c.mode == case.kind
    assert_reported_bounds(path, name)


def test_random_recordings_without_reversals() -> None:
    rng = np.random.default_rng(13)
    for trial in range(12):
        path = load_csv(*_recording(rng))
        assert path.conditioning.mode == "samples", trial
        assert_reported_bounds(path, f"recording {trial}")


def _manoeuvres(seed: int, n: int, spacing: tuple[float, float], noise: tuple[float, float]):
    """As the reverse fuzz draws them (tests/test_reverse_sim.py): signed v on each point."""
    rng = np.random.default_rng(seed)
    for trial in range(n):
        m = random_manoeuvre(rng)
        speed = float(rng.uniform(0.15, 0.4))
        xy, v = m.recording(rng, speed, spacing=spacing, noise=float(rng.uniform(*noise)))
        yield trial, m, xy, v


def test_the_reverse_fuzz_manoeuvres() -> None:
    """The 50 of the reverse fuzz (same seed, same draws), loaded as the fuzz loads them."""
    checked = 0
    for trial, m, xy, v in _manoeuvres(2024, 50, (0.005, 0.015), (0.001, 0.002)):
        spec = {"points": [[float(a), float(b), float(c)] for (a, b), c in zip(xy, v)]}
        try:
            path = load_path(spec, LIM, paths=CFG.paths)
        except PathError:
            continue
        assert len(path.cusps) == m.cusps, trial
        assert_reported_bounds(path, f"fuzz {trial}")
        checked += 1
    assert checked >= 45


@pytest.mark.parametrize("spacing, noise", [((0.02, 0.06), (0.001, 0.002)), ((0.005, 0.015), (0.002, 0.004))],
                         ids=["sparse_20_60mm", "noisy_2_4mm"])
def test_manoeuvres_whose_cusps_cannot_all_be_shared(spacing, noise) -> None:
    """Recorded sparsely (few points near a cusp for its estimate) or noisily (an estimated
    cusp point beyond the tolerance from the cusp sample): the runs that cannot share a cusp
    meet at one point, held by both fits, not moved onto each other. Before that (a run
    fitted free and shifted onto the previous one's end, the shift added to the deviation)
    a quarter of the sparse ones reported up to 19 mm on a 10 mm tolerance, and a noisy one
    pinned a cusp 10.3 mm from its sample."""
    fallbacks = 0
    for trial, m, xy, v in _manoeuvres(11, 40, spacing, noise):
        path = load_csv(xy, v)
        assert len(path.cusps) == m.cusps, trial
        fallbacks += m.cusps - path.conditioning.extra["cusps_shared"]
        assert_reported_bounds(path, f"manoeuvre {trial}")
    assert fallbacks > 0  # the joins this is about were exercised


def test_tight_tolerance_manoeuvres() -> None:
    """A path's own tolerance of 4-7 mm on 1-2 mm of noise: held where a curve that does not
    follow the noise can hold it; else refused with a tolerance that would work, which then
    loads."""
    rng = np.random.default_rng(5)
    held = 0
    for trial, m, xy, v in _manoeuvres(5, 20, (0.005, 0.015), (0.001, 0.002)):
        tol = float(rng.uniform(0.004, 0.007))
        try:
            path = load_csv(xy, v, tolerance=tol)
            held += 1
        except PathError as exc:
            found = re.search(r"a tolerance of ([0-9.]+) m would work", str(exc))
            assert found and float(found.group(1)) > tol, str(exc)
            path = load_csv(xy, v, tolerance=float(found.group(1)))
        assert_reported_bounds(path, f"tight {trial}")
    assert held >= 10


def test_the_report_claims_no_corridor_it_did_not_measure() -> None:
    """`ddrt path` on a recording joined at cusps: the deviation line gives the reported
    largest deviation, and no "within X mm of the input polyline" figure (that figure is not
    computed for joined runs, so printed it would read 0.00 mm)."""
    from ddrt.path.report import report_text

    _trial, _m, xy, v = next(_manoeuvres(2024, 1, (0.005, 0.015), (0.001, 0.002)))
    path = load_csv(xy, v)
    assert path.cusps
    text = report_text(path_report(path, "recorded manoeuvre"))
    line = next(t for t in text.splitlines() if t.startswith("deviation"))
    assert f"largest {path.deviation_m * 1000:.2f} mm" in line and "of the input polyline" not in line
    plain = load_csv(*_recording(np.random.default_rng(5)))
    line = next(t for t in report_text(path_report(plain, "recording")).splitlines() if t.startswith("deviation"))
    assert "of the input polyline" in line and "within 0.00 mm" not in line
