"""Real-time set-up of the loop thread: SCHED_FIFO, locked memory, CPU pinning, timer slack.

Every step is best effort. A robot on a dev laptop, in a container or under a unit without
LimitRTPRIO still runs, just with worse jitter, so a refused step becomes a warning string
for the caller to log, never an exception. Invalid arguments (a priority of 200) are still
errors.

Order matters: scheduling policy and CPU affinity are per thread and are INHERITED by threads
created afterwards. Start the helper threads (telemetry writer, control socket) first, then
call `apply_realtime` from the loop thread; the helpers also drop back to SCHED_OTHER
themselves (`demote_current_thread`) in case they were started later.

SCHED_FIFO needs CAP_SYS_NICE or a non-zero RLIMIT_RTPRIO (LimitRTPRIO= in the unit);
mlockall needs CAP_IPC_LOCK or a large enough RLIMIT_MEMLOCK (LimitMEMLOCK=infinity).
"""

from __future__ import annotations

import ctypes
import errno
import gc
import os
import sys
from typing import Any

MCL_CURRENT = 1  # <sys/mman.h> on x86, ARM, arm64, RISC-V (not Alpha/PowerPC/SPARC)
MCL_FUTURE = 2
PR_SET_TIMERSLACK = 29  # <linux/prctl.h>
PR_GET_TIMERSLACK = 30

_libc: Any = None


def _get_libc() -> Any:
    global _libc
    if _libc is None:
        _libc = ctypes.CDLL(None, use_errno=True)  # the interpreter's symbols include libc's
    return _libc


def _why(exc: OSError) -> str:
    code = errno.errorcode.get(exc.errno or 0, str(exc.errno))
    hint = ""
    if exc.errno == errno.EPERM:
        hint = " (needs CAP_SYS_NICE/CAP_IPC_LOCK or LimitRTPRIO=/LimitMEMLOCK=)"
    elif exc.errno == errno.ENOMEM:
        hint = " (RLIMIT_MEMLOCK too small: LimitMEMLOCK=infinity)"
    return f"{code}: {exc.strerror or exc}{hint}"


def _validate(priority: int | None, cpus: set[int] | None, timer_slack_ns: int | None) -> None:
    if priority is not None:
        if isinstance(priority, bool) or not isinstance(priority, int):
            raise ValueError(f"apply_realtime: priority must be an int or None, got {priority!r}")
        lo, hi = os.sched_get_priority_min(os.SCHED_FIFO), os.sched_get_priority_max(os.SCHED_FIFO)
        if not lo <= priority <= hi:
            raise ValueError(f"apply_realtime: priority must be in [{lo}, {hi}] for SCHED_FIFO, got {priority}")
    if cpus is not None:
        if not cpus or any(isinstance(c, bool) or not isinstance(c, int) or c < 0 for c in cpus):
            raise ValueError(f"apply_realtime: cpus must be a non-empty set of CPU numbers >= 0, got {cpus!r}")
    if timer_slack_ns is not None:
        if isinstance(timer_slack_ns, bool) or not isinstance(timer_slack_ns, int) or timer_slack_ns < 1:
            # 0 would mean "reset to the default slack" (50 us), the opposite of the intent.
            raise ValueError(f"apply_realtime: timer_slack_ns must be an int >= 1, got {timer_slack_ns!r}")


def apply_realtime(
    priority: int | None,
    cpus: set[int] | None,
    lock_memory: bool,
    timer_slack_ns: int | None,
    *,
    gil_switch_interval_s: float | None = None,
) -> list[str]:
    """Make the CALLING thread real-time as far as permitted; return one warning per refusal.

    - priority: SCHED_FIFO priority (1..99), None to keep the current policy.
    - cpus: pin this thread to these CPUs (e.g. an isolcpus= core), None to leave it.
    - lock_memory: mlockall(MCL_CURRENT | MCL_FUTURE) so no page fault stalls a tick.
    - timer_slack_ns: how late the kernel may fire our timers to batch wake-ups (default
      50 us for normal threads; 1 asks for none). SCHED_FIFO threads already get none.
    - gil_switch_interval_s: sys.setswitchinterval; a helper thread holding the GIL can
      delay the loop's wake-up by up to this (default 5 ms, a whole tick at 200 Hz).
    """
    _validate(priority, cpus, timer_slack_ns)
    warnings: list[str] = []

    if lock_memory:
        libc = _get_libc()
        if libc.mlockall(MCL_CURRENT | MCL_FUTURE) != 0:
            err = ctypes.get_errno()
            warnings.append(f"mlockall: {_why(OSError(err, os.strerror(err)))}")

    if cpus is not None:
        try:
            os.sched_setaffinity(0, cpus)
        except OSError as exc:
            warnings.append(f"sched_setaffinity({sorted(cpus)}): {_why(exc)}")

    if timer_slack_ns is not None:
        libc = _get_libc()
        if libc.prctl(PR_SET_TIMERSLACK, ctypes.c_ulong(timer_slack_ns), ctypes.c_ulong(0),
                      ctypes.c_ulong(0), ctypes.c_ulong(0)) != 0:
            err = ctypes.get_errno()
            warnings.append(f"prctl(PR_SET_TIMERSLACK, {timer_slack_ns}): {_why(OSError(err, os.strerror(err)))}")

    if priority is not None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        except OSError as exc:
            warnings.append(f"sched_setscheduler(SCHED_FIFO, {priority}): {_why(exc)}")

    if gil_switch_interval_s is not None:
        try:
            sys.setswitchinterval(gil_switch_interval_s)
        except (ValueError, TypeError) as exc:
            raise ValueError(f"apply_realtime: gil_switch_interval_s: {exc}") from None
    return warnings


