"""The hold/recovery rules (ddrt/loop/hold.py) on their own: `HoldMachine` driven with
synthetic gaps, sample times and at-rest flags, no loop and no robot. The closed-loop
behaviour (freezes, stalls, read timeouts on the simulated robot) is tests/test_recovery.py's."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import pytest

from ddrt.config import load_config
from ddrt.core.estimator import EstimatorHealth
from ddrt.loop.hold import RECOVER_FRESH_TICKS, HoldBounds, HoldMachine
from ddrt.loop.states import LoopState

SIM_YAML = Path(__file__).resolve().parents[1] / "configs" / "sim.yaml"
PERIOD = 0.005
MAX_GAP = 0.05


@dataclass
class Gaps:
    """What the rules read from the estimator, set by hand."""

    blind_s: float = 0.0
    gap_s: float = 0.0
    stall_s: float = 0.0
    max_gap: float = MAX_GAP
    health: EstimatorHealth = field(default_factory=EstimatorHealth)


def bounds(**changes: float) -> HoldBounds:
    b = dict(period_s=PERIOD, latch_s=0.5, zero_after_s=0.1, stale_ticks=20, max_holds=5, hold_window_s=60.0)
    b.update(changes)
    return HoldBounds(**b)  # type: ignore[arg-type]


def held(machine: HoldMachine, cause: str = "sensors stale", t: float = 0.0, stall: bool = False,
         blind_s: float = 0.06) -> HoldMachine:
    assert machine.begin(cause, t, stall, LoopState.FOLLOWING, blind_s) == ""
    return machine


# ------------------------------------------------------------------ when to hold, when to latch

def test_fresh_samples_on_time_are_no_reason_to_hold_or_latch() -> None:
    m = HoldMachine(bounds())
    assert m.transient(Gaps()) == "" and m.persistent(Gaps()) == ""
    # Blind for a few ticks, within max_gap and stale_ticks: still no hold.
    gaps = Gaps(blind_s=0.03)
    gaps.health.stale_ticks = 6
    assert m.transient(gaps) == "" and m.persistent(gaps) == ""
    assert m.counters.latched == 0 and m.active is None


@pytest.mark.parametrize("gaps, read_error, expected", [
    (Gaps(gap_s=0.08), "", "sensor gap of 80.0 ms"),
    (Gaps(gap_s=0.159, stall_s=0.159), "", "sensor gap of 159.0 ms (the loop did not run)"),
    (Gaps(blind_s=0.06), "", "ms without a fresh sample"),
    (Gaps(), "STATE stream stale for 52 ms", "sensor read timed out: STATE stream stale for 52 ms"),
])
def test_each_transient_cause_is_named(gaps: Gaps, read_error: str, expected: str) -> None:
    m = HoldMachine(bounds())
    assert expected in m.transient(gaps, read_error)


def test_stale_ticks_alone_are_a_transient_fault() -> None:
    m = HoldMachine(bounds(stale_ticks=4))
    gaps = Gaps(blind_s=0.02)  # within max_gap, but 4 stale samples in a row
    gaps.health.stale_ticks = 4
    assert m.transient(gaps) == "sensors stale for 4 ticks (20 ms without a fresh sample)"
    gaps.health.stale_ticks = 3
    assert m.transient(gaps) == ""


def test_blind_for_fault_latch_s_latches_and_counts() -> None:
    m = HoldMachine(bounds(latch_s=0.5))
    assert m.persistent(Gaps(blind_s=0.499)) == ""
    assert m.counters.latched == 0
    why = m.persistent(Gaps(blind_s=0.5))
    assert why.startswith("sensors stale for 0 ticks: 0.500 s without a fresh sample")
    assert "estimator.fault_latch_s = 0.5 s" in why and m.counters.latched == 1
    assert m.persistent(Gaps(blind_s=0.7), "I2C timeout").startswith("sensor read timed out (I2C timeout): 0.700 s")
    assert m.counters.latched == 2


# ------------------------------------------------------------------ a hold from start to end

def test_a_braking_hold_ends_after_ten_fresh_samples_at_rest_and_resumes() -> None:
    m = held(HoldMachine(bounds()), cause="sensor gap of 60.0 ms", blind_s=0.06)
    h = m.active
    assert h is not None and h.resume_to == LoopState.FOLLOWING and not h.zeroed and m.braking
    assert (m.counters.holds, m.counters.stalls, m.counters.zeroed) == (1, 0, 0)
    assert m.counters.last_cause == "sensor gap of 60.0 ms"
    # Still blind: the hold goes on; fresh samples while the robot still moves do not end it.
    for _ in range(5):
        assert m.tick(0.06) is False and not m.recovered(False, True)
    for _ in range(RECOVER_FRESH_TICKS + 3):
        m.tick(0.0)
        assert not m.recovered(True, False)
    # One stale sample restarts the count: the next nine fresh ones at rest are not enough.
    m.tick(0.0)
    assert not m.recovered(False, True)
    for _ in range(RECOVER_FRESH_TICKS - 1):
        m.tick(0.0)
        assert not m.recovered(True, True)
    m.tick(0.0)
    assert m.recovered(True, True)
    ticks = 5 + RECOVER_FRESH_TICKS + 3 + 1 + RECOVER_FRESH_TICKS
    assert h.ticks == ticks and m.counters.longest_hold_s == pytest.approx(ticks * PERIOD)
    assert m.end(resumed=True) is h and m.active is None
    assert (m.counters.resumes, m.counters.waits, m.counters.latched) == (1, 0, 0)


def test_blind_beyond_the_motors_watchdog_zeroes_the_motors_once() -> None:
    m = held(HoldMachine(bounds(zero_after_s=0.1)), blind_s=0.06)
    assert m.braking
    assert m.tick(0.099) is False and m.braking
    assert m.tick(0.1) is True and not m.braking  # the loop zeroes the motors now
    assert m.tick(0.2) is False and m.counters.zeroed == 1  # and only once
    # Already blind that long when the hold begins: zeroed from the start, counted once.
    m2 = held(HoldMachine(bounds(zero_after_s=0.1)), blind_s=0.15)
    assert m2.active is not None and m2.active.zeroed and not m2.braking
    m2.zero()
    assert m2.counters.zeroed == 1


def test_a_stop_asked_during_the_hold_ends_it_stopped() -> None:
    m = held(HoldMachine(bounds()))
    m.stop_when_over()
    assert m.active is not None and m.active.resume_to == LoopState.STOPPING
    m.end(resumed=False)
    assert (m.counters.resumes, m.counters.waits) == (0, 1)
    m.stop_when_over()  # no hold: nothing to do
    assert m.active is None


def test_a_hold_that_does_not_end_latches_after_its_bound() -> None:
    # fault_latch_s + twice the time to stop from v_max at decel + 1 s: 0.5 + 2 * 0.5 / 1.0 + 1 = 2.5 s.
    m = held(HoldMachine(bounds(latch_s=0.5)), cause="sensors stale for 20 ticks")
    for _ in range(round(2.5 / PERIOD)):
        m.tick(0.0)
    assert m.overdue(0.5, 1.0) == "" and m.counters.latched == 0
    m.tick(0.0)
    assert m.overdue(0.5, 1.0) == ("sensors stale for 20 ticks: the hold did not end within 2.5 s "
                                   "(sensors back and the robot at rest)")
    assert m.counters.latched == 1


# ------------------------------------------------------------------ holds that keep coming

def test_more_than_max_holds_within_the_window_latch() -> None:
    m = HoldMachine(bounds(max_holds=2, hold_window_s=60.0))
    for t in (10.0, 20.0):
        held(m, t=t).end(resumed=True)
    why = m.begin("sensors stale", 30.0, False, LoopState.FOLLOWING, 0.06)
    assert why == "sensors stale: 3 holds within 60 s (estimator.max_holds = 2)"
    assert m.active is None and m.counters.holds == 2 and m.counters.latched == 1


def test_holds_further_apart_than_the_window_never_latch() -> None:
    m = HoldMachine(bounds(max_holds=2, hold_window_s=60.0))
    for t in (0.0, 40.0, 80.0, 120.0, 160.0):  # never more than two within 60 s
        held(m, t=t).end(resumed=True)
    assert m.counters.holds == 5 and m.counters.latched == 0 and m.counters.resumes == 5


def test_loop_stalls_are_held_every_time_and_never_latch() -> None:
    m = HoldMachine(bounds(max_holds=2, hold_window_s=60.0))
    for i in range(10):
        held(m, cause="sensor gap of 159.0 ms (the loop did not run)", t=float(i), stall=True).end(resumed=True)
    assert (m.counters.holds, m.counters.stalls, m.counters.latched) == (10, 10, 0)
    # A hold on the sensors' account after them is the first of its kind in the window.
    assert m.begin("sensors stale", 10.0, False, LoopState.DRIVING, 0.06) == ""
    assert m.active is not None and m.active.resume_to == LoopState.DRIVING


def test_cancel_forgets_the_hold_uncounted() -> None:
    m = held(HoldMachine(bounds()))
    m.cancel()
    assert m.active is None and not m.braking
    assert (m.counters.holds, m.counters.resumes, m.counters.waits) == (1, 0, 0)


# ------------------------------------------------------------------ the bounds from the config

def test_bounds_come_from_the_estimator_section_the_hal_and_on_recover() -> None:
    cfg = load_config(SIM_YAML, {"estimator": {"fault_latch_s": 0.8, "stale_ticks": 7, "max_holds": 3,
                                               "hold_window_s": 30.0}, "daemon": {"on_recover": "wait"}})
    b = HoldBounds.of(cfg, 0.25, PERIOD)
    assert (b.latch_s, b.stale_ticks, b.max_holds, b.hold_window_s) == (0.8, 7, 3, 30.0)
    assert b.zero_after_s == 0.25 and b.resume is False and b.period_s == PERIOD  # the HAL's watchdog
    assert HoldBounds.of(cfg, None, PERIOD).zero_after_s == 0.1  # no watchdog: the MCU's default
    own = load_config(SIM_YAML, {"estimator": {"zero_motors_after_s": 0.04}})
    assert HoldBounds.of(own, 0.25, PERIOD).zero_after_s == 0.04 and HoldBounds.of(own, 0.25, PERIOD).resume
