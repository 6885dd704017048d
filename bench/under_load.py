"""The daemon under CPU load: does `ddrt run --follow` finish its path while other processes
compete for the CPUs?

Target: with two CPU burners on a 2-core machine, a 60 s `ddrt run --follow` on the
simulated robot (paced to the wall clock) finishes its path in 3 runs of 3 without exiting.
Before sensor gaps were held and recovered (ddrt/loop/hold.py, `holding`), a stall of ~150 ms
under such load faulted the loop ("sensor gap") and the daemon exited within seconds.

Each run is a fresh daemon process on a config in a temp dir that extends configs/sim.yaml
(telemetry in the temp dir, no control socket) and follows four laps of the slow
figure-eight (~49 s, crossing itself at the origin) for `--duration` seconds; the burners
are busy-looping Python processes, one per core, at the daemon's own priority. A run
passes when the daemon exits 0 at the end of its duration, in state `stopped`, with the
reference at the end of the path. Each run's --stats-json gives the holds, resumes, gaps
and timing.

    python -m bench.under_load [--runs 3] [--duration 60] [--burners 2] [--json FILE]
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path as FsPath
from typing import Any

import yaml

from bench.common import SIM_CONFIG, spawn_daemon

PATH = {"shape": "figure_eight", "width": 1.2, "height": 0.6, "speed": 0.3, "laps": 4}
BURN = "while True:\n    pass\n"


@dataclass
class LoadRun:
    """One daemon run under load."""

    index: int
    exit_code: int | None
    wall_s: float
    final_state: str | None = None
    path_length_m: float = 0.0
    progress_m: float = 0.0
    stats: dict[str, Any] = field(default_factory=dict)
    error: str = ""

    @property
    def finished(self) -> bool:
        return (self.exit_code == 0 and self.final_state == "stopped"
                and self.progress_m >= self.path_length_m - 0.01)


@dataclass
class UnderLoad:
    burners: int
    duration_s: float
    cpus: int
    runs: list[LoadRun]

    @property
    def passed(self) -> int:
        return sum(r.finished for r in self.runs)


def _path_length() -> float:
    from ddrt.config import load_config
    from ddrt.path import load_path
    from ddrt.path.spec import speed_limits

    return load_path(dict(PATH), speed_limits(load_config(SIM_CONFIG))).length


def _progress(telemetry_dir: FsPath) -> float:
    """The furthest the reference got along the path (telemetry's `sigma`)."""
    best = 0.0
    for f in sorted(telemetry_dir.glob("telemetry*.csv")):
        with open(f, newline="") as fh:
            reader = csv.reader(fh)
            header = next(reader, None)
            if not header or "sigma" not in header:
                continue
            i = header.index("sigma")
            for row in reader:
                if len(row) == len(header):
                    best = max(best, float(row[i]))
    return best


def run_once(index: int, duration_s: float, length_m: float) -> LoadRun:
    with tempfile.TemporaryDirectory(prefix="ddrt-load-") as tmp:
        tmpdir = FsPath(tmp)
        cfg = tmpdir / "cfg.yaml"
        tel = tmpdir / "tel"
        stats_file = tmpdir / "stats.json"
        cfg.write_text(yaml.safe_dump({
            "extends": str(SIM_CONFIG),
            "daemon": {"telemetry_dir": str(tel), "socket": None},
            "path": dict(PATH),
        }, sort_keys=False))
        t0 = time.monotonic()
        with open(tmpdir / "stderr.log", "wb") as err:
            proc = spawn_daemon(cfg, "--follow", "--duration", str(duration_s), "--stats-json", str(stats_file),
                                stderr=err)
            try:
                rc: int | None = proc.wait(timeout=duration_s + 60.0)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
                rc = None
        wall = time.monotonic() - t0
        run = LoadRun(index=index, exit_code=rc, wall_s=wall, path_length_m=length_m)
        try:
            run.stats = json.loads(stats_file.read_text())
            run.final_state = run.stats.get("final_state")
        except (OSError, ValueError) as exc:
            run.error = f"no stats: {exc}"
        run.progress_m = _progress(tel)
        if rc != 0:
            lines = (tmpdir / "stderr.log").read_text(errors="replace").strip().splitlines()
            run.error = run.error or (lines[-1] if lines else f"exit code {rc}")
        return run


def measure(runs: int = 3, duration_s: float = 60.0, burners: int = 2) -> UnderLoad:
    length = _path_length()
    procs = [subprocess.Popen([sys.executable, "-c", BURN], stdin=subprocess.DEVNULL,
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL) for _ in range(burners)]
    try:
        time.sleep(0.5)  # the burners are running before the daemon starts
        results = [run_once(i + 1, duration_s, length) for i in range(runs)]
    finally:
        for p in procs:
            p.kill()
        for p in procs:
            p.wait()
    return UnderLoad(burners=burners, duration_s=duration_s, cpus=os.cpu_count() or 0, runs=results)


def render(u: UnderLoad) -> list[str]:
    lines = [
        f"{u.burners} CPU burners (busy Python loops) on a {u.cpus}-CPU machine; each run a fresh "
        f"`ddrt run --follow --duration {u.duration_s:g}` on the simulated robot at 200 Hz, following four "
        "laps of the slow figure-eight (bench/under_load.py). Target: the path finished in 3 runs of 3, "
        "no exit before the duration.",
        "",
        "| run | exit | final state | path done | holds | resumed | gaps | longest gap (ms) | missed ticks | "
        "lateness p99 / max (ms) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in u.runs:
        rec = r.stats.get("recovery") or {}
        late = r.stats.get("lateness_us") or {}
        p99 = late.get("p99")
        mx = late.get("max")
        lines.append(
            f"| {r.index} | {r.exit_code} | {r.final_state} | "
            f"{'yes' if r.finished else 'no'} ({r.progress_m:.2f} of {r.path_length_m:.2f} m) | "
            f"{rec.get('holds', '-')} | {rec.get('resumes', '-')} | {rec.get('gaps', '-')} | "
            f"{rec.get('longest_gap_ms', 0.0):.0f} | {r.stats.get('missed', '-')} | "
            f"{(p99 or 0) / 1000:.1f} / {(mx or 0) / 1000:.1f} |")
    lines += ["", f"Result: {u.passed} of {len(u.runs)} runs finished their path."]
    errors = [f"run {r.index}: {r.error}" for r in u.runs if r.error]
    if errors:
        lines += ["", *errors]
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--burners", type=int, default=2)
    ap.add_argument("--json", help="also write the results to this file")
    args = ap.parse_args(argv)
    u = measure(args.runs, args.duration, args.burners)
    print("\n".join(render(u)))
    if args.json:
        FsPath(args.json).write_text(json.dumps(
            {**asdict(u), "passed": u.passed}, indent=2, default=str) + "\n")
    return 0 if u.passed == len(u.runs) else 1


if __name__ == "__main__":
    sys.exit(main())
