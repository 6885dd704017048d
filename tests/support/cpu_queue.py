"""How long a thread or process has waited for a CPU: what a loaded machine adds to any
wall-clock measurement, and not the doing of the code being measured.

The kernel keeps it per task as run_delay, the second field of /proc/<pid>/task/<tid>/schedstat
(CONFIG_SCHED_INFO): nanoseconds spent runnable but not running. Tests subtract it from a
wall-clock interval to bound what the code itself took or overslept, so the bound does not
depend on how busy the machine is. Where the kernel does not keep it, it reads 0.0 and the
bound is the plain wall-clock one.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable


def waited_for_cpu_s(task: str = "thread-self") -> float:
    """Seconds the task (`thread-self`, or a pid for its main thread) has spent waiting for a CPU."""
    try:
        with open(f"/proc/{task}/schedstat") as fh:
            return int(fh.read().split()[1]) * 1e-9
    except (OSError, IndexError, ValueError):
        return 0.0


def process_waited_for_cpu_s(pid: int | str = "self") -> float:
    """The same, summed over every thread of a process: for a round trip that passes through
    several threads (client, I/O thread, loop), each of which may wait for a CPU on the way.
    An upper bound of what the waits added to it, since they may overlap."""
    total = 0.0
    try:
        tids = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return 0.0
    for tid in tids:
        total += waited_for_cpu_s(f"{pid}/task/{tid}")
    return total


class Stopwatch:
    """Wall time of a block, and the part of it spent waiting for a CPU: by this thread, or
    (given pids) by every thread of those processes, "self" for this one."""

    def __init__(self, *pids: int | str) -> None:
        self.pids = pids

    def _queued(self) -> float:
        if not self.pids:
            return waited_for_cpu_s()
        return sum(process_waited_for_cpu_s(pid) for pid in self.pids)

    def __enter__(self) -> "Stopwatch":
        self.queued = -self._queued()
        self.wall = -time.monotonic()
        return self

    def __exit__(self, *exc: object) -> None:
        self.wall += time.monotonic()
        self.queued += self._queued()

    @property
    def running_s(self) -> float:
        """The wall time less the wait for a CPU: what the block took where it ran at once."""
        return self.wall - self.queued


def late_beyond_queue(sleep: Callable[[float], float], deadline: float) -> tuple[float, float]:
    """(what `sleep(deadline)` returned, how late that was less the wait for a CPU meanwhile)."""
    q0 = waited_for_cpu_s()
    woke = sleep(deadline)
    return woke, woke - deadline - (waited_for_cpu_s() - q0)
