"""`python -m bench.sim_instructions [--repo A [--repo B ...]]`: machine instructions per tick of `ddrt sim`.

CPU time on this shared virtual machine moves by 2x over hours and by 10-20 % between two runs
a minute apart, so a code change of a few percent cannot be seen in it. The number of machine
instructions a run executes does not depend on the machine's load: counted by valgrind's
cachegrind (no cache simulation), with address-space randomisation off (`setarch -R`) and a
fixed string hash seed, two runs of the same code agree to about 0.1 %.

Each checkout's `run_sim` runs the 0.8 m/s figure-eight (figure8_fast.yaml, as
bench/sim_paired.py) twice, for SHORT and for LONG simulated seconds, telemetry streamed to a
temporary CSV; the difference of the two counts over the difference of their controller ticks
is the steady-state cost of a tick, everything in (plant, tick, telemetry row), start-up out.
Without `--no-cpu` the same pair also runs without valgrind, for CPU time, which gives this
hour's instructions per CPU second and so the tick cost the simulator's 200x target (at most
25 us of CPU a tick at 200 Hz) allows in instructions at that rate.

The simulated robot's own share is counted the same way, by a loop that does only what the
simulator adds around the robot's tick (SimHal's sleep_until, read and write, the truth and a
row appended, as run_sim does) with a fixed command: what is left of a tick is the code that
also runs on the robot (the tick) and telemetry.csv.

Needs valgrind (apt-get install valgrind); not part of CI.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path as FsPath

from bench.common import child_env
from bench.sim_paired import RUN_SIM_CHILD
from bench.sim_scaling import figure8_path

REPO = FsPath(__file__).resolve().parent.parent
TARGET_US = 1e6 / (200.0 * 200.0)  # 200x real time at 200 Hz is 25 us of CPU a tick

# The simulator's part of a tick alone: run_sim's loop without ControlLoop.tick (a fixed duty).
_ROBOT_ONLY = r"""
import json, sys
from array import array
from ddrt.config import load_config
from ddrt.path.spec import resolve_path
from hal.registry import open_hal
config, path_file, duration = sys.argv[1], sys.argv[2], float(sys.argv[3])
cfg = load_config(config)
path = resolve_path(cfg, path_file)
hal = open_hal(cfg, start=path.start_pose, seed=1)
period = 1.0 / cfg.controller.rate_hz
n = int(round(duration / period))
rows = array("d")
extend, truth, row = rows.extend, hal.robot.truth, array("d", [0.0] * 47)
sleep_until, read, write = hal.sleep_until, hal.read, hal.write
for i in range(n):
    sleep_until((i + 1) * period)
    read()
    write(0.30, 0.31)
    extend(truth())
    extend(row)
    if len(rows) > 400000:
        del rows[:]
