"""Paths as people hand them over: polylines from recordings, planners and exports, closed loop.

`python -m bench.paths_as_given [--seed N] [--cases a,b]` prints the table; bench/run.py
includes it as a section. Every input is generated here with a fixed seed:

- circle_1cm: a 1.2 m radius circle recorded every 1 cm with 1 mm of noise (per axis), 0.5 m/s;
- figure_eight_361: the 1.2 m x 0.6 m figure-eight exported as 361 exact points, 0.8 m/s;
- grid_5cm, grid_10cm: A* plans (8-connected, octile distance) through a 4 m x 3 m room with
  two obstacles, cell by cell, 0.4 m/s; their "curve" is the staircase itself;
- teach_repeat: a corridor route (straights, arcs of 0.5-0.7 m joined by clothoids)
  recorded at random spacing of 5-30 mm with 2 mm of noise, 0.6 m/s;
- rectangle_recorded: a 1.2 m x 0.8 m rectangle recorded every 1 cm with 1 mm of noise
  (genuine 90 degree corners: they must stay turns in place), 0.3 m/s;
- waypoints_sparse: configs/paths/waypoints_sparse.csv (must not change);
- three_point_*, parallel_park_*: manoeuvres with two cusps (bench/cusp_inputs.py), recorded
  every 1 cm with 1.5 mm of noise or as exact waypoints every ~0.3 m, negative v on the
  reverse legs, 0.3 m/s. Each cusp is a stop: the ideal time adds v / limits.accel per cusp
  (braking to rest and starting again), and the exact curve's own profile (or, for
  waypoints, the waypoints' own, turns in place included) makes the same stops; the larger
  of the two is the ideal.

Each is written as an x,y,v CSV, loaded as `ddrt sim --path` would (configs/sim.yaml) and
run on the simulated robot (`run_sim`, seed 1). Reported: the time against
1.3 x max(length / speed, the profile of the exact curve at the same limits) + 3 s, the true
pose's distance from the underlying curve (RMS, max), the RMS of d(omega_ref)/dt, the share of
saturated ticks, and the reference's largest distance from the input points. Where the exact
curve is known, the same closed loop on it is the "exact" line beside it.

A last row times conditioning and profiling alone for a long recording (100 000 points,
1 cm apart, 1 mm noise: a 1 km route) and the default budget's largest (10 000 points).
"""

from __future__ import annotations

import argparse
import heapq
import math
import os
import sys
import tempfile
import time
from dataclasses import dataclass, field, replace
from pathlib import Path as FsPath
from typing import Callable, Sequence

import numpy as np

from bench.cusp_inputs import Manoeuvre, parallel_park, three_point_turn
from ddrt.config import load_config
from ddrt.path.geometry import Geometry, Piece
from ddrt.path.sampled import Path, distances_to_polyline
from ddrt.path.spec import load_path, speed_limits
from ddrt.simrun.runner import run_sim

REPO = FsPath(__file__).resolve().parents[1]
SIM_CONFIG = REPO / "configs" / "sim.yaml"
SPARSE_CSV = REPO / "configs" / "paths" / "waypoints_sparse.csv"

TIME_FACTOR, TIME_EXTRA_S = 1.3, 3.0
TARGET_TRUE_RMS_M = 3e-3  # from the underlying curve (samples with 1-2 mm noise)
TARGET_GRID_RMS_M = 15e-3  # from a grid plan's staircase
TARGET_DOMEGA_RMS = 1.5  # rad/s^2, RMS of d(omega_ref)/dt
TARGET_SATURATION = 0.01
TARGET_LONG_S = 2.0


@dataclass
class Case:
    """One input: its points (n, 2), the speed asked (the CSV's v), the curve it stands for."""

    name: str
    xy: np.ndarray
    speed: float
    curve: np.ndarray  # the underlying curve, dense (m, 2)
    kind: str  # "samples" (true-pose target 3 mm) or "grid" (15 mm from the staircase) or "waypoints"
    exact: Path | None = None  # the underlying curve as a path (same limits), when known
    csv: FsPath | None = None  # an existing file instead of xy
    v: np.ndarray | None = None  # signed speed per point (negative: reached in reverse); else `speed`
    cusps: int = 0  # of the manoeuvre (each a stop the exact curve's profile makes too)


