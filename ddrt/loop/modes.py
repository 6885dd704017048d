"""The loop's mode machine: its states (ddrt/loop/states.py) and every change between them,
declared once in `TRANSITIONS`, in the manner of a lifecycle node.

A row says: in these states, this event goes to that state (or stays), if its guard allows,
and runs its entry action. An event with no row for the state the loop is in is refused with
one message that names the request and the state ("follow refused in estop: send reset
first"); an event that is never refused (stop, estop, a fault, reset, shutdown, a reload)
changes nothing there instead. `ModeMachine` is the only code that assigns a state:
`ControlLoop` is one (it inherits the machine), so the tick reads its state as a plain
attribute, and a state change, which is rare, costs a dictionary look-up.

What an event does besides changing the state (a path's reference, a hold's braking) stays
in the loop method that fires it; the table holds what every such change shares: where it
may go, what refuses it, and the motors to zero on the way into rest or a fault.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from typing import Callable

from ddrt.errors import DdrtError
from ddrt.loop.states import LoopState

__all__ = ["Event", "ModeMachine", "ModeRefused", "Transition", "TRANSITIONS", "modes_md", "refusal", "refused_in", "row"]

IDLE, FOLLOWING, STOPPING, STOPPED = LoopState.IDLE, LoopState.FOLLOWING, LoopState.STOPPING, LoopState.STOPPED
ESTOP, FAULT, HOLDING, DRIVING = LoopState.ESTOP, LoopState.FAULT, LoopState.HOLDING, LoopState.DRIVING
ALL = tuple(LoopState)
AT_REST = (IDLE, STOPPED)


class ModeRefused(DdrtError, ValueError, RuntimeError):
    """A request the loop's state (or a guard) does not allow; the loop changed nothing.
    Catch it by this kind; it is a ValueError and a RuntimeError too, so a caller that catches
    either (a bad request, or a latched state) catches it."""


class Event(Enum):
    """What may change the loop's state: requests (follow, drive, ...) and what the tick finds."""

    FOLLOW = "follow"  # a path or any reference starts (ControlLoop.follow, follow_reference)
    DRIVE = "drive"  # velocity mode: start driving, or a new command while driving
    STOP = "stop"  # a controlled stop: along the path, by the drive's ramp, or a hold's end
    RESUME = "resume"  # an interrupted path resumes from where the robot stands
    CALIBRATE = "calibrate"  # the gyro's bias measured at rest
    POSE = "pose"  # "the robot is here": the estimator's pose set
    RELOAD = "reload"  # a new config put in force between two ticks
    ARRIVE = "arrive"  # the reference is done and the robot at rest
    HOLD = "hold"  # a transient sensor fault while moving (ddrt/loop/hold.py)
    RECOVER = "recover"  # a hold ends by resuming the path
    HOLD_STOPPED = "hold_stopped"  # a hold ends stopped, waiting for a command
    FAULT = "fault"  # a fault that cannot wait
    ESTOP = "estop"  # an emergency stop, requested or the hardware input
    RESET = "reset"  # leave estop or fault
    SHUTDOWN = "shutdown"  # the process stops

    def __str__(self) -> str:
        return self.value


Guard = Callable[["ModeMachine"], str]  # why the change is refused now, or ''
Action = Callable[["ModeMachine"], None]


def _zero(host: ModeMachine) -> None:
    host.zero_motors()


def _start(host: ModeMachine) -> str:
    return host.start_guard()


def _resume(host: ModeMachine) -> str:
    return host.resume_guard() or host.start_guard()


def _drive(host: ModeMachine) -> str:
    return host.drive_guard() or host.start_guard()


def _reset(host: ModeMachine) -> str:
    return host.reset_guard()


@dataclass(frozen=True)
class Transition:
    """In any of `sources`, `event` goes to `to` (None: stays), if `guard` gives ''; then `enter` runs."""

    event: Event
    sources: tuple[LoopState, ...]
    to: LoopState | None
    about: str
    guard: Guard | None = None
    enter: Action | None = None
    guard_about: str = ""  # the guard, in words (the reference page)
    enter_about: str = ""  # the entry action, in words


ZERO = "the motors to zero"
NOTHING_TO_RESUME = ("nothing to resume (only a path interrupted by a hold, with daemon.on_recover: wait, "
                     "or stopped by a low battery, is resumed)")
BATTERY = "the battery is not low (limits.battery_min_v)"