def timer_slack_ns() -> int:
    """The calling thread's current timer slack (ns)."""
    return int(_get_libc().prctl(PR_GET_TIMERSLACK, ctypes.c_ulong(0), ctypes.c_ulong(0),
                                 ctypes.c_ulong(0), ctypes.c_ulong(0)))


def demote_current_thread() -> None:
    """Put the calling (helper) thread back on SCHED_OTHER if it inherited a RT policy.

    Lowering one's own policy is always permitted; errors are ignored on purpose (a helper
    thread must start even where sched_* calls are filtered).
    """
    try:
        if os.sched_getscheduler(0) & ~os.SCHED_RESET_ON_FORK in (os.SCHED_FIFO, os.SCHED_RR):
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    except (OSError, AttributeError):
        pass


def raise_gil_helper(loop_priority: int, reset_on_fork: bool = False) -> str | None:
    """Run the calling helper thread at SCHED_FIFO 1, below a loop at SCHED_FIFO `loop_priority`
    (>= 2); otherwise (loop not real-time) back to SCHED_OTHER. Returns a warning on refusal.

    For a helper that takes the GIL in short bursts while the loop sleeps (the Foxglove
    publisher, the telemetry writer, the path worker's reader): at SCHED_OTHER the machine's
    other processes can preempt it in the middle of a burst, with the GIL held, and the loop
    thread, woken at its deadline, then waits for the GIL until the helper gets a CPU back
    (priority inversion; measured: a tick 9 ms late behind a publisher preempted for 12 ms
    with 0.6 ms of work to do; a niced helper behind CPU hogs, 40-60 ms). At SCHED_FIFO 1
    only real-time threads preempt it, and the loop's own priority still wins any CPU they
    share. `reset_on_fork`: processes the thread starts begin at SCHED_OTHER (keeping its
    nice value), not real-time.
    """
    if loop_priority < 2:
        demote_current_thread()
        return None
    policy = os.SCHED_FIFO | (os.SCHED_RESET_ON_FORK if reset_on_fork else 0)
    try:
        os.sched_setscheduler(0, policy, os.sched_param(1))
    except (OSError, AttributeError) as exc:
        demote_current_thread()
        return f"sched_setscheduler(SCHED_FIFO, 1): {_why(exc) if isinstance(exc, OSError) else exc}"
    return None


def freeze_gc() -> None:
    """Collect once, move every live object to the permanent generation, stop the collector.

    Call once after start-up (config loaded, HAL open, buffers allocated), just before the
    loop: a generation-2 collection over a big heap takes milliseconds, longer than a tick.
    From then on only GcSweeper frees reference cycles (and the free lists), once a second at
    most, so the loop must not create them per tick; `gc_stats()["pending"]` growing over time
    shows that it does.
    """
    gc.collect()
    gc.freeze()
    gc.disable()


INTERN_SETTLE = 6144  # strings interned and let go by settle_interned


def settle_interned(count: int = INTERN_SETTLE) -> None:
    """Grow the interpreter's table of interned strings, once, to the size it keeps.

    Every string pathlib splits a path into is interned and leaves the table when the path
    is dropped; each one still uses up a slot of the table until the table is rebuilt, at a
    size set by the strings alive. So a reload (about 9 such strings: its config's path,
    the files it names) brings that rebuild nearer, and the daemon's first one, after a few
    hundred reloads, doubles the table: about 470 KiB more at once (32768 -> 65536 slots for its
    about 18 000 live strings). Later rebuilds keep that size. Interning `count` distinct
    strings and dropping them makes that first rebuild here, before the loop starts, so
    the daemon's memory is flat from its first command; it takes a few milliseconds.
    `count` is more than the table's free slots for the daemon's strings (about 3000), and
    small, since every string interned takes a slot until the next rebuild: afterwards, the
    table has room for about 2000 reloads before it is rebuilt again, at the same size.
    """
    held = [sys.intern(f"ddrt settle {i}") for i in range(count)]
    del held


SWEEP_BLOCKS = 256  # about 25 KB of small objects: what a few commands leave in the free lists


class GcSweeper:
    """Frees, between two ticks, what the stopped collector would keep for good.

    With the collector stopped (freeze_gc) nothing empties the interpreter's free lists: a
    tuple built at one size and shrunk to another (tuple() of a generator,
    dataclasses.fields) is freed into the other size's list, so every config read by a
    reload, every status and every follow parks a few dozen more objects there, up to
    thousands per size: unswept, the daemon grows about 6 KB a command cycle for thousands
    of cycles. A full collection empties them and frees any reference cycle;
    after freeze_gc it scans only the objects made since (hundreds, tens of microseconds
    to a millisecond), so `maybe` runs it only when the interpreter holds SWEEP_BLOCKS more
    blocks than after the last sweep, and at most as often as it is called.
    """

    def __init__(self, threshold: int = SWEEP_BLOCKS) -> None:
        self.threshold = threshold
        self.level = sys.getallocatedblocks()
        self.sweeps = 0

    def maybe(self) -> bool:
        """Collect if the blocks grew by the threshold since the last sweep; True if it did."""
        if sys.getallocatedblocks() - self.level < self.threshold:
            return False
        gc.collect()
        self.level = sys.getallocatedblocks()
        self.sweeps += 1
        return True


def gc_stats() -> dict[str, Any]:
    """Collector state for the status command: is it on, what is frozen, what is pending."""
    return {
        "enabled": gc.isenabled(),
        "frozen": gc.get_freeze_count(),
        "pending": list(gc.get_count()),  # allocations minus frees per generation since last run
        "collections": [s["collections"] for s in gc.get_stats()],
    }
