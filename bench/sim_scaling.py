"""`python -m bench.sim_scaling [--repo DIR] [--repeats N] [--json FILE]`: does `ddrt sim` scale linearly?

Each case is `ddrt sim` (its `main`, telemetry.csv and metrics.json written to a temporary
directory) in a fresh child process, so its peak resident memory (ru_maxrss) is its own.
Per case, the median over `--repeats` runs of:

- loop: the metrics' `realtime_factor` (simulated s per wall s of the control loop; since the
  telemetry is streamed, it includes writing telemetry.csv and the metrics),
- command: simulated s per wall s of the whole command after start-up (config, path,
  calibration, the run, the files), and per CPU s of it (process_time: less disturbed by
  other processes on the machine),
- peak RSS of the child (MiB), and its wall time.

`--repo DIR` runs another checkout's ddrt (e.g. the commit before a change) with this same
script, for a before/after. The figure-eight cases generate their path (the 0.8 m/s
figure-eight with enough laps) in the temporary directory.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path as FsPath

from bench.common import REPO, child_env

# name, config (relative to the repo), figure-eight laps (None: the config's own path), --duration
CASES: tuple[tuple[str, str, int | None, float | None], ...] = (
    ("figure8_fast 20 s", "configs/scenarios/figure8_fast.yaml", 4, 20.0),
    ("figure8_fast 300 s", "configs/scenarios/figure8_fast.yaml", 52, 300.0),
    ("seed_square (290 s)", "configs/scenarios/seed_square.yaml", None, None),
)

_CHILD = r"""
import json, resource, sys, time
from ddrt.cli import main
argv = json.loads(sys.argv[1])
t, c = time.perf_counter(), time.process_time()
code = main(argv)
wall, cpu = time.perf_counter() - t, time.process_time() - c
print(json.dumps({"code": code, "wall_s": wall, "cpu_s": cpu,
                  "maxrss_kb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss}))
"""


@dataclass(frozen=True)
class CaseResult:
    name: str
    sim_s: float
    ticks: int
    loop_x: float  # median realtime_factor
    command_x: float  # median simulated s / command wall s
    command_cpu_x: float  # median simulated s / command CPU s (less sensitive to other load)
    maxrss_mib: float  # median peak RSS of the child
    child_wall_s: float  # median wall of the child process (start-up included)
    samples: tuple[dict, ...]


def figure8_path(laps: int, dest: FsPath) -> FsPath:
    dest.write_text(f"shape: figure_eight\nwidth: 1.2\nheight: 0.6\nspeed: 0.8\nlaps: {laps}\n")
    return dest


def run_case(repo: FsPath, config: str, laps: int | None, duration: float | None) -> dict:
    """One `ddrt sim` in a child python whose ddrt is `repo`'s."""
    with tempfile.TemporaryDirectory(prefix="ddrt-scaling-") as tmp:
        out = FsPath(tmp) / "out"
        argv = ["sim", str(repo / config), "--out", str(out), "--quiet"]
        if laps is not None:
            argv += ["--path", str(figure8_path(laps, FsPath(tmp) / f"figure8_{laps}laps.yaml"))]
        if duration is not None:
            argv += ["--duration", f"{duration:g}"]
        env = child_env(repo, OPENBLAS_NUM_THREADS="1")
        t0 = time.perf_counter()
        p = subprocess.run([sys.executable, "-c", _CHILD, json.dumps(argv)], cwd=repo, env=env,
                           capture_output=True, text=True, timeout=900)
        child_wall = time.perf_counter() - t0
        if p.returncode != 0 or not (out / "metrics.json").exists():
            raise RuntimeError(f"ddrt sim {config} failed (exit {p.returncode}): {p.stderr[-400:]}")
        info = json.loads(p.stdout.strip().splitlines()[-1])
        m = json.loads((out / "metrics.json").read_text())
    return {"sim_s": m["sim_duration_s"], "ticks": m["ticks"], "loop_x": m["realtime_factor"],
            "command_x": m["sim_duration_s"] / info["wall_s"], "command_cpu_x": m["sim_duration_s"] / info["cpu_s"],
            "maxrss_mib": info["maxrss_kb"] / 1024.0,
            "child_wall_s": child_wall}


def measure(repo: FsPath = REPO, repeats: int = 3,
            cases: tuple[tuple[str, str, int | None, float | None], ...] = CASES) -> list[CaseResult]:
    """Every case `repeats` times, interleaved (case 1, 2, 3, 1, 2, 3, ...) so load drifts hit all alike."""
    runs: dict[str, list[dict]] = {c[0]: [] for c in cases}
    for _ in range(repeats):
        for name, config, laps, duration in cases:
            runs[name].append(run_case(repo, config, laps, duration))
    out = []
    for name, *_ in cases:
        s = runs[name]
        med = {k: statistics.median(r[k] for r in s)
               for k in ("loop_x", "command_x", "command_cpu_x", "maxrss_mib", "child_wall_s")}
        out.append(CaseResult(name, s[0]["sim_s"], s[0]["ticks"], med["loop_x"], med["command_x"],
                              med["command_cpu_x"], med["maxrss_mib"], med["child_wall_s"], tuple(s)))
    return out


def _each(r: CaseResult, key: str) -> str:
    return ", ".join(f"{s[key]:.0f}" for s in r.samples)


def render(results: list[CaseResult], repo: FsPath) -> str:
    lines = [f"`ddrt sim` scaling ({repo}), median of {len(results[0].samples)} runs per case:", "",
             "| case | simulated | ticks | loop (realtime_factor) | command (wall) | command (CPU) | peak RSS "
             "| child wall |",
             "|---|---|---|---|---|---|---|---|"]
    for r in results:
        lines.append(f"| {r.name} | {r.sim_s:.1f} s | {r.ticks} | {r.loop_x:.0f}x ({_each(r, 'loop_x')}) | "
                     f"{r.command_x:.0f}x ({_each(r, 'command_x')}) | {r.command_cpu_x:.0f}x "
                     f"({_each(r, 'command_cpu_x')}) | {r.maxrss_mib:.1f} MiB | {r.child_wall_s:.2f} s |")
    return "\n".join(lines)


TARGET_X = 200.0  # at least 200x real time on one core, at 300 s as at 20 s
PERIOD_S = 0.005  # the controller's tick (200 Hz) in every case


def _cpu_s(r: CaseResult) -> float:
    """Median CPU seconds of the case's command."""
    return statistics.median(x["sim_s"] / x["command_cpu_x"] for x in r.samples)


def render_section(results: list[CaseResult]) -> list[str]:
    """BENCHMARKS.md's "Simulation speed" (`python -m bench.run --only 4`): the table, the CPU a
    controller tick costs once started (the 300 s figure-eight's CPU less the 20 s one's, over
    the ticks between: start-up, path and calibration cancel), and the 200x target judged on
    it. Wall-clock factors move with whatever else the machine runs; CPU time much less."""
    lines = ["`ddrt sim` on one core (the command's `main` in a child process: config, path, calibration, the "
             "closed loop of `run_sim` with its 200 Hz controller and 1 kHz plant, telemetry.csv and "
             "metrics.json written), by `bench/sim_scaling.py`. loop: the metrics' `realtime_factor` "
             "(simulated s per wall s of the loop, telemetry streamed); command: simulated s per wall s, and "
             "per CPU s (process_time), of the whole command, start-up included. On a machine that other "
             "work shares, CPU time is the figure to read: wall time counts the time the process waited "
             "for a core.", ""]
    lines += render(results, REPO).splitlines()[2:]
    by_name = {r.name: r for r in results}
    short, long = by_name.get(CASES[0][0]), by_name.get(CASES[1][0])
    if short is None or long is None or long.ticks <= short.ticks:
        return lines + ["", "The figure-eight pair (20 s and 300 s) was not measured: no verdict on the 200x target."]
    tick_s = (_cpu_s(long) - _cpu_s(short)) / (long.ticks - short.ticks)
    factor = PERIOD_S / tick_s
    verdict = "**MET**" if factor >= TARGET_X else "**NOT MET** on this machine"
    lines += ["", f"CPU per controller tick once started, all in (plant, estimator, reference, controller, "
              f"telemetry.csv, metrics), from the figure-eight pair: {tick_s * 1e6:.1f} us = {factor:.0f}x real time "
              f"per CPU second (20 s run {short.command_cpu_x:.0f}x and 300 s run {long.command_cpu_x:.0f}x with "
              f"their start-up). Target: at least {TARGET_X:.0f}x on one core on the figure-eight, at "
              f"300 s as at 20 s, i.e. at most {PERIOD_S / TARGET_X * 1e6:.0f} us a tick: {verdict}."]
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repo", type=FsPath, default=REPO, help="the checkout whose ddrt runs (default: this one)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--json", type=FsPath, help="also write the raw samples here")
    args = ap.parse_args(argv)
    repo = args.repo.resolve()
    results = measure(repo, args.repeats)
    print(render(results, repo))
    if args.json is not None:
        args.json.write_text(json.dumps([r.__dict__ for r in results], indent=2, default=list) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
