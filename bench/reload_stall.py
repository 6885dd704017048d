"""Reload stall: how long the loop goes without a tick while a running daemon reloads its config.

A fresh `ddrt run --follow` on the simulated robot (200 Hz, a circle) is reloaded over its
control socket `--reloads` times, 0.2 s apart, each time with a changed inner kp (alternating
two values, so every reload puts something in force), waiting for each reply; after each, a
`gains` request (answered between two ticks, nothing read) is the control: what any request
costs the loop. The window of each is from a `status` count before it to one after its reply.
Afterwards the telemetry (one row per tick, the paced robot's time, 1 ms steps) gives every
tick-to-tick gap: the largest in each window, against the gaps away from all of them. A
reload that stalls the loop shows as a gap of periods.

    python -m bench.reload_stall [--reloads 40] [--points N] [--repo DIR ...] [--json FILE]

`--points N` writes the config's path inline as N points of the same circle (about 30 bytes
a point: 10 000 make a 300 KB file, a recorded path pasted into the config), so each reload
reads that much YAML.

`--repo` runs the same against other checkouts of ddrt (e.g. a worktree of an older commit),
one daemon each, one after the other, in this process's Python.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import subprocess
import tempfile
import time
from pathlib import Path
from typing import Any

import yaml

from bench.common import REPO, SIM_CONFIG, await_daemon, percentile, spawn_daemon
from ddrt.service.ctlclient import request

RATE_HZ = 200.0
KP = (40.0, 41.0)


def _start(repo: Path, tmp: Path, kp: float, points: int) -> tuple[subprocess.Popen, Path, Path]:
    cfg = tmp / "ddrt.yaml"
    _write(cfg, tmp, kp, points)
    sock = tmp / "ddrt.sock"
    with open(tmp / "stderr.log", "wb") as err:
        proc = spawn_daemon(cfg, "--follow", "--socket", str(sock), stderr=err, repo=repo)
    return proc, cfg, sock


def _path(points: int) -> dict[str, Any]:
    if points <= 0:
        return {"shape": "circle", "radius": 0.5, "speed": 0.2, "laps": 20}
    ring = [[round(0.5 * math.sin(a), 6), round(0.5 - 0.5 * math.cos(a), 6)]
            for a in (2.0 * math.pi * k / points for k in range(points + 1))]
    return {"points": ring, "speed": 0.1}


def _write(cfg: Path, tmp: Path, kp: float, points: int) -> None:
    text = yaml.safe_dump({
        "extends": str(SIM_CONFIG),
        "daemon": {"telemetry_dir": str(tmp / "telemetry"), "telemetry_format": "csv"},
        "estimator": {"calibration_s": 0.5},
        "controller": {"inner": {"kp": kp}},
        "path": _path(points),
    }, sort_keys=False, default_flow_style=None)
    part = cfg.with_suffix(".part")
    part.write_text(text, encoding="utf-8")
    part.replace(cfg)  # whole or not at all: a reload never reads half a file


def _count(sock: Path) -> int:
    return int(request(str(sock), {"cmd": "status"}, timeout=10.0)["status"]["timing"]["count"])


def measure(repo: Path, reloads: int, points: int = 0) -> dict[str, Any]:
    """One daemon from `repo`: the worst gap around each reload and the gaps elsewhere (ms)."""
    with tempfile.TemporaryDirectory(prefix="ddrt-reload-") as tmp_s:
        tmp = Path(tmp_s)
        proc, cfg, sock = _start(repo, tmp, KP[0], points)
        size_kb = cfg.stat().st_size / 1024
        try:
            await_daemon(proc, str(sock), lambda reply: reply.get("status", {}).get("state") == "following",
                         "follow", tmp / "stderr.log")
            time.sleep(1.0)
            windows: dict[str, list[tuple[int, int]]] = {"reload": [], "gains": []}
            replies_ms = []
            for i in range(reloads):
                _write(cfg, tmp, KP[(i + 1) % 2], points)
                for cmd in ("reload", "gains"):
                    time.sleep(0.2)
                    before = _count(sock)
                    t0 = time.perf_counter()
                    reply = request(str(sock), {"cmd": cmd}, timeout=120.0)
                    if cmd == "reload":
                        replies_ms.append((time.perf_counter() - t0) * 1e3)
                    if not reply.get("ok"):
                        raise RuntimeError(f"{cmd} refused: {reply}")
                    windows[cmd].append((before, _count(sock)))
            time.sleep(0.5)
        finally:
            proc.terminate()
            proc.wait(timeout=30)
        with open(tmp / "telemetry" / "telemetry.csv", newline="") as fh:
            rows = list(csv.DictReader(fh))
    t = [float(r["t"]) for r in rows]
    gap = [0.0] + [(b - a) * 1e3 for a, b in zip(t, t[1:])]
    near: set[int] = set()
    worst: dict[str, list[float]] = {}
    for cmd, spans in windows.items():
        for lo, hi in spans:
            idx = range(max(lo - 1, 1), min(hi + 2, len(gap)))
            near.update(idx)
            worst.setdefault(cmd, []).append(max(gap[i] for i in idx))
    steady = [gap[i] for i in range(int(RATE_HZ) * 2, len(gap) - 2) if i not in near]
    period_ms = 1e3 / RATE_HZ
    out: dict[str, Any] = {"repo": str(repo), "reloads": len(worst["reload"]), "file_kb": size_kb}
    for cmd, gaps in worst.items():
        out[cmd] = {"median_ms": percentile(gaps, 50), "max_ms": max(gaps),
                    "missed_a_period": sum(g > 1.5 * period_ms for g in gaps)}
    out.update(steady_gap_ms={"p99": percentile(steady, 99), "max": max(steady), "n": len(steady)},
               steady_gaps_over_1_5_periods=sum(g > 1.5 * period_ms for g in steady),
               reply_ms_median=percentile(replies_ms, 50))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--reloads", type=int, default=40)
    ap.add_argument("--points", type=int, default=0, help="the path inline as this many points (0: a shape)")
    ap.add_argument("--repo", action="append", type=Path, help="a checkout to measure (default: this one)")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    out = [measure(r.resolve(), args.reloads, args.points) for r in (args.repo or [REPO])]
    print("| checkout | config (KB) | reloads | worst gap around a reload: median / max (ms), how many > 1.5 periods "
          "| the same around a `gains` request | gaps elsewhere: p99 / max (ms), > 1.5 periods | reload reply median (ms) |")
    print("|---|---|---|---|---|---|---|")
    for r in out:
        cells = [f"{r[c]['median_ms']:.0f} / {r[c]['max_ms']:.0f}, {r[c]['missed_a_period']}" for c in ("reload", "gains")]
        print(f"| {r['repo']} | {r['file_kb']:.0f} | {r['reloads']} | {cells[0]} | {cells[1]} | {r['steady_gap_ms']['p99']:.0f} / "
              f"{r['steady_gap_ms']['max']:.0f}, {r['steady_gaps_over_1_5_periods']} of {r['steady_gap_ms']['n']} "
              f"| {r['reply_ms_median']:.1f} |")
    if args.json:
        args.json.write_text(json.dumps(out, indent=1), encoding="utf-8")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
