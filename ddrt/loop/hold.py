"""Transient faults degrade, persistent ones latch: when the loop holds, when a hold ends and
when a fault that keeps coming back latches (docs/design.md, "Faults").

- A gap in the samples while moving (the loop stalled, the sensors went stale for longer
  than `estimator.max_gap_s` or `estimator.stale_ticks`, a HAL read timed out) puts the
  loop in `holding`: a controlled stop along the path, or the motors to zero at once when
  the robot has been blind for longer than the motors' own watchdog
  (`estimator.zero_motors_after_s`, default the HAL's DRIVE timeout). When fresh samples are
  back and the robot is at rest, the hold ends: the loop resumes the path from where the
  robot is (`daemon.on_recover: resume`) or stops and waits for a command (`wait`).
- Such a fault latches `fault` only if it persists: no fresh sample for
  `estimator.fault_latch_s`, more than `estimator.max_holds` holds within
  `estimator.hold_window_s`, or a hold that does not end.

`HoldMachine`'s rules decide and count with plain numbers (times, gaps, fresh or not, at rest or
not), so they can be driven on their own; `enter` and `step` carry out what they decide on the
loop (ddrt/loop/tick.py): the motors to zero, the controlled stop, the resume, the fault.
"""

from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Protocol

from ddrt.config import Config
from ddrt.core.estimator import EstimatorHealth
from ddrt.core.types import Sample
from ddrt.loop.modes import Event
from ddrt.loop.states import LoopState

if TYPE_CHECKING:
    from ddrt.loop.tick import ControlLoop

__all__ = ["ActiveHold", "DEFAULT_ZERO_AFTER_S", "HoldBounds", "HoldMachine", "RECOVER_FRESH_TICKS",
           "RecoveryCounters", "SensorGaps"]

log = logging.getLogger("ddrt.loop")

RECOVER_FRESH_TICKS = 10  # fresh samples in a row before a hold may end
DEFAULT_ZERO_AFTER_S = 0.1  # a HAL whose motors have no watchdog: the microcontroller's default


@dataclass
class RecoveryCounters:
    """What the loop did about transient faults (status, stats, telemetry)."""

    holds: int = 0  # controlled stops on a sensor gap / stale samples / a read timeout
    stalls: int = 0  # of them, gaps because the loop itself did not run (a busy or stopped host)
    zeroed: int = 0  # holds in which the motors went to zero at once (blind beyond the watchdog)
    resumes: int = 0  # holds that ended by resuming the path
    waits: int = 0  # holds that ended stopped (daemon.on_recover: wait, or a stop was asked)
    latched: int = 0  # transient faults that persisted and latched
    longest_hold_s: float = 0.0
    last_cause: str = ""

    def as_dict(self) -> dict[str, float | int | str]:
        return {"holds": self.holds, "stalls": self.stalls, "zeroed": self.zeroed, "resumes": self.resumes, "waits": self.waits,
                "latched": self.latched, "longest_hold_s": self.longest_hold_s, "last_cause": self.last_cause}


@dataclass
class ActiveHold:
    """The hold in progress."""

    cause: str
    resume_to: LoopState  # the state it interrupted: FOLLOWING resumes, STOPPING ends stopped
    zeroed: bool = False  # the motors went to zero (no controlled stop along the path)
    ticks: int = 0
    fresh: int = 0  # fresh samples in a row


@dataclass(frozen=True)
class HoldBounds:
    """The numbers the rules use, from the config (`estimator:`, `daemon.on_recover`) and the HAL."""

    period_s: float  # the loop's
    latch_s: float  # estimator.fault_latch_s: blind this long, the fault latches
    zero_after_s: float  # blind this long, the motors go to zero (the motors' own watchdog)
    stale_ticks: int  # estimator.stale_ticks stale samples in a row are a gap
    max_holds: int  # estimator.max_holds on the sensors' account ...
    hold_window_s: float  # ... within estimator.hold_window_s latch
    resume: bool = True  # daemon.on_recover: resume (else wait): a path's hold ends by resuming it

    @classmethod
    def of(cls, cfg: Config, drive_timeout_s: float | None, period_s: float) -> "HoldBounds":
        """`drive_timeout_s`: the HAL's DRIVE watchdog (HalInfo.drive_timeout_s; None: none)."""
        e = cfg.estimator
        zero_after = (e.zero_motors_after_s if e.zero_motors_after_s is not None
                      else drive_timeout_s if drive_timeout_s is not None else DEFAULT_ZERO_AFTER_S)
        return cls(period_s=period_s, latch_s=e.fault_latch_s, zero_after_s=zero_after,
                   stale_ticks=e.stale_ticks, max_holds=e.max_holds, hold_window_s=e.hold_window_s,
                   resume=cfg.daemon.on_recover == "resume")


