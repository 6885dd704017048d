"""Loop timing: the daemon (`ddrt run`) on the simulated robot, paced to the wall clock.

Each rate gets a fresh daemon process and a config in a temp dir that extends configs/sim.yaml
with `controller.rate_hz` and a temp telemetry dir; the daemon writes its own timing stats
(`--stats-json`). Until `ddrt run` exists this section says so instead of failing.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path as FsPath
from typing import Any, Sequence

import yaml

from bench.common import REPO, SIM_CONFIG, child_env, spawn_daemon

# A path longer than any run here (80 s at 31 mm/s), so the loop follows for the whole run.
FOLLOW_PATH = REPO / "configs" / "paths" / "seed_circle.yaml"
RATES_HZ = (100, 200, 500, 1000)


def daemon_help() -> str | None:
    """`ddrt run --help`'s text, or None when the command does not exist (yet)."""
    try:
        p = subprocess.run([sys.executable, "-m", "ddrt.cli", "run", "--help"], cwd=REPO, env=child_env(),
                           capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return p.stdout if p.returncode == 0 else None


@dataclass(frozen=True)
class LoopRun:
    """One daemon run at one rate: its stats JSON, or why there is none."""

    rate_hz: float
    duration_s: float
    stats: dict[str, Any] | None
    error: str = ""
    followed: bool = False
    spin_us: int = 0


@dataclass(frozen=True)
class LoopTiming:
    available: bool
    reason: str
    runs: list[LoopRun]


def write_config(directory: FsPath, rate_hz: float, spin_us: int = 0) -> FsPath:
    """A config that extends configs/sim.yaml at `rate_hz`, telemetry and socket in `directory`."""
    data = {
        "extends": str(SIM_CONFIG),
        "controller": {"rate_hz": rate_hz},
        "daemon": {"telemetry_dir": str(directory / "telemetry"), "socket": str(directory / "ddrt.sock"),
                   "spin_us": spin_us},
        "path": str(FOLLOW_PATH),
    }
    path = directory / f"bench_{int(rate_hz)}hz.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


def run_daemon(rate_hz: float, duration_s: float, follow: bool, spin_us: int = 0) -> LoopRun:
    with tempfile.TemporaryDirectory(prefix="ddrt-bench-") as tmp:
        d = FsPath(tmp)
        cfg = write_config(d, rate_hz, spin_us)
        stats_file = d / "stats.json"
        args = ["--duration", f"{duration_s:g}", "--socket", str(d / "ddrt.sock"), "--stats-json", str(stats_file)]
        if follow:
            args.append("--follow")
        p = spawn_daemon(cfg, *args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            _, stderr = p.communicate(timeout=duration_s + 60.0)
        except subprocess.TimeoutExpired:
            p.kill()
            p.communicate()
            return LoopRun(rate_hz, duration_s, None, "timed out", follow, spin_us)
        if not stats_file.exists():
            return LoopRun(rate_hz, duration_s, None, f"exit {p.returncode}, no stats: {last_error(stderr)}", follow, spin_us)
        try:
            stats = json.loads(stats_file.read_text(encoding="utf-8"))
        except ValueError as exc:
            return LoopRun(rate_hz, duration_s, None, f"{stats_file.name}: not JSON: {exc}", follow, spin_us)
        err = "" if p.returncode == 0 else f"exit {p.returncode}: {last_error(stderr)}"
        return LoopRun(rate_hz, duration_s, stats, err, follow, spin_us)


def last_error(stderr: str) -> str:
    """The daemon's last ERROR log line (else its last line), for the table's note column."""
    lines = [ln.strip() for ln in stderr.splitlines() if ln.strip()]
    errors = [ln for ln in lines if ln.startswith("ERROR") or "Error" in ln]
    text = (errors or lines or ["no output"])[-1]
    return text.replace("|", "/")


def measure_loop_timing(rates: Sequence[float] = RATES_HZ, duration_s: float = 30.0) -> LoopTiming:
    help_text = daemon_help()
    if help_text is None:
        return LoopTiming(False, "ddrt run not available", [])
    follow = "--follow" in help_text
    runs = [run_daemon(r, duration_s, follow) for r in rates]
    # The robot's config polls the last 200 us before each tick (daemon.spin_us): the same
    # 200 Hz run with it, to show what it buys against its CPU.
    runs.append(run_daemon(200.0, duration_s, follow, spin_us=200))
    return LoopTiming(True, "", runs)


def ready_s(timing: LoopTiming) -> float | None:
    """Start-up to READY from the daemon's own stats (the first run that reported it)."""
    for run in timing.runs:
        if run.stats and isinstance(run.stats.get("ready_s"), (int, float)):
            return float(run.stats["ready_s"])
    return None


def _get(stats: dict[str, Any], key: str, sub: str | None = None) -> str:
    v: Any = stats.get(key)
    if sub is not None:
        v = v.get(sub) if isinstance(v, dict) else None
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return "n/a"
    return f"{v:.0f}" if isinstance(v, int) or abs(v) >= 100 else f"{v:.1f}"


def _cpu(stats: dict[str, Any]) -> str:
    """CPU time over wall time of the whole daemon process (the simulated robot included)."""
    cpu, wall = stats.get("cpu_s"), stats.get("wall_s")
    if not isinstance(cpu, (int, float)) or not isinstance(wall, (int, float)) or wall <= 0:
        return "n/a"
    return f"{100.0 * cpu / wall:.1f}"


def render(timing: LoopTiming) -> list[str]:
    if not timing.available:
        return [f"not measured: {timing.reason}"]
    follow = any(r.followed for r in timing.runs)
    lines = [
        "The daemon (`ddrt run`) on the simulated robot paced to the wall clock"
        + (", following a path (`--follow`)" if follow else ", idle (this `ddrt run` has no `--follow`)")
        + ". Lateness is wake-up time minus deadline; compute is the tick (the paced plant's catch-up "
          "is done before it). Statistics are the daemon's own (`--stats-json`). The daemon's compute "
          "per tick is several times section 2's: there the ticks run back to back, here each one "
          "starts after the process slept for a period, with the interpreter's code and data out of "
          "the CPU's caches. CPU is the whole process, the simulated robot's physics and the "
          "gyro calibration at start included.",
        "",
        "| rate (Hz) | period (us) | run (s) | ticks | missed | overruns | lateness p50 (us) | lateness p99 (us) "
        "| lateness max (us) | compute p50 (us) | compute p99 (us) | compute max (us) | CPU (% of a core) | note |",
        "|" + "---|" * 14,
    ]
    for r in timing.runs:
        s = r.stats or {}
        lines.append("| " + " | ".join([
            f"{r.rate_hz:g}", f"{1e6 / r.rate_hz:.0f}", f"{r.duration_s:g}", _get(s, "ticks"), _get(s, "missed"),
            _get(s, "overruns"), _get(s, "lateness_us", "p50"), _get(s, "lateness_us", "p99"),
            _get(s, "lateness_us", "max"), _get(s, "compute_us", "p50"), _get(s, "compute_us", "p99"),
            _get(s, "compute_us", "max"), _cpu(s),
            "; ".join(x for x in (f"spin_us {r.spin_us}" if r.spin_us else "", r.error) if x),
        ]) + " |")
    return lines
