"""Grid plans as planners hand them over (lab/path_inputs.py, grid_fuzz_plan): A*
plans, A* plans through via points and staircase walks, 4- and 8-connected, 2-10 cm cells.
Their corners of 90 degrees and more turn in place at the cell's centre; what is smoothed stays
within the planned cells and bends no tighter than a cell's radius (ddrt/path/gridplan.py)."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from ddrt.config import load_config
from ddrt.path import load_path
from ddrt.path.gridplan import straight_runs, straightened
from ddrt.path.report import pivot_runs
from ddrt.path.sampled import Path, distances_to_polyline
from ddrt.path import gridplan, turnspeed
from ddrt.path.spec import speed_limits
from lab import path_inputs as pg
from tests.support.repo import SIM_YAML

LIM = speed_limits(load_config(SIM_YAML))
STEPS = {"E": (1, 0), "N": (0, 1), "W": (-1, 0), "S": (0, -1), "NE": (1, 1), "NW": (-1, 1)}


def _cells(moves: list[str], cell: float = 0.05) -> np.ndarray:
    c = [(0, 0)]
    for m in moves:
        d = STEPS[m]
        c.append((c[-1][0] + d[0], c[-1][1] + d[1]))
    return (np.array(c, dtype=float) + 0.5) * cell


def _within_bound(path: Path, xy: np.ndarray, speed: float) -> bool:
    """The bound on the profile's duration, 1.3 x length / speed + 3 s, with the plan's own
    length (the polyline through its cells: no time allowed for turning in place)."""
    return path.duration <= 1.3 * float(np.sum(np.hypot(*np.diff(xy, axis=0).T))) / speed + 3.0


@pytest.mark.parametrize("moves, turn, k, centre, cell", [
    (["E"] * 20 + ["NW"] * 20, 135.0, 20, True, 0.05),
    (["E", "E", "NE"] * 8 + ["W", "NW"] * 10, 135.0, 24, False, 0.05),  # staircases either side
    (["E"] * 20 + ["N"] * 20, 90.0, 20, True, 0.03),  # a corridor under GRID_BLEND_CORRIDOR_M
])
def test_a_grid_corner_turns_in_place_at_its_cell(moves, turn, k, centre, cell) -> None:
    """A 135 degree corner was bent to a 9 mm radius and crawled (2.3x length / speed). Between
    straight runs it turns at the corner cell's centre; between staircases, where their lines
    meet within that cell (each staircase is driven as its line, gridplan.straightened)."""
    xy = _cells(moves, cell)
    path = load_path({"points": xy.tolist(), "speed": 0.4}, LIM)
    corners = path.conditioning.corners
    assert len(corners) == 1 and len(pivot_runs(path)) == 1
    assert abs(math.degrees(corners[0].turn)) == pytest.approx(turn, abs=20.0)
    off = (abs(corners[0].x - xy[k, 0]), abs(corners[0].y - xy[k, 1]))
    assert max(off) < (1e-9 if centre else 0.5 * cell)  # at the cell's centre, or within the cell
    assert np.abs(path.arrays()["kappa"]).max() < 1.0 / cell
    assert _within_bound(path, xy, 0.4)  # a 135 degree corner bent to 9 mm: 2.3 x length / speed


@pytest.mark.parametrize("cell", [0.04, 0.05, 0.08])
def test_a_square_corner_in_cells_of_4_cm_or_more_is_blended_within_its_cell(cell, monkeypatch) -> None:
    """Within half a cell a blended 90 degree corner's radius can reach 1.7 cells: from 4 cm
    cells on that is faster than stopping to turn in place (configs/sim.yaml)."""
    xy = _cells(["E"] * 20 + ["N"] * 20, cell)
    path = load_path({"points": xy.tolist(), "speed": 0.4}, LIM)
    c = path.conditioning
    assert not c.corners and not pivot_runs(path) and len(c.blended) == 1
    assert c.deviation_m <= 0.5 * cell + 1e-9
    _, peak = _yaw_accel(path, c.blended[0])
    assert peak <= LIM.alpha_max
    monkeypatch.setattr(gridplan, "GRID_BLEND_CORRIDOR_M", 1.0)  # every corner turns in place
    pivoted = load_path({"points": xy.tolist(), "speed": 0.4}, LIM)
    assert len(pivoted.conditioning.corners) == 1
    assert path.duration < pivoted.duration


@pytest.mark.parametrize("moves, runs", [
    (["E", "N", "N"] * 10, [(1, 30)]),  # a line's staircase: one run (the plan's start stays in its cell)
    (["E", "N"] * 6 + ["E", "E", "E", "N"] * 5, [(0, 14), (14, 31)]),  # two slopes sharing a cell; the last
    # step, a rarer one, is left to the end cell
    (["S"] * 17 + ["SE"] * 8, []),  # two runs of one step each and a 45 degree turn: left as they are
    (["S"] * 10 + ["SE", "SE"] + ["S"] * 10, []),  # a jog is no staircase
])
def test_straight_runs_are_a_lines_staircases(moves, runs) -> None:
    steps = {**STEPS, "SE": (1, -1)}
    g = np.cumsum([(0, 0)] + [steps[m] for m in moves], axis=0).astype(float)
    found = straight_runs(g)
    assert [(a, b) for a, b, _ in found] == runs
    q = (straightened(0.03 * (g + 0.5), 0.03, 0.0) / 0.03) - 0.5
    assert np.abs(q - g).max() <= 0.49 + 1e-9  # every cell's point stays in its cell
    for a, b, on in found:  # on one line
        d = on - on[0]
        assert np.abs(d[:, 0] * d[-1, 1] - d[:, 1] * d[-1, 0]).max() < 1e-6 * float(d[-1] @ d[-1])


def _is_line_staircase(steps: list[tuple[int, int]]) -> bool:
    """The definition, read whole: one kind of step, or two where one of them (the rarer) never
    comes twice in a row and the runs of the other between its occurrences differ by at most
    one, the first and last run no longer than the shortest inner one plus one."""
    kinds = set(steps)
    if len(kinds) != 2:
        return len(kinds) == 1
    for rare in kinds:
        if any(a == b == rare for a, b in zip(steps[:-1], steps[1:])):
            continue
        runs = [len(list(grp)) if key else 0 for key, grp in itertools.groupby(steps, key=lambda s: s != rare)]
        # between rare steps (each a run of one): the lengths of the other's runs, with 0 where two rare steps
        # would touch (they do not) and at either end when the run starts or ends with a rare step
        others = [n for n in runs if n]
        firsts = (steps[0] != rare, steps[-1] != rare)
        inner = others[int(firsts[0]):len(others) - int(firsts[1])]
        ends = [others[0] if firsts[0] else 0, others[-1] if firsts[1] else 0]
        if not inner or (max(inner) - min(inner) <= 1 and max(ends) <= min(inner) + 1):
            return True
    return False


def test_a_runs_staircase_is_read_as_it_grows() -> None:
    """straight_runs reads whether a growing run is a staircase a step at a time; at every
    length it agrees with the definition read over the whole run."""
    rng = np.random.default_rng(4)
    kinds = [(1, 0), (0, 1), (1, 1)]
    checked = 0
    for _ in range(400):
        period = int(rng.integers(1, 6))
        use = kinds[:int(rng.choice([2, 2, 2, 3]))]
        steps = []
        while len(steps) < 40:  # mostly staircases, with the odd slip
            steps += [use[0]] * (period + int(rng.random() < 0.2)) + [use[1]]
            if rng.random() < 0.1:
                steps.append(use[int(rng.integers(len(use)))])
        start = int(rng.integers(0, period + 1))
        steps = steps[start:]
        window = gridplan._StairWindow()
        for n in range(1, len(steps) + 1):
            assert window.add(steps[n - 1]) == _is_line_staircase(steps[:n]), steps[:n]
            checked += 1
    assert checked > 10_000


@pytest.mark.parametrize("kinds,length", [([(1, 0), (1, 1)], 13), ([(1, 0), (0, 1), (1, 1)], 8)])
def test_every_short_run_is_read_as_a_staircase_as_the_definition_reads_it(kinds, length) -> None:
    """Every sequence of `length` steps of these kinds, read a step at a time, agrees with the
    definition at every length: the first and last runs too (a straight leg then a staircase is
    no staircase: `[E] * 4 + [NE, E, NE]`), which random staircases seldom try."""
    assert not _is_line_staircase([(1, 0)] * 4 + [(1, 1), (1, 0), (1, 1)])
    for steps in itertools.product(kinds, repeat=length):
        window = gridplan._StairWindow()
        for n in range(1, length + 1):
            assert window.add(steps[n - 1]) == _is_line_staircase(list(steps[:n])), steps[:n]


def test_a_runs_line_is_fitted_over_its_hull() -> None:
    """A run's line is fitted to its extremes only: over its hull's corners it is the line fitted
    over every cell (random staircases and random clouds)."""
    rng = np.random.default_rng(9)
    for _ in range(200):
        if rng.random() < 0.5:
            steps = rng.choice([0, 1], size=(int(rng.integers(3, 80)), 1))
            g = np.cumsum(np.vstack([[0, 0], np.hstack([1 - steps, steps])]), axis=0).astype(float)
        else:
            g = rng.normal(size=(int(rng.integers(3, 60)), 2)) * [5.0, 1.0]
        hull = gridplan._hull(g.tolist(), list(range(len(g))))
        assert len(hull) <= len(g)
        dev, n, off = gridplan._line_fit(g)
        dev_h, n_h, off_h = gridplan._line_fit(g[hull], g[-1] - g[0])
        assert dev_h == pytest.approx(dev, abs=1e-12) and off_h == pytest.approx(off, abs=1e-9)
        assert np.allclose(n_h, n, atol=1e-12)


def test_a_long_staircase_is_read_in_linear_work(monkeypatch) -> None:
    """A straight staircase of 3000 cells is one run, found by refitting its line over a few
    hull corners a cell at a time and putting its cells onto the line once: the cells every fit
    and every move onto a line read add up to a few per cell (reading the whole run at each
    cell, n^2 / 2: a 2000-cell plan took 8 s to load)."""
    g = np.array(pg.staircase((0, 0), (2100, 900), diagonal=False), dtype=float)
    read = []
    fit, onto = gridplan._line_fit, gridplan._onto
    monkeypatch.setattr(gridplan, "_line_fit", lambda pts, chord=None: (read.append(len(pts)), fit(pts, chord))[1])
    monkeypatch.setattr(gridplan, "_onto", lambda pts, n, off: (read.append(len(pts)), onto(pts, n, off))[1])
    runs = straight_runs(g)
    assert [(a, b) for a, b, _ in runs] == [(0, len(g) - 1)] or [(a, b) for a, b, _ in runs] == [(1, len(g) - 1)]
    assert sum(read) < 20 * len(g)


@pytest.mark.parametrize("moves", [["E", "N"] * 20, ["E", "NE"] * 20, ["E", "E", "NE"] * 12])
def test_a_staircase_is_smoothed_not_turned(moves) -> None:
    path = load_path({"points": _cells(moves).tolist(), "speed": 0.4}, LIM)
    assert not pivot_runs(path)
    assert path.duration < 1.15 * path.length / 0.4


def _yaw_accel(path: Path, span: tuple[float, float]) -> tuple[float, float]:
    """(RMS over time, largest) of the profile's d(omega)/dt over the intervals within `span`."""
    a = path.arrays()
    sig, dt, al = np.asarray(a["sigma"]), np.diff(a["t"]), np.asarray(a["alpha"])
    sel = (sig[:-1] >= span[0]) & (sig[1:] <= span[1]) & (dt > 0)
    return float(np.sqrt(np.sum(al[sel] ** 2 * dt[sel]) / np.sum(dt[sel]))), float(np.abs(al[sel]).max())