# --------------------------------------------------------------------------- inputs


def _dense(xy: np.ndarray, step: float = 0.001) -> np.ndarray:
    """A polyline resampled every `step` (for distances)."""
    u = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))))
    s = np.linspace(0.0, u[-1], max(2, int(math.ceil(u[-1] / step)) + 1))
    return np.column_stack((np.interp(s, u, xy[:, 0]), np.interp(s, u, xy[:, 1])))


def _curve_path(s: np.ndarray, x: np.ndarray, y: np.ndarray, th: np.ndarray, k: np.ndarray,
                speed: float, step: float = 0.002) -> Path:
    """The exact curve as a Path at configs/sim.yaml's limits and `speed` (for its duration)."""
    n = max(2, int(math.ceil(s[-1] / step)))
    ss = np.linspace(0.0, s[-1], n + 1)
    piece = Piece(ss, np.interp(ss, s, x), np.interp(ss, s, y), np.interp(ss, s, th), np.interp(ss, s, k))
    cfg = load_config(SIM_CONFIG)
    return Path(Geometry([piece]), speed_limits(cfg), v_cap=speed, pivot_radius=cfg.paths.pivot_radius_m)


def circle_recording(seed: int = 1, radius: float = 1.2, spacing: float = 0.01, noise: float = 0.001) -> Case:
    rng = np.random.default_rng(seed)
    n = int(round(2.0 * math.pi * radius / spacing))
    phi = np.linspace(0.0, 2.0 * math.pi, n + 1)
    xy = np.column_stack((radius * np.sin(phi), radius - radius * np.cos(phi)))
    fine = np.linspace(0.0, 2.0 * math.pi, 20001)
    s = radius * fine
    curve = np.column_stack((radius * np.sin(fine), radius - radius * np.cos(fine)))
    exact = _curve_path(s, curve[:, 0], curve[:, 1], fine, np.full_like(fine, 1.0 / radius), 0.5)
    return Case("circle_1cm", xy + rng.normal(0.0, noise, xy.shape), 0.5, curve, "samples", exact)


def figure_eight_export(n: int = 361, width: float = 1.2, height: float = 0.6) -> Case:
    u = np.linspace(0.0, 2.0 * math.pi, n)
    xy = np.column_stack((0.5 * width * np.sin(u), 0.5 * height * np.sin(2.0 * u)))
    exact = load_path({"shape": "figure_eight", "width": width, "height": height, "speed": 0.8},
                      speed_limits(load_config(SIM_CONFIG)))
    a = exact.arrays()
    return Case("figure_eight_361", xy, 0.8, np.column_stack((a["x"], a["y"])), "samples", exact)


ROOM = (4.0, 3.0)
OBSTACLES = ((1.0, 0.0, 1.5, 1.8), (2.3, 1.1, 2.8, 3.0))  # x0, y0, x1, y1 (m)
CLEARANCE = 0.2
START, GOAL = (0.3, 0.3), (3.7, 2.6)


def astar(cell: float) -> np.ndarray:
    """An 8-connected A* plan (octile heuristic, deterministic tie-breaks) through ROOM."""
    nx, ny = int(round(ROOM[0] / cell)), int(round(ROOM[1] / cell))
    cx = (np.arange(nx) + 0.5) * cell
    cy = (np.arange(ny) + 0.5) * cell
    gx, gy = np.meshgrid(cx, cy, indexing="ij")
    free = (gx > CLEARANCE) & (gx < ROOM[0] - CLEARANCE) & (gy > CLEARANCE) & (gy < ROOM[1] - CLEARANCE)
    for x0, y0, x1, y1 in OBSTACLES:
        free &= ~((gx > x0 - CLEARANCE) & (gx < x1 + CLEARANCE) & (gy > y0 - CLEARANCE) & (gy < y1 + CLEARANCE))
    start = (int(START[0] / cell), int(START[1] / cell))
    goal = (int(GOAL[0] / cell), int(GOAL[1] / cell))
    cells = astar_cells(free, start, goal, diagonal=True)
    assert cells is not None
    return np.array([((i + 0.5) * cell, (j + 0.5) * cell) for i, j in cells])


