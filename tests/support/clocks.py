"""A clock a test moves by hand: drivers and emulators read it where they would read the
monotonic clock, so a test's timing is what the test says, not what the machine's load makes it."""

from __future__ import annotations


class ManualClock:
    """`clock()` is `clock.t`, which the test advances."""

    def __init__(self, t: float = 0.0) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t
