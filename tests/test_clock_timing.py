"""Clock, scheduler, timing statistics and real-time set-up.

Real-time calls (SCHED_FIFO, mlockall) run in a subprocess so the test runner itself never
becomes a real-time process.
"""

from __future__ import annotations

import gc
import json
import math
import os
import signal
import subprocess
import sys
import textwrap
import time
import tracemalloc

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ddrt.runtime import rt
from ddrt.runtime.clock import ManualClock, MonotonicClock
from ddrt.service.timing import RateScheduler, TimingStats, percentile
from tests.support.cpu_queue import late_beyond_queue, waited_for_cpu_s
from tests.support.repo import REPO

SLACK = 0.05  # bound on oversleeping, beyond the time the thread waited for a CPU


# ----- MonotonicClock ----------------------------------------------------------------------

@pytest.mark.parametrize("use_libc", [True, False])
def test_sleep_until_wakes_at_deadline_never_before(use_libc: bool) -> None:
    clock = MonotonicClock(use_libc=use_libc)
    if use_libc:
        assert clock.uses_clock_nanosleep  # Linux with glibc: the absolute sleep is used
    for delay in (0.001, 0.003, 0.0071, 0.02):
        deadline = clock.now() + delay
        woke, late = late_beyond_queue(clock.sleep_until, deadline)
        after = time.monotonic()
        assert woke >= deadline, f"woke {deadline - woke:.6f} s early"
        assert late < SLACK
        assert woke <= after  # the returned value is a real reading, not the deadline


def test_sleep_until_past_deadline_returns_at_once() -> None:
    clock = MonotonicClock()
    t0 = time.monotonic()
    q0 = waited_for_cpu_s()
    woke = clock.sleep_until(t0 - 1.0)
    assert t0 <= woke < t0 + 0.005 + (waited_for_cpu_s() - q0)


def test_sleep_until_rejects_nan() -> None:
    with pytest.raises(ValueError, match="deadline"):
        MonotonicClock().sleep_until(math.nan)


def test_sleep_until_restarts_after_signal() -> None:
    """A signal interrupts clock_nanosleep (EINTR); the sleep must resume, not end early.
    The alarm comes 10 ms into a 0.5 s sleep; should a loaded machine delay its handler past
    the deadline, that attempt tested nothing and another is made."""
    for _attempt in range(20):
        hits: list[float] = []
        old = signal.signal(signal.SIGALRM, lambda *_: hits.append(time.monotonic()))
        try:
            clock = MonotonicClock()
            deadline = clock.now() + 0.5
            signal.setitimer(signal.ITIMER_REAL, 0.01)
            woke = clock.sleep_until(deadline)
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
            signal.signal(signal.SIGALRM, old)
        assert hits, "the alarm never fired"
        assert woke >= deadline
        if hits[0] < deadline:  # it fired during the sleep
            return
    pytest.fail("the alarm never came during the sleep")


def test_absolute_deadlines_do_not_drift() -> None:
    """50 ticks with 1 ms of work each stay on the grid start + k * period: neither the work nor
    a late wake-up moves the next deadline (a relative sleep(period) loop drifts by both, and
    would end at start + 50 * 5 ms). The slots a loaded machine made it skip are counted, and
    only they move a tick to a later slot."""
    clock = MonotonicClock()
    period = 0.004
    start = clock.now() + period
    sched = RateScheduler(period, start)
    for i in range(50):
        deadline = sched.next_deadline()
        k = (deadline - start) / period
        assert abs(k - round(k)) < 1e-6, (i, k)  # on the grid
        assert round(k) == i + sched.missed, (i, k, sched.missed)  # one slot a tick, or skipped
        woke = clock.sleep_until(deadline)
        assert woke >= deadline
        sched.account(woke)
        busy_until = woke + 0.001
        while time.monotonic() < busy_until:
            pass
    assert sched.ticks == 50


def test_manual_clock_jumps_to_deadline_and_never_goes_back() -> None:
    c = ManualClock(5.0)
    assert c.sleep_until(7.5) == 7.5 and c.now() == 7.5
    assert c.sleep_until(6.0) == 7.5
    assert c.advance(0.5) == 8.0
    with pytest.raises(ValueError, match="seconds"):
        c.advance(-1.0)


