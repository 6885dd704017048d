"""Paths as people hand them over, generated with fixed seeds: polylines from recordings,
planners and exports, each with the curve it stands for. bench/paths_as_given.py runs them in
closed loop for BENCHMARKS.md; the conditioning tests load them; both hold them to the targets
below.

- circle_1cm: a 1.2 m radius circle recorded every 1 cm with 1 mm of noise (per axis), 0.5 m/s;
- figure_eight_361: the 1.2 m x 0.6 m figure-eight exported as 361 exact points, 0.8 m/s;
- grid_5cm, grid_10cm: A* plans (8-connected, octile distance) through a 4 m x 3 m room with
  two obstacles, cell by cell, 0.4 m/s; their "curve" is the staircase itself;
- teach_repeat: a corridor route (straights, arcs of 0.5-0.7 m joined by clothoids)
  recorded at random spacing of 5-30 mm with 2 mm of noise, 0.6 m/s;
- rectangle_recorded: a 1.2 m x 0.8 m rectangle recorded every 1 cm with 1 mm of noise
  (genuine 90 degree corners: they must stay turns in place), 0.3 m/s;
- waypoints_sparse: configs/paths/waypoints_sparse.csv (must not change);
- three_point_*, parallel_park_*: manoeuvres with two cusps (lab/cusp_inputs.py),
  recorded every 1 cm with 1.5 mm of noise or as exact waypoints every ~0.3 m, negative v on
  the reverse legs, 0.3 m/s;
- long_recording: a long smooth route recorded every 1 cm with 1 mm of noise (the timing of
  conditioning and profiling).
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass
from pathlib import Path as FsPath
from typing import Callable

import numpy as np

from ddrt.config import load_config
from ddrt.path.geometry import Geometry, Piece
from ddrt.path.sampled import Path, distances_to_polyline
from ddrt.path.spec import load_path, speed_limits
from lab.cusp_inputs import Manoeuvre, parallel_park, three_point_turn
from lab.repo import REPO, SIM_YAML

SPARSE_CSV = REPO / "configs" / "paths" / "waypoints_sparse.csv"

TARGET_TRUE_RMS_M = 3e-3  # from the underlying curve (samples with 1-2 mm noise)
TARGET_GRID_RMS_M = 15e-3  # from a grid plan's staircase
TARGET_DOMEGA_RMS = 1.5  # rad/s^2, RMS of d(omega_ref)/dt
TARGET_SATURATION = 0.01


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


def dense(xy: np.ndarray, step: float = 0.001) -> np.ndarray:
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
    cfg = load_config(SIM_YAML)
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
                      speed_limits(load_config(SIM_YAML)))
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
    return Case(f"grid_{cell * 100:.0f}cm", xy, 0.4, dense(xy), "grid")


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
    xy = dense(corners, spacing)
    exact = load_path({"shape": "rectangle", "width": width, "height": height, "speed": 0.3},
                      speed_limits(load_config(SIM_YAML)))
    return Case("rectangle_recorded", xy + rng.normal(0.0, noise, xy.shape), 0.3, dense(corners), "samples", exact)


def sparse_waypoints() -> Case:
    data = np.loadtxt(SPARSE_CSV, delimiter=",", comments="#", skiprows=3)
    return Case("waypoints_sparse", data[:, :2], float(data[:, 2].max()), dense(data[:, :2]), "waypoints",
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
    exact = Path(m.exact_path_geometry(), speed_limits(load_config(SIM_YAML)), v_cap=speed,
                 pivot_radius=load_config(SIM_YAML).paths.pivot_radius_m)
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
    return Case(name, xy, speed, dense(xy), "waypoints", None, v=np.array(vs), cusps=m.cusps)


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
    """x,y,v rows in metres, stated by the header (a long recording reaches beyond
    paths.workspace_m); `speed` one value or one (signed) per point."""
    v = np.broadcast_to(np.asarray(speed, dtype=float), (len(xy),))
    with open(fname, "w", encoding="utf-8") as fh:
        fh.write("x_m,y_m,v\n")
        for (x, y), s in zip(xy, v):
            fh.write(f"{x:.6f},{y:.6f},{s:g}\n")


FULL_SEARCH_POINTS = 2000  # a curve this short is searched whole (1024 x 2000 distances a chunk)


def curve_distance(curve: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Distance of each point to the polyline `curve`: a coarse search for the two nearest
    stretches (where a figure-eight crosses itself both are near), then a window round each.
    A curve of few points (a grid plan's cells) is searched whole: every 20th of its points
    can all lie far from a point near the curve (one at 9.7 mm from a plan's last cells read
    as 203 mm)."""
    if len(xy) == 0:
        return np.zeros(0)
    if len(curve) <= FULL_SEARCH_POINTS:
        return distances_to_polyline(curve, xy)
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


