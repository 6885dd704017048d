"""Soak: does `ddrt run` keep anything per command it is sent?

A fresh `ddrt run` on configs/sim.yaml (a short calibration, telemetry in a temporary folder)
is sent, over its control socket, N cycles of what a user sends: `follow` (the slow
figure-eight's file content, as `ddrt ctl follow FILE` sends it), `stop`, `drive 0.1 0 --for
1`, `status`, `reload`, `estop` and `reset`. The requests are the ones `ddrt ctl` sends, made
by its own client functions in this process (a python started per command would make the
bench measure interpreter starts); the drive waits until the stop has braked, as a drive
does not take over a path still stopping. Every `--every` cycles, at the same point of the cycle
(after the reset), it reads the resident set (/proc/PID/status VmRSS), the open descriptors
(/proc/PID/fd) and the threads of the daemon and of the processes it started (the path
workers, the ROS 2 bridge), summed by role, as the children are restarted with new ids.

The verdict (lab/soak.py), per long-lived process after the first 30 cycles: RSS grows at
most 100 KiB per 100 cycles (least-squares slope), and descriptors and threads do not grow.
A path worker lives for one build (zero, one or two are alive at a sample), so its sum is
shown but not judged.
`--ros2` enables the ROS 2 bridge (a child process, its own DDS domain), `--foxglove` the
Foxglove server with one client subscribed to every channel. Exit status 1 if a bound is
broken, 2 if the daemon could not be driven.

    python -m bench.soak --cycles 1000 [--ros2] [--foxglove] [--every 10] [--plot FILE] [--json FILE]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path as FsPath
from typing import Any, Callable, Sequence

import yaml

from bench.common import REPO, SIM_CONFIG, await_daemon, spawn_daemon
from ddrt.service.ctlclient import request
from ddrt.service.drivecmd import drive_for
from lab.soak import RSS_LIMIT_KB_PER_100, WARMUP_CYCLES, Sample, Trend, trend

PATH_FILE = REPO / "configs" / "paths" / "figure8_slow.yaml"
DRIVE = (0.1, 0.0, 1.0)  # ddrt ctl drive 0.1 0 --for 1
REPLY_TIMEOUT_S = 30.0  # a follow's path is built in the worker; on a busy machine, seconds
STOPPING_WAIT_S = 10.0  # a stop from the figure-eight's speed brakes within a second
SHORT_LIVED = ("path worker",)
ROLES = (("ddrt.ros2", "ros2 bridge"), ("multiprocessing", "path worker"), ("pathworker", "path worker"))


@dataclass
class Soak:
    """The samples of every process, by role, and what the cycles' replies said."""

    options: dict[str, Any]
    samples: dict[str, list[Sample]] = field(default_factory=dict)
    refused: dict[str, int] = field(default_factory=dict)  # command -> replies with ok false
    errors: dict[str, str] = field(default_factory=dict)  # command -> its last refusal's error
    seconds: float = 0.0


def _read(path: FsPath) -> str:
    try:
        return path.read_text(errors="replace")
    except OSError:
        return ""


def process_sample(pid: int, cycle: int) -> Sample | None:
    """One process's RSS, descriptors and threads; None once it has exited."""
    status = _read(FsPath(f"/proc/{pid}/status"))
    fields = dict(line.split(":", 1) for line in status.splitlines() if ":" in line)
    try:
        rss_kb = int(fields["VmRSS"].split()[0])
        threads = int(fields["Threads"])
        fds = len(os.listdir(f"/proc/{pid}/fd"))
    except (KeyError, ValueError, OSError):
        return None
    return Sample(cycle, rss_kb, fds, threads)


def children(pid: int) -> list[int]:
    """The processes `pid` started (every thread's children), and theirs."""
    out: list[int] = []
    for task in FsPath(f"/proc/{pid}/task").glob("*"):
        for child in _read(task / "children").split():
            out.append(int(child))
            out.extend(children(int(child)))
    return out


def role(pid: int) -> str:
    """A child's role from its command line (the ROS 2 bridge, the path worker), else its name."""
    cmd = _read(FsPath(f"/proc/{pid}/cmdline")).replace("\0", " ")
    for marker, name in ROLES:
        if marker in cmd:
            return name
    return cmd.split(" ")[0].rsplit("/", 1)[-1] or f"pid {pid}"


def sample_tree(daemon_pid: int, cycle: int, into: dict[str, list[Sample]]) -> None:
    """The daemon's sample, and each role's: the sum over its processes (the path worker keeps
    a standby beside the one building, and both are replaced when they end)."""
    by_role: dict[str, list[Sample]] = {}
    for pid, name in [(daemon_pid, "daemon")] + [(c, role(c)) for c in children(daemon_pid)]:
        s = process_sample(pid, cycle)
        if s is not None:
            by_role.setdefault(name, []).append(s)
    for name, found in by_role.items():
        into.setdefault(name, []).append(Sample(cycle, sum(s.rss_kb for s in found), sum(s.fds for s in found),
                                                sum(s.threads for s in found)))


