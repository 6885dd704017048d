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

`measure_mcap` adds what recording costs `ddrt sim`: its wall time and files with and without
`--mcap`. `section` and `render_section` are BENCHMARKS.md's section on both (bench/run.py).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import re
import shlex
import statistics
import subprocess
import sys
import tempfile
import time
import timeit
from pathlib import Path as FsPath
from typing import Any, Sequence

import yaml

from bench.common import REPO, SIM_CONFIG, child_env, percentile, spawn_daemon

PATH = REPO / "configs" / "paths" / "figure8_fast_5laps.yaml"
TARGET_TICK_P99_US = 5.0
TARGET_RSS_MB = 40.0
TARGET_AGE_MS = 100.0


def _start(workdir: FsPath, enabled: bool, duration: float) -> tuple[subprocess.Popen[bytes], FsPath, FsPath]:
    cfg = {"extends": str(SIM_CONFIG), "path": str(PATH),
           "daemon": {"socket": str(workdir / "ctl.sock"), "telemetry_dir": str(workdir / "tel"), "rt_priority": 10,
                      "foxglove": {"enabled": enabled, "port": 0}}}
    config = workdir / "cfg.yaml"
    config.write_text(yaml.safe_dump(cfg))
    stats, err = workdir / "stats.json", workdir / "stderr.log"
    with open(err, "wb") as fh:
        proc = spawn_daemon(config, "--follow", "--duration", str(duration), "--stats-json", str(stats),
                            stdout=fh, stderr=fh)
    return proc, stats, err


