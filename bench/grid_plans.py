"""Grid plans against 1.3 x length / speed + 3 s: the profile's duration over fuzzed plans.

`python -m bench.grid_plans [--seeds 11,12,13,14] [--count 150] [--closed-loop N]` builds, per
seed, `count` plans of lab/path_inputs.py `grid_fuzz_plan` (A* plans, A* plans through via
points and walks of straight staircases; 4- and 8-connected; 2-10 cm cells), loads each at
0.4 m/s on configs/sim.yaml as `ddrt sim --path` would, and counts the profiles within the
bound (no simulation: the time is the reference's own). The length is the plan's own (the
polyline through its cells); the count against the path's length (ddrt's progress, a turn in
place counting its wheels' travel, pivot_radius x angle) is printed too. For the
plans that miss it prints each one, with the turns of 40 degrees or more its cells force
(`forced_turns`) per metre. `--closed-loop N` also drives the first N plans of each seed on
the simulated robot (seed 1) and reports the true pose's distance from the plan's cells.
Last it loads a straight staircase of about 1000 and 4000 cells: the time should grow with the
cells, not their square.
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from bench.common import SIM_CONFIG
from ddrt.config import load_config
from ddrt.path.gridplan import straight_runs
from ddrt.path.report import turn_spans
from ddrt.path.sampled import Path
from ddrt.path.spec import load_path, speed_limits
from ddrt.simrun.runner import run_sim
from lab import path_inputs as pg

FORCED_TURN_DEG = 40.0  # a turn the cells force when their runs' directions differ by this much


@dataclass(frozen=True)
class PlanResult:
    seed: int
    index: int
    kind: str
    cell_m: float
    diagonal: bool
    length_m: float  # the path's: a turn in place counts pivot_radius x its angle
    plan_length_m: float  # the polyline through the plan's cells
    duration_s: float
    turns_in_place: int
    blended_turns: int
    forced_turns: int
    yaw_accel_rms: float  # rad/s^2, the profile's d(omega)/dt over its gentle driving (turns in place and blended turns left out)

    @property
    def ideal_s(self) -> float:
        """The plan's own length over the asked speed."""
        return self.plan_length_m / pg.GRID_FUZZ_SPEED

    @property
    def within(self) -> bool:
        return self.duration_s <= 1.3 * self.ideal_s + 3.0

    @property
    def within_path_length(self) -> bool:
        """Within the bound with the path's length, a turn in place counting its wheels' travel."""
        return self.duration_s <= 1.3 * self.length_m / pg.GRID_FUZZ_SPEED + 3.0


@dataclass(frozen=True)
class ClosedLoop:
    seed: int
    index: int
    cell_m: float
    completed: bool
    time_s: float
    true_rms_m: float  # the true pose's distance from the polyline through the plan's cells
    true_max_m: float
    saturated: float  # fraction of ticks


def forced_turns(xy: np.ndarray, cell: float) -> int:
    """Turns of FORCED_TURN_DEG or more between the plan's runs: its staircases
    (gridplan.straight_runs) and its runs of one step (at least three steps, outside any
    staircase), each taken as its line, in order, and the steps between two runs as their chord
    (a jog sideways is two turns)."""
    g = (xy - xy[0]) / cell  # the fuzz's grids are not rotated
    runs = [(a, b, float(math.atan2(*(on[-1] - on[0])[::-1]))) for a, b, on in straight_runs(g)]
    covered = np.zeros(len(g) - 1, dtype=bool)
    for a, b, _ in runs:
        covered[a:b] = True
    d = np.round(np.diff(g, axis=0)).astype(int)
    k = 0
    while k < len(d):
        m = k
        while m + 1 < len(d) and np.array_equal(d[m + 1], d[k]) and not covered[m + 1]:
            m += 1
        if not covered[k] and m - k + 1 >= 3:
            runs.append((k, m + 1, math.atan2(float(d[k, 1]), float(d[k, 0]))))
        k = m + 1
    runs.sort()
    gaps = [(b, a, math.atan2(float(g[a, 1] - g[b, 1]), float(g[a, 0] - g[b, 0])))
            for (_, b, _), (a, _, _) in zip(runs[:-1], runs[1:]) if a > b]  # a jog between runs: its chord
    heading = [h for _, _, h in sorted(runs + gaps)]
    turn = [abs((b - a + math.pi) % (2.0 * math.pi) - math.pi) for a, b in zip(heading[:-1], heading[1:])]
    return sum(t >= math.radians(FORCED_TURN_DEG) for t in turn)


def gentle_yaw_accel_rms(path: Path) -> float:
    """RMS over time of the profile's d(omega)/dt on the intervals that are neither in a turn
    in place nor in a blended turn (those are taken at the profile's own yaw limits)."""
    a = path.arrays()
    sig, dt, alpha = np.asarray(a["sigma"]), np.diff(a["t"]), np.asarray(a["alpha"])
    keep = dt > 0
    for s0, s1 in turn_spans(path):
        keep &= ~((sig[1:] > s0) & (sig[:-1] < s1))
    return float(np.sqrt(np.sum(alpha[keep] ** 2 * dt[keep]) / np.sum(dt[keep]))) if keep.any() else 0.0


def measure(seed: int, count: int) -> list[PlanResult]:
    lim = speed_limits(load_config(SIM_CONFIG))
    out: list[PlanResult] = []
    for kind, cell, xy in pg.grid_fuzz_plans(seed, count):
        path = load_path({"points": xy.tolist(), "speed": pg.GRID_FUZZ_SPEED}, lim)
        diagonal = bool(np.any(np.all(np.abs(np.diff(xy, axis=0)) > 1e-9, axis=1)))
        plan_length = float(np.sum(np.hypot(*np.diff(xy, axis=0).T)))
        c = path.conditioning
        out.append(PlanResult(seed, len(out), kind, cell, diagonal, path.length, plan_length, path.duration,
                              len(c.corners), len(c.blended), forced_turns(xy, cell), gentle_yaw_accel_rms(path)))
    return out