class SensorGaps(Protocol):
    """What the rules read from the estimator (ddrt.core.estimator.Estimator) each tick."""

    blind_s: float  # without a fresh sample for this long
    gap_s: float  # the gap between the last two samples the estimator fused (0: none)
    stall_s: float  # of that gap, the interval in which the loop itself did not run
    max_gap: float  # a gap longer than this is one
    health: EstimatorHealth  # its stale_ticks: stale samples in a row


class HoldMachine:
    """The hold in progress (`active`), the counters, and the rules that start and end it."""

    def __init__(self, bounds: HoldBounds) -> None:
        self.bounds = bounds  # replaced whole on a reload (rebound)
        self.counters = RecoveryCounters()
        self.active: ActiveHold | None = None
        self._starts: deque[float] = deque()  # sample times at which holds on the sensors' account began

    def rebound(self, bounds: HoldBounds) -> None:
        """A reload's bounds, in force from the next check."""
        self.bounds = bounds

    # ------------------------------------------------------------------ outside a hold

    def persistent(self, gaps: SensorGaps, read_error: str = "") -> str:
        """Why the fault latches now (blind for estimator.fault_latch_s), counted; else ''.
        (Never while blind_s is 0: fault_latch_s > max_gap_s > 0, ddrt.config.) `read_error`:
        the HAL's timeout this tick, while reads keep timing out."""
        if not gaps.blind_s >= self.bounds.latch_s:
            return ""
        self.counters.latched += 1
        what = (f"sensor read timed out ({read_error})" if read_error
                else f"sensors stale for {gaps.health.stale_ticks} ticks")
        return (f"{what}: {gaps.blind_s:.3f} s without a fresh sample "
                f"(estimator.fault_latch_s = {self.bounds.latch_s:g} s)")

    def transient(self, gaps: SensorGaps, read_error: str = "") -> str:
        """Why the sensors cannot be trusted this tick (a hold while moving), or ''."""
        if not (gaps.blind_s or gaps.gap_s or read_error):
            return ""
        if read_error:
            return f"sensor read timed out: {read_error}"
        if gaps.gap_s > gaps.max_gap:
            stalled = " (the loop did not run)" if gaps.stall_s > 0.0 else ""
            return f"sensor gap of {gaps.gap_s * 1000:.1f} ms{stalled}"
        stale = gaps.health.stale_ticks
        if gaps.blind_s > gaps.max_gap or stale >= self.bounds.stale_ticks:
            return f"sensors stale for {stale} ticks ({gaps.blind_s * 1000:.0f} ms without a fresh sample)"
        return ""

    def begin(self, cause: str, t: float, stall: bool, interrupted: LoopState, blind_s: float) -> str:
        """Start a hold at sample time `t` of the state it `interrupted`, blind for `blind_s`;
        '' or why it latches instead (counted).

        Holds on the sensors' account (stale samples, read timeouts) count towards
        estimator.max_holds: sensors that keep failing latch, and the restart that follows
        re-opens the devices. A stall of the loop itself does not: it is over when the loop
        runs again, each one is held safely, and a restart cannot cure a busy host (it would
        only lose the path). Blind beyond the motors' watchdog, the hold starts `zeroed`."""
        b = self.bounds
        rec = self.counters
        rec.last_cause = cause
        if not stall:
            starts = self._starts
            starts.append(t)
            while starts and starts[0] < t - b.hold_window_s:
                starts.popleft()
            if len(starts) > b.max_holds:
                rec.latched += 1
                return (f"{cause}: {len(starts)} holds within {b.hold_window_s:g} s "
                        f"(estimator.max_holds = {b.max_holds})")
        else:
            rec.stalls += 1
        rec.holds += 1
        self.active = ActiveHold(cause=cause, resume_to=interrupted)
        if blind_s >= b.zero_after_s:
            self.zero()
        return ""

    # ------------------------------------------------------------------ during a hold

    @property
    def braking(self) -> bool:
        """A hold is in progress and brakes along the path (the motors are not at zero)."""
        return self.active is not None and not self.active.zeroed

    def zero(self) -> None:
        """The motors of the hold in progress go to zero (the loop zeroes them), counted once."""
        h = self.active
        assert h is not None
        if not h.zeroed:
            h.zeroed = True
            self.counters.zeroed += 1

    def tick(self, blind_s: float) -> bool:
        """One more tick of the hold, blind for `blind_s`; True when its motors must go to zero
        now (blind beyond the motors' watchdog while it was braking)."""
        h = self.active
        assert h is not None
        h.ticks += 1
        held_s = h.ticks * self.bounds.period_s
        if held_s > self.counters.longest_hold_s:
            self.counters.longest_hold_s = held_s
        if not h.zeroed and blind_s >= self.bounds.zero_after_s:
            self.zero()
            return True
        return False

    def recovered(self, fresh: bool, at_rest: bool) -> bool:
        """Has the hold done its job: RECOVER_FRESH_TICKS fresh samples in a row, the robot at rest?"""
        h = self.active
        assert h is not None
        h.fresh = h.fresh + 1 if fresh else 0
        return h.fresh >= RECOVER_FRESH_TICKS and at_rest

    def overdue(self, v_max: float, decel: float) -> str:
        """Why the hold latches (counted): it has not ended within estimator.fault_latch_s + twice
        the time to stop from `v_max` at `decel` + 1 s; else ''."""
        h = self.active
        assert h is not None
        limit_s = self.bounds.latch_s + 2.0 * v_max / decel + 1.0
        if h.ticks * self.bounds.period_s <= limit_s:
            return ""
        self.counters.latched += 1
        return f"{h.cause}: the hold did not end within {limit_s:.1f} s (sensors back and the robot at rest)"

    def stop_when_over(self) -> None:
        """A stop was asked during the hold: it ends stopped, not resumed."""
        if self.active is not None:
            self.active.resume_to = LoopState.STOPPING

    def end(self, resumed: bool) -> ActiveHold:
        """The hold is over, by resuming the path or stopped (counted); returns it."""
        h = self.active
        assert h is not None
        self.active = None
        if resumed:
            self.counters.resumes += 1
        else:
            self.counters.waits += 1
        return h

    def cancel(self) -> None:
        """Forget the hold in progress (a reset, a new path), uncounted."""
        self.active = None

    # ------------------------------------------------------------------ on the loop

    def enter(self, loop: ControlLoop, cause: str, t: float, stall: bool) -> None:
        """Hold the loop (moving, its sensors not to be trusted since sample time `t`): a
        controlled stop along its reference, or the motors to zero at once; or the fault, when
        holds keep coming."""
        est = loop.estimator
        if why := self.begin(cause, t, stall, loop.state, max(est.blind_s, est.gap_s)):
            loop.enter_fault(why)
            return
        loop.fire(Event.HOLD)
        if not self.braking:
            loop.zero_motors()
        elif loop.reference is not None:
            loop.reference.request_stop(_hold_decel(loop))
        log.warning("holding: %s; %s", cause,
                    "decelerating to a stop along the path" if self.braking else "motors zeroed")

    def step(self, loop: ControlLoop, sample: Sample, stamp: Callable[[], None]) -> None:
        """One tick of the loop in `holding`, after the estimator took `sample`."""
        est = loop.estimator
        blind = max(est.blind_s, est.gap_s)
        if self.tick(blind):
            loop.zero_motors()
            log.warning("holding: blind for %.0f ms, beyond the motors' watchdog: motors zeroed", blind * 1000)
        ref = loop.reference
        if not self.braking:
            loop.write_zero()
        elif ref is not None:
            loop.steer(ref, stamp)  # the controlled stop along the path
        else:
            self.zero()
            loop.zero_motors()
            loop.write_zero()
        if loop.state != LoopState.HOLDING:
            return  # the stop itself faulted (off the path, a write failed)
        if self.recovered(sample.fresh, loop.at_rest):
            self._end(loop)
            return
        lim = loop.limits.limits  # numbers, even where the config's are null
        if why := self.overdue(lim.v_max, min(_hold_decel(loop), lim.accel)):
            loop.enter_fault(why)

    def _end(self, loop: ControlLoop) -> None:
        """Fresh samples and the robot at rest: resume the path, or stop and wait for a command."""
        h = self.active
        assert h is not None
        ref = loop.reference
        if (h.resume_to == LoopState.FOLLOWING and self.bounds.resume and ref is not None
                and ref.resumable and not (ref.done and not ref.stopping)):
            self.end(resumed=True)
            loop.resume_reference(ref)
            log.info("hold ended (%s): resuming the path at %.3f m", h.cause, ref.sigma)
        else:
            self.end(resumed=False)
            loop.fire(Event.HOLD_STOPPED)  # the motors to zero
            log.info("hold ended (%s): stopped, waiting for a command", h.cause)


def _hold_decel(loop: ControlLoop) -> float:
    """The hardest braking the path's limits allow (the speed profile's own)."""
    if loop.path is not None:
        return loop.path.limits.decel_eff  # may be inf: the stop then brakes as the motors allow
    return loop.limits.limits.accel
