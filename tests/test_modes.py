"""The loop's mode machine (ddrt/loop/modes.py): the table is whole and consistent, a refusal
names the request and the state and changes nothing, and a loop driven by random requests and
ticks only ever changes state by a row of the table."""

from __future__ import annotations

import random
from collections import deque
from typing import Any, Callable

import pytest

from ddrt.loop import ControlLoop, Event, LoopState, ModeRefused
from ddrt.loop.modes import QUIET, TRANSITIONS, ModeMachine, modes_md, refusal, refused_in, row
from ddrt.loop.record import COLUMNS
from ddrt.path import load_path
from ddrt.path.spec import speed_limits
from tests.support.drive_rigs import DaemonRig, Robot

REQUESTS = (Event.FOLLOW, Event.DRIVE, Event.RESUME, Event.POSE, Event.CALIBRATE)
STATE_COL = list(COLUMNS).index("state")


def test_every_event_in_every_state_has_one_row_or_is_quiet_or_refused_by_name() -> None:
    for event in Event:
        for state in LoopState:
            rows = [t for t in TRANSITIONS if t.event is event and state in t.sources]
            assert len(rows) <= 1, (event, state)
            if not rows and event not in QUIET:
                msg = refusal(event, state)
                assert msg.startswith(f"{event} refused in {state.label}: ") and len(msg) > 30, msg


def test_every_state_is_reachable_and_estop_fault_and_reset_leave_from_anywhere() -> None:
    seen, todo = {LoopState.IDLE}, deque([LoopState.IDLE])
    while todo:
        s = todo.popleft()
        for t in TRANSITIONS:
            if s in t.sources and t.to is not None and t.to not in seen:
                seen.add(t.to)
                todo.append(t.to)
    assert seen == set(LoopState)
    for s in LoopState:
        assert row(Event.ESTOP, s).to is LoopState.ESTOP
        assert row(Event.FAULT, s).to is LoopState.FAULT
        assert row(Event.RESET, s).to is LoopState.IDLE
    # The latched states are left only by reset (or a fault/estop, which latch again).
    for latched in (LoopState.ESTOP, LoopState.FAULT):
        out = {t.event for t in TRANSITIONS if latched in t.sources and t.to not in (None, latched)}
        assert out <= {Event.RESET, Event.ESTOP, Event.FAULT}, out


def test_a_request_is_allowed_only_from_rest_or_its_own_mode() -> None:
    def sources(e: Event) -> set[LoopState]:
        return {s for s in LoopState if row(e, s) is not None}

    assert sources(Event.FOLLOW) == {LoopState.IDLE, LoopState.STOPPED}
    assert sources(Event.DRIVE) == {LoopState.IDLE, LoopState.STOPPED, LoopState.DRIVING}
    assert sources(Event.RESUME) == {LoopState.STOPPED}


def test_the_reference_page_lists_every_row_and_every_refusal() -> None:
    page = modes_md()
    for t in TRANSITIONS:
        assert any(line.startswith(f"| `{t.event}` |") and t.about in line for line in page.splitlines()), t
    for event in REQUESTS:
        for s in LoopState:
            if row(event, s) is None:
                assert f"| `{event}` | `{s.label}` | {refusal(event, s).split(': ', 1)[1]} |" in page


class _Host(ModeMachine):
    """The least a machine needs: guards that say what the test sets, a count of zeroings."""

    def __init__(self, why: str = "") -> None:
        super().__init__()
        self.why = why
        self.zeroed = 0

    def zero_motors(self) -> None:
        self.zeroed += 1

    def start_guard(self) -> str:
        return self.why

    def reset_guard(self) -> str:
        return self.why

    def resume_guard(self) -> str:
        return ""

    def drive_guard(self) -> str:
        return ""


def test_a_guard_refuses_with_its_reason_and_changes_nothing() -> None:
    h = _Host(why="hardware emergency-stop input open: close it")
    assert h.state is LoopState.IDLE
    with pytest.raises(ModeRefused, match="^follow refused in idle: hardware emergency"):
        h.fire(Event.FOLLOW)
    h.fire(Event.ESTOP)
    assert h.state is LoopState.ESTOP and h.zeroed == 1
    with pytest.raises(ModeRefused, match="^reset refused in estop: hardware emergency-stop input open"):
        h.fire(Event.RESET)
    assert h.state is LoopState.ESTOP and h.zeroed == 1
    with pytest.raises(ModeRefused, match="^follow refused in estop: send reset first$"):
        h.fire(Event.FOLLOW)
    h.fire(Event.STOP)  # quiet: nothing happens
    assert h.state is LoopState.ESTOP and h.zeroed == 1
    h.fire(Event.ESTOP)  # the entry action runs again: the motors re-asserted at zero
    assert h.zeroed == 2
    h.why = ""
    h.fire(Event.RESET)
    assert h.state is LoopState.IDLE and h.zeroed == 3
    assert isinstance(ModeRefused("x"), ValueError) and isinstance(ModeRefused("x"), RuntimeError)