def test_a_paths_own_tolerance_of_2_cm_blends_a_square_corner_in_3_cm_cells() -> None:
    """The corridor, not the cell, sets the radius a blended corner can have: 3 cm cells turn
    a 90 degree corner in place within their half cell, and blend it within the path's own
    `tolerance:` of 3 cm, staying within that."""
    xy = _cells(["E"] * 20 + ["N"] * 20, 0.03)
    own = load_path({"points": xy.tolist(), "speed": 0.4}, LIM)
    wide = load_path({"points": xy.tolist(), "speed": 0.4, "tolerance": 0.03}, LIM)
    assert len(own.conditioning.corners) == 1 and not own.conditioning.blended
    assert not wide.conditioning.corners and len(wide.conditioning.blended) == 1
    assert wide.conditioning.deviation_m <= 0.03 + 1e-9
    assert wide.duration < own.duration


def test_a_45_degree_grid_turn_is_blended_at_the_profiles_own_limits(monkeypatch) -> None:
    """Taken at the gentle turn speed (RMS d(omega)/dt 1.4 rad/s^2) a 45 degree step lasts at
    least 1.5 s; blended, it is left to the profile's limits: faster, rougher than gentle, and
    within half a turn in place's yaw acceleration (its peak within a turn in place's)."""
    xy = _cells(["E"] * 20 + ["NE"] * 20)
    path = load_path({"points": xy.tolist(), "speed": 0.4}, LIM)
    c = path.conditioning
    assert not c.corners and len(c.blended) == 1
    rms, peak = _yaw_accel(path, c.blended[0])
    assert turnspeed.GRID_YAW_ACCEL < rms <= 0.5 * LIM.alpha_max and peak <= LIM.alpha_max
    assert c.deviation_m <= 0.5 * 0.05 + 1e-9
    monkeypatch.setattr(turnspeed, "BLENDED_TURN_DEG", 1e9)
    gentle = load_path({"points": xy.tolist(), "speed": 0.4}, LIM)
    assert not gentle.conditioning.blended
    assert path.duration < gentle.duration - 0.3  # 6.4 s against 7.0 s


