"""What the loop asks of a reference stage, whichever it is.

The reference stage turns the estimated pose into the controller's `Setpoint` each tick. It is
a path's (`PathReference`, nearest point and schedule, or the seed's time-indexed mode), the
start of a path the robot is not lined up with (`StartReference`), the velocity mode's
(`DriveReference`) or calibration's spin in place (`SpinReference`). The loop treats them alike
through this protocol, so every stage has every member, trivially where it does not apply (a
drive has no progress along a path and is never resumed).
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from ddrt.core.types import Setpoint

__all__ = ["Reference"]


@runtime_checkable
class Reference(Protocol):
    """One reference stage, as ddrt.loop's tick, hold and status use it."""

    @property
    def sigma(self) -> float:
        """Progress of the reference point along the path (m; 0 without a path)."""

    @property
    def cross_track(self) -> float:
        """The robot's signed lateral offset from the path (m, left positive; 0 without a path)."""

    @property
    def done(self) -> bool:
        """Finished: at the end of the path, or at rest after a stop (the loop then stops)."""

    @property
    def stopping(self) -> bool:
        """A stop was asked (`request_stop`): `done` then means stopped part way, not at the end."""

    @property
    def phase(self) -> str:
        """What the stage is doing, for status: turn, join, release, follow (ddrt/path/start.py), drive."""

    @property
    def resumable(self) -> bool:
        """Can `resume` restart it from where the robot stands (after a hold stopped the robot)?"""

    def update(self, x: float, y: float, theta: float, sp: Setpoint, dt: float | None = None) -> None:
        """Fill `sp` for the robot at (x, y, theta), `dt` s after the previous call (None: one period)."""

    def request_stop(self, decel: float) -> None:
        """Come to rest at no more than `decel` m/s^2 (a controlled stop along the path)."""

    def resume(self, x: float, y: float, theta: float) -> None:
        """Restart from rest with the robot at (x, y, theta); ValueError unless `resumable`."""
