"""Foxglove load: what the live view costs the loop, and how fresh the client's view is.

Two fresh `ddrt run` daemons on the simulated robot at 200 Hz, one after the other, each for
`--duration` s following five laps of the fast figure-eight (then standing still):

- off: daemon.foxglove disabled (the daemon as it was);
- on: daemon.foxglove enabled, a `websockets` client subscribed to every channel for the
  whole run. The client stamps each /state message on arrival and compares it with the log
  time in its data frame (the tick's start on the daemon's clock, as epoch ns): the age of
  the client's view.

Reported: the daemon's tick cost p50/p99/max and lateness p99 (its own --stats-json: the timed
part is the tick and the telemetry ring append), missed ticks, peak RSS, the messages the
client received against the ticks, and the age of the view (p50, p99, max). The loop thread's
one added call (`VizRing.put`, after the timed part) is timed on its own. Targets: tick p99
up by at most 5 us, RSS up by at most 40 MB, no missed tick, view age max < 100 ms.

    python -m bench.foxglove_load [--duration S] [--json FILE]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
import timeit
from pathlib import Path as FsPath
from typing import Any, Sequence

import yaml

REPO = FsPath(__file__).resolve().parent.parent
BASE_CONFIG = REPO / "configs" / "sim.yaml"
PATH = REPO / "configs" / "paths" / "figure8_fast_5laps.yaml"
TARGET_TICK_P99_US = 5.0
TARGET_RSS_MB = 40.0
TARGET_AGE_MS = 100.0


def _start(workdir: FsPath, enabled: bool, duration: float) -> tuple[subprocess.Popen[bytes], FsPath, FsPath]:
    cfg = {"extends": str(BASE_CONFIG), "path": str(PATH),
           "daemon": {"socket": str(workdir / "ctl.sock"), "telemetry_dir": str(workdir / "tel"), "rt_priority": 10,
                      "foxglove": {"enabled": enabled, "port": 0}}}
    config = workdir / "cfg.yaml"
    config.write_text(yaml.safe_dump(cfg))
    stats, err = workdir / "stats.json", workdir / "stderr.log"
    env = {k: v for k, v in os.environ.items() if k not in ("NOTIFY_SOCKET", "LOGS_DIRECTORY")}
    env["PYTHONPATH"] = str(REPO)
    with open(err, "wb") as fh:
        proc = subprocess.Popen([sys.executable, "-m", "ddrt.cli", "run", str(config), "--follow", "--duration",
                                 str(duration), "--stats-json", str(stats)], cwd=REPO, env=env, stdout=fh, stderr=fh)
    return proc, stats, err


async def _client(port: int, until: float) -> dict[str, Any]:
    import websockets

    ages: list[float] = []
    counts: dict[str, int] = {}
    async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"], max_size=None) as ws:
        topics: dict[int, str] = {}
        subscribed = False
        while time.monotonic() < until:
            try:
                msg = await asyncio.wait_for(ws.recv(), 0.5)
            except asyncio.TimeoutError:
                continue
            except websockets.ConnectionClosed:
                break
            now = time.time_ns()
            if isinstance(msg, str):
                doc = json.loads(msg)
                if doc.get("op") == "advertise":
                    for c in doc["channels"]:
                        topics[c["id"]] = c["topic"]
                    if not subscribed and "/state" in topics.values():
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                            {"id": cid, "channelId": cid} for cid in topics]}))
                        subscribed = True
                continue
            if msg[0] != 0x01:
                continue
            sub = int.from_bytes(msg[1:5], "little")
            topic = topics.get(sub, "?")
            counts[topic] = counts.get(topic, 0) + 1
            if topic == "/state":
                ages.append((now - int.from_bytes(msg[5:13], "little")) / 1e6)
    ages.sort()
    return {"counts": counts, "age_ms": {"p50": _pct(ages, 50), "p99": _pct(ages, 99), "max": ages[-1] if ages else None,
                                         "n": len(ages)}}


def _pct(xs: list[float], p: float) -> float | None:
    return xs[min(len(xs) - 1, int(round(p / 100 * (len(xs) - 1))))] if xs else None


def run_one(enabled: bool, duration: float) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="ddrt-fx-", dir="/tmp") as tmp:
        workdir = FsPath(tmp)
        proc, stats_path, err = _start(workdir, enabled, duration)
        client: dict[str, Any] | None = None
        try:
            if enabled:
                deadline = time.monotonic() + 30.0
                port = None
                while port is None and time.monotonic() < deadline and proc.poll() is None:
                    m = re.search(r"serving ws://127\.0\.0\.1:(\d+)", err.read_text(errors="replace"))
                    port = int(m.group(1)) if m else None
                    time.sleep(0.02)
                if port is None:
                    raise RuntimeError(f"no Foxglove server:\n{err.read_text(errors='replace')}")
                client = asyncio.run(_client(port, time.monotonic() + duration + 30.0))
            proc.wait(timeout=duration + 60.0)
        finally:
            if proc.poll() is None:
                proc.kill()
        stats = json.loads(stats_path.read_text())
    return {"enabled": enabled, "exit_code": stats["exit_code"], "ticks": stats["ticks"], "missed": stats["missed"],
            "compute_us": stats["compute_us"], "lateness_us": stats["lateness_us"],
            "maxrss_mb": stats["maxrss_kb"] / 1024.0, "cpu_s": stats["cpu_s"], "client": client}


def put_cost_us() -> float:
    """The loop thread's added call, VizRing.put with a telemetry-sized row and a truth tuple."""
    from ddrt.loop import COLUMNS
    from ddrt.viz.ring import VizRing

    ring = VizRing(len(COLUMNS))
    row = [0.1] * len(COLUMNS)
    truth = (1.0, 2.0, 3.0) + (0.5, 0.1)
    n = 200_000
    best = min(timeit.repeat(lambda: ring.put(row, 1e-5, 2e-4, 123.0, truth), number=n, repeat=5))
    return best / n * 1e6


