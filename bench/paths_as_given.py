"""Paths as people hand them over: polylines from recordings, planners and exports, closed loop.

`python -m bench.paths_as_given [--seed N] [--cases a,b]` prints the table; bench/run.py
includes it as a section. The inputs, each generated with a fixed seed, and the targets they
are held to are lab/path_inputs.py's (the conditioning tests load the same ones).
For the manoeuvres with cusps, each cusp is a stop: the ideal time adds v / limits.accel per
cusp (braking to rest and starting again), and the exact curve's own profile (or, for
waypoints, the waypoints' own, turns in place included) makes the same stops; the larger of
the two is the ideal.

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
import math
import os
import sys
import tempfile
import time
from dataclasses import dataclass, field, replace
from pathlib import Path as FsPath
from typing import Callable, Sequence

import numpy as np

from bench.common import SIM_CONFIG
from ddrt.config import load_config
from ddrt.path.sampled import Path
from ddrt.path.report import turn_spans
from ddrt.path.spec import load_path, speed_limits
from ddrt.simrun.runner import run_sim
from lab.path_inputs import (CASES, TARGET_DOMEGA_RMS, TARGET_GRID_RMS_M, TARGET_SATURATION,
                                       TARGET_TRUE_RMS_M, Case, curve_distance, long_recording, write_csv)

TIME_FACTOR, TIME_EXTRA_S = 1.3, 3.0
TARGET_LONG_S = 2.0


# --------------------------------------------------------------------------- measuring


@dataclass
class Run:
    completed: bool
    fault: str
    time_s: float
    true_rms_m: float
    true_max_m: float
    domega_rms: float  # over the whole run
    domega_gentle_rms: float  # turns in place and a grid plan's blended turns left out
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
        if self.kind != "waypoints":
            # Where the exact curve itself needs more (the 0.8 m/s figure-eight), within 10 % of it.
            floor = 1.1 * self.exact.domega_gentle_rms if self.exact is not None else 0.0
            out["d(omega)/dt"] = r.domega_gentle_rms <= max(TARGET_DOMEGA_RMS, floor)
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
    gentle = _gentle(path, res.column("sigma"))
    gentle = gentle[1:] & gentle[:-1] if len(t) > 1 else np.ones(1, dtype=bool)
    return Run(bool(m["completed"]), str(m.get("fault") or ""), float(m["sim_duration_s"]),
               float(np.sqrt(np.mean(d ** 2))), float(d.max()), float(np.sqrt(np.mean(dw ** 2))),
               float(np.sqrt(np.mean(dw[gentle] ** 2))) if gentle.any() else 0.0,
               float(m["saturated_fraction"]))


def _gentle(path: Path, sigma: np.ndarray) -> np.ndarray:
    """Which ticks (by the reference's progress) are neither in a turn in place nor in a grid
    plan's blended turn (ddrt/path/report.py `turn_spans`)."""
    out = np.ones(len(sigma), dtype=bool)
    for s0, s1 in turn_spans(path):
        out &= ~((sigma >= s0) & (sigma <= s1))
    return out


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
        "with fixed seeds by lab/path_inputs.py), loaded as `ddrt sim --path FILE` loads a CSV on configs/sim.yaml and run on the "
        "simulated robot (seed 1). time: simulated time to the end, against the target "
        f"{TIME_FACTOR:g} x max(length / speed, the exact curve's own profile) + {TIME_EXTRA_S:g} s; "
        "true: distance of the true pose from the underlying curve (a grid plan: its staircase), RMS / max; "
        "d(omega)/dt: RMS of the commanded yaw acceleration over the whole run / while driving gently "
        "(turns in place and a grid plan's blended turns, taken at the profile's own yaw limits, left out); "
        "dev: the reference's largest distance from the input points. **x** marks a missed target (true pose "
        f"3 mm RMS for samples, 15 mm for a grid; d(omega)/dt {TARGET_DOMEGA_RMS:g} rad/s^2 RMS while driving "
        "gently, or within 10 % of the exact curve's where that needs more; saturation 1 %). "
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
            f"| {ru.domega_rms:.2f} / {ru.domega_gentle_rms:.2f}{_mark(c.get('d(omega)/dt'))} | {ru.saturated * 100:.2f} %{_mark(c.get('saturation'))} "
            f"| {row.deviation_m * 1000:.1f} | {row.load_ms:.0f} |")
        if row.exact is not None:
            ex = row.exact
            lines.append(f"| &nbsp;&nbsp;exact curve | | | | | | {ex.time_s:.1f} | {ex.true_rms_m * 1000:.2f} / "
                         f"{ex.true_max_m * 1000:.1f} | {ex.domega_rms:.2f} / {ex.domega_gentle_rms:.2f} | {ex.saturated * 100:.2f} % | | |")
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
