"""The daemon's audit trail in the journal: one line for every change of the loop's state and
every safety command, with its cause and who asked over which channel.

The daemon calls `StateLog.check` after each tick and after the work between two ticks; it
costs one identity comparison while the state stays the same (no allocation, no logging).
A command handler says who asked with `note(...)` before it acts: the next change of state
is logged with that cause. A safety command that changes nothing (an estop while in estop,
a stop while idle) still gets its line; a drive that changes nothing does not (a teleop
panel sends 20 of them a second). A change the loop makes by itself (the end of a path, a
hold and its end, a fault, a drive's timeout) is logged with the cause the loop knows.

At most `BURST` lines per second: beyond that lines are counted, and the count is logged
with the next line after the second is over, so a flapping sensor cannot flood the journal.

Lines look like `state following -> estop: estop over the control socket (pid 4242, uid 1000)`.
"""

from __future__ import annotations

import logging
import time
from typing import TYPE_CHECKING

from ddrt.core.drive import DriveReference
from ddrt.loop import LoopState

if TYPE_CHECKING:
    from ddrt.loop import ControlLoop

log = logging.getLogger("ddrt.service.daemon")

BURST = 10  # lines per second at most


class StateLog:
    """The last state logged, the cause a command gave for the next change, the rate limit."""

    __slots__ = ("last", "cause", "always", "_window", "_lines", "_suppressed")

    def __init__(self, state: LoopState) -> None:
        self.last = state
        self.cause = ""
        self.always = False
        self._window = 0.0
        self._lines = 0
        self._suppressed = 0

    def note(self, cause: str, always: bool = True) -> None:
        """A command about to act: `cause` says what and who. `always`: log it even if the
        state does not change (safety commands)."""
        self.cause = cause
        self.always = always

    def check(self, loop: ControlLoop) -> None:
        """After a tick, or after the commands between two ticks: log a change of state."""
        state = loop.state
        if state is self.last and not self.cause:
            return
        self._changed(loop, state)

    def _changed(self, loop: ControlLoop, state: LoopState) -> None:
        prev = self.last
        cause, always = self.cause, self.always
        self.cause = ""
        self.always = False
        if state is prev:
            if always:
                self.emit(logging.WARNING if "estop" in cause else logging.INFO,
                          f"{cause}: state stays {state.label}")
            return
        self.last = state
        cause = cause or inferred_cause(loop, prev, state)
        level = logging.WARNING if state in (LoopState.ESTOP, LoopState.FAULT, LoopState.HOLDING) else logging.INFO
        if state is LoopState.FAULT:
            level = logging.ERROR
        self.emit(level, f"state {prev.label} -> {state.label}: {cause}")

    def emit(self, level: int, line: str) -> None:
        """One line, within the rate limit."""
        now = time.monotonic()
        if now - self._window >= 1.0:
            if self._suppressed:
                log.warning("state log: %d lines left out in the last second (rate limit %d/s)",
                            self._suppressed, BURST)
            self._window = now
            self._lines = 0
            self._suppressed = 0
        if self._lines >= BURST:
            self._suppressed += 1
            return
        self._lines += 1
        log.log(level, "%s", line)


def inferred_cause(loop: ControlLoop, prev: LoopState, state: LoopState) -> str:
    """Why the loop changed state by itself, as far as it knows."""
    ref = loop.reference
    if state is LoopState.FAULT or state is LoopState.ESTOP:
        return loop.fault or "fault"
    if state is LoopState.HOLDING:
        hold = loop.holds.active
        return f"hold: {hold.cause}" if hold is not None else "hold"
    if prev is LoopState.HOLDING:
        if state is LoopState.FOLLOWING:
            return "the hold ended: resuming the path"
        return "the hold ended stopped (daemon.on_recover: wait): send resume or follow"
    if state is LoopState.STOPPED:
        if prev is LoopState.DRIVING:
            braking = ref.braking if isinstance(ref, DriveReference) else ""
            if braking == "timeout":
                return "drive timeout: no command within daemon.command_timeout_s, braked to rest"
            return f"drive ended ({braking or 'stopped'}), at rest"
        if loop.path_completed:
            return "reached the end of the path"
        return "at rest after a stop"
    return "by the loop"


def peer_text(peer: str, channel: str = "the control socket") -> str:
    """'over the control socket (pid 1, uid 0)' or without the parenthesis."""
    return f"over {channel} ({peer})" if peer else f"over {channel}"