async def view_client(port: int, until: float) -> dict[str, Any]:
    """A `websockets` client subscribed to every channel until `until` (time.monotonic()): the
    messages it received per topic and the age of each /state message on arrival."""
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
    return {"counts": counts, "age_ms": {"p50": percentile(ages, 50) if ages else None,
                                         "p99": percentile(ages, 99) if ages else None,
                                         "max": max(ages) if ages else None, "n": len(ages)}}


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
                client = asyncio.run(view_client(port, time.monotonic() + duration + 30.0))
            proc.wait(timeout=duration + 60.0)
        finally:
            if proc.poll() is None:
                proc.kill()
        stats = json.loads(stats_path.read_text())
    return {"enabled": enabled, "exit_code": stats["exit_code"], "ticks": stats["ticks"], "missed": stats["missed"],
            "overruns": stats["overruns"], "compute_us": stats["compute_us"], "lateness_us": stats["lateness_us"],
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


def _typical(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """One mode's runs as one row: median p50/p99 (the machine's noise between runs is larger
    than the difference measured), the worst maximum, missed ticks summed, the largest RSS, the
    first run's client."""
    med = statistics.median
    out = dict(runs[0])
    for key in ("compute_us", "lateness_us"):
        out[key] = {"p50": med(r[key]["p50"] for r in runs), "p99": med(r[key]["p99"] for r in runs),
                    "max": max(r[key]["max"] for r in runs)}
    out["first_ticks"] = runs[0]["ticks"]
    out["ticks"] = sum(r["ticks"] for r in runs)
    out["missed"] = sum(r["missed"] for r in runs)
    out["overruns"] = sum(r["overruns"] for r in runs)
    out["maxrss_mb"] = max(r["maxrss_mb"] for r in runs)
    out["cpu_s"] = med(r["cpu_s"] for r in runs)
    out["runs"] = len(runs)
    return out


def measure(duration: float, pairs: int = 2) -> dict[str, Any]:
    """Off and on in ABBA order (off, on, on, off, ...) so drift in the machine's load falls on
    both; each mode's p50/p99 the median over its runs, and the per-pair p99 differences."""
    offs: list[dict[str, Any]] = []
    ons: list[dict[str, Any]] = []
    for i in range(pairs):
        for enabled in ((False, True) if i % 2 == 0 else (True, False)):
            (ons if enabled else offs).append(run_one(enabled, duration))
    put = put_cost_us()
    off, on = _typical(offs), _typical(ons)
    return {"duration_s": duration, "off": off, "on": on, "put_us": put, "pairs": pairs,
            "pair_p99_deltas_us": [b["compute_us"]["p99"] - a["compute_us"]["p99"] + put for a, b in zip(offs, ons)],
            "tick_p99_delta_us": on["compute_us"]["p99"] - off["compute_us"]["p99"] + put,
            "rss_delta_mb": on["maxrss_mb"] - off["maxrss_mb"]}


def measure_mcap(scenario: str = "figure8_fast", duration: float | None = None,
                 repeats: int = 2) -> dict[str, Any]:
    """`ddrt sim` on one scenario with the daemon runs' path (PATH) with and without `--mcap`
    (best wall time of `repeats`), and the sizes of its telemetry.csv and the MCAP file."""
    env = child_env()
    out: dict[str, Any] = {"scenario": scenario, "path": str(PATH.relative_to(REPO))}
    with tempfile.TemporaryDirectory(prefix="ddrt-mcap-", dir="/tmp") as tmp:
        for mcap in (False, True):
            cmd = [sys.executable, "-m", "ddrt.cli", "sim", str(REPO / "configs" / "scenarios" / f"{scenario}.yaml"),
                   "--path", str(PATH), "--quiet", "--out", tmp] + (["--duration", str(duration)] if duration else [])
            cmd += ["--mcap", f"{tmp}/run.mcap"] if mcap else []
            walls = []
            for _ in range(repeats):
                t0 = time.perf_counter()
                done = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True)
                if done.returncode not in (0, 1):  # 1: the path not completed (a --duration shorter than it)
                    raise RuntimeError(f"{shlex.join(cmd)}: exit {done.returncode}\n{done.stderr}")
                walls.append(time.perf_counter() - t0)
            metrics = json.loads(FsPath(tmp, "metrics.json").read_text())
            out["mcap" if mcap else "csv"] = {
                "wall_s": min(walls), "sim_s": metrics["sim_duration_s"], "ticks": metrics["ticks"],
                "csv_mb": FsPath(tmp, "telemetry.csv").stat().st_size / 1e6,
                "mcap_mb": FsPath(tmp, "run.mcap").stat().st_size / 1e6 if mcap else None}
    return out


def section(duration: float, mcap_duration: float | None, repeats: int) -> dict[str, Any]:
    r = measure(duration)
    r["mcap"] = measure_mcap(duration=mcap_duration, repeats=repeats)
    return r


def render_section(r: dict[str, Any]) -> list[str]:
    """BENCHMARKS.md's rows: off against on, the targets beside the numbers."""
    off, on = r["off"], r["on"]
    lines = [
        f"Fresh `ddrt run` daemons on the simulated robot at 200 Hz, one after the other, {r['duration_s']:g} s "
        "each following five laps of the fast figure-eight (bench/foxglove_load.py): Foxglove off, and on with a "
        "`websockets` client subscribed to every channel for the whole run, "
        f"{r.get('pairs', 1)} of each in ABBA order; p50 and p99 are the median over a mode's runs, maxima the "
        "worst, missed ticks the sum. Tick compute and lateness are the "
        "daemon's own (`--stats-json`); the loop thread's one added call (`VizRing.put`, outside the timed "
        "tick) is timed on its own and added to the difference. View age: the client's arrival time of each "
        "/state message minus the tick start in it. The targets beside the numbers.",
        "",
        "| | Foxglove off | on, client subscribed | on - off | target |",
        "|---|---|---|---|---|",
    ]
    def row(name: str, a: float, b: float, target: str, fmt: str = "{:.0f}", delta: float | None = None) -> None:
        d = (b - a) if delta is None else delta
        lines.append(f"| {name} | {fmt.format(a)} | {fmt.format(b)} | {d:+.1f} | {target} |")

    c0, c1, l0, l1 = off["compute_us"], on["compute_us"], off["lateness_us"], on["lateness_us"]
    lines.append(f"| ticks | {off['ticks']} | {on['ticks']} | | |")
    row("tick compute p50 (us)", c0["p50"], c1["p50"], "")
    row("tick compute p99 (us), on + VizRing.put", c0["p99"], c1["p99"] + r["put_us"],
        f"+{TARGET_TICK_P99_US:g}", delta=r["tick_p99_delta_us"])
    row("tick compute max (us)", c0["max"], c1["max"], "")
    row("lateness p99 (us)", l0["p99"], l1["p99"], "")
    row("lateness max (us)", l0["max"], l1["max"], "")
    lines.append(f"| missed ticks (in how many late wake-ups) | {off['missed']} ({off.get('overruns', '?')}) | "
                 f"{on['missed']} ({on.get('overruns', '?')}) | {on['missed'] - off['missed']:+d} | 0 |")
    row("peak RSS (MB)", off["maxrss_mb"], on["maxrss_mb"], f"+{TARGET_RSS_MB:g}", fmt="{:.1f}")
    row("CPU (s)", off["cpu_s"], on["cpu_s"], "", fmt="{:.1f}")
    if r.get("pair_p99_deltas_us"):
        lines += ["", "Tick compute p99 on - off, pair by pair (us, with VizRing.put): "
                  + ", ".join(f"{d:+.1f}" for d in r["pair_p99_deltas_us"]) + "."]
    cl = on["client"]
    a = cl["age_ms"]
    lines += ["", f"The client of the first run with Foxglove on received {cl['counts'].get('/state', 0)} /state messages for its {on.get('first_ticks', on['ticks'])} ticks "
              f"(per topic: {', '.join(f'{k} {v}' for k, v in sorted(cl['counts'].items()))}); view age p50 "
              f"{a['p50']:.1f} ms, p99 {a['p99']:.1f} ms, max {a['max']:.1f} ms (target <= {TARGET_AGE_MS:g} ms). "
              f"VizRing.put: {r['put_us']:.2f} us. Whether a missed tick is the machine or the publisher holding "
              "the GIL: `python -m bench.foxglove_gil` (docs/foxglove.md, \"What it costs the loop\")."]
    m = r.get("mcap")
    if m:
        c, x = m["csv"], m["mcap"]
        lines += ["", f"Recording: `ddrt sim configs/scenarios/{m['scenario']}.yaml --path {m['path']} --quiet` "
                  "with and without "
                  f"`--mcap FILE` ({c['sim_s']:.1f} simulated s, {c['ticks']} ticks; wall time of the whole command, "
                  "start-up included, best of the runs):", "",
                  "| | wall (s) | telemetry.csv (MB) | MCAP (MB) |", "|---|---|---|---|",
                  f"| without --mcap | {c['wall_s']:.2f} | {c['csv_mb']:.1f} | |",
                  f"| with --mcap | {x['wall_s']:.2f} | {x['csv_mb']:.1f} | {x['mcap_mb']:.1f} |",
                  "", f"MCAP adds {x['wall_s'] - c['wall_s']:.2f} s of wall time "
                  f"({(x['wall_s'] - c['wall_s']) / max(x['ticks'], 1) * 1e6:.0f} us a tick) and "
                  f"{x['mcap_mb'] / max(x['sim_s'], 1e-9):.2f} MB per simulated second."]
    return lines


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
