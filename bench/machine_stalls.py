"""Are the daemon's missed ticks its own or the machine's? A `ddrt run` daemon on the simulated
robot at 200 Hz (`rt_priority: 10`, following the slow figure-eight, no ROS 2 bridge: the
"no bridge" phase of bench.ros2_flood) runs beside a bare probe: a process with one thread
and no work that sleeps to the same 200 Hz grid at the same SCHED_FIFO priority and counts
missed slots by the daemon's rule (ddrt/service/timing.py). Both see the same machine for the
same seconds; `--hogs` busy loops at nice 0 run beside them. The hypervisor's steal time
(/proc/stat) over the run is reported too: time the virtual CPUs wanted to run and did not.

If the probe, which has no helper threads and no GIL to wait for, misses as many ticks as the
daemon, the daemon's misses are the machine's, not a priority inversion inside it.

    python -m bench.machine_stalls [--duration 30] [--runs 3] [--hogs 1] [--json FILE]
    python -m bench.machine_stalls --spin CPU    # how long the CPU itself goes missing
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import yaml

from bench.common import REPO, child_env, spawn_daemon

PERIOD_S = 0.005
PRIORITY = 10


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


def probe(duration: float, priority: int = PRIORITY) -> dict[str, Any]:
    """The bare loop (run in its own process): clock_nanosleep to absolute slots, skip and
    count the slots a late wake-up passed, as the daemon's Deadlines.account does."""
    libc = ctypes.CDLL(None, use_errno=True)
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        fifo = True
    except OSError:
        fifo = False
    start = time.monotonic() + 0.01
    tick, missed, late = 1, 0, []
    while tick * PERIOD_S <= duration:
        deadline = start + tick * PERIOD_S
        ts = _Timespec(int(deadline), int((deadline % 1.0) * 1e9))
        libc.clock_nanosleep(1, 1, ctypes.byref(ts), None)  # CLOCK_MONOTONIC, TIMER_ABSTIME
        now = time.monotonic()
        late.append(now - deadline)
        tick += 1
        if start + tick * PERIOD_S <= now:
            skipped = int((now - (start + tick * PERIOD_S)) / PERIOD_S) + 1
            missed += skipped
            tick += skipped
    late.sort()
    return {"fifo": fifo, "ticks": len(late), "missed": missed,
            "late_p99_us": late[int(0.99 * (len(late) - 1))] * 1e6, "late_max_us": late[-1] * 1e6}


def spin(cpu: int, rounds: int = 10, spin_s: float = 0.4) -> dict[str, Any]:
    """Spin at SCHED_FIFO 99 on `cpu` reading the clock, `rounds` times `spin_s` (resting the
    rest of each second, under the kernel's 95% real-time limit): nothing in the machine can
    preempt it but interrupts and the hypervisor, so every gap is time the CPU was taken away."""
    os.sched_setaffinity(0, {cpu})
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(99))
    gaps, spun = [], 0.0
    for _ in range(rounds):
        prev = time.perf_counter_ns()
        first, end = prev, prev + int(spin_s * 1e9)
        while prev < end:
            now = time.perf_counter_ns()
            if now - prev > 200_000:
                gaps.append((now - prev) / 1e6)
            prev = now
        spun += (prev - first) / 1e9
        time.sleep(1.0 - spin_s)
    gaps.sort()
    return {"cpu": cpu, "spun_s": spun, "lost_ms": sum(gaps), "gaps_over_1ms": sum(g > 1.0 for g in gaps),
            "gaps_over_5ms": sum(g > 5.0 for g in gaps), "max_gap_ms": gaps[-1] if gaps else 0.0}


def steal_s() -> float:
    """Seconds of steal time summed over all CPUs so far (/proc/stat, USER_HZ ticks)."""
    with open("/proc/stat") as f:
        fields = f.readline().split()
    return int(fields[8]) / os.sysconf("SC_CLK_TCK") if len(fields) > 8 else 0.0