TRANSITIONS: tuple[Transition, ...] = (
    Transition(Event.FOLLOW, AT_REST, FOLLOWING, "start following a path (or calibration's turn)",
               _start, None, BATTERY),
    Transition(Event.DRIVE, AT_REST, DRIVING, "start the velocity mode", _drive, None,
               BATTERY + "; controller.mode is not seed"),
    Transition(Event.DRIVE, (DRIVING,), None, "a new velocity command", _drive, None,
               BATTERY + "; controller.mode is not seed"),
    Transition(Event.STOP, (FOLLOWING,), STOPPING, "decelerate to a stop along the path"),
    Transition(Event.STOP, (DRIVING,), None, "brake to rest within the drive's limits"),
    Transition(Event.STOP, (HOLDING,), None, "the hold ends stopped, not resumed"),
    Transition(Event.RESUME, (STOPPED,), FOLLOWING, "resume an interrupted path from where the robot stands",
               _resume, None, "a path a hold or a low battery interrupted; " + BATTERY),
    Transition(Event.CALIBRATE, AT_REST, None, "measure the gyro's bias with the motors at zero"),
    Transition(Event.POSE, (IDLE, STOPPED, ESTOP, FAULT), None, "set the estimator's pose, the robot at rest"),
    Transition(Event.RELOAD, ALL, None, "a new config in force between two ticks"),
    Transition(Event.ARRIVE, (FOLLOWING, STOPPING, DRIVING), STOPPED, "the reference is done, the robot at rest",
               None, _zero, "", ZERO),
    Transition(Event.HOLD, (FOLLOWING, STOPPING, DRIVING), HOLDING,
               "samples missing or stale while moving: a controlled stop (ddrt/loop/hold.py)"),
    Transition(Event.RECOVER, (HOLDING,), FOLLOWING, "the hold ends: fresh samples, at rest; resume the path"),
    Transition(Event.HOLD_STOPPED, (HOLDING,), STOPPED, "the hold ends stopped, waiting for a command",
               None, _zero, "", ZERO),
    Transition(Event.FAULT, ALL, FAULT, "a fault that cannot wait; latched until reset", None, _zero, "", ZERO),
    Transition(Event.ESTOP, ALL, ESTOP, "emergency stop; latched until reset", None, _zero, "", ZERO),
    Transition(Event.RESET, ALL, IDLE, "leave estop or fault (or whatever runs) for idle", _reset, _zero,
               "the hardware estop input is closed", ZERO),
    Transition(Event.SHUTDOWN, (IDLE, FOLLOWING, STOPPING, HOLDING, DRIVING), STOPPED, "the process stops",
               None, _zero, "", ZERO),
    Transition(Event.SHUTDOWN, (ESTOP, FAULT), None, "the process stops; the latched state stays",
               None, _zero, "", ZERO),
)

# Events that are never refused for the state alone: with no row, they change nothing.
QUIET = frozenset({Event.STOP, Event.RELOAD, Event.FAULT, Event.ESTOP, Event.RESET, Event.SHUTDOWN})

# What to do instead, for a request refused in a state: per (event, state), else per state.
_ADVICE: dict[LoopState, str] = {
    ESTOP: "send reset first",
    FAULT: "send reset first",
    HOLDING: "a sensor gap: wait until the hold ends (or stop)",
    FOLLOWING: "send stop first",
    STOPPING: "send stop first",
    DRIVING: "send stop first, and follow once status says 'stopped'",
    IDLE: "nothing to do",
    STOPPED: "nothing to do",
}
_EVENT_ADVICE: dict[tuple[Event, LoopState], str] = {
    (Event.FOLLOW, STOPPING): ("the robot is still stopping on its last path; send follow again once status "
                               "says 'stopped' (estop stops it at once)"),
    (Event.DRIVE, FOLLOWING): "a drive does not take over a path; send stop, and drive once status says 'stopped'",
    (Event.DRIVE, STOPPING): "a drive does not take over a path; drive once status says 'stopped'",
    (Event.CALIBRATE, DRIVING): "send stop first",
    (Event.CALIBRATE, STOPPING): "wait until status says 'stopped'",
    **{(Event.POSE, s): ("send stop, and set the pose once status says 'stopped' (or send the measured pose "
                         "as a pose_fix)") for s in (FOLLOWING, STOPPING, DRIVING, HOLDING)},
    **{(Event.RESUME, s): NOTHING_TO_RESUME for s in ALL if s not in (ESTOP, FAULT, HOLDING)},
}

