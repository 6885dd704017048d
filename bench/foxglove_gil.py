"""Why a tick was late with Foxglove on: the machine, or the publisher holding the GIL?

One `ddrt run` on the simulated robot at 200 Hz (bench/foxglove_load.py's config, in this
process, a `websockets` client in another), with two probes patched in:

- each tick: its deadline, when it started, the slots it skipped, and the loop thread's
  run-queue wait so far (/proc/thread-self/schedstat): a tick late with no run-queue wait was
  blocked (on the GIL, most likely), one late by its run-queue wait had no CPU (the machine);
- each publish (`VizService.publish_once`): start, end, CPU time and run-queue wait: wall time
  far beyond CPU time, as run-queue wait, is the publisher preempted, with the GIL held.

A late tick (> 1 ms) whose deadline falls inside a publish is counted against the publisher.

`--normal-publisher` keeps the publisher at SCHED_OTHER (as before rt.raise_gil_helper), for
an A/B of that change.

    python -m bench.foxglove_gil [--duration S] [--off | --normal-publisher]
"""

from __future__ import annotations

import argparse
import asyncio
import bisect
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path as FsPath
from typing import Any, Sequence

import yaml

from bench.common import REPO, SIM_CONFIG, child_env
from bench.foxglove_load import PATH, view_client

PORT = 18766
LATE_S = 0.001


def _schedstat() -> tuple[int, int]:
    with open("/proc/thread-self/schedstat") as fh:
        run_ns, wait_ns, _ = fh.read().split()
    return int(run_ns), int(wait_ns)


def probe(enabled: bool, duration: float, normal_publisher: bool = False) -> dict[str, list[tuple[float, ...]]]:
    from ddrt import cli
    from ddrt.runtime import rt
    from ddrt.service import timing
    from ddrt.viz import service

    if normal_publisher:
        rt.raise_gil_helper = lambda _prio: rt.demote_current_thread()  # type: ignore[assignment]

    ticks: list[tuple[float, ...]] = []
    pubs: list[tuple[float, ...]] = []
    account, publish = timing.RateScheduler.account, service.VizService.publish_once

    def timed_account(self: Any, now: float) -> int:
        deadline = self._deadline
        skipped = account(self, now)
        ticks.append((deadline, now, skipped, _schedstat()[1] / 1e9))
        return skipped

    def timed_publish(self: Any) -> None:
        w0, t0, c0 = _schedstat()[1], time.monotonic(), time.thread_time()
        publish(self)
        pubs.append((t0, time.monotonic(), time.thread_time() - c0, (_schedstat()[1] - w0) / 1e9))

    timing.RateScheduler.account, service.VizService.publish_once = timed_account, timed_publish  # type: ignore
    try:
        with tempfile.TemporaryDirectory(prefix="ddrt-gil-", dir="/tmp") as tmp:
            cfg = {"extends": str(SIM_CONFIG), "path": str(PATH),
                   "daemon": {"socket": f"{tmp}/ctl.sock", "telemetry_dir": f"{tmp}/tel", "rt_priority": 10,
                              "foxglove": {"enabled": enabled, "port": PORT}}}
            FsPath(tmp, "cfg.yaml").write_text(yaml.safe_dump(cfg))
            client = None
            if enabled:  # another process: the client must not share this one's GIL
                client = subprocess.Popen([sys.executable, "-m", "bench.foxglove_gil", "--client", str(duration)],
                                          cwd=REPO, env=child_env(),
                                          stdout=subprocess.DEVNULL)
            try:
                cli.main(["run", f"{tmp}/cfg.yaml", "--follow", "--duration", str(duration)])
            finally:
                if client is not None:
                    client.wait(60)
    finally:
        timing.RateScheduler.account, service.VizService.publish_once = account, publish  # type: ignore
    return {"ticks": ticks, "pubs": pubs}


def analyse(p: dict[str, list[tuple[float, ...]]]) -> dict[str, Any]:
    ticks, pubs = p["ticks"], p["pubs"]
    starts = [q[0] for q in pubs]
    late = []
    for i in range(1, len(ticks)):
        deadline, started, skipped, wait = ticks[i]
        if started - deadline > LATE_S:
            k = bisect.bisect_right(starts, deadline) - 1
            under = pubs[k] if k >= 0 and pubs[k][1] > deadline else None
            late.append({"t_s": deadline - ticks[0][0], "late_ms": (started - deadline) * 1e3, "skipped": skipped,
                         "loop_runqueue_ms": (wait - ticks[i - 1][3]) * 1e3,
                         "publish_cpu_ms": under[2] * 1e3 if under else None,
                         "publish_runqueue_ms": under[3] * 1e3 if under else None})
    span = ticks[-1][1] - ticks[0][1] if ticks else 0.0
    return {"ticks": len(ticks), "missed": sum(int(t[2]) for t in ticks), "late": late,
            "late_under_publish": sum(1 for x in late if x["publish_cpu_ms"] is not None),
            "missed_under_publish": sum(x["skipped"] for x in late if x["publish_cpu_ms"] is not None),
            "publish_busy": sum(q[1] - q[0] for q in pubs) / span if span else 0.0,
            "publish_runqueue_max_ms": max((q[3] for q in pubs), default=0.0) * 1e3,
            "publishes_preempted_over_1ms": sum(1 for q in pubs if q[3] > 1e-3), "publishes": len(pubs)}


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--off", action="store_true", help="Foxglove off (the loop's stalls without a publisher)")
    ap.add_argument("--normal-publisher", action="store_true", help="the publisher at SCHED_OTHER (the old way)")
    ap.add_argument("--client", type=float, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.client is not None:
        time.sleep(float(os.environ.get("DDRT_GIL_CLIENT_DELAY_S", "3.0")))  # the daemon's start-up
        asyncio.run(view_client(PORT, time.monotonic() + args.client))
        return 0
    r = analyse(probe(not args.off, args.duration, args.normal_publisher))
    r["load_average"] = " ".join(f"{x:.2f}" for x in os.getloadavg())
    print(json.dumps({k: v for k, v in r.items() if k != "late"}, indent=1))
    for x in r["late"]:
        print(json.dumps(x))
    return 0


if __name__ == "__main__":
    sys.exit(main())
