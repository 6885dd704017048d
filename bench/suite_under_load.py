"""`python -m bench.suite_under_load [--runs 5] [--hogs 1] [-- PYTEST ARGS]`: the README's test
command, run again and again with CPU-bound processes beside it.

A suite that passes only on a quiet machine is a red CI waiting to happen. This runs the whole
suite `--runs` times in a row, each time beside `--hogs` processes that spin on a core, and
stops at the first run that fails (its output is kept in the log file named). Each run's
closing line and wall time are printed; exit status 0 only when every run passed.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Sequence

REPO = Path(__file__).resolve().parents[1]
HOG = "while True: pass"


def start_hogs(n: int) -> list[subprocess.Popen]:
    """`n` processes that each keep one core busy until killed."""
    return [subprocess.Popen([sys.executable, "-c", HOG], stdin=subprocess.DEVNULL) for _ in range(n)]


def stop_hogs(hogs: list[subprocess.Popen]) -> None:
    for p in hogs:
        p.kill()
    for p in hogs:
        p.wait()


def closing_line(output: str) -> str:
    """pytest's summary line ("N passed, ..."), or the last line when there is none."""
    lines = [ln.strip("= ").strip() for ln in output.strip().splitlines() if ln.strip()]
    for ln in reversed(lines):
        if " passed" in ln or " failed" in ln or " error" in ln:
            return ln
    return lines[-1] if lines else "(no output)"


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.suite_under_load", description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5, help="full runs in a row (default 5)")
    ap.add_argument("--hogs", type=int, default=1, help="CPU-bound processes beside each run (default 1)")
    ap.add_argument("--log-dir", default="out/suite_under_load", help="each run's output (default out/suite_under_load)")
    ap.add_argument("pytest_args", nargs="*", help="extra pytest arguments after --")
    args = ap.parse_args(argv)
    if args.runs < 1 or args.hogs < 0:
        ap.error("--runs must be >= 1 and --hogs >= 0")
    log_dir = Path(args.log_dir)
    log_dir.mkdir(parents=True, exist_ok=True)
    env = dict(os.environ)
    failed = 0
    for i in range(1, args.runs + 1):
        hogs = start_hogs(args.hogs)
        t0 = time.monotonic()
        try:
            proc = subprocess.run([sys.executable, "-m", "pytest", *args.pytest_args], cwd=REPO, env=env,
                                  stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        finally:
            stop_hogs(hogs)
        wall = time.monotonic() - t0
        log = log_dir / f"run{i}.log"
        log.write_text(proc.stdout, encoding="utf-8")
        load = " ".join(f"{x:.2f}" for x in os.getloadavg())
        print(f"run {i}/{args.runs}: exit {proc.returncode}, {closing_line(proc.stdout)}, {wall / 60:.1f} min "
              f"wall, load average {load} ({log})", flush=True)
        if proc.returncode != 0:
            failed += 1
            break
    print("all runs passed" if not failed else f"stopped at run {i}: it failed (see {log})")
    return 0 if not failed else 1


if __name__ == "__main__":
    sys.exit(main())