def astar_cells(free: np.ndarray, start: tuple[int, int], goal: tuple[int, int],
                diagonal: bool = True) -> list[tuple[int, int]] | None:
    """A* over the free cells of a boolean grid, 8-connected (octile heuristic, no cutting past
    an occupied cell's corner) or 4-connected (Manhattan); deterministic tie-breaks; None if the
    goal cannot be reached."""
    nx, ny = free.shape
    sq2 = math.sqrt(2.0)

    def h(a: tuple[int, int]) -> float:
        dx, dy = abs(a[0] - goal[0]), abs(a[1] - goal[1])
        return (dx + dy) + ((sq2 - 2.0) * min(dx, dy) if diagonal else 0.0)

    openq: list[tuple[float, int, tuple[int, int]]] = [(h(start), 0, start)]
    g = {start: 0.0}
    came: dict[tuple[int, int], tuple[int, int]] = {}
    count = 0
    moves = [(1, 0), (0, 1), (-1, 0), (0, -1)] + ([(1, 1), (-1, 1), (-1, -1), (1, -1)] if diagonal else [])
    while openq:
        _, _, cur = heapq.heappop(openq)
        if cur == goal:
            break
        for dx, dy in moves:
            nb = (cur[0] + dx, cur[1] + dy)
            if not (0 <= nb[0] < nx and 0 <= nb[1] < ny) or not free[nb]:
                continue
            if dx and dy and not (free[cur[0] + dx, cur[1]] and free[cur[0], cur[1] + dy]):
                continue  # no corner cutting
            cost = g[cur] + (sq2 if dx and dy else 1.0)
            if cost < g.get(nb, math.inf) - 1e-12:
                g[nb] = cost
                came[nb] = cur
                count += 1
                heapq.heappush(openq, (cost + h(nb), count, nb))
    if goal not in g:
        return None
    node = goal
    cells = [node]
    while node != start:
        node = came[node]
        cells.append(node)
    cells.reverse()
    return cells


def grid_plan(cell: float) -> Case:
    xy = astar(cell)
    return Case(f"grid_{cell * 100:.0f}cm", xy, 0.4, _dense(xy), "grid")


