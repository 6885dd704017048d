"""Fixed-rate scheduling and per-tick timing statistics for the control loop.

`RateScheduler` hands out absolute deadlines `start + n * period` (an integer tick index
times the period, so rounding never accumulates). When the loop wakes too late it SKIPS the
slots already in the past instead of running them back to back: a controller fed a burst
of catch-up ticks sees a wrong dt and commands a jerk. Skipped slots are counted.

`TimingStats` keeps the last N compute times and wake-up latenesses in preallocated arrays;
`record` is a few float stores. Percentiles are only computed when `summary()` is asked for
(by the control socket, or at exit), never on the hot path.

Typical loop::

    sched = RateScheduler(0.005, clock.now())
    while running:
        deadline = sched.next_deadline()
        clock.sleep_until(deadline)
        started = clock.now()
        skipped = sched.account(started)
        ...read, control, write...
        stats.record(clock.now() - started, started - deadline, skipped)

Lateness and missed slots are measured when the tick really starts (takes its sample), not
when the sleep returned: a thread that loses the CPU (or the GIL) between the two is as late
as one that woke late, and measuring before the sleep would leave a stall there uncounted (a 159 ms stall at 200 Hz read
as 6 ms late and 3 missed slots, when it is ~159 ms and 31). The daemon does this in
`Daemon._fixed_rate_loop`.
"""

from __future__ import annotations

import math
from array import array

import numpy as np


def _positive_finite(name: str, value: float) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name}: expected a finite number > 0, got {value!r}")
    return float(value)


class RateScheduler:
    """Absolute deadlines on a fixed grid; late wake-ups skip missed slots and count them."""

    __slots__ = ("period_s", "start", "_tick", "_deadline", "ticks", "missed", "overruns")

    def __init__(self, period_s: float, start: float) -> None:
        self.period_s = _positive_finite("RateScheduler.period_s", period_s)
        if not isinstance(start, (int, float)) or not math.isfinite(start):
            raise ValueError(f"RateScheduler.start: expected a finite time in seconds, got {start!r}")
        self.start = float(start)
        self._tick = 0  # index of the slot the loop is waiting for
        self._deadline = self.start
        self.ticks = 0  # slots served
        self.missed = 0  # slots skipped because the loop woke after them
        self.overruns = 0  # wake-ups that had to skip at least one slot

    def next_deadline(self) -> float:
        """The absolute time (same clock as `start`) of the slot to sleep until."""
        return self._deadline

    def account(self, now: float) -> int:
        """Mark the current slot served at `now` (when its tick starts, not when the sleep
        returned); return how many later slots were skipped.

        The next deadline becomes the first slot strictly after `now`, so a late wake-up
        never produces a burst of immediate ticks.
        """
        self.ticks += 1
        tick = self._tick + 1
        deadline = self.start + tick * self.period_s
        skipped = 0
        if deadline <= now:
            # Jump in one step (an overrun of 1000 periods costs no more than one of 2).
            skipped = int((now - deadline) / self.period_s) + 1
            tick += skipped
            deadline = self.start + tick * self.period_s
            while deadline <= now:  # float rounding at an exact slot boundary
                tick += 1
                skipped += 1
                deadline = self.start + tick * self.period_s
            self.missed += skipped
            self.overruns += 1
        self._tick = tick
        self._deadline = deadline
        return skipped


def percentile(sorted_values: list[float], q: float) -> float:
    """The q-th percentile (0..100) of sorted data, interpolating linearly between ranks.

    Same definition as numpy.percentile's default ("linear"), without needing numpy.
    """
    n = len(sorted_values)
    if n == 0:
        raise ValueError("percentile: no data")
    if not 0.0 <= q <= 100.0:
        raise ValueError(f"percentile: q must be in [0, 100], got {q!r}")
    pos = (n - 1) * q / 100.0
    lo = math.floor(pos)
    hi = min(lo + 1, n - 1)
    frac = pos - lo
    return sorted_values[lo] + (sorted_values[hi] - sorted_values[lo]) * frac