print(json.dumps({"ticks": n, "cpu_s": 0.0}))
"""

_IREFS = re.compile(r"I\s+refs:\s+([\d,]+)")


class InstructionCountError(RuntimeError):
    """valgrind is missing, or a run failed or printed no count."""


@dataclass(frozen=True)
class Count:
    """One run: controller ticks, machine instructions of the whole process, CPU s of run_sim."""

    ticks: int
    instructions: int
    cpu_s: float


def parse_irefs(stderr: str) -> int:
    """The instruction count cachegrind prints at exit (`==pid== I   refs:   1,234,567`)."""
    found = _IREFS.findall(stderr)
    if not found:
        raise InstructionCountError("valgrind printed no 'I refs' line: " + stderr[-300:])
    return int(found[-1].replace(",", ""))


def valgrind_command() -> list[str]:
    """cachegrind without its cache model, under `setarch -R` where there is one."""
    vg = shutil.which("valgrind")
    if vg is None:
        raise InstructionCountError("valgrind is not installed (apt-get install valgrind)")
    cmd = [vg, "--tool=cachegrind", "--cache-sim=no", "--cachegrind-out-file=/dev/null"]
    setarch = shutil.which("setarch")
    return ([setarch, os.uname().machine, "-R"] + cmd) if setarch else cmd


def run_child(repo: FsPath, path_file: FsPath, duration: float, counted: bool, robot_only: bool = False) -> Count:
    """One run_sim of `repo`'s ddrt in a child python (`robot_only`: the simulated robot's part
    alone), under valgrind when `counted`."""
    config = repo / "configs/scenarios/figure8_fast.yaml"
    argv = [sys.executable, "-c", _ROBOT_ONLY if robot_only else RUN_SIM_CHILD, str(config), str(path_file), f"{duration:g}"]
    if counted:
        argv = valgrind_command() + argv
    env = child_env(repo, OPENBLAS_NUM_THREADS="1", PYTHONHASHSEED="0")
    p = subprocess.run(argv, cwd=repo, env=env, capture_output=True, text=True, timeout=3600)
    if p.returncode != 0:
        raise InstructionCountError(f"run_sim in {repo} failed (exit {p.returncode}): {p.stderr[-400:]}")
    out = json.loads(p.stdout.strip().splitlines()[-1])
    return Count(int(out["ticks"]), parse_irefs(p.stderr) if counted else 0, float(out["cpu_s"]))


def per_tick(short: Count, long: Count, field: str) -> float:
    """The steady-state cost of one tick: the two runs' difference over their ticks'."""
    dt = long.ticks - short.ticks
    if dt <= 0:
        raise InstructionCountError(f"the long run has no more ticks than the short one ({long.ticks} <= {short.ticks})")
    return (getattr(long, field) - getattr(short, field)) / dt


def pair(repo: FsPath, path_file: FsPath, short_s: float, long_s: float, counted: bool,
         robot_only: bool = False) -> tuple[Count, Count]:
    """The short and the long run of one kind (see run_child)."""
    return (run_child(repo, path_file, short_s, counted, robot_only),
            run_child(repo, path_file, long_s, counted, robot_only))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.sim_instructions", description=__doc__.split("\n")[0])
    ap.add_argument("--repo", action="append", type=FsPath, help="a checkout (default: this one); repeat to compare")
    ap.add_argument("--short", type=float, default=2.0, help="simulated s of the short run")
    ap.add_argument("--long", type=float, default=22.0, help="simulated s of the long run")
    ap.add_argument("--laps", type=int, default=12, help="laps of the figure-eight (enough for --long)")
    ap.add_argument("--no-cpu", action="store_true", help="count instructions only (no timed runs)")
    args = ap.parse_args(argv)
    if not 0.0 < args.short < args.long or args.laps < 1:
        ap.error("0 < --short < --long and --laps >= 1")
    repos = [r.resolve() for r in (args.repo or [REPO])]
    try:
        with tempfile.TemporaryDirectory(prefix="ddrt-instructions-") as tmp:
            path_file = figure8_path(args.laps, FsPath(tmp) / "figure8.yaml")
            results = []
            for repo in repos:
                short, long = pair(repo, path_file, args.short, args.long, counted=True)
                ins = per_tick(short, long, "instructions")
                line = f"{repo}: {ins:,.0f} instructions a tick ({short.ticks} and {long.ticks} ticks)"
                if not args.no_cpu:
                    cpu = per_tick(*pair(repo, path_file, args.short, args.long, counted=False), "cpu_s")
                    rate = ins / cpu if cpu > 0.0 else float("nan")
                    line += (f"; {cpu * 1e6:.1f} us of CPU a tick now, {rate / 1e9:.2f} G instructions per CPU s, "
                             f"so 200x ({TARGET_US:.0f} us) is {rate * TARGET_US * 1e-6:,.0f} instructions a tick")
                sim = per_tick(*pair(repo, path_file, args.short, args.long, counted=True, robot_only=True),
                               "instructions")
                line += (f"\n  of which the simulated robot (SimHal, plant, truth, row gathering) {sim:,.0f}, "
                         f"the rest (the robot's tick, telemetry.csv) {ins - sim:,.0f}")
                results.append(ins)
                print(line, flush=True)
    except InstructionCountError as exc:
        print(f"sim_instructions: {exc}", file=sys.stderr)
        return 1
    for repo, ins in zip(repos[1:], results[1:]):
        print(f"{repo} / {repos[0]}: {ins / results[0]:.4f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