def corridor_route(step: float = 0.001) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(s, x, y, theta, kappa) of a route: straights and arcs joined by 0.3 m clothoids."""
    ramp = 0.3
    legs = [(1.5, 0.0), (math.pi / 2 * 0.6, 1 / 0.6), (1.0, 0.0), (2 * math.pi / 3 * 0.5, -1 / 0.5),
            (0.8, 0.0), (5 * math.pi / 6 * 0.7, 1 / 0.7), (1.2, 0.0)]
    total = sum(length for length, _ in legs)
    s = np.arange(0.0, total + step / 2, step)
    k = np.zeros_like(s)
    start = 0.0
    for length, kap in legs:
        if kap:
            # Curvature ramps up over `ramp` centred on the arc's ends (the turn is kept).
            a, b = start, start + length
            k += kap * np.clip((s - (a - ramp / 2)) / ramp, 0.0, 1.0) * np.clip(((b + ramp / 2) - s) / ramp, 0.0, 1.0)
        start += length
    th = np.concatenate(([0.0], np.cumsum(0.5 * (k[1:] + k[:-1]) * np.diff(s))))
    x = np.concatenate(([0.0], np.cumsum(0.5 * (np.cos(th[1:]) + np.cos(th[:-1])) * np.diff(s))))
    y = np.concatenate(([0.0], np.cumsum(0.5 * (np.sin(th[1:]) + np.sin(th[:-1])) * np.diff(s))))
    return s, x, y, th, k


def teach_and_repeat(seed: int = 3, noise: float = 0.002) -> Case:
    rng = np.random.default_rng(seed)
    s, x, y, th, k = corridor_route()
    at = [0.0]
    while at[-1] < s[-1]:
        at.append(at[-1] + rng.uniform(0.005, 0.030))
    at[-1] = s[-1]
    at_ = np.array(at)
    xy = np.column_stack((np.interp(at_, s, x), np.interp(at_, s, y)))
    exact = _curve_path(s, x, y, th, k, 0.6)
    return Case("teach_repeat", xy + rng.normal(0.0, noise, xy.shape), 0.6, np.column_stack((x, y)), "samples", exact)


def rectangle_recording(seed: int = 2, width: float = 1.2, height: float = 0.8, spacing: float = 0.01,
                        noise: float = 0.001) -> Case:
    rng = np.random.default_rng(seed)
    corners = np.array([(0.0, 0.0), (width, 0.0), (width, height), (0.0, height), (0.0, 0.0)])
    xy = _dense(corners, spacing)
    exact = load_path({"shape": "rectangle", "width": width, "height": height, "speed": 0.3},
                      speed_limits(load_config(SIM_CONFIG)))
    return Case("rectangle_recorded", xy + rng.normal(0.0, noise, xy.shape), 0.3, _dense(corners), "samples", exact)


def sparse_waypoints() -> Case:
    data = np.loadtxt(SPARSE_CSV, delimiter=",", comments="#", skiprows=3)
    return Case("waypoints_sparse", data[:, :2], float(data[:, 2].max()), _dense(data[:, :2]), "waypoints",
                csv=SPARSE_CSV)


def long_recording(n: int = 100_000, seed: int = 5, spacing: float = 0.01, noise: float = 0.001) -> np.ndarray:
    """A long smooth route (|kappa| <= 2 /m) recorded every `spacing` with noise: (n, 2)."""
    rng = np.random.default_rng(seed)
    s = np.arange(n) * spacing
    k = np.zeros(n)
    for f, a in zip(rng.uniform(0.05, 0.6, 6), rng.uniform(0.2, 0.4, 6)):
        k += a * np.sin(2 * math.pi * f * s + rng.uniform(0, 2 * math.pi))
    th = np.concatenate(([0.0], np.cumsum(k[:-1] * spacing)))
    x = np.concatenate(([0.0], np.cumsum(np.cos(th[:-1]) * spacing)))
    y = np.concatenate(([0.0], np.cumsum(np.sin(th[:-1]) * spacing)))
    return np.column_stack((x, y)) + rng.normal(0.0, noise, (n, 2))


def _cusp_case(name: str, m: Manoeuvre, speed: float, seed: int, waypoints: bool) -> Case:
    """A manoeuvre as a recording (every 1 cm, 1.5 mm noise) or as waypoints (each leg's ends
    and a point every ~0.3 m along it, exact); negative v on the reverse legs."""
    exact = Path(m.exact_path_geometry(), speed_limits(load_config(SIM_CONFIG)), v_cap=speed,
                 pivot_radius=load_config(SIM_CONFIG).paths.pivot_radius_m)
    if not waypoints:
        xy, v = m.recording(np.random.default_rng(seed), speed)
        return Case(name, xy, speed, m.xy(), "samples", exact, v=v, cusps=m.cusps)
    pts, vs = [m.xy()[0]], [speed]
    for k, d in enumerate(m.directions):
        sel = np.flatnonzero(m.leg == k)
        n = max(1, int(round((m.s[sel[-1]] - m.s[sel[0]]) / 0.3)))
        for j in np.linspace(0, len(sel) - 1, n + 1)[1:].round().astype(int):
            pts.append(m.xy()[sel[j]])
            vs.append(speed * d)
    xy = np.array(pts)
    return Case(name, xy, speed, _dense(xy), "waypoints", None, v=np.array(vs), cusps=m.cusps)


CASES: dict[str, Callable[[], Case]] = {
    "circle_1cm": circle_recording,
    "figure_eight_361": figure_eight_export,
    "grid_5cm": lambda: grid_plan(0.05),
    "grid_10cm": lambda: grid_plan(0.10),
    "teach_repeat": teach_and_repeat,
    "rectangle_recorded": rectangle_recording,
    "waypoints_sparse": sparse_waypoints,
    "three_point_recorded": lambda: _cusp_case("three_point_recorded", three_point_turn(), 0.3, 7, False),
    "three_point_waypoints": lambda: _cusp_case("three_point_waypoints", three_point_turn(), 0.3, 7, True),
    "parallel_park_recorded": lambda: _cusp_case("parallel_park_recorded", parallel_park(), 0.3, 8, False),
    "parallel_park_waypoints": lambda: _cusp_case("parallel_park_waypoints", parallel_park(), 0.3, 8, True),
}


def write_csv(fname: FsPath, xy: np.ndarray, speed: float | np.ndarray) -> None:
    """x,y,v rows; `speed` one value or one (signed) per point."""
    v = np.broadcast_to(np.asarray(speed, dtype=float), (len(xy),))
    with open(fname, "w", encoding="utf-8") as fh:
        fh.write("x,y,v\n")
        for (x, y), s in zip(xy, v):
            fh.write(f"{x:.6f},{y:.6f},{s:g}\n")


# --------------------------------------------------------------------------- measuring


def curve_distance(curve: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Distance of each point to the polyline `curve`: a coarse search for the two nearest
    stretches (where a figure-eight crosses itself both are near), then a window round each."""
    if len(xy) == 0:
        return np.zeros(0)
    stride = 20
    coarse = curve[::stride]
    near = np.empty((2, len(xy)), dtype=np.intp)
    idx = np.arange(len(coarse))
    for a in range(0, len(xy), 512):
        d2 = ((xy[a:a + 512, None, :] - coarse[None, :, :]) ** 2).sum(axis=2)
        first = np.argmin(d2, axis=1)
        d2[np.abs(idx[None, :] - first[:, None]) <= 3] = np.inf
        second = np.argmin(d2, axis=1)
        near[0, a:a + 512], near[1, a:a + 512] = first * stride, second * stride
    top = len(curve) - 2
    return np.minimum(distances_to_polyline(curve, xy, np.clip(near[0], 0, top), window=2 * stride),
                      distances_to_polyline(curve, xy, np.clip(near[1], 0, top), window=2 * stride))