def cycle(send: Callable[..., dict[str, Any]], content: str, refused: dict[str, int], errors: dict[str, str]) -> None:
    """One command cycle; a refusal is counted, not fatal (a reset after an estop is what
    makes the next follow possible, so each cycle starts from the same state)."""
    def ask(payload: dict[str, Any], timeout: float = REPLY_TIMEOUT_S) -> dict[str, Any]:
        reply = send(payload, timeout)
        if not reply.get("ok"):
            refused[payload["cmd"]] = refused.get(payload["cmd"], 0) + 1
            errors[payload["cmd"]] = str(reply.get("error", ""))
        return reply

    ask({"cmd": "follow", "content": content, "format": "yaml", "name": PATH_FILE.name})
    ask({"cmd": "stop"})
    deadline = time.monotonic() + STOPPING_WAIT_S
    while send({"cmd": "status"}, REPLY_TIMEOUT_S)["status"]["state"] == "stopping" and time.monotonic() < deadline:
        time.sleep(0.05)  # a drive does not take over a path that is still braking
    drive_for(lambda p: ask(p, 2.0), *DRIVE)
    ask({"cmd": "status"})
    ask({"cmd": "reload"})
    ask({"cmd": "estop"})
    ask({"cmd": "reset"})


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def foxglove_client(port: int, stop: threading.Event, counts: dict[str, int]) -> None:
    """A client subscribed to every channel, reading until `stop`; reconnects if dropped."""
    import websockets

    async def run() -> None:
        while not stop.is_set():
            try:
                async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"],
                                              max_size=None) as ws:
                    subscribed = False
                    while not stop.is_set():
                        try:
                            msg = await asyncio.wait_for(ws.recv(), 0.5)
                        except asyncio.TimeoutError:
                            continue
                        if isinstance(msg, str):
                            doc = json.loads(msg)
                            if doc.get("op") == "advertise" and not subscribed:
                                subs = [{"id": c["id"], "channelId": c["id"]} for c in doc["channels"]]
                                await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
                                subscribed = True
                        else:
                            counts["messages"] = counts.get("messages", 0) + 1
            except (OSError, websockets.ConnectionClosed):
                await asyncio.sleep(0.5)

    asyncio.run(run())


def write_config(directory: FsPath, ros2: bool, foxglove_port: int | None) -> FsPath:
    daemon: dict[str, Any] = {"telemetry_dir": str(directory / "telemetry"), "rt_priority": 10}
    if ros2:
        daemon["ros2"] = {"enabled": True, "domain_id": 100 + os.getpid() % 100}  # no other bench's domain
    if foxglove_port is not None:
        daemon["foxglove"] = {"enabled": True, "host": "127.0.0.1", "port": foxglove_port}
    cfg = directory / "soak.yaml"
    cfg.write_text(yaml.safe_dump({"extends": str(SIM_CONFIG), "daemon": daemon,
                                   "estimator": {"calibration_s": 0.5}}, sort_keys=False), encoding="utf-8")
    return cfg


def soak(cycles: int, every: int, ros2: bool = False, foxglove: bool = False,
         say: Callable[[str], None] = print) -> Soak:
    result = Soak(options={"cycles": cycles, "every": every, "ros2": ros2, "foxglove": foxglove})
    content = PATH_FILE.read_text(encoding="utf-8")
    with tempfile.TemporaryDirectory(prefix="ddrt-soak-") as tmp:
        directory = FsPath(tmp)
        port = free_port() if foxglove else None
        cfg = write_config(directory, ros2, port)
        sock = str(directory / "ddrt.sock")
        err_path = directory / "stderr.log"
        with open(err_path, "wb") as err:
            proc = spawn_daemon(cfg, "--socket", sock, stderr=err)
            stop = threading.Event()
            counts: dict[str, int] = {}
            try:
                await_daemon(proc, sock, lambda r: r.get("ok") and r["status"]["state"] == "idle", "calibrate", err_path)
                if port is not None:
                    threading.Thread(target=foxglove_client, args=(port, stop, counts), daemon=True).start()

                def send(payload: dict[str, Any], timeout: float) -> dict[str, Any]:
                    return request(sock, payload, timeout=timeout)

                t0 = time.monotonic()
                sample_tree(proc.pid, 0, result.samples)
                for i in range(1, cycles + 1):
                    if proc.poll() is not None:
                        raise RuntimeError(f"the daemon exited at cycle {i}: {err_path.read_text()[-500:]}")
                    cycle(send, content, result.refused, result.errors)
                    if i % every == 0 or i == cycles:
                        time.sleep(0.1)  # the last reply's connection closed on the daemon's side too
                        sample_tree(proc.pid, i, result.samples)
                        d = result.samples["daemon"][-1]
                        say(f"cycle {i}: daemon RSS {d.rss_kb} KiB, {d.fds} fds, {d.threads} threads "
                            f"({time.monotonic() - t0:.0f} s)")
                result.seconds = time.monotonic() - t0
                if port is not None:
                    result.options["foxglove_messages"] = counts.get("messages", 0)
            finally:
                stop.set()
                proc.terminate()
                try:
                    proc.wait(timeout=30)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
    return result


