"""Transient faults degrade, persistent ones latch.

A sensor gap, a short run of stale samples or a HAL read timeout that recovers brings the
robot to a controlled stop (`holding`), re-anchors the estimator and resumes the path; only a
fault that persists (`estimator.fault_latch_s`, `estimator.max_holds` in
`estimator.hold_window_s`) latches `fault`. The timing statistics count a stall as what it
was. Everything here runs in simulated time or on a manual clock, so a loaded machine cannot
change a result.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest

from ddrt.config import load_config, with_overrides
from ddrt.service.clock import ManualClock
from ddrt.service.daemon import Daemon

ROOT = Path(__file__).resolve().parents[1]
SIM_YAML = ROOT / "configs" / "sim.yaml"


# ---------------------------------------------------------------- the scheduler counts a stall


class _StallingPlant:
    """A simulated-time backend stand-in whose plant catch-up stalls once (the thread lost
    the CPU after waking) by jumping the manual clock."""

    owns_time = True

    def __init__(self, clock: ManualClock, stall_on: int, stall_s: float) -> None:
        self.clock = clock
        self.stall_on = stall_on
        self.stall_s = stall_s
        self.calls = 0

    def advance_to_wall_clock(self) -> None:
        self.calls += 1
        if self.calls == self.stall_on:
            self.clock.advance(self.stall_s)


class _StallingClock(ManualClock):
    """A wall clock whose thread is preempted right after one sleep returns: the sleep
    reports the deadline, the next reading is `stall_s` later."""

    def __init__(self, start: float, stall_on: int, stall_s: float) -> None:
        super().__init__(start)
        self.sleeps = 0
        self.stall_on = stall_on
        self.stall_s = stall_s

    def sleep_until(self, deadline: float) -> float:
        woke = super().sleep_until(deadline)
        self.sleeps += 1
        if self.sleeps == self.stall_on:
            self.t += self.stall_s  # preempted after the sleep returned `woke`
        return woke


class _FakeLoop:
    """Ticks; optionally faults on one tick, or stalls inside one tick (after its read)."""

    def __init__(self, clock: ManualClock, fault_on: int | None = None,
                 stall_in_tick_on: int | None = None, stall_s: float = 0.0) -> None:
        self.clock = clock
        self.state = "following"
        self.fault = ""
        self.row: list[float] = []
        self.ticks = 0
        self.fault_on = fault_on
        self.stall_in_tick_on = stall_in_tick_on
        self.stall_s = stall_s
        self.duty_l = self.duty_r = 0.0

    def tick(self) -> None:
        self.ticks += 1
        if self.ticks == self.stall_in_tick_on:
            self.clock.advance(self.stall_s)
        if self.ticks == self.fault_on:
            self.state = "fault"
            self.fault = "injected"


def _daemon_on(tmp_path: Path, clock: ManualClock, loop: _FakeLoop, hal: Any, duration: float) -> Daemon:
    cfg = tmp_path / "d.yaml"
    cfg.write_text(f"extends: {SIM_YAML}\ndaemon: {{telemetry_dir: {tmp_path}, socket: null}}\n")
    d = Daemon(str(cfg), duration=duration)
    d.clock = clock
    d.loop = loop  # type: ignore[assignment]
    d.hal = hal
    return d


RATE_PERIOD = 0.005  # configs/sim.yaml runs at 200 Hz
STALL_S = 0.159


def test_a_stall_after_waking_is_counted_as_late_and_missed_even_on_the_tick_that_exits(tmp_path: Path) -> None:
    """The field report: a 159 ms stall between the wake-up and the sample, and the loop
    exits on that very tick. It was counted as 3 missed ticks and 6 ms (the wake-up was on
    time); it is ~31 missed slots and ~159 ms late."""
    clock = ManualClock(100.0)
    loop = _FakeLoop(clock, fault_on=50)
    d = _daemon_on(tmp_path, clock, loop, _StallingPlant(clock, stall_on=50, stall_s=STALL_S), duration=5.0)
    d._fixed_rate_loop()
    s = d.stats.summary()
    assert d.exit_code == 1 and s["count"] == 50
    assert s["missed_ticks"] == int(STALL_S / RATE_PERIOD)  # 31 slots (155 ms of them) passed
    assert s["late_worst_us"] == pytest.approx(STALL_S * 1e6, abs=50.0)


def test_a_stall_inside_a_tick_makes_the_next_one_late(tmp_path: Path) -> None:
    clock = ManualClock(100.0)
    loop = _FakeLoop(clock, stall_in_tick_on=20, stall_s=STALL_S)
    d = _daemon_on(tmp_path, clock, loop, _StallingPlant(clock, stall_on=0, stall_s=0.0), duration=1.0)
    d._fixed_rate_loop()
    s = d.stats.summary()
    assert d.exit_code == 0
    # The next slot is served 154 ms late; the 30 after it had passed by then.
    assert s["missed_ticks"] == 30
    # The tick after the stall starts 159 - 5 ms after its own slot's deadline.
    assert s["late_worst_us"] == pytest.approx((STALL_S - RATE_PERIOD) * 1e6, abs=50.0)
    assert s["count"] + s["missed_ticks"] == round(1.0 / RATE_PERIOD) + 1  # every slot of the second, both ends


def test_a_thread_preempted_right_after_its_sleep_returns_is_late(tmp_path: Path) -> None:
    """Hardware (no simulated plant): the sleep returns on time, then the thread is off the
    CPU before it reads the sensors."""
    clock = _StallingClock(100.0, stall_on=30, stall_s=STALL_S)
    loop = _FakeLoop(clock)

    class _Hardware:
        owns_time = False

    d = _daemon_on(tmp_path, clock, loop, _Hardware(), duration=1.0)
    d._fixed_rate_loop()
    s = d.stats.summary()
    assert s["missed_ticks"] == int(STALL_S / RATE_PERIOD)
    assert s["late_worst_us"] == pytest.approx(STALL_S * 1e6, abs=50.0)