@dataclass
class Run:
    completed: bool
    fault: str
    time_s: float
    true_rms_m: float
    true_max_m: float
    domega_rms: float
    saturated: float


@dataclass
class Row:
    case: str
    kind: str
    points: int
    mode: str
    corners: int
    length_m: float  # of the underlying curve
    speed: float
    ideal_s: float  # max(length / speed, the exact curve's profile)
    target_s: float
    path_s: float  # the reference's own profile
    deviation_m: float  # the reference's largest distance from the input points
    load_ms: float
    run: Run
    exact: Run | None = None
    warnings: list[str] = field(default_factory=list)

    def checks(self) -> dict[str, bool]:
        r = self.run
        out = {"completed": r.completed, "time": r.time_s <= self.target_s,
               "saturation": r.saturated <= TARGET_SATURATION}
        if self.kind == "samples":
            out["true pose"] = r.true_rms_m <= TARGET_TRUE_RMS_M
        elif self.kind == "grid":
            out["true pose"] = r.true_rms_m <= TARGET_GRID_RMS_M
        if self.corners == 0 and self.kind != "waypoints":
            # Where the exact curve itself needs more (the 0.8 m/s figure-eight), within 10 % of it.
            floor = 1.1 * self.exact.domega_rms if self.exact is not None else 0.0
            out["d(omega)/dt"] = r.domega_rms <= max(TARGET_DOMEGA_RMS, floor)
        return out


@dataclass
class LongRow:
    points: int
    length_m: float
    samples: int
    read_s: float  # CPU seconds to read the CSV
    total_s: float  # CPU seconds of load_path: read, condition, profile (best of the repeats)

    @property
    def condition_s(self) -> float:
        return self.total_s - self.read_s


@dataclass
class PathsResult:
    rows: list[Row]
    long: list[LongRow]
    wall_s: float = 0.0