class TimingStats:
    """Ring of the last `capacity` ticks' compute time and lateness, plus running counters.

    A tick is an overrun when it ended after the next slot began (lateness + compute >
    period): that is what forces the scheduler to skip. `record` and `summary` are meant
    for the same thread (the loop answers status requests between ticks); a summary taken
    from another thread may mix two ticks, never crash.
    """

    __slots__ = ("period_s", "capacity", "_compute", "_late", "_n", "overruns", "missed",
                 "worst_compute_s", "worst_late_s")

    def __init__(self, period_s: float, capacity: int = 1 << 14) -> None:
        self.period_s = _positive_finite("TimingStats.period_s", period_s)
        if isinstance(capacity, bool) or not isinstance(capacity, int) or capacity < 1:
            raise ValueError(f"TimingStats.capacity: expected an int >= 1, got {capacity!r}")
        self.capacity = capacity
        self._compute = array("d", bytes(8 * capacity))
        self._late = array("d", bytes(8 * capacity))
        self._n = 0  # ticks recorded since start (the ring holds the last `capacity`)
        self.overruns = 0
        self.missed = 0
        self.worst_compute_s = 0.0  # since start, not just the window
        self.worst_late_s = 0.0

    def record(self, compute_s: float, lateness_s: float, skipped: int = 0) -> None:
        """Store one tick (seconds). `skipped` is RateScheduler.account's return value."""
        i = self._n % self.capacity
        self._compute[i] = compute_s
        self._late[i] = lateness_s
        self._n += 1
        if compute_s + lateness_s > self.period_s:
            self.overruns += 1
        if skipped:
            self.missed += skipped
        if compute_s > self.worst_compute_s:
            self.worst_compute_s = compute_s
        if lateness_s > self.worst_late_s:
            self.worst_late_s = lateness_s

    @property
    def count(self) -> int:
        return self._n

    def summary(self) -> dict[str, float | int | None]:
        """Percentiles over the window in microseconds, and counters since start.

        The loop thread answers `status`, so this must be cheap: a selection (O(n), about
        0.15 ms for the full window) rather than a sort of 16 384 floats (3-12 ms, most of
        a 5 ms tick). The ring's order does not matter for a percentile."""
        out: dict[str, float | int | None] = {
            "count": self._n,
            "window": min(self._n, self.capacity),
            "overruns": self.overruns,
            "missed_ticks": self.missed,
            "compute_worst_us": self.worst_compute_s * 1e6,
            "late_worst_us": self.worst_late_s * 1e6,
        }
        n = min(self._n, self.capacity)
        for name, ring in (("compute", self._compute), ("late", self._late)):
            if n:
                p50, p99, top = select_quantiles(np.frombuffer(ring, dtype=np.float64, count=n))
                out[f"{name}_p50_us"] = p50 * 1e6
                out[f"{name}_p99_us"] = p99 * 1e6
                out[f"{name}_max_us"] = top * 1e6
            else:
                # None, not NaN: the summary goes out as JSON, which has no NaN.
                out[f"{name}_p50_us"] = out[f"{name}_p99_us"] = out[f"{name}_max_us"] = None
        return out


def select_quantiles(data: np.ndarray) -> tuple[float, float, float]:
    """(p50, p99, max) of unsorted, non-empty data, numpy.percentile's "linear" definition, by
    partitioning around the four ranks the two percentiles interpolate between (O(n): cheap
    enough for the loop thread, where a sort of a full window is not)."""
    n = len(data)
    ranks: list[int] = []
    fracs: list[float] = []
    for q in (50.0, 99.0):
        r = (n - 1) * q / 100.0
        lo = int(math.floor(r))
        ranks += [lo, min(lo + 1, n - 1)]
        fracs.append(r - lo)
    part = np.partition(data, sorted(set(ranks)))
    p50 = float(part[ranks[0]] + (part[ranks[1]] - part[ranks[0]]) * fracs[0])
    p99 = float(part[ranks[2]] + (part[ranks[3]] - part[ranks[2]]) * fracs[1])
    return p50, p99, float(data.max())
