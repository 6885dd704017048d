"""Grid plans against 1.3 x length / speed + 3 s: the profile's duration over fuzzed plans.

`python -m bench.grid_plans [--seeds 11,12,13,14] [--count 150]` builds, per seed, `count`
plans of lab/path_inputs.py `grid_fuzz_plan` (A* plans, A* plans through via points and
walks of straight staircases; 4- and 8-connected; 2-10 cm cells), loads each at 0.4 m/s on
configs/sim.yaml as `ddrt sim --path` would, and counts the profiles within the bound (no
simulation: the time is the reference's own). For the plans that miss it prints each one,
with the turns of 40 degrees or more its cells force (`forced_turns`) per metre.
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
from ddrt.path.spec import load_path, speed_limits
from lab import path_inputs as pg

FORCED_TURN_DEG = 40.0  # a turn the cells force when their runs' directions differ by this much


@dataclass(frozen=True)
class PlanResult:
    seed: int
    index: int
    kind: str
    cell_m: float
    diagonal: bool
    length_m: float
    duration_s: float
    turns_in_place: int
    forced_turns: int

    @property
    def ideal_s(self) -> float:
        return self.length_m / pg.GRID_FUZZ_SPEED

    @property
    def within(self) -> bool:
        return self.duration_s <= 1.3 * self.ideal_s + 3.0


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


def measure(seed: int, count: int) -> list[PlanResult]:
    lim = speed_limits(load_config(SIM_CONFIG))
    rng = np.random.default_rng(seed)
    out: list[PlanResult] = []
    while len(out) < count:
        plan = pg.grid_fuzz_plan(rng)
        if plan is None:
            continue
        kind, cell, xy = plan
        path = load_path({"points": xy.tolist(), "speed": pg.GRID_FUZZ_SPEED}, lim)
        diagonal = bool(np.any(np.all(np.abs(np.diff(xy, axis=0)) > 1e-9, axis=1)))
        out.append(PlanResult(seed, len(out), kind, cell, diagonal, path.length, path.duration,
                              len(path.conditioning.corners), forced_turns(xy, cell)))
    return out


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.grid_plans", description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="11,12,13,14", help="comma-separated seeds (default 11,12,13,14)")
    ap.add_argument("--count", type=int, default=150, help="plans per seed (default 150)")
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
    print(f"all: {len(held)} of {len(results)}; median {np.median(ratio):.2f} x length / speed "
          f"({time.monotonic() - t0:.0f} s)")
    for lo, hi in ((0.0, 0.03), (0.03, 0.05), (0.05, 1.0)):
        band = [r for r in results if lo <= r.cell_m < hi]
        print(f"cells {lo * 100:.0f}-{hi * 100:.0f} cm: {sum(r.within for r in band)} of {len(band)}")

    def per_metre(rs: list[PlanResult]) -> float:
        return float(np.median([r.forced_turns / r.length_m for r in rs])) if rs else float("nan")

    print(f"forced turns of {FORCED_TURN_DEG:.0f} degrees or more per metre (median): "
          f"within {per_metre(held):.2f}, missed {per_metre(missed):.2f}")
    for r in missed:
        print(f"  miss: seed {r.seed} #{r.index} {r.kind} {r.cell_m * 100:.1f} cm "
              f"{'8' if r.diagonal else '4'}-connected, {r.length_m:.2f} m, {r.duration_s:.1f} s against "
              f"{1.3 * r.ideal_s + 3.0:.1f} s, {r.turns_in_place} turned in place, {r.forced_turns} forced turns")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