def measure(duration: float) -> dict[str, Any]:
    off = run_one(False, duration)
    on = run_one(True, duration)
    put = put_cost_us()
    return {"duration_s": duration, "off": off, "on": on, "put_us": put,
            "tick_p99_delta_us": on["compute_us"]["p99"] - off["compute_us"]["p99"] + put,
            "rss_delta_mb": on["maxrss_mb"] - off["maxrss_mb"]}


def markdown(r: dict[str, Any]) -> str:
    lines = ["| Foxglove | ticks | missed | tick p50 / p99 / max (us) | lateness p99 (us) | peak RSS (MB) | CPU (s) |",
             "|---|---|---|---|---|---|---|"]
    for name in ("off", "on"):
        s = r[name]
        c, lt = s["compute_us"], s["lateness_us"]
        lines.append(f"| {name} | {s['ticks']} | {s['missed']} | {c['p50']:.0f} / {c['p99']:.0f} / {c['max']:.0f} | "
                     f"{lt['p99']:.0f} | {s['maxrss_mb']:.1f} | {s['cpu_s']:.1f} |")
    cl = r["on"]["client"]
    a = cl["age_ms"]
    lines += ["", f"Client (on): {cl['counts'].get('/state', 0)} /state messages for {r['on']['ticks']} ticks; "
              f"view age p50 {a['p50']:.1f} ms, p99 {a['p99']:.1f} ms, max {a['max']:.1f} ms (target < {TARGET_AGE_MS:g}). "
              f"VizRing.put on the loop thread: {r['put_us']:.2f} us. Tick p99 on - off + put: "
              f"{r['tick_p99_delta_us']:+.1f} us (target <= {TARGET_TICK_P99_US:g}); RSS on - off: "
              f"{r['rss_delta_mb']:+.1f} MB (target <= {TARGET_RSS_MB:g})."]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--json")
    args = ap.parse_args(argv)
    r = measure(args.duration)
    print(markdown(r))
    if args.json:
        FsPath(args.json).write_text(json.dumps(r, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