# ----- RateScheduler -----------------------------------------------------------------------

def test_scheduler_on_time_follows_exact_grid() -> None:
    start, period = 100.0, 0.005
    s = RateScheduler(period, start)
    for k in range(1000):
        d = s.next_deadline()
        assert d == start + k * period  # no accumulated rounding
        assert s.account(d + 0.1 * period) == 0
    assert s.missed == 0 and s.overruns == 0 and s.ticks == 1000


def test_scheduler_skips_missed_ticks_after_overrun() -> None:
    start, period = 10.0, 0.005
    s = RateScheduler(period, start)
    assert s.account(start + 0.0001) == 0
    d = s.next_deadline()
    assert d == pytest.approx(start + period)
    now = d + 3.5 * period  # woke 3.5 periods late
    assert s.account(now) == 3
    nxt = s.next_deadline()
    assert now < nxt <= now + period  # the next future slot, no burst
    assert nxt == pytest.approx(start + 5 * period)
    assert (s.missed, s.overruns) == (3, 1)


def test_scheduler_huge_overrun_is_one_jump() -> None:
    s = RateScheduler(0.005, 0.0)
    skipped = s.account(1000 * 0.005 + 0.0025)
    assert skipped == 1000
    assert 5.0025 < s.next_deadline() <= 5.0075


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(min_value=0.0, max_value=20.0), min_size=1, max_size=30),
       st.floats(min_value=1e-4, max_value=0.1))
def test_scheduler_properties(lates: list[float], period: float) -> None:
    """For any wake-up delays: the next deadline is on the grid, in the future, within one
    period of now, and the skipped count is the number of grid slots jumped over."""
    start = 3.0
    s = RateScheduler(period, start)
    total = 0
    for late in lates:
        d = s.next_deadline()
        now = d + late * period
        skipped = s.account(now)
        nxt = s.next_deadline()
        k = (nxt - start) / period
        assert abs(k - round(k)) < 1e-6
        assert nxt > now
        assert nxt - now <= period * (1 + 1e-9)
        slots_jumped = round((nxt - d) / period) - 1
        assert skipped == slots_jumped
        total += skipped
    assert s.missed == total


@pytest.mark.parametrize("bad", [0.0, -0.005, math.nan, math.inf, True])
def test_scheduler_rejects_bad_period(bad: float) -> None:
    with pytest.raises(ValueError, match="period_s"):
        RateScheduler(bad, 0.0)


# ----- TimingStats -------------------------------------------------------------------------

@settings(max_examples=100, deadline=None)
@given(st.lists(st.floats(min_value=-1e3, max_value=1e3), min_size=1, max_size=200),
       st.floats(min_value=0.0, max_value=100.0))
def test_percentile_matches_numpy(data: list[float], q: float) -> None:
    data.sort()
    assert percentile(data, q) == pytest.approx(float(np.percentile(data, q)), rel=1e-9, abs=1e-9)


@pytest.mark.parametrize("n", [1, 7, 1000, 2500])
def test_timing_stats_percentiles_against_numpy(n: int) -> None:
    rng = np.random.default_rng(n)
    compute = rng.gamma(2.0, 0.0005, n)
    late = rng.exponential(0.0001, n)
    stats = TimingStats(period_s=0.005, capacity=1024)
    for c, l in zip(compute.tolist(), late.tolist()):
        stats.record(c, l)
    s = stats.summary()
    window = slice(max(0, n - 1024), n)  # the ring holds the last 1024
    for name, arr in (("compute", compute[window]), ("late", late[window])):
        assert s[f"{name}_p50_us"] == pytest.approx(np.percentile(arr, 50) * 1e6, rel=1e-9)
        assert s[f"{name}_p99_us"] == pytest.approx(np.percentile(arr, 99) * 1e6, rel=1e-9)
        assert s[f"{name}_max_us"] == pytest.approx(arr.max() * 1e6, rel=1e-12)
    assert s["count"] == n and s["window"] == min(n, 1024)
    assert s["compute_worst_us"] == pytest.approx(compute.max() * 1e6)
    expected_overruns = int(np.sum(compute + late > 0.005))
    assert s["overruns"] == expected_overruns
    json.dumps(s)  # goes out over the control socket


