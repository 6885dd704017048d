"""Sweep throughput: a campaign of N short runs on a Dask LocalCluster of W worker processes,
against the same runs one after another in this process.

`python -m bench.sweep_throughput [--runs 1000] [--workers 2] [--duration 5]` prints a
markdown table. The campaign is the slow figure-eight (configs/sim.yaml) with ten outer
gains K_y (100-1600, log-spaced) times as many noise seeds as it takes; each run is
`--duration` simulated seconds after the 1 s calibration at rest (no start delay), so the
runs are short and Dask's cost per task shows. Both sides run the same cases through the
same `run_case`; the two tables are compared (wall-time columns aside) and must be equal.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path as FsPath
from typing import Sequence

from ddrt.sweep.campaign import campaign_from_mapping
from ddrt.sweep.cases import Plan, expand
from ddrt.sweep.execute import DaskCluster, InProcess
from ddrt.sweep.table import arrow_table, without_wall_time

REPO = FsPath(__file__).resolve().parents[1]
GAINS = 10


@dataclass(frozen=True)
class Side:
    """One way of running the campaign."""

    label: str
    workers: int
    wall_s: float  # everything, cluster start-up and shut-down included
    runs_s: float  # first submission to last row
    cpu_s: float  # the runs' own wall times summed (what one core would need without overhead)

    @property
    def busy(self) -> float:
        """The fraction of the workers' time between first submission and last row spent in runs."""
        return self.cpu_s / (self.workers * self.runs_s)

    def per_s(self, runs: int) -> float:
        return runs / self.wall_s


@dataclass(frozen=True)
class Throughput:
    runs: int
    duration_s: float
    expand_s: float  # checking every case before anything runs
    sequential: Side
    dask: Side
    identical: bool
    cores: int
    load: tuple[float, float, float]

    def lines(self) -> list[str]:
        sim = self.runs * (1.0 + self.duration_s)
        rows = ["| how | workers | wall (s) | of it the runs (s) | runs/s | simulated s per wall s |",
                "|---|---|---|---|---|---|"]
        for side in (self.sequential, self.dask):
            rows.append(f"| {side.label} | {side.workers} | {side.wall_s:.1f} | {side.runs_s:.1f} | "
                        f"{side.per_s(self.runs):.2f} | {sim / side.wall_s:.0f} |")
        speedup = self.sequential.wall_s / self.dask.wall_s
        return [
            f"{self.runs} runs of {self.duration_s:g} s (after 1 s of calibration at rest) on the slow figure-eight, "
            f"{GAINS} gains x {math.ceil(self.runs / GAINS)} seeds; {self.cores} cores, load average "
            f"{' '.join(f'{x:.2f}' for x in self.load)} at the start. Checking every case first took "
            f"{self.expand_s:.1f} s.", "", *rows, "",
            f"Dask on {self.dask.workers} workers: {speedup:.2f}x the sequential loop's throughput "
            f"(runs alone: {self.sequential.runs_s / self.dask.runs_s:.2f}x); the summed run times were "
            f"{self.sequential.cpu_s:.1f} s in this process and {self.dask.cpu_s:.1f} s on the workers, which "
            f"were busy with runs {self.dask.busy:.0%} of the time (the rest is Dask's own cost per task); "
            f"a run took {self.dask.cpu_s / self.sequential.cpu_s:.2f}x as long on a worker as in the loop "
            f"(above 1: the workers compete for the cores, with each other and the machine's other load). "
            f"Tables equal (wall time aside): {'yes' if self.identical else '**NO**'}.",
        ]


def plan(runs: int, duration_s: float) -> Plan:
    camp = campaign_from_mapping({
        "name": "sweep throughput",
        "base": str(REPO / "configs" / "sim.yaml"),
        "overrides": {"sim": {"start_delay_s": 0.0}, "daemon": {"socket": None}},
        "axes": {"controller.outer.k_y": {"start": 100, "stop": 1600, "num": GAINS, "scale": "log"}},
        "seeds": math.ceil(runs / GAINS),
        "run": {"duration_s": duration_s},
    }, source="bench/sweep_throughput.py")
    full = expand(camp)
    return Plan(full.campaign, full.cases[:runs], full.paths, full.columns, full.fingerprint)


def _side(label: str, executor: InProcess | DaskCluster, p: Plan) -> tuple[Side, list[dict]]:
    t0 = time.perf_counter()
    with executor as ex:
        t1 = time.perf_counter()
        rows = list(ex.run(p.cases, p.paths, p.campaign.run))
        t2 = time.perf_counter()
        workers = ex.workers
    wall = time.perf_counter() - t0
    return Side(label, workers, wall, t2 - t1, sum(r["wall_s"] for r in rows)), rows


def measure(runs: int = 1000, workers: int = 2, duration_s: float = 5.0) -> Throughput:
    load = os.getloadavg()
    t0 = time.perf_counter()
    p = plan(runs, duration_s)
    expand_s = time.perf_counter() - t0
    seq, seq_rows = _side("sequential loop (this process)", InProcess(), p)
    dsk, dsk_rows = _side("Dask LocalCluster", DaskCluster(workers), p)
    bad = [r for r in seq_rows + dsk_rows if r["status"] != "ok"]
    if bad:
        raise RuntimeError(f"sweep throughput: case {bad[0]['case']}: {bad[0]['status']}: {bad[0]['error']}")
    same = without_wall_time(arrow_table(p, seq_rows)).equals(without_wall_time(arrow_table(p, dsk_rows)))
    return Throughput(len(p.cases), duration_s, expand_s, seq, dsk, same, os.cpu_count() or 1, load)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.sweep_throughput", description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=1000)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--duration", type=float, default=5.0, help="simulated seconds per run (default 5)")
    args = ap.parse_args(argv)
    print("\n".join(measure(args.runs, args.workers, args.duration).lines()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
