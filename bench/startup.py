"""Start-up and memory: what importing each dependency costs, and the peak RSS of `ddrt sim`.

On a Raspberry Pi class board import time is most of a service's start-up, and resident
memory is what `lock_memory` pins; both are measured in fresh child processes.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path as FsPath
from typing import Sequence

from bench.common import REPO, child_env

MODULES = ("numpy", "filterpy", "yaml", "serial", "smbus2", "ddrt.loop")


@dataclass(frozen=True)
class ImportCost:
    """Cumulative import time of one module (its own dependencies included), in ms."""

    module: str
    median_ms: float
    samples_ms: tuple[float, ...]


def parse_importtime(stderr: str, module: str) -> float:
    """The cumulative microseconds of `module` from `python -X importtime` output."""
    for line in stderr.splitlines():
        if not line.startswith("import time:"):
            continue
        parts = [p.strip() for p in line[len("import time:"):].split("|")]
        if len(parts) == 3 and parts[2] == module and parts[1].isdigit():
            return float(parts[1])
    raise ValueError(f"importtime output has no line for module {module!r}")


def import_cost(module: str, repeats: int = 3) -> ImportCost:
    samples = []
    for _ in range(repeats):
        p = subprocess.run([sys.executable, "-X", "importtime", "-c", f"import {module}"], cwd=REPO,
                           env=child_env(), capture_output=True, text=True, timeout=120)
        if p.returncode != 0:
            raise RuntimeError(f"import {module} failed: {p.stderr.strip().splitlines()[-1:]}")
        samples.append(parse_importtime(p.stderr, module) / 1000.0)
    return ImportCost(module, statistics.median(samples), tuple(samples))


@dataclass(frozen=True)
class SimMemory:
    """Peak resident set of one `ddrt sim` child process, and what it ran."""

    maxrss_kb: int
    wall_s: float
    command: str


def sim_peak_rss(config: str | FsPath = "configs/sim.yaml", duration_s: float | None = None) -> SimMemory:
    """Run `python -m ddrt.cli sim CONFIG` as a child; its own rusage (os.wait4) gives the peak RSS."""
    with tempfile.TemporaryDirectory(prefix="ddrt-bench-") as tmp:
        cmd = [sys.executable, "-m", "ddrt.cli", "sim", str(config), "--out", tmp, "--quiet"]
        if duration_s is not None:
            cmd += ["--duration", f"{duration_s:g}"]
        t0 = time.perf_counter()
        p = subprocess.Popen(cmd, cwd=REPO, env=child_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        assert p.stderr is not None
        err = p.stderr.read()
        _, status, usage = os.wait4(p.pid, 0)
        p.returncode = os.waitstatus_to_exitcode(status)
        p.stderr.close()
        wall = time.perf_counter() - t0
        # A run cut short by --duration exits 1 (path not completed) but still writes its metrics.
        wrote = (FsPath(tmp) / "metrics.json").exists()
    if not wrote:
        raise RuntimeError(f"ddrt sim {config} failed (exit {p.returncode}, no metrics.json): "
                           f"{err.decode(errors='replace')[-300:]}")
    shown = "ddrt sim " + " ".join(cmd[4:5]) + (f" --duration {duration_s:g}" if duration_s is not None else "")
    return SimMemory(maxrss_kb=int(usage.ru_maxrss), wall_s=wall, command=shown)


def loaded_by(module: str, candidates: Sequence[str]) -> dict[str, bool]:
    """Which of `candidates` importing `module` pulls in (a dependency nothing imports costs nothing)."""
    code = (f"import sys, json, {module}; "
            f"print(json.dumps({{m: m in sys.modules for m in {list(candidates)!r}}}))")
    p = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=child_env(), capture_output=True,
                       text=True, timeout=120)
    if p.returncode != 0:
        raise RuntimeError(f"import {module} failed: {p.stderr.strip().splitlines()[-1:]}")
    return {str(k): bool(v) for k, v in json.loads(p.stdout).items()}


@dataclass(frozen=True)
class Startup:
    imports: list[ImportCost]
    sim: SimMemory
    loop_loads: dict[str, bool]  # dependency -> imported by `import ddrt.loop`


def measure_startup(modules: Sequence[str] = MODULES, repeats: int = 3,
                    sim_duration_s: float | None = None) -> Startup:
    deps = [m for m in modules if not m.startswith("ddrt")]
    return Startup(imports=[import_cost(m, repeats) for m in modules], sim=sim_peak_rss(duration_s=sim_duration_s),
                   loop_loads=loaded_by("ddrt.loop", deps))


def render(st: Startup, ready_s: float | None, daemon_rss_kb: int | None) -> list[str]:
    from ddrt.config import EstimatorConfig

    ready = f"{ready_s:.2f} s" if ready_s is not None else "N/A (no daemon stats)"
    lines = [
        f"- Process start to READY (`ddrt run` on the simulated robot, from its stats; this includes "
        f"the gyro calibration at rest, estimator.calibration_s = {EstimatorConfig().calibration_s:g} s "
        f"by default): {ready}",
        f"- Peak resident memory of `{st.sim.command}` (child's own rusage): {st.sim.maxrss_kb / 1024:.1f} MiB "
        f"({st.sim.wall_s:.1f} s wall)",
    ]
    if daemon_rss_kb is not None:
        lines.append(f"- Peak resident memory of the daemon (its stats, 200 Hz run): {daemon_rss_kb / 1024:.1f} MiB")
    n = len(st.imports[0].samples_ms) if st.imports else 0
    lines += ["", f"Import cost (`python -X importtime -c \"import M\"`, cumulative, median of {n}):", "",
              "| module | ms | samples (ms) |", "|---|---|---|"]
    for c in st.imports:
        lines.append(f"| {c.module} | {c.median_ms:.1f} | {', '.join(f'{s:.1f}' for s in c.samples_ms)} |")
    if st.loop_loads:
        yes = [m for m, v in st.loop_loads.items() if v]
        no = [m for m, v in st.loop_loads.items() if not v]
        lines += ["", f"`import ddrt.loop` pulls in: {', '.join(yes) or 'none of them'}; "
                      f"not: {', '.join(no) or 'none'} (those cost nothing until a backend or test imports them)."]
    return lines