def test_timing_stats_counts_overruns_and_missed() -> None:
    stats = TimingStats(period_s=0.005, capacity=16)
    stats.record(0.001, 0.0001)
    stats.record(0.0049, 0.0002, skipped=0)  # ends after the next slot: an overrun
    stats.record(0.001, 0.012, skipped=2)
    s = stats.summary()
    assert (s["overruns"], s["missed_ticks"], s["count"]) == (2, 2, 3)
    assert s["late_worst_us"] == pytest.approx(12000.0)


def test_timing_stats_empty_summary_is_json() -> None:
    s = TimingStats(0.005).summary()
    assert s["count"] == 0 and s["compute_p99_us"] is None
    json.dumps(s, allow_nan=False)


def test_timing_stats_record_does_not_allocate() -> None:
    stats = TimingStats(period_s=0.005, capacity=1 << 14)
    values = [(i * 1e-6, i * 1e-7) for i in range(2000)]
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        for _ in range(10):
            for c, l in values:
                stats.record(c, l)
        grown = tracemalloc.get_traced_memory()[0] - before
    finally:
        tracemalloc.stop()
    assert stats.count == 20000
    assert grown < 4096, f"record() kept {grown} bytes for 20000 ticks"


def test_timing_stats_rejects_bad_capacity() -> None:
    with pytest.raises(ValueError, match="capacity"):
        TimingStats(0.005, capacity=0)


# ----- rt ----------------------------------------------------------------------------------

def _run_isolated(code: str) -> dict:
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True,
                         timeout=20, cwd=REPO)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_apply_realtime_applies_or_warns_per_step() -> None:
    res = _run_isolated("""
        import json, os, gc
        from ddrt.runtime import rt
        cpu = min(os.sched_getaffinity(0))
        warnings = rt.apply_realtime(10, {cpu}, True, 1, gil_switch_interval_s=0.0005)
        import sys
        print(json.dumps({"warnings": warnings, "cpu": cpu,
                          "policy": os.sched_getscheduler(0), "fifo": os.SCHED_FIFO,
                          "prio": os.sched_getparam(0).sched_priority,
                          "affinity": sorted(os.sched_getaffinity(0)),
                          "slack": rt.timer_slack_ns(), "switch": sys.getswitchinterval()}))
    """)
    w = " | ".join(res["warnings"])
    # Each step either took effect or left a warning naming it.
    assert (res["policy"] == res["fifo"] and res["prio"] == 10) or "sched_setscheduler" in w
    assert res["affinity"] == [res["cpu"]] or "sched_setaffinity" in w
    assert res["slack"] == 1 or res["policy"] == res["fifo"] or "PR_SET_TIMERSLACK" in w
    assert res["switch"] == pytest.approx(0.0005)
    for warning in res["warnings"]:
        assert warning.split("(")[0].split(":")[0] in ("mlockall", "sched_setaffinity", "prctl", "sched_setscheduler")


def test_apply_realtime_turns_refusals_into_warnings(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*_a: object) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    monkeypatch.setattr(os, "sched_setaffinity", refuse)

    class Libc:  # mlockall and prctl refused like an unprivileged process without rlimits
        @staticmethod
        def mlockall(_flags: int) -> int:
            import ctypes
            ctypes.set_errno(12)  # ENOMEM: RLIMIT_MEMLOCK too small
            return -1

        @staticmethod
        def prctl(*_a: object) -> int:
            import ctypes
            ctypes.set_errno(1)
            return -1

    monkeypatch.setattr(rt, "_libc", Libc())
    warnings = rt.apply_realtime(50, {0}, True, 1000)
    assert len(warnings) == 4
    joined = "\n".join(warnings)
    for step in ("mlockall", "sched_setaffinity", "PR_SET_TIMERSLACK", "sched_setscheduler(SCHED_FIFO, 50)"):
        assert step in joined
    assert "EPERM" in joined and "ENOMEM" in joined
    assert "LimitRTPRIO" in joined and "LimitMEMLOCK=infinity" in joined  # hints point at the unit's fix


