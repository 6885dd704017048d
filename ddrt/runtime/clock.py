"""Clocks for the control loop: monotonic time and sleeping to an absolute deadline.

The loop asks the clock (the `Clock` protocol of ddrt.core.types) for `now()` and sleeps with
`sleep_until(deadline)`. Sleeping to an
ABSOLUTE deadline (not "sleep 5 ms") is what keeps a fixed-rate loop from drifting: the time
spent computing a tick does not push every later tick back. The simulated HAL implements the
same two methods and is its own clock.
"""

from __future__ import annotations

import ctypes
import errno
import math
import time
from typing import Protocol

from ddrt.core.types import Clock

__all__ = ["Clock", "ManualClock", "MonotonicClock", "SpinClock"]


class SpinClock(Clock, Protocol):
    """A clock whose wake-up spin a reload sets (`daemon.spin_us`): the daemon's."""

    def set_spin(self, spin_s: float) -> None: ...

CLOCK_MONOTONIC = time.CLOCK_MONOTONIC  # 1 on Linux; time.monotonic() reads this clock
TIMER_ABSTIME = 1  # flags value for clock_nanosleep (same on every Linux architecture)


class _Timespec(ctypes.Structure):
    # time_t and long are both the C long on the Linux ABIs we run on (LP64, ILP32 with
    # 32-bit time_t); the monotonic clock counts from boot, so 32 bits of seconds suffice.
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


def _load_clock_nanosleep():  # -> ctypes function or None
    """libc's clock_nanosleep, or None where there is no such C function (not Linux)."""
    # dlopen(NULL): the interpreter's own symbols, which include libc's. (find_library would
    # run ldconfig in a subprocess at import.)
    try:
        fn = ctypes.CDLL(None, use_errno=True).clock_nanosleep
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.POINTER(_Timespec), ctypes.c_void_p]
    fn.restype = ctypes.c_int
    return fn


def _check_deadline(deadline: float) -> None:
    if not math.isfinite(deadline):
        raise ValueError(f"sleep_until: deadline must be a finite number of seconds, got {deadline!r}")


class MonotonicClock:
    """CLOCK_MONOTONIC time, with absolute-deadline sleeps (clock_nanosleep + TIMER_ABSTIME).

    `sleep_until` never returns before the deadline. With `use_libc=False`, or where libc has
    no clock_nanosleep, it falls back to time.sleep(deadline - now) in a loop.
    One instance belongs to one thread: the timespec is preallocated and reused so a sleep
    allocates nothing but its float result.
    """

    __slots__ = ("_nanosleep", "_ts", "_ts_ref", "spin_s")

    def __init__(self, use_libc: bool = True, spin_s: float = 0.0) -> None:
        self.set_spin(spin_s)
        self._nanosleep = _load_clock_nanosleep() if use_libc else None
        self._ts = _Timespec()
        self._ts_ref = ctypes.byref(self._ts)

    def set_spin(self, spin_s: float) -> None:
        """Sleep until `spin_s` before each deadline, then poll the clock: trades that much CPU
        per tick for a wake-up that does not depend on the kernel's timer latency."""
        if not (isinstance(spin_s, (int, float)) and 0.0 <= spin_s < 0.01):
            raise ValueError(f"MonotonicClock.spin_s: expected seconds in [0, 0.01), got {spin_s!r}")
        self.spin_s = float(spin_s)

    @property
    def uses_clock_nanosleep(self) -> bool:
        return self._nanosleep is not None

    def now(self) -> float:
        return time.monotonic()

    def sleep_until(self, deadline: float) -> float:
        _check_deadline(deadline)
        if self.spin_s > 0.0:
            now = self._sleep(deadline - self.spin_s)
            while now < deadline:
                now = time.monotonic()
            return now
        return self._sleep(deadline)

    def _sleep(self, deadline: float) -> float:
        now = time.monotonic()
        if now >= deadline:
            return now
        fn = self._nanosleep
        if fn is not None:
            # Round the deadline UP to the next nanosecond so we never wake before it.
            sec = math.floor(deadline)
            nsec = math.ceil((deadline - sec) * 1e9)
            if nsec >= 1_000_000_000:
                sec += 1
                nsec -= 1_000_000_000
            self._ts.tv_sec = sec
            self._ts.tv_nsec = nsec
            while True:
                rc = fn(CLOCK_MONOTONIC, TIMER_ABSTIME, self._ts_ref, None)
                if rc == 0:
                    break
                if rc != errno.EINTR:  # clock_nanosleep returns the error, it does not set errno
                    raise OSError(rc, f"clock_nanosleep: {errno.errorcode.get(rc, rc)}")
            now = time.monotonic()
        # Fallback, and a guard against float rounding in the conversion above.
        while now < deadline:
            time.sleep(deadline - now)
            now = time.monotonic()
        return now


class ManualClock:
    """A clock that only moves when told to: `sleep_until` jumps straight to the deadline.

    For tests of code that takes a Clock (the scheduler, stale-command timeouts) without
    waiting in real time.
    """

    __slots__ = ("t",)

    def __init__(self, start: float = 0.0) -> None:
        _check_deadline(start)
        self.t = float(start)

    def now(self) -> float:
        return self.t

    def set_spin(self, spin_s: float) -> None:
        """Nothing: it jumps to each deadline, so there is no wake-up to spin for."""

    def advance(self, seconds: float) -> float:
        if not math.isfinite(seconds) or seconds < 0:
            raise ValueError(f"ManualClock.advance: seconds must be finite and >= 0, got {seconds!r}")
        self.t += seconds
        return self.t

    def sleep_until(self, deadline: float) -> float:
        _check_deadline(deadline)
        if deadline > self.t:
            self.t = float(deadline)
        return self.t
