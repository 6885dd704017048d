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
    """Turns of FORCED_TURN_DEG or more between the plan's runs: each step's direction, a
    staircase's steps taken along its line (gridplan.straight_runs), consecutive changes summed
    while they turn the same way."""
    g = (xy - xy[0]) / cell  # the fuzz's grids are not rotated
    d = np.diff(g, axis=0)
    heading = np.arctan2(d[:, 1], d[:, 0])
    for a, b, on in straight_runs(g):
        e = on[-1] - on[0]
        heading[a:b] = math.atan2(float(e[1]), float(e[0]))
    turn = (np.diff(heading) + math.pi) % (2.0 * math.pi) - math.pi
    count, run = 0, 0.0
    for t in turn.tolist() + [0.0]:
        if t != 0.0 and (run == 0.0 or (t > 0.0) == (run > 0.0)):
            run += t
            continue
        count += abs(run) >= math.radians(FORCED_TURN_DEG)
        run = t
    return count + (abs(run) >= math.radians(FORCED_TURN_DEG))


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