def closed_loop(seed: int, count: int) -> list[ClosedLoop]:
    """The first `count` plans of `seed` driven on the simulated robot (sim seed 1)."""
    cfg = load_config(SIM_CONFIG)
    lim = speed_limits(cfg)
    out: list[ClosedLoop] = []
    for i, (_, cell, xy) in enumerate(pg.grid_fuzz_plans(seed, count)):
        path = load_path({"points": xy.tolist(), "speed": pg.GRID_FUZZ_SPEED}, lim)
        res = run_sim(cfg, path, seed=1)
        d = pg.curve_distance(xy, np.column_stack((res.column("x"), res.column("y"))))
        m = res.metrics
        out.append(ClosedLoop(seed, i, cell, bool(m["completed"]), float(m["sim_duration_s"]),
                              float(np.sqrt(np.mean(d ** 2))), float(d.max()), float(m["saturated_fraction"])))
    return out


def staircase_load_s(cells: int, repeats: int = 3) -> tuple[int, float]:
    """(cells, median seconds) to load one straight staircase of about `cells` 1 cm cells (slope
    3/7, one run): how a plan's load time grows with its length (gridplan.straight_runs)."""
    lim = speed_limits(load_config(SIM_CONFIG))
    n = round(cells * 0.7)
    xy = (np.array(pg.staircase((0, 0), (n, round(n * 3 / 7)), diagonal=False), dtype=float) + 0.5) * 0.01
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        load_path({"points": xy.tolist(), "speed": pg.GRID_FUZZ_SPEED}, lim)
        times.append(time.perf_counter() - t0)
    return len(xy), float(np.median(times))


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.grid_plans", description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="11,12,13,14", help="comma-separated seeds (default 11,12,13,14)")
    ap.add_argument("--count", type=int, default=150, help="plans per seed (default 150)")
    ap.add_argument("--closed-loop", type=int, default=0, metavar="N",
                    help="also drive the first N plans of each seed on the simulated robot")
    args = ap.parse_args(argv)
    t0 = time.monotonic()
    results: list[PlanResult] = []
    for seed in (int(s) for s in args.seeds.split(",")):
        rs = measure(seed, args.count)
        results += rs
        print(f"seed {seed}: {sum(r.within for r in rs)} of {len(rs)} within 1.3 x length / speed + 3 s")
    ratio = [r.duration_s / r.ideal_s for r in results]
    held = [r for r in results if r.within]
    missed = [r for r in results if not r.within]
    print(f"all: {len(held)} of {len(results)}; median {np.median(ratio):.2f} x length / speed, "
          f"{sum(r.duration_s for r in results):.0f} s in all ({time.monotonic() - t0:.0f} s)")
    print(f"against the path's length (a turn in place counting its wheels' travel): "
          f"{sum(r.within_path_length for r in results)} of {len(results)}")
    gentle = np.array([r.yaw_accel_rms for r in results])
    print(f"turns in place {sum(r.turns_in_place for r in results)}, blended {sum(r.blended_turns for r in results)}; "
          f"gentle driving's RMS d(omega)/dt median {np.median(gentle):.2f}, 90th percentile "
          f"{np.percentile(gentle, 90):.2f}, largest {gentle.max():.2f} rad/s^2")
    for lo, hi in ((0.0, 0.03), (0.03, 0.05), (0.05, 1.0)):
        band = [r for r in results if lo <= r.cell_m < hi]
        print(f"cells {lo * 100:.0f}-{hi * 100:.0f} cm: {sum(r.within for r in band)} of {len(band)}")

    def per_metre(rs: list[PlanResult]) -> float:
        return float(np.median([r.forced_turns / r.length_m for r in rs])) if rs else float("nan")

    print(f"forced turns of {FORCED_TURN_DEG:.0f} degrees or more per metre (median): "
          f"within {per_metre(held):.2f}, missed {per_metre(missed):.2f}")
    for r in missed:
        print(f"  miss: seed {r.seed} #{r.index} {r.kind} {r.cell_m * 100:.1f} cm "
              f"{'8' if r.diagonal else '4'}-connected, {r.plan_length_m:.2f} m, {r.duration_s:.1f} s against "
              f"{1.3 * r.ideal_s + 3.0:.1f} s, {r.turns_in_place} turned in place, {r.blended_turns} blended, "
              f"{r.forced_turns} forced turns")
    (n1, t1), (n4, t4) = staircase_load_s(1000), staircase_load_s(4000)
    print(f"a straight staircase loads in {t1:.2f} s at {n1} cells, {t4:.2f} s at {n4} ({t4 / t1:.1f}x for "
          f"{n4 / n1:.1f}x the cells; median of 3)")
    if args.closed_loop > 0:
        runs = [c for seed in (int(s) for s in args.seeds.split(",")) for c in closed_loop(seed, args.closed_loop)]
        rms = np.array([c.true_rms_m for c in runs]) * 1000.0
        mx = np.array([c.true_max_m for c in runs]) * 1000.0
        rel = np.array([c.true_max_m / c.cell_m for c in runs])
        print(f"closed loop, {len(runs)} plans: {sum(c.completed for c in runs)} completed; true pose from the "
              f"plan's cells RMS median {np.median(rms):.2f} mm (largest {rms.max():.2f}), max median "
              f"{np.median(mx):.2f} mm (largest {mx.max():.2f}, {rel.max():.2f} cells); saturated at most "
              f"{max(c.saturated for c in runs) * 100:.2f} % of ticks")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