_TABLE: dict[tuple[Event, LoopState], Transition] = {}
for _t in TRANSITIONS:
    for _s in _t.sources:
        assert (_t.event, _s) not in _TABLE, f"two rows for {_t.event} in {_s}"
        _TABLE[(_t.event, _s)] = _t


def row(event: Event, state: LoopState) -> Transition | None:
    """The table's row for `event` in `state`, or None."""
    return _TABLE.get((event, state))


def refused_in(event: Event, state: LoopState) -> str:
    """The refusal of `event` in `state` by the table's rows alone, or '' (its guard is asked
    when it fires): a service refuses a request before it prepares anything for it."""
    if _TABLE.get((event, state)) is not None or event in QUIET:
        return ""
    return refusal(event, state)


def refusal(event: Event, state: LoopState, why: str = "") -> str:
    """The one message of a refused request: the request, the state, and what to do."""
    advice = why or _EVENT_ADVICE.get((event, state)) or _ADVICE[state]
    return f"{event} refused in {state}: {advice}"


class ModeMachine:
    """The state and the one place that changes it, by the table. `ControlLoop` is one, and
    gives the table's guards and entry action what they ask (the methods below)."""

    def __init__(self) -> None:
        self.state = IDLE

    def zero_motors(self) -> None:
        """The entry action into rest, estop and fault."""
        raise NotImplementedError

    def start_guard(self) -> str:
        """Why the robot may not start moving now, or ''."""
        raise NotImplementedError

    def drive_guard(self) -> str:
        """Why the velocity mode is refused (by the config), or ''."""
        raise NotImplementedError

    def resume_guard(self) -> str:
        """Why there is nothing to resume, or ''."""
        raise NotImplementedError

    def reset_guard(self) -> str:
        """Why a reset is refused now, or ''."""
        raise NotImplementedError

    def allow(self, event: Event) -> Transition | None:
        """The transition `event` takes now; None for a quiet event with no row here;
        ModeRefused (naming the request and the state) for anything else it may not do."""
        state = self.state
        t = _TABLE.get((event, state))
        if t is None:
            if event in QUIET:
                return None
            raise ModeRefused(refusal(event, state))
        if t.guard is not None and (why := t.guard(self)):
            raise ModeRefused(refusal(event, state, why))
        return t

    def enter(self, t: Transition | None) -> None:
        """Make the transition `allow` gave (in this state): the new state, then its entry action."""
        if t is None:
            return
        assert self.state in t.sources, f"{t.event} from {self.state}: allowed in {t.sources}"
        if t.to is not None:
            self.state = t.to
        if t.enter is not None:
            t.enter(self)

    def fire(self, event: Event) -> None:
        """`allow` and `enter` in one: the event now, or ModeRefused."""
        self.enter(self.allow(event))


def modes_md() -> str:
    """docs/reference/modes.md: the states and the transition table, from `TRANSITIONS`."""
    lines = [
        "# The loop's modes",
        "",
        "Generated by `python -m ddrt.docgen` from ddrt/loop/modes.py; do not edit by hand.",
        "",
        "The loop is in one of these states (telemetry's `state` column holds the code):",
        "",
        "| code | state |",
        "|---|---|",
        *[f"| {s.value} | `{s.label}` |" for s in LoopState],
        "",
        "Every change of state is one of these rows. `to` blank: the state stays.",
        "",
        "| event | from | to | what | guard | on entry |",
        "|---|---|---|---|---|---|",
    ]
    for t in TRANSITIONS:
        src = "any" if t.sources == ALL else ", ".join(f"`{s.label}`" for s in t.sources)
        to = f"`{t.to.label}`" if t.to is not None else ""
        lines.append(f"| `{t.event}` | {src} | {to} | {t.about} | {t.guard_about} | {t.enter_about} |")
    lines += [
        "",
        "A request with no row for the loop's state is refused, and the loop changes nothing; the",
        "reply names the request and the state, for example `follow refused in estop: send reset first`.",
        f"These never are: {', '.join(f'`{e}`' for e in Event if e in QUIET)}; with no row, they change nothing.",
        "The tick's own events (`arrive`, `hold`, `recover`, `hold_stopped`) fire only where a row allows them.",
        "",
        "| request | refused in | advice |",
        "|---|---|---|",
    ]
    for event in (Event.FOLLOW, Event.DRIVE, Event.RESUME, Event.POSE, Event.CALIBRATE):
        for s in LoopState:
            if row(event, s) is None:
                lines.append(f"| `{event}` | `{s.label}` | {refusal(event, s).split(': ', 1)[1]} |")
    return "\n".join(lines) + "\n"