GRID_FUZZ_SPEED = 0.4  # m/s, as the bench's grid plans


def random_grid(rng: np.random.Generator) -> np.ndarray:
    """A boolean grid of free cells, 20-80 cells a side, with up to 10 random rectangular obstacles."""
    nx, ny = int(rng.integers(20, 81)), int(rng.integers(20, 81))
    free = np.ones((nx, ny), dtype=bool)
    for _ in range(int(rng.integers(0, 11))):
        w, h = int(rng.integers(1, max(2, nx // 3))), int(rng.integers(1, max(2, ny // 3)))
        x0, y0 = int(rng.integers(0, nx - w)), int(rng.integers(0, ny - h))
        free[x0:x0 + w, y0:y0 + h] = False
    return free


def staircase(a: tuple[int, int], b: tuple[int, int], diagonal: bool) -> list[tuple[int, int]]:
    """The cells of a straight line from cell a to cell b, one step at a time (a step along an axis
    or, `diagonal`, a diagonal): the staircase a planner's line of sight leaves on a grid."""
    cells = [a]
    x, y = a
    dx, dy = b[0] - a[0], b[1] - a[1]
    while (x, y) != b:
        # The step that keeps the cell closest to the line a-b.
        best = None
        for sx, sy in ((int(np.sign(b[0] - x)), 0), (0, int(np.sign(b[1] - y))),
                       (int(np.sign(b[0] - x)), int(np.sign(b[1] - y)))):
            if (sx, sy) == (0, 0) or (sx and sy and not diagonal):
                continue
            nx_, ny_ = x + sx, y + sy
            off = abs(dx * (ny_ - a[1]) - dy * (nx_ - a[0]))
            if best is None or off < best[0] - 1e-9:
                best = (off, nx_, ny_)
        assert best is not None
        x, y = best[1], best[2]
        cells.append((x, y))
    return cells


def grid_fuzz_plan(rng: np.random.Generator) -> tuple[str, float, np.ndarray] | None:
    """A grid plan as planners hand them over, cell centres on a 2-10 cm grid, 4- or 8-connected:
    an A* plan between two far-apart free cells of a random grid with obstacles, an A* plan through
    one to three random via points (its legs meet at any angle, 135 and 180 degrees included), or a
    walk of straight staircases between random cells of an open grid. (kind, cell, points); None
    when the goal is walled off or the plan is shorter than 8 cells."""
    cell = float(rng.uniform(0.02, 0.10))
    diagonal = bool(rng.integers(2))
    kind = ("astar", "via", "walk")[int(rng.integers(3))]
    free = random_grid(rng) if kind != "walk" else np.ones((int(rng.integers(20, 81)),) * 2, dtype=bool)
    cells = np.argwhere(free)
    nx, ny = free.shape

    def pick() -> tuple[int, int]:
        c = cells[rng.integers(len(cells))]
        return int(c[0]), int(c[1])

    if kind == "astar":
        a, b = pick(), pick()
        for _ in range(50):
            if math.hypot(a[0] - b[0], a[1] - b[1]) > 0.5 * max(nx, ny):
                break
            a, b = pick(), pick()
        stops = [a, b]
    else:
        stops = [pick() for _ in range(int(rng.integers(3, 6)))]
    plan: list[tuple[int, int]] = [stops[0]]
    for a, b in zip(stops[:-1], stops[1:]):
        leg = staircase(a, b, diagonal) if kind == "walk" else astar_cells(free, a, b, diagonal=diagonal)
        if leg is None:
            return None
        plan.extend(leg[1:])
    # A plan does not revisit the cell it just left (A* legs through a via point can).
    out: list[tuple[int, int]] = []
    for c in plan:
        if len(out) >= 2 and c == out[-2]:
            out.pop()
        elif not out or c != out[-1]:
            out.append(c)
    if len(out) < 8:
        return None
    return kind, cell, np.array([((i + 0.5) * cell, (j + 0.5) * cell) for i, j in out])


def grid_fuzz_plans(seed: int, count: int) -> list[tuple[str, float, np.ndarray]]:
    """The first `count` plans `grid_fuzz_plan` draws from `seed` (skipping those it returns None for)."""
    rng = np.random.default_rng(seed)
    out: list[tuple[str, float, np.ndarray]] = []
    while len(out) < count:
        plan = grid_fuzz_plan(rng)
        if plan is not None:
            out.append(plan)
    return out