def test_a_shallow_grid_turn_stays_gentle() -> None:
    """An 18 degree turn (20 cells east, then a 3:1 staircase) is below BLENDED_TURN_DEG: taken
    at the gentle turn speed, no span blended."""
    xy = _cells(["E"] * 20 + ["E", "E", "NE"] * 8)
    path = load_path({"points": xy.tolist(), "speed": 0.4}, LIM)
    assert not path.conditioning.blended and not path.conditioning.corners
    rms, _ = _yaw_accel(path, (0.0, path.length))
    assert 0.0 < rms <= turnspeed.GRID_YAW_ACCEL


def _fuzz(seed: int, count: int) -> list[tuple[str, float, np.ndarray, Path]]:
    return [(kind, cell, xy, load_path({"points": xy.tolist(), "speed": pg.GRID_FUZZ_SPEED}, LIM))
            for kind, cell, xy in pg.grid_fuzz_plans(seed, count)]


def _check_shape(plans: list[tuple[str, float, np.ndarray, Path]]) -> None:
    kinds = {k for k, *_ in plans}
    assert kinds == {"astar", "via", "walk"}
    for kind, cell, xy, path in plans:
        c = path.conditioning
        assert c.mode == "grid" and c.grid_cell_m == pytest.approx(cell)
        assert c.deviation_m <= 0.5 * cell + 1e-9, (kind, cell)  # every planned cell is crossed
        a = path.arrays()
        kap = np.abs(a["kappa"][:-1][~a["seg_pivot"]])
        assert kap.max() <= 1.0 / cell, (kind, cell, len(xy))  # no bend tighter than a cell's radius