# ---------------------------------------------------------------------- on a real loop

LINE = {"shape": "line", "length": 0.6, "speed": 0.3}


def _allowed(event: Event, before: LoopState) -> set[LoopState]:
    t = row(event, before)
    if t is None:
        return {before}
    return {t.to if t.to is not None else before}


@pytest.mark.parametrize("seed", range(3))
def test_random_requests_and_ticks_change_state_only_by_the_table(seed: int) -> None:
    """Requests in any order, a sensor freeze now and then: a refused request changes nothing
    and says why by the request and the state; an accepted one lands where its row says; the
    telemetry row's state is the loop's."""
    rng = random.Random(seed)
    robot = Robot(daemon={"on_recover": rng.choice(["resume", "wait"])})
    loop, hal = robot.loop, robot.hal
    path = load_path(LINE, speed_limits(robot.cfg))
    ops: list[tuple[Event, Callable[[ControlLoop], Any]]] = [
        (Event.FOLLOW, lambda lp: lp.follow(path, lp.estimator_pose())),
        (Event.DRIVE, lambda lp: lp.drive(rng.uniform(-0.3, 0.3), rng.uniform(-1.0, 1.0))),
        (Event.STOP, lambda lp: lp.stop()),
        (Event.RESUME, lambda lp: lp.resume()),
        (Event.ESTOP, lambda lp: lp.estop("test")),
        (Event.RESET, lambda lp: lp.reset()),
        (Event.RELOAD, lambda lp: lp.reconfigure(lp.cfg)),
    ]
    refused = accepted = 0
    seen: set[LoopState] = set()
    for _ in range(70):
        event, op = rng.choice(ops)
        before, ref, fault = loop.state, loop.reference, loop.fault
        try:
            op(loop)
        except ModeRefused as exc:
            refused += 1
            assert str(exc).startswith(f"{event} refused in {before.label}: "), exc
            assert (loop.state, loop.reference, loop.fault) == (before, ref, fault)
        else:
            accepted += 1
            assert loop.state in _allowed(event, before), (event, before, loop.state)
        if rng.random() < 0.1:
            hal.freeze(hal.now() + 0.001, rng.choice([0.03, 0.06]))
        for _ in range(rng.choice([1, 5, 40, 150])):
            hal.sleep_until(hal.now() + loop.period)
            loop.tick()
            seen.add(loop.state)
            assert loop.row[STATE_COL] == loop.state.value
    robot.close()
    assert refused > 5 and accepted > 5, (refused, accepted)
    assert len(seen) >= 5, seen


def test_over_the_socket_a_refusal_is_the_machines_one_message(tmp_path: Any) -> None:
    rig = DaemonRig(tmp_path)
    d = rig.d
    assert d.handle({"cmd": "estop"})["state"] == "estop"
    for cmd, msg in (("follow", "follow refused in estop: send reset first"),
                     ("drive", "drive refused in estop: send reset first"),
                     ("resume", "resume refused in estop: send reset first")):
        req: dict[str, Any] = {"cmd": cmd, **({"v": 0.1, "omega": 0.0} if cmd == "drive" else {}),
                               **(LINE if cmd == "follow" else {})}
        assert d.handle(req) == {"ok": False, "error": msg}
        assert d.loop.state is LoopState.ESTOP and d.loop.reference is None
    assert d.handle({"cmd": "reset"}) == {"ok": True, "state": "idle"}


def test_refused_in_is_what_the_machine_says_without_its_guards() -> None:
    """The service's early check (before it prepares a path) and the machine agree, state by state."""
    for event in Event:
        for state in LoopState:
            h = _Host()
            h.state = state  # a test's stand-in for a loop in that state
            try:
                h.allow(event)
                said = ""
            except ModeRefused as exc:
                said = str(exc)
            assert refused_in(event, state) == said, (event, state)