def test_apply_realtime_nothing_requested_does_nothing() -> None:
    before = (os.sched_getscheduler(0), os.sched_getaffinity(0))
    assert rt.apply_realtime(None, None, False, None) == []
    assert (os.sched_getscheduler(0), os.sched_getaffinity(0)) == before


@pytest.mark.parametrize("kwargs, field", [
    (dict(priority=0), "priority"), (dict(priority=100), "priority"), (dict(priority=5.0), "priority"),
    (dict(cpus=set()), "cpus"), (dict(cpus={-1}), "cpus"), (dict(timer_slack_ns=0), "timer_slack_ns"),
])
def test_apply_realtime_rejects_bad_arguments(kwargs: dict, field: str) -> None:
    args = dict(priority=None, cpus=None, lock_memory=False, timer_slack_ns=None)
    args.update(kwargs)
    with pytest.raises(ValueError, match=field):
        rt.apply_realtime(**args)


def test_freeze_gc_in_subprocess() -> None:
    res = _run_isolated("""
        import json, gc
        from ddrt.runtime import rt
        junk = [[i] for i in range(10000)]
        rt.freeze_gc()
        print(json.dumps(rt.gc_stats()))
    """)
    assert res["enabled"] is False
    assert res["frozen"] > 10000  # the live objects were moved out of the collector's reach
    assert len(res["pending"]) == 3 and len(res["collections"]) == 3


def test_demote_current_thread_leaves_normal_thread_alone() -> None:
    before = os.sched_getscheduler(0)
    rt.demote_current_thread()
    assert os.sched_getscheduler(0) == before
    assert gc.isenabled()  # nothing here touched the collector of the test process


def test_a_gil_helper_runs_just_below_a_real_time_loop_or_at_normal_priority() -> None:
    """rt.raise_gil_helper in a fresh thread: SCHED_FIFO 1 under a loop at FIFO >= 2 (or, where
    that is refused, a warning and SCHED_OTHER); SCHED_OTHER when the loop is not real-time."""
    import threading

    seen: dict[int, tuple[str | None, int, int]] = {}

    def helper(loop_priority: int) -> None:
        why = rt.raise_gil_helper(loop_priority)
        seen[loop_priority] = (why, os.sched_getscheduler(0), os.sched_getparam(0).sched_priority)

    for prio in (0, 10):
        t = threading.Thread(target=helper, args=(prio,))
        t.start()
        t.join()
    assert seen[0] == (None, os.SCHED_OTHER, 0)
    why, policy, priority = seen[10]
    if why is None:
        assert (policy, priority) == (os.SCHED_FIFO, 1)
    else:
        assert "SCHED_FIFO, 1" in why and policy == os.SCHED_OTHER


def test_spinning_clock_never_wakes_early_and_rejects_bad_spin():
    import time as _time

    from ddrt.runtime.clock import MonotonicClock as _Clock

    clock = _Clock(spin_s=0.0002)
    late = []
    for _ in range(50):
        deadline = _time.monotonic() + 0.002
        woke, beyond_queue = late_beyond_queue(clock.sleep_until, deadline)
        assert woke >= deadline
        late.append(beyond_queue)
    late.sort()
    assert late[len(late) // 2] < 0.001  # typically a few microseconds (less any wait for a CPU)
    for bad in (-1e-6, 0.02, float("nan")):
        with pytest.raises(ValueError):
            _Clock(spin_s=bad)


def test_timing_stats_summary_of_a_full_window_is_cheap() -> None:
    """status is answered on the loop thread: a full 16 384-tick window must summarise in a
    small part of a 5 ms tick (a sort took 3-12 ms). Measured in the thread's CPU time, which
    a loaded host does not inflate."""
    stats = TimingStats(period_s=0.005)
    rng = np.random.default_rng(3)
    for c, l in zip(rng.random(3 * stats.capacity).tolist(), rng.random(3 * stats.capacity).tolist()):
        stats.record(c * 1e-4, l * 1e-4)
    stats.summary()
    costs = []
    for _ in range(15):
        t0 = time.thread_time()
        stats.summary()
        costs.append(time.thread_time() - t0)
    assert sorted(costs)[len(costs) // 2] < 2e-3