def _run(cfg, path: Path, seed: int, curve: np.ndarray) -> Run:
    res = run_sim(cfg, path, seed=seed)
    m = res.metrics
    t = res.column("t")
    xy = np.column_stack((res.column("x"), res.column("y")))
    d = curve_distance(curve, xy)
    w = res.column("omega_ref")
    dw = np.diff(w) / np.diff(t) if len(t) > 1 else np.zeros(1)
    return Run(bool(m["completed"]), str(m.get("fault") or ""), float(m["sim_duration_s"]),
               float(np.sqrt(np.mean(d ** 2))), float(d.max()), float(np.sqrt(np.mean(dw ** 2))),
               float(m["saturated_fraction"]))


def measure_case(case: Case, seed: int = 1, directory: str | None = None, exact: bool = True) -> Row:
    cfg = load_config(SIM_CONFIG)
    lim = speed_limits(cfg)
    with tempfile.TemporaryDirectory(dir=directory) as tmp:
        fname = case.csv if case.csv is not None else FsPath(tmp) / f"{case.name}.csv"
        if case.csv is None:
            write_csv(fname, case.xy, case.speed if case.v is None else case.v)
        t0 = time.process_time()
        path = load_path(str(fname), lim, paths=cfg.paths)
        load_ms = 1000.0 * (time.process_time() - t0)
    cond = getattr(path, "conditioning", None)
    length = float(np.sum(np.hypot(*np.diff(case.curve, axis=0).T)))
    # Each cusp is a stop: braking to rest and starting again at limits.accel costs v / a over
    # driving through. The exact curve's own profile makes those stops too (at every limit);
    # waypoints are their own exact curve, pivots included.
    stops = case.cusps * case.speed / cfg.limits.accel if cfg.limits.accel else 0.0
    own = case.exact.duration if case.exact is not None else (path.duration if case.kind == "waypoints" and case.cusps else 0.0)
    ideal = max(length / case.speed + stops, own)
    run = _run(cfg, path, seed, case.curve)
    ex = _run(cfg, case.exact, seed, case.curve) if exact and case.exact is not None else None
    piv = path.arrays()["seg_pivot"]
    n_piv = int(np.sum(piv[1:] & ~piv[:-1]) + (1 if len(piv) and piv[0] else 0))
    return Row(case.name, case.kind, len(case.xy), cond.mode if cond is not None else "waypoints", n_piv, length,
               case.speed, ideal, TIME_FACTOR * ideal + TIME_EXTRA_S, path.duration,
               float(getattr(path, "deviation_m", 0.0)), load_ms, run, ex, list(path.warnings))


def measure_long(sizes: Sequence[int] = (10_000, 100_000), repeats: int = 2) -> list[LongRow]:
    """CPU time of load_path on a long recording's CSV: reading, then conditioning and profiling."""
    from ddrt.config.sections import PathsConfig
    from ddrt.path.spec import read_points_csv

    cfg = load_config(SIM_CONFIG)
    lim = speed_limits(cfg)
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in sizes:
            fname = FsPath(tmp) / f"long_{n}.csv"
            write_csv(fname, long_recording(n), 0.5)
            paths = replace(PathsConfig(), max_points=max(n, 10_000), max_samples=max(2_000_000, 10 * n))
            best_read = best = math.inf
            path = None
            for _ in range(repeats):
                t0 = time.process_time()
                read_points_csv(str(fname), paths)
                best_read = min(best_read, time.process_time() - t0)
                t0 = time.process_time()
                path = load_path(str(fname), lim, paths=paths)
                best = min(best, time.process_time() - t0)
            assert path is not None
            out.append(LongRow(n, path.length, len(path.sigma), best_read, best))
    return out


def measure(cases: Sequence[str] | None = None, seed: int = 1, long_sizes: Sequence[int] = (10_000, 100_000),
            say: Callable[[str], None] | None = None) -> PathsResult:
    t0 = time.perf_counter()
    rows = []
    for name in (cases if cases is not None else CASES):
        rows.append(measure_case(CASES[name](), seed))
        if say:
            say(f"  {name}: {rows[-1].run.time_s:.1f} s")
    long = measure_long(long_sizes) if long_sizes else []
    return PathsResult(rows, long, time.perf_counter() - t0)