def start_probe(duration: float) -> subprocess.Popen:
    """`probe` for `duration` s in a process of its own (started now); read it with probe_result."""
    return subprocess.Popen([sys.executable, "-m", "bench.machine_stalls", "--probe", str(duration)],
                            cwd=REPO, env=child_env(), stdout=subprocess.PIPE, text=True)


def probe_result(bare: subprocess.Popen, timeout: float) -> dict[str, Any]:
    """What a started probe measured (its last line of output)."""
    out, _ = bare.communicate(timeout=timeout)
    return json.loads(out.strip().splitlines()[-1])


def one_run(duration: float, hogs: int) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="ddrt-stalls-", dir="/tmp") as tmp:
        work = Path(tmp)
        cfg = {"extends": str(REPO / "configs" / "sim.yaml"),
               "daemon": {"telemetry_dir": str(work / "tel"), "rt_priority": PRIORITY},
               "estimator": {"calibration_s": 0.5},
               "path": str(REPO / "configs" / "paths" / "figure8_slow.yaml")}
        (work / "cfg.yaml").write_text(yaml.safe_dump(cfg, sort_keys=False))
        stats = work / "stats.json"
        busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(hogs)]
        steal0 = steal_s()
        try:
            with open(work / "stderr.log", "wb") as err:
                daemon = spawn_daemon(work / "cfg.yaml", "--socket", str(work / "ctl.sock"), "--duration",
                                      str(duration), "--follow", "--stats-json", str(stats), stderr=err)
                probe_out = probe_result(start_probe(duration), duration + 60.0)
                daemon.wait(duration + 60.0)
        finally:
            for p in busy:
                p.kill()
                p.wait()
        steal = steal_s() - steal0
        s = json.loads(stats.read_text())
        return {"daemon_missed": s["missed"], "daemon_late_max_us": s["lateness_us"]["max"],
                "daemon_late_p99_us": s["lateness_us"]["p99"], "steal_s": steal,
                **{f"probe_{k}": v for k, v in probe_out.items()}}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.machine_stalls", description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=30.0, help="seconds per run (default 30)")
    ap.add_argument("--runs", type=int, default=3, help="runs (default 3)")
    ap.add_argument("--hogs", type=int, default=1, help="busy loops at nice 0 beside them (default 1)")
    ap.add_argument("--json", help="also write the rows to this file")
    ap.add_argument("--spin", type=int, metavar="CPU",
                    help="instead: spin at SCHED_FIFO 99 on CPU 10 x 0.4 s and print the gaps (needs root)")
    ap.add_argument("--probe", type=float, help=argparse.SUPPRESS)  # the bare loop's own process
    a = ap.parse_args(argv)
    if a.spin is not None:
        try:
            print(json.dumps(spin(a.spin)))
        except OSError as exc:
            print(f"bench.machine_stalls: --spin {a.spin}: {exc}", file=sys.stderr)
            return 1
        return 0
    if a.probe is not None:
        print(json.dumps(probe(a.probe)), flush=True)
        return 0
    if a.duration <= 0 or a.runs < 1 or a.hogs < 0:
        ap.error("--duration must be > 0, --runs >= 1, --hogs >= 0")
    rows = []
    print("| run | daemon missed | daemon lateness max (us) | probe missed | probe lateness max (us) | steal (CPU-s) |")
    print("|---|---|---|---|---|---|")
    for i in range(a.runs):
        r = one_run(a.duration, a.hogs)
        rows.append(r)
        print(f"| {i + 1} | {r['daemon_missed']} | {r['daemon_late_max_us']:.0f} | {r['probe_missed']} | "
              f"{r['probe_late_max_us']:.0f} | {r['steal_s']:.2f} |", flush=True)
    print(f"| median | {statistics.median(r['daemon_missed'] for r in rows)} | "
          f"{statistics.median(r['daemon_late_max_us'] for r in rows):.0f} | "
          f"{statistics.median(r['probe_missed'] for r in rows)} | "
          f"{statistics.median(r['probe_late_max_us'] for r in rows):.0f} | "
          f"{statistics.median(r['steal_s'] for r in rows):.2f} |")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
