"""The ROS 2 bridge cannot cost the loop a tick: a `ddrt run` daemon on the simulated robot
at 200 Hz with `daemon.ros2.enabled`, one fresh daemon per phase, `--duration` seconds each:

- no bridge: `daemon.ros2.enabled: false`, what the machine alone costs the loop;
- baseline: the bridge up, no ROS 2 peer;
- flood: a process publishes geometry_msgs/Twist on /cmd_vel at 10 kHz (cyclonedds, reliable,
  depth 10, as rclpy would), alternating two commands: the velocity mode runs on them;
- slow subscriber: a process subscribes to /odom, /tf, /imu/data_raw and /diagnostics
  (reliable, depth 10) and is stopped (SIGSTOP) once matched, for the whole phase;
- stalled, then vanished bridge: the bridge process itself is stopped (its datagram buffer
  fills: the daemon's non-blocking sends fail and count drops) for half the phase, then
  killed (SIGKILL: the daemon's supervisor starts it again).

Missed ticks, lateness and compute are the daemon's own (`--stats-json`). The daemon follows
the config's path in every phase but the flood (where /cmd_vel drives it).

    python -m bench.ros2_flood [--duration 60] [--json FILE]

Beside each phase, for the same seconds, bench/machine_stalls.py's bare probe (one SCHED_FIFO
thread on the same 200 Hz grid, no work, no GIL to share) counts the ticks the machine itself
misses: where the daemon misses no more than the probe, the misses are the machine's.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import yaml

from bench.common import REPO, child_env, spawn_daemon
from bench.machine_stalls import probe_result, start_probe

PHASES = ("no bridge", "baseline", "flood", "slow subscriber", "stalled, then vanished bridge")
FLOOD_HZ = 10_000.0


def write_config(workdir: Path, domain: int, enabled: bool = True) -> Path:
    cfg = {"extends": str(REPO / "configs" / "sim.yaml"),
           "daemon": {"telemetry_dir": str(workdir / "tel"), "rt_priority": 10,
                      "ros2": {"enabled": enabled, "domain_id": domain}},
           "estimator": {"calibration_s": 0.5},
           "path": str(REPO / "configs" / "paths" / "figure8_slow.yaml")}
    path = workdir / "cfg.yaml"
    path.write_text(yaml.safe_dump(cfg, sort_keys=False))
    return path


def bridge_pid(daemon_pid: int) -> int | None:
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            stat = Path(f"/proc/{entry}/stat").read_text()
            cmd = Path(f"/proc/{entry}/cmdline").read_bytes()
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        if ppid == daemon_pid and b"ddrt.ros2" in cmd:
            return int(entry)
    return None


def wait_bridge(daemon: subprocess.Popen, timeout: float = 60.0) -> int:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        pid = bridge_pid(daemon.pid)
        if pid is not None:
            return pid
        time.sleep(0.2)
    raise RuntimeError("the daemon did not start its ROS 2 bridge")


def child(role: str, domain: int, seconds: float) -> int:
    """The ROS 2 peer of a phase (run in its own process)."""
    from ddrt.ros2.idl import msg
    from ddrt.ros2.node import TF, Node

    node = Node(f"bench_{role}", "/", domain)
    if role == "flood":
        w = node.writer("cmd_vel", "geometry_msgs/msg/Twist")
        node.announce()
        time.sleep(2.0)
        twist = msg("geometry_msgs/msg/Twist")
        cmds = [twist(), twist()]
        cmds[0].linear.x, cmds[0].angular.z = 0.2, 0.5
        cmds[1].linear.x, cmds[1].angular.z = 0.15, -0.5
        t0 = time.monotonic()
        n = 0
        period = 1.0 / FLOOD_HZ
        while (now := time.monotonic()) - t0 < seconds:
            target = int((now - t0) / period) + 1
            while n < target:
                w.write(cmds[(n // 20000) % 2])  # a new command every 2 s
                n += 1
            time.sleep(0.0005)
        print(json.dumps({"sent": n, "seconds": time.monotonic() - t0}), flush=True)
        return 0
    readers = [node.reader("odom", "nav_msgs/msg/Odometry"), node.reader("/tf", "tf2_msgs/msg/TFMessage", TF),
               node.reader("imu/data_raw", "sensor_msgs/msg/Imu"),
               node.reader("/diagnostics", "diagnostic_msgs/msg/DiagnosticArray")]
    node.announce()
    got = 0
    t0 = time.monotonic()
    while got == 0 and time.monotonic() - t0 < 30.0:
        got = sum(len(r.take(N=10)) for r in readers)
        time.sleep(0.05)
    print(json.dumps({"matched": got > 0}), flush=True)
    time.sleep(seconds + 60.0)  # stopped meanwhile
    return 0


def run_phase(phase: str, duration: float, domain: int) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="ddrt-r2b-", dir="/tmp") as tmp:
        work = Path(tmp)
        cfg = write_config(work, domain, enabled=phase != "no bridge")
        stats = work / "stats.json"
        sock = str(work / "ctl.sock")
        args = ["--socket", sock, "--duration", str(duration + 5.0), "--stats-json", str(stats)]
        if phase != "flood":
            args.append("--follow")
        with open(work / "stderr.log", "wb") as err:
            daemon = spawn_daemon(cfg, *args, stderr=err)
        peer = bare = None
        extra: dict[str, Any] = {}
        try:
            bpid = wait_bridge(daemon) if phase != "no bridge" else 0
            # The machine's own misses in the same seconds: bench/machine_stalls.py's bare loop.
            bare = start_probe(duration)
            if phase == "flood":
                peer = subprocess.Popen([sys.executable, "-m", "bench.ros2_flood", "--child", "flood",
                                         "--domain", str(domain), "--duration", str(duration)],
                                        cwd=REPO, env=child_env(), stdout=subprocess.PIPE, text=True)
            elif phase == "slow subscriber":
                peer = subprocess.Popen([sys.executable, "-m", "bench.ros2_flood", "--child", "slow",
                                         "--domain", str(domain), "--duration", str(duration)],
                                        cwd=REPO, env=child_env(), stdout=subprocess.PIPE, text=True)
                assert peer.stdout is not None
                extra.update(json.loads(peer.stdout.readline()))
                peer.send_signal(signal.SIGSTOP)
            elif phase.startswith("stalled"):
                time.sleep(3.0)
                os.kill(bpid, signal.SIGSTOP)
                time.sleep(duration / 2.0)
                os.kill(bpid, signal.SIGKILL)
                extra["restarted"] = wait_bridge(daemon, 30.0) != bpid
            daemon.wait(duration + 120.0)
            probe = probe_result(bare, 120.0)
            extra["probe_missed"], extra["probe_late_max_us"] = probe["missed"], probe["late_max_us"]
            if phase == "flood" and peer is not None:
                out, _ = peer.communicate(timeout=60.0)
                extra.update(json.loads(out.strip().splitlines()[-1]))
        finally:
            for p in (peer, bare):
                if p is not None and p.poll() is None:
                    p.kill()
                    p.wait()
            if daemon.poll() is None:
                daemon.kill()
                daemon.wait()
        s = json.loads(stats.read_text())
        log = (work / "stderr.log").read_text(errors="replace")
        extra["drops"] = sum("dropped)" in ln for ln in log.splitlines())
        return {"phase": phase, "exit": daemon.returncode, "ticks": s["ticks"], "missed": s["missed"],
                "late_p99_us": s["lateness_us"]["p99"], "late_max_us": s["lateness_us"]["max"],
                "compute_p99_us": s["compute_us"]["p99"], "final_state": s["final_state"], **extra}


def render(rows: list[dict[str, Any]], duration: float) -> list[str]:
    lines = ["| phase | ticks | missed ticks | lateness p99 (us) | lateness max (us) | tick compute p99 (us) | "
             "end state | bare probe: missed, lateness max (us) |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        probe = f"{r['probe_missed']}, {r['probe_late_max_us']:.0f}" if "probe_missed" in r else "-"
        lines.append(f"| {r['phase']} | {r['ticks']} | {r['missed']} | {r['late_p99_us']:.0f} | "
                     f"{r['late_max_us']:.0f} | {r['compute_p99_us']:.0f} | {r['final_state']} | {probe} |")
    flood = next((r for r in rows if r["phase"] == "flood"), None)
    if flood and "sent" in flood:
        lines += ["", f"The flood published {flood['sent']} Twist messages in {flood['seconds']:.1f} s "
                      f"({flood['sent'] / flood['seconds']:.0f} /s)."]
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.ros2_flood", description=__doc__.split("\n\n")[0])
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--json")
    ap.add_argument("--only", choices=PHASES)
    ap.add_argument("--child", choices=("flood", "slow"), help=argparse.SUPPRESS)
    ap.add_argument("--domain", type=int, default=0, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        return child(args.child, args.domain, args.duration)
    domain = 150 + os.getpid() % 80
    rows = []
    for phase in PHASES if args.only is None else (args.only,):
        t0 = time.monotonic()
        rows.append(run_phase(phase, args.duration, domain))
        print(f"{phase}: {json.dumps(rows[-1])} ({time.monotonic() - t0:.0f} s)", file=sys.stderr, flush=True)
    print("\n".join(render(rows, args.duration)))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
