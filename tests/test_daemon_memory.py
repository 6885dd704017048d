"""The daemon's memory over many commands: with the collector stopped (rt.freeze_gc), what
each command leaves in the interpreter's free lists is freed by rt.GcSweeper, so a few hundred
command cycles (drive, stop, status, reload, estop, reset, a path followed) on a daemon's loop
in process leave the traced memory flat; unswept, the same cycles grow it. Strings interned
and dropped after rt.settle_interned (as each reload's path parts are) leave it flat too;
unsettled, the interned table doubles once. bench/soak.py measures the real `ddrt run`
over its socket."""

from __future__ import annotations

import gc
import subprocess
import sys
import tracemalloc
from collections.abc import Iterator
from pathlib import Path

import pytest

from ddrt.path import load_path
from ddrt.path.spec import speed_limits
from ddrt.runtime import rt
from tests.support.drive_rigs import DaemonRig

WARMUP = 40
CYCLES = 300
BOUND_BYTES = 64 * 1024  # over 260 cycles: 250 bytes a cycle at most (unswept: several KB)
PATH = {"shape": "circle", "radius": 0.3, "speed": 0.2}


@pytest.fixture
def frozen_gc() -> Iterator[None]:
    """The daemon's collector regime for the test, restored after it."""
    rt.freeze_gc()
    try:
        yield
    finally:
        gc.unfreeze()
        gc.enable()
        gc.collect()


def _cycle(rig: DaemonRig) -> None:
    d = rig.d
    d.loop.follow(load_path(PATH, speed_limits(d.cfg)))
    rig.ticks(10)
    assert d.handle({"cmd": "stop"})["ok"]
    rig.ticks(60)
    assert d.handle({"cmd": "drive", "v": 0.1, "omega": 0.0})["ok"]
    rig.ticks(10)
    assert d.handle({"cmd": "status"})["ok"]
    assert d.reload()["ok"]
    assert d.handle({"cmd": "estop"})["ok"]
    rig.ticks(2)
    assert d.handle({"cmd": "reset"})["ok"], d.loop.state
    rig.ticks(2)


def _traced_growth(tmp_path: Path, sweep: bool) -> int:
    tmp_path.mkdir()
    rig = DaemonRig(tmp_path)
    sweeper = rt.GcSweeper()
    try:
        tracemalloc.start(1)
        try:
            for i in range(CYCLES):
                _cycle(rig)
                if sweep:
                    sweeper.maybe()
                if i == WARMUP - 1:
                    base = tracemalloc.get_traced_memory()[0]
            return tracemalloc.get_traced_memory()[0] - base
        finally:
            tracemalloc.stop()
    finally:
        rig.d.hal.close()


@pytest.mark.slow
def test_command_cycles_leave_the_traced_memory_flat(tmp_path: Path, frozen_gc: None) -> None:
    swept = _traced_growth(tmp_path / "swept", sweep=True)
    unswept = _traced_growth(tmp_path / "unswept", sweep=False)
    assert swept < BOUND_BYTES, f"{swept} bytes over {CYCLES - WARMUP} cycles"
    assert unswept > 4 * BOUND_BYTES  # the check can fail: without the sweep the free lists fill


def test_the_sweeper_collects_only_when_the_blocks_grew() -> None:
    sweeper = rt.GcSweeper(threshold=100)
    assert not sweeper.maybe() and sweeper.sweeps == 0
    kept = [(i, str(i)) for i in range(500)]  # 1000 blocks and more
    assert sweeper.maybe() and sweeper.sweeps == 1
    assert not sweeper.maybe()  # the new level is the base
    del kept


CHURN = """
import sys, tracemalloc
import ddrt.service.daemon  # the daemon's modules: its live interned strings
from ddrt.runtime import rt
tracemalloc.start()
if {settle}:
    rt.settle_interned()
base = tracemalloc.get_traced_memory()[0]
for i in range(30000):  # what reloads do, a few path parts each, over days
    sys.intern(f"path part {{i}}")
print(tracemalloc.get_traced_memory()[0] - base)
"""


def _churn_growth(settle: bool) -> int:
    out = subprocess.run([sys.executable, "-c", CHURN.format(settle=settle)], capture_output=True, text=True,
                         cwd=Path(__file__).resolve().parents[1], timeout=120, check=True)
    return int(out.stdout.split()[-1])


def test_interned_strings_dropped_after_start_up_leave_the_memory_flat() -> None:
    settled = _churn_growth(settle=True)
    unsettled = _churn_growth(settle=False)
    assert settled < 64 * 1024, f"{settled} bytes after 30000 strings interned and dropped"
    assert unsettled > 256 * 1024  # the check can fail: unsettled, the table doubles on the way
