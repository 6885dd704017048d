"""`python -m bench.sim_paired --repo A --repo B [--rounds N] [--duration S] [--laps L]`: is B's `ddrt sim` faster than A's?

A speed-up of a few percent is below the spread of one run on a shared machine, so the
checkouts are measured in turns (A, B, A, B, ...) by the same script, and each run reports the
CPU time (process_time) of `run_sim` alone per controller tick: the 0.8 m/s figure-eight
(figure8_fast.yaml with a path of L laps) for S simulated seconds, telemetry streamed to a
temporary CSV, start-up (imports, config, path) outside the timed region. Prints, per checkout,
every run's us per tick sorted, and the minimum (the run least disturbed by other work).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path as FsPath

from bench.common import child_env
from bench.sim_scaling import figure8_path

# run_sim on CONFIG PATH_FILE DURATION, its CPU time printed as JSON (bench.sim_instructions uses it too).
RUN_SIM_CHILD = r"""
import json, sys, tempfile, time
from ddrt.config import load_config
from ddrt.path.spec import resolve_path
from ddrt.simrun.runner import run_sim
config, path_file, duration = sys.argv[1], sys.argv[2], float(sys.argv[3])
cfg = load_config(config)
path = resolve_path(cfg, path_file)
with tempfile.TemporaryDirectory() as d:
    c = time.process_time()
    r = run_sim(cfg, path, duration=duration, telemetry=d + "/telemetry.csv")
    c = time.process_time() - c
print(json.dumps({"us_per_tick": c / r.metrics["ticks"] * 1e6, "ticks": r.metrics["ticks"], "cpu_s": c}))
"""


def run_once(repo: FsPath, path_file: FsPath, duration: float) -> float:
    """CPU us per tick of one run_sim with `repo`'s ddrt, in a child python."""
    config = repo / "configs/scenarios/figure8_fast.yaml"
    p = subprocess.run([sys.executable, "-c", RUN_SIM_CHILD, str(config), str(path_file), f"{duration:g}"], cwd=repo,
                       env=child_env(repo, OPENBLAS_NUM_THREADS="1"), capture_output=True, text=True, timeout=900)
    if p.returncode != 0:
        raise RuntimeError(f"run_sim in {repo} failed (exit {p.returncode}): {p.stderr[-400:]}")
    return float(json.loads(p.stdout.strip().splitlines()[-1])["us_per_tick"])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.sim_paired", description=__doc__.split("\n")[0])
    ap.add_argument("--repo", action="append", type=FsPath, required=True, help="a checkout (give two or more)")
    ap.add_argument("--rounds", type=int, default=6)
    ap.add_argument("--duration", type=float, default=60.0, help="simulated s per run")
    ap.add_argument("--laps", type=int, default=12, help="laps of the figure-eight (enough for the duration)")
    args = ap.parse_args(argv)
    if len(args.repo) < 2 or args.rounds < 1 or not args.duration > 0.0 or args.laps < 1:
        ap.error("two or more --repo, --rounds >= 1, --duration > 0 and --laps >= 1")
    runs: dict[FsPath, list[float]] = {r: [] for r in args.repo}
    with tempfile.TemporaryDirectory(prefix="ddrt-paired-") as tmp:
        path_file = figure8_path(args.laps, FsPath(tmp) / "figure8.yaml")
        for _ in range(args.rounds):
            for repo in args.repo:
                runs[repo].append(run_once(repo.resolve(), path_file, args.duration))
    for repo, us in runs.items():
        us.sort()
        print(f"{repo}: min {us[0]:.1f}  median {statistics.median(us):.1f}  us/tick CPU  "
              f"({' '.join(f'{u:.1f}' for u in us)})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
