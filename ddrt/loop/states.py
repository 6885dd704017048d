"""The loop's states. Each one's value is its code in telemetry's `state` column, so a code
never changes: new states go at the end."""

from __future__ import annotations

from enum import IntEnum

__all__ = ["LoopState", "MOVING", "state_label"]


class LoopState(IntEnum):
    """What the loop is doing; `label` is the name status, logs and metrics.json report."""

    IDLE = 0
    FOLLOWING = 1
    STOPPING = 2
    STOPPED = 3
    ESTOP = 4
    FAULT = 5
    HOLDING = 6
    DRIVING = 7

    @property
    def label(self) -> str:
        """The state as text: "following", "holding", ..."""
        return self.name.lower()

    def __str__(self) -> str:
        return self.label

    def __format__(self, spec: str) -> str:
        return format(self.label, spec)


# The robot is driven along a reference (a hold decides for itself whether it still is). A tuple:
# the tick tests it every tick, and `in` a short tuple of members is the fastest test.
MOVING = (LoopState.FOLLOWING, LoopState.STOPPING, LoopState.DRIVING)


def state_label(code: int) -> str:
    """The label of telemetry's state `code`, or the number for a code this version does not know."""
    return LoopState(code).label if code in _CODES else str(code)


_CODES = frozenset(int(s) for s in LoopState)