def test_fuzzed_grid_plans_stay_in_their_cells_and_bend_no_tighter_than_a_cell() -> None:
    _check_shape(_fuzz(20263, 40))


@pytest.mark.slow
def test_many_fuzzed_grid_plans_stay_in_their_cells_and_bend_no_tighter_than_a_cell() -> None:
    _check_shape(_fuzz(20264, 400))


def _slow(plans: list[tuple[str, float, np.ndarray, Path]]) -> list[tuple[str, float, float]]:
    return [(kind, round(cell, 3), round(p.duration * pg.GRID_FUZZ_SPEED / float(np.sum(np.hypot(*np.diff(xy, axis=0).T))), 2))
            for kind, cell, xy, p in plans if not _within_bound(p, xy, pg.GRID_FUZZ_SPEED)]


def test_fuzzed_grid_plans_mostly_hold_1_3_x_length_over_speed_plus_3_s() -> None:
    """36 of these 40 within the bound (31 with every smoothed turn gentle and every 90 degree
    corner turned in place); the 4 that miss have cells under 5 cm but one (5.4 cm, 8 corners
    in 5 m)."""
    slow = _slow(_fuzz(20263, 40))
    assert len(slow) <= 4, slow


@pytest.mark.slow
def test_the_benchs_600_fuzzed_grid_plans_mostly_hold_the_bound() -> None:
    """python -m bench.grid_plans's plans (seeds 11-14, 150 each): 563 of 600 within the bound
    (517 with every smoothed turn gentle and every 90 degree corner turned in place)."""
    slow = [(seed, kind, cell, ratio) for seed in (11, 12, 13, 14) for kind, cell, ratio in _slow(_fuzz(seed, 150))]
    assert len(slow) <= 37, slow


