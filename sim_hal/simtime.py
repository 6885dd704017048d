"""Simulated time, as the two backends whose robot lives in it keep it (sim_hal.backend.SimHal,
sim_hal.emulated.EmulatedRealHal).

Unpaced (the default, for CI) sim time moves only when the loop sleeps: `sleep_until`
integrates the plant to the deadline at once, so a run goes as fast as the CPU allows.
Paced, sim time follows the wall clock (time.monotonic since start, plus the sim time at
start): `catch_up` brings the plant to it, and `sleep_until` waits for the wall clock first.
"""

from __future__ import annotations

import math
import time
from typing import Callable

from hal.base import HalValueError


class SimTime:
    """A Clock over a plant: `sim_now()` reads its time, `advance(t)` integrates it to t."""

    def __init__(self, sim_now: Callable[[], float], advance: Callable[[float], None], paced: bool = False) -> None:
        self._sim_now = sim_now
        self._advance = advance
        self.paced = paced
        self._wall0 = time.monotonic()
        self._sim0 = sim_now()

    def wall_sim_time(self) -> float:
        """The sim time the wall clock stands at (paced)."""
        return time.monotonic() - self._wall0 + self._sim0

    def catch_up(self) -> None:
        """Paced: integrate the plant up to the wall clock now; unpaced, sim time waits."""
        if self.paced:
            self._advance(self.wall_sim_time())

    def now(self) -> float:
        """Sim time (s); paced, the plant is first brought up to the wall clock."""
        if self.paced:
            self._advance(self.wall_sim_time())
        return self._sim_now()

    def sleep_until(self, deadline: float) -> float:
        """Advance the plant to `deadline` (paced: to the wall clock once it has passed it)."""
        if not math.isfinite(deadline):
            raise HalValueError(f"deadline={deadline!r} is not finite")
        if self.paced:
            remaining = deadline - self.wall_sim_time()
            if remaining > 0.0:
                time.sleep(remaining)
            deadline = max(deadline, self.wall_sim_time())
        self._advance(deadline)
        return self._sim_now()