def trends(result: Soak, warmup: int = WARMUP_CYCLES) -> dict[str, Trend]:
    return {name: trend(s, warmup) for name, s in result.samples.items()
            if sum(1 for x in s if x.cycle >= warmup) >= 2}


def render(result: Soak, found: dict[str, Trend]) -> list[str]:
    o = result.options
    extras = ", ".join(n for n in ("ros2", "foxglove") if o[n]) or "neither the ROS 2 bridge nor Foxglove"
    lines = [f"{o['cycles']} cycles in {result.seconds:.0f} s ({extras}); refused replies: "
             f"{result.refused or 'none'}", *(f"- {k}: {v}" for k, v in result.errors.items()), "",
             f"| process | RSS after {WARMUP_CYCLES} cycles (KiB) | RSS at the end (KiB) | slope (KiB/100 cycles) "
             "| descriptors | threads |",
             "|---|---|---|---|---|---|"]
    for name, t in found.items():
        label = f"{name} (one per build, not judged)" if name in SHORT_LIVED else name
        lines.append(f"| {label} | {t.rss_first_kb} | {t.rss_last_kb} | {t.rss_kb_per_100:.1f} | "
                     f"{t.fds[0]} -> {t.fds[1]} | {t.threads[0]} -> {t.threads[1]} |")
    return lines


def plot(result: Soak, out: FsPath) -> bool:
    """RSS against cycles for the daemon and the ROS 2 bridge, as the change since the warm-up
    (a path worker lives for one build: its RSS is in the table, not here), and the daemon's
    descriptors and threads; False without matplotlib."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return False
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(6.4, 4.4), sharex=True, height_ratios=(3, 1))
    judged: list[int] = []  # the changes after the warm-up, which set the scale (a child still starting does not)
    for name, s in result.samples.items():
        if name in SHORT_LIVED:
            continue
        base = next((x.rss_kb for x in s if x.cycle >= WARMUP_CYCLES), s[0].rss_kb)
        ax.plot([x.cycle for x in s], [x.rss_kb - base for x in s], label=f"{name} (from {base / 1024:.1f} MiB)")
        judged += [x.rss_kb - base for x in s if x.cycle >= WARMUP_CYCLES]
    if judged:
        pad = max(64, (max(judged) - min(judged)) // 5)
        ax.set_ylim(min(judged) - pad, max(judged) + pad)
    ax.axvline(WARMUP_CYCLES, color="grey", lw=0.8, ls=":")
    ax.set_ylabel(f"RSS - RSS at cycle {WARMUP_CYCLES} (KiB)")
    ax.legend(fontsize=8)
    extras = " + ".join(n for n in ("ros2", "foxglove") if result.options[n])
    ax.set_title(f"ddrt run over {result.options['cycles']} command cycles" + (f" ({extras})" if extras else ""),
                 fontsize=10)
    d = result.samples["daemon"]
    ax2.plot([x.cycle for x in d], [x.fds for x in d], label="daemon fds")
    ax2.plot([x.cycle for x in d], [x.threads for x in d], label="daemon threads")
    ax2.set_xlabel("command cycles")
    ax2.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=80)
    plt.close(fig)
    return True


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.soak", description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=1000)
    ap.add_argument("--every", type=int, default=10, help="sample every N cycles (default 10)")
    ap.add_argument("--ros2", action="store_true", help="enable the ROS 2 bridge")
    ap.add_argument("--foxglove", action="store_true", help="enable the Foxglove server, with one client")
    ap.add_argument("--limit", type=float, default=RSS_LIMIT_KB_PER_100, help="KiB per 100 cycles (default 100)")
    ap.add_argument("--plot", type=FsPath, help="write RSS against cycles here (PNG; needs matplotlib)")
    ap.add_argument("--json", type=FsPath, help="write every sample here")
    args = ap.parse_args(argv)
    if args.cycles < WARMUP_CYCLES + 2 * args.every or args.every < 1:
        ap.error(f"--cycles must be at least {WARMUP_CYCLES} + two samples (--every {args.every})")
    try:
        result = soak(args.cycles, args.every, args.ros2, args.foxglove)
    except RuntimeError as exc:
        print(f"bench.soak: {exc}", file=sys.stderr)
        return 2
    found = trends(result)
    print("\n".join(render(result, found)))
    if args.json:
        args.json.write_text(json.dumps({"options": result.options, "seconds": result.seconds,
                                         "refused": result.refused,
                                         "samples": {k: [asdict(s) for s in v] for k, v in result.samples.items()},
                                         "trends": {k: asdict(t) for k, t in found.items()}}, indent=1))
    if args.plot and not plot(result, args.plot):
        print("bench.soak: no plot (matplotlib is not installed)", file=sys.stderr)
    bad = [f"{name}: {f}" for name, t in found.items() if name not in SHORT_LIVED for f in t.failures(args.limit)]
    for b in bad:
        print("FAIL", b)
    print("PASS" if not bad else "FAIL")
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