def test_a_staircase_between_turns_is_driven_as_its_line() -> None:
    """A walk of three straight staircases (4-connected, 2 cm cells). Fitted cell by cell it
    wiggled within the cells (43 % of it curved more than 0.25 /m), a staircase's rarer step
    read as a third corner, and it took 10.5 s against the bound's 10.0 s; driven as its lines
    it turns in place at its two corners only and holds the bound."""
    moves = ["E", "N", "N"] * 12 + ["E", "E", "E", "S"] * 8 + ["N", "E", "N", "N"] * 8
    xy = _cells(moves, cell=0.02)
    path = load_path({"points": xy.tolist(), "speed": 0.4}, LIM)
    a = path.arrays()
    drive = ~a["seg_pivot"]
    assert np.mean(np.abs(a["kappa"][:-1][drive]) < 0.25) > 0.8  # straight but near its corners
    assert len(path.conditioning.corners) == 2 and len(pivot_runs(path)) == 2
    assert path.conditioning.deviation_m <= 0.5 * 0.02 + 1e-9
    assert _within_bound(path, xy, 0.4), path.duration


@pytest.mark.xfail(strict=True, reason="plans of many tight corners in small cells: 4 of these 40 and 37 of the "
                   "bench's 600 exceed the bound (python -m bench.grid_plans), 35 of the 37 with cells under 5 cm "
                   "and 26 4-connected. A 90 degree corner costs about 1 s on configs/sim.yaml: in place, a stop "
                   "from 0.4 m/s at 1 m/s^2 (0.4 s) and 90 degrees at 4 rad/s and 20 rad/s^2 (0.6 s); blended "
                   "within half a cell under 4 cm, no faster; against the bound's 0.3 x length / speed + 3 s "
                   "(docs/BENCHMARKS.md, grid plans)")
def test_fuzzed_grid_plans_take_at_most_1_3_x_length_over_speed_plus_3_s() -> None:
    slow = _slow(_fuzz(20263, 40))
    assert not slow, slow


def test_a_plan_given_to_the_micrometre_is_read_on_its_own_grid() -> None:
    """Rounding a plan's metres to the micrometre leaves its axis steps' lengths apart by more
    than 1e-5 of a cell: its first axis is still read along its first step (not 45 degrees off,
    reading its staircases on a grid turned by 45 degrees) and it is driven as the exact plan."""
    for kind, cell, p in pg.grid_fuzz_plans(31, 12):
        q = np.round(p, 6)
        turn = gridplan.grid_axis(q) - gridplan.grid_axis(p)
        assert abs((turn + 0.25 * math.pi) % (0.5 * math.pi) - 0.25 * math.pi) < 1e-3, (kind, cell)
        exact = load_path({"points": p.tolist(), "speed": 0.4}, LIM)
        given = load_path({"points": q.tolist(), "speed": 0.4}, LIM)
        assert given.duration == pytest.approx(exact.duration, rel=0.01), (kind, cell)