# --------------------------------------------------------------------------- the table


def _mark(ok: bool | None) -> str:
    return "" if ok is None else ("" if ok else " **x**")


def render(r: PathsResult) -> list[str]:
    lines = [
        "Polylines as recordings, planners and exports deliver them (bench/paths_as_given.py, inputs generated "
        "with fixed seeds), loaded as `ddrt sim --path FILE` loads a CSV on configs/sim.yaml and run on the "
        "simulated robot (seed 1). time: simulated time to the end, against the target "
        f"{TIME_FACTOR:g} x max(length / speed, the exact curve's own profile) + {TIME_EXTRA_S:g} s; "
        "true: distance of the true pose from the underlying curve (a grid plan: its staircase), RMS / max; "
        "d(omega)/dt: RMS of the commanded yaw acceleration; dev: the reference's largest distance from the "
        "input points. **x** marks a missed target (true pose 3 mm RMS for samples, 15 mm for a grid; "
        f"d(omega)/dt {TARGET_DOMEGA_RMS:g} rad/s^2 RMS without turns in place, or within 10 % of the exact "
        "curve's where that needs more; saturation 1 %). "
        "The indented line under a case is the same closed loop on the exact curve.",
        "",
        "| input | points | read as | turns in place | length m | v m/s | time s (target) | true mm RMS / max "
        "| d(omega)/dt rad/s^2 | saturated | dev mm | load ms |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for row in r.rows:
        c = row.checks()
        ru = row.run
        done = "" if ru.completed else f" (not completed: {ru.fault or 'time limit'})"
        lines.append(
            f"| {row.case}{done} | {row.points} | {row.mode} | {row.corners} | {row.length_m:.2f} | {row.speed:g} "
            f"| {ru.time_s:.1f}{_mark(c.get('time'))} ({row.target_s:.1f}) "
            f"| {ru.true_rms_m * 1000:.2f}{_mark(c.get('true pose'))} / {ru.true_max_m * 1000:.1f} "
            f"| {ru.domega_rms:.2f}{_mark(c.get('d(omega)/dt'))} | {ru.saturated * 100:.2f} %{_mark(c.get('saturation'))} "
            f"| {row.deviation_m * 1000:.1f} | {row.load_ms:.0f} |")
        if row.exact is not None:
            ex = row.exact
            lines.append(f"| &nbsp;&nbsp;exact curve | | | | | | {ex.time_s:.1f} | {ex.true_rms_m * 1000:.2f} / "
                         f"{ex.true_max_m * 1000:.1f} | {ex.domega_rms:.2f} | {ex.saturated * 100:.2f} % | | |")
    if r.long:
        lines += ["", "A long recording as a CSV (1 cm apart, 1 mm noise, a smooth route with |kappa| up to "
                  "2 /m; paths.max_points raised where needed): CPU seconds of `load_path`, best of 2, split "
                  f"into reading the file and conditioning + profiling (target {TARGET_LONG_S:g} s):", "",
                  "| points | length m | path samples | read CSV s | condition + profile s |", "|---|---|---|---|---|"]
        for lr in r.long:
            lines.append(f"| {lr.points} | {lr.length_m:.0f} | {lr.samples} | {lr.read_s:.2f} "
                         f"| {lr.condition_s:.2f}{_mark(lr.condition_s <= TARGET_LONG_S)} |")
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.paths_as_given", description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--cases", help=f"comma-separated subset of {', '.join(CASES)}")
    ap.add_argument("--no-long", action="store_true", help="skip the long-recording timing")
    args = ap.parse_args(argv)
    cases = args.cases.split(",") if args.cases else None
    for c in cases or ():
        if c not in CASES:
            ap.error(f"--cases: unknown case {c!r} (known: {', '.join(CASES)})")
    res = measure(cases, args.seed, () if args.no_long else (10_000, 100_000),
                  say=lambda t: (sys.stderr.write(t + "\n"), sys.stderr.flush()))
    print("\n".join(render(res)))
    print(f"\n({res.wall_s:.0f} s wall)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    sys.exit(main())
