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