@pytest.mark.parametrize("decimals", [6, 3])
def test_a_plan_on_a_rotated_grid_written_to_a_few_decimals_is_read_as_its_cells(decimals) -> None:
    """A planner's cells on a grid at any angle, written to the micrometre or the millimetre:
    every plan is read as a grid plan, its cells recovered to within the rounding (the grid
    fitted to every point, gridplan.read_grid), and driven as the exact plan on its own axes
    is (a 4 cm cell at 30 degrees to the millimetre is off by up to 2.5 % of a cell a step)."""
    rng = np.random.default_rng(decimals)
    close = 0
    plans = pg.grid_fuzz_plans(33, 20)
    for kind, cell, p in plans:
        th = float(rng.uniform(0.0, 2.0 * math.pi))
        rot = np.array([[math.cos(th), math.sin(th)], [-math.sin(th), math.cos(th)]])
        exact = p @ rot + rng.uniform(-2.0, 2.0, 2)
        given = np.round(exact, decimals)
        grid = gridplan.read_grid(given)
        assert grid is not None, (kind, cell)
        assert grid.cell == pytest.approx(cell, rel=10.0 ** -decimals / cell)
        assert np.abs(grid.points() - exact).max() < 10.0 ** -decimals
        ratio = (load_path({"points": given.tolist(), "speed": 0.4}, LIM).duration
                 / load_path({"points": p.tolist(), "speed": 0.4}, LIM).duration)
        close += abs(ratio - 1.0) <= 0.02
    assert close >= 18  # the rest: one smoothing's choice among near-equal fits (BENCHMARKS, grid plans)


def test_near_grid_points_that_do_not_add_up_to_one_grid_are_not_a_grid_plan() -> None:
    """Steps each within the rounding allowance (written to the millimetre, 5 cm cells) that
    bend, drifting 1 mm a cell one way then the other, are samples of a curve, not a grid
    plan: no one grid (at any angle) puts their cells within a quarter cell of them."""
    p = _cells(["E"] * 120, 0.05)
    p[:, 1] += 0.001 * np.minimum(np.arange(len(p)), len(p) - 1 - np.arange(len(p)))
    assert gridplan.read_grid(np.round(p, 3)) is None
    straight = _cells(["E"] * 120, 0.05)
    straight[:, 1] += 0.001 * np.arange(len(p))  # one way only: a grid turned by 1.1 degrees
    assert gridplan.read_grid(np.round(straight, 3)) is not None


def _turned(p: np.ndarray, th: float) -> np.ndarray:
    return p @ np.array([[math.cos(th), math.sin(th)], [-math.sin(th), math.cos(th)]])


def test_points_a_grid_would_move_by_more_than_their_rounding_are_not_a_grid_plan() -> None:
    """Gentle arcs densified at 2-3 cm and straight recordings at 2 cm (20 Hz at 0.4 m/s, noise
    and a 4 mm sway), written to the millimetre, have every step one cell to within the
    rounding, but no grid puts each point within a quantum of its cell (an arc of 8 m radius
    over 0.8 m was read as a straight grid run, its points moved 5.7 mm, its deviation
    reported as 0): they are samples, or a grid within a millimetre of every point."""
    rng = np.random.default_rng(5)
    cases = []
    for radius, length, spacing in itertools.product((3.0, 5.0, 8.0, 20.0), (0.4, 0.8), (0.02, 0.03)):
        t = np.arange(0.0, length + 1e-9, spacing) / radius
        cases.append(_turned(np.c_[radius * np.sin(t), radius * (1.0 - np.cos(t))], 0.3) + [1.2345, 0.5])
    for _ in range(12):
        x = np.cumsum(0.02 + rng.normal(0.0, 0.0004, 40))
        y = 0.004 * np.sin(3.0 * x) + rng.normal(0.0, 0.0004, 40)
        cases.append(_turned(np.c_[x, y], rng.uniform(0.0, 2.0 * math.pi)) + 0.5)
    read = 0
    for p in (np.round(c, 3) for c in cases):
        grid = gridplan.read_grid(p)
        if grid is not None:
            read += 1
            assert np.abs(grid.points() - p).max() <= 0.001 + 1e-12
    assert read < len(cases) // 2
    arc = np.round(cases[11], 3)  # 8 m radius, 0.8 m, every 3 cm
    path = load_path({"points": arc.tolist(), "speed": 0.4}, LIM)
    a = path.arrays()
    far = distances_to_polyline(np.c_[a["x"], a["y"]], arc).max()
    assert path.conditioning.mode == "samples" and far <= path.deviation_m + 1e-6


def test_a_plan_of_2_cm_cells_written_to_the_millimetre_is_read_at_any_angle() -> None:
    """Its shortest step may be 1.4 mm short of the cell and its median step under 2 cm: the
    millimetre is still within GRID_ROUNDING_CELLS (5 %) of the cell it can be, so the plan is
    read as a grid plan at every angle (its points within a millimetre of their cells)."""
    moves = [["E", "NE", "NE", "N", "NE", "NE", "E"], ["NE", "NE", "E", "NE", "NE"], ["E", "E", "N", "N", "W", "W"]]
    for m, deg in itertools.product(moves, range(0, 360, 2)):
        p = np.round(_turned(_cells(m, 0.02), math.radians(deg)) + [0.3, -0.7], 3)
        grid = gridplan.read_grid(p)
        assert grid is not None, (m, deg)
        assert np.abs(grid.points() - p).max() <= 0.001 + 1e-12


def test_a_coarse_grid_plan_read_as_waypoints_says_so_and_how_to_smooth_it() -> None:
    """Cells of paths.waypoint_spacing_m (25 cm) or more are waypoints, each staircase step a
    turn in place: the reading says so, that a path's own tolerance is unused, and which key
    smooths them; a polygon drawn on a grid (no staircase) gets no such note."""
    xy = (np.array(pg.staircase((0, 0), (12, 5), diagonal=False), dtype=float) + 0.5) * 0.3
    path = load_path({"points": xy.tolist(), "speed": 0.4, "tolerance": 0.05}, LIM)
    c = path.conditioning
    assert c.mode == "waypoints" and len(c.corners) >= 8
    note = " ".join(path.notes)
    assert "paths.waypoint_spacing_m" in note and "staircase" in note and "tolerance (50 mm) is not used" in note
    assert c.note in c.summary() and c.note in note
    square = [[0, 0], [1, 0], [2, 0], [2, 1], [2, 2], [1, 2], [0, 2], [0, 1], [0, 0]]
    drawn = load_path({"points": square, "speed": 0.4}, LIM)
    assert drawn.conditioning.mode == "waypoints" and not drawn.notes


def test_every_turn_in_place_is_a_corner_the_reading_counts() -> None:
    """The reading's corners are the path's turns in place, those a short leg makes as
    waypoints included (`ddrt path` said 4 corners and 5 turns in place for seed 20263's plan 11)."""
    for kind, cell, xy, path in _fuzz(20263, 30):
        assert len(path.conditioning.corners) == len(pivot_runs(path)), (kind, cell)


@pytest.mark.parametrize("degrees", [0.0, 17.0, 30.0, 90.0, 133.7])
def test_a_step_back_is_one_turn_in_place_on_a_grid_at_any_angle(degrees) -> None:
    """A plan that steps back the way it came turns in place at that cell only: a corner read
    a cell early over windows straddling the step back would leave a one-step leg and a turn
    in place of a few degrees beside it, there or not as the coordinates' last bits fall."""
    moves = ["E"] * 10 + ["W"] * 5 + ["N"] * 10 + ["NE"] * 6 + ["SW"] * 3 + ["N"] * 5
    steps = {**STEPS, "SW": (-1, -1)}
    g = np.cumsum([(0, 0)] + [steps[m] for m in moves], axis=0).astype(float)
    th = math.radians(degrees)
    xy = (g + 0.5) * 0.05 @ np.array([[math.cos(th), math.sin(th)], [-math.sin(th), math.cos(th)]]) + [1.234, 0.5]
    path = load_path({"points": xy.tolist(), "speed": 0.4}, LIM)
    turns = sorted(round(abs(math.degrees(c.turn))) for c in path.conditioning.corners)
    assert turns == [135, 180, 180]
