"""The robot's power as the loop sees it: the motor driver's supply voltage, measured and
filtered, put into the motor model, the controller's limits and the speed profile; the stop
on a low battery; and the hardware emergency-stop input.

The voltage. A backend that measures it (`HalInfo.battery_measured`) puts it in every
`Sample.battery_v`; a reading that is NaN (none this tick) keeps the last good value, and one
outside [PLAUSIBLE_LO, PLAUSIBLE_HI] x `robot.motor.supply_v` (a broken divider, a torn
frame) is rejected and counted. Two first-order low-passes, started at the first good
reading, follow it:

- `v`, time constant TAU_MODEL_S = 20 ms (four ticks at 200 Hz): the voltage the inverse
  motor model (the controller's duty), the estimator's prediction and the adapter use, set
  into the one `Motor` they share every tick (`Motor.set_supply_v`, a float). Short, so a
  battery sagging under a load the controller just asked for is followed within a few ticks;
  long enough to average the ADC's quantisation and the PWM's ripple.
- `v_slow`, time constant TAU_SLOW_S = 1 s: the voltage the limits and the low-battery check
  use, so an acceleration's brief sag neither moves the clamps nor stops the robot. When it
  has moved LIMITS_STEP (2 %) from the voltage the loop's limits were resolved at, they are
  resolved again at it (ddrt/core/envelope.py `resolve_limits` with the measured supply):
  the controller's clamps (v_max, accel, torque_max_nm from the motors) and the velocity
  mode's top speed follow the battery. A path is re-profiled under the motors' envelope at
  `v_slow` when it starts (`fit_path`), if it asks more than they give there; a path being
  followed keeps its profile (re-profiling holds up the loop), its clamps follow.

Without a measurement (a protocol-v1 MCU, sysfs PWM) the config's `robot.motor.supply_v` is
used throughout.

`limits.battery_min_v` (null: off; only with a measured voltage): when `v_slow` is within
WARN_MARGIN (5 %) above it, a warning, once; below it, the controlled stop along the path
(`ControlLoop.stop`, not estop) with the reason in status; a follow, drive or resume is
refused until `v_slow` is back above the minimum by HYSTERESIS (3 %), and then the robot moves
only when asked (a resume continues the path it stopped).

The hardware estop: a sample with `hw_estop` latches estop at once (`ControlLoop.estop`: the
motors to zero, the same latch as the socket's); `reset` is refused while the input is open.
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace
from typing import TYPE_CHECKING, Any

from ddrt.config import Config
from ddrt.core.envelope import resolve_limits
from ddrt.core.reference import Reference
from ddrt.core.types import HalInfo, Sample
from ddrt.loop.reload import REPROFILE_MAX_SAMPLES
from ddrt.loop.states import LoopState

if TYPE_CHECKING:
    from ddrt.loop.tick import ControlLoop
    from ddrt.path import Path

__all__ = ["HW_ESTOP_REASON", "Power"]

log = logging.getLogger("ddrt.loop")

TAU_MODEL_S = 0.02  # s: the motor model's voltage filter
TAU_SLOW_S = 1.0  # s: the limits' and the low-battery check's voltage filter
PLAUSIBLE_LO, PLAUSIBLE_HI = 0.25, 2.0  # x robot.motor.supply_v: a reading outside is rejected
LIMITS_STEP = 0.02  # relative change of v_slow that resolves the limits again
WARN_MARGIN = 0.05  # warn once when v_slow is this fraction above limits.battery_min_v
HYSTERESIS = 0.03  # v_slow must be this fraction above limits.battery_min_v to move again
HW_ESTOP_REASON = "hardware emergency-stop input open"

_ESTOP, _FAULT = LoopState.ESTOP, LoopState.FAULT


class Power:
    """The supply voltage in use and the hardware estop input, for one ControlLoop."""

    def __init__(self, cfg: Config, info: HalInfo, period_s: float) -> None:
        self.measured = info.battery_measured
        self.hw_estop_wired = info.hw_estop_wired
        self.a_model = 1.0 - math.exp(-period_s / TAU_MODEL_S)
        self.a_slow = 1.0 - math.exp(-period_s / TAU_SLOW_S)
        self.hw_estop = False  # the input was open on the last sample
        self.rejected = 0  # implausible readings
        self.last_rejected = math.nan
        self.low_stops = 0  # controlled stops for a low battery
        self.reason = ""  # why the robot may not move now (a low battery), else ""
        self.stopped_ref: Reference | None = None  # the reference the low battery stopped
        self._limits_failed = False
        self.configure(cfg)
        self.good = False  # a plausible reading arrived
        self.v = self.v_slow = self.config_v
        self.limits_v = self.config_v  # the supply the loop's limits were resolved at
        self.warned = False

    def configure(self, cfg: Config) -> None:
        """The config's part: the supply it states, the plausible range, the minimum."""
        self.config_v = cfg.robot_motor.supply_v
        self.lo = PLAUSIBLE_LO * self.config_v
        self.hi = PLAUSIBLE_HI * self.config_v
        self.min_v = cfg.limits.battery_min_v if self.measured else None

    @property
    def low(self) -> bool:
        return bool(self.reason)

    # ------------------------------------------------------------------ the tick

    def step(self, loop: ControlLoop, sample: Sample) -> None:
        """Once a tick, before the estimate: the estop input, then the voltage."""
        if sample.hw_estop:
            if not self.hw_estop:
                log.error("estop: %s; motors zeroed, latched until reset", HW_ESTOP_REASON)
            self.hw_estop = True
            if loop.state != _ESTOP and loop.state != _FAULT:
                loop.estop(HW_ESTOP_REASON)
        elif self.hw_estop:
            self.hw_estop = False
            log.info("the hardware emergency-stop input closed: reset to move again")
        x = sample.battery_v
        if not self.measured or x != x:
            return  # not measured, or no reading this tick: the last good value stays
        if not self.lo <= x <= self.hi:
            self.rejected += 1
            self.last_rejected = x
            return
        if self.good:
            self.v += self.a_model * (x - self.v)
            self.v_slow += self.a_slow * (x - self.v_slow)
        else:
            self.v = self.v_slow = x
            self.good = True
        loop.motor.set_supply_v(self.v)
        if abs(self.v_slow - self.limits_v) > LIMITS_STEP * self.limits_v:
            self.apply_limits(loop)
        if self.min_v is not None:
            self._check_low(loop, self.min_v)

    def _check_low(self, loop: ControlLoop, min_v: float) -> None:
        v = self.v_slow
        if self.reason:
            if v > min_v * (1.0 + HYSTERESIS):
                log.warning("battery at %.2f V, back above limits.battery_min_v = %g V: the robot may move again",
                            v, min_v)
                self.reason = ""
                self.warned = False
            return
        if v < min_v:
            self.reason = (f"battery low: {v:.2f} V (filtered) below limits.battery_min_v = {min_v:g} V; "
                           f"stopped along the path; follow, drive or resume once above "
                           f"{min_v * (1.0 + HYSTERESIS):.2f} V")
            log.warning("%s", self.reason)
            self.low_stops += 1
            if loop.state in (LoopState.FOLLOWING, LoopState.STOPPING, LoopState.HOLDING):
                self.stopped_ref = loop.reference
            loop.stop()
        elif not self.warned and v < min_v * (1.0 + WARN_MARGIN):
            self.warned = True
            log.warning("battery at %.2f V, within %.0f %% of limits.battery_min_v = %g V: the robot stops below it",
                        v, 100 * WARN_MARGIN, min_v)

    # ------------------------------------------------------------------ what follows the voltage

    def apply_limits(self, loop: ControlLoop) -> None:
        """Resolve the loop's limits at `v_slow` and put them in force (between two ticks)."""
        cfg = loop.cfg
        self.limits_v = self.v_slow
        try:
            limits = resolve_limits(cfg.limits, cfg.robot, replace(cfg.robot_motor, supply_v=self.v_slow))
        except ValueError as exc:  # the motors cannot overcome friction at this voltage
            if not self._limits_failed:
                log.warning("supply %.2f V: %s; the limits stay as they were", self.v_slow, exc)
            self._limits_failed = True
            return
        self._limits_failed = False
        loop.controller.set_limits(loop.put_limits(limits))

    def reconfigure(self, loop: ControlLoop, cfg: Config) -> None:
        """A reload: the new config's supply, bounds and minimum; a new motor model and new
        limits (resolved at the config's supply) get the measured voltage again."""
        self.configure(cfg)
        if not self.good:
            self.v = self.v_slow = self.limits_v = self.config_v
            return
        loop.motor.set_supply_v(self.v)
        self.limits_v = cfg.robot_motor.supply_v
        if abs(self.v_slow - self.limits_v) > LIMITS_STEP * self.limits_v:
            self.apply_limits(loop)
        if self.min_v is None:
            self.reason = ""

    def fit_path(self, path: Path) -> tuple[Path, str]:
        """`path`, re-profiled under the motors' envelope at the measured supply when that is
        lower than the one it was profiled for and the path asks more than it gives; and what
        was done, for `ControlLoop.reprofiled` ('' when nothing was)."""
        env = path.limits.envelope
        if not self.good or env is None or self.v_slow >= env.motor.supply_v:
            return path, ""
        if len(path.sigma) > REPROFILE_MAX_SAMPLES:
            note = (f"the path has {len(path.sigma)} samples, more than {REPROFILE_MAX_SAMPLES} to re-profile "
                    f"between two ticks: it keeps its profile for {env.motor.supply_v:g} V "
                    f"(measured {self.v_slow:.2f} V)")
            log.warning("follow: %s", note)
            return path, note
        env_v = replace(env, motor=replace(env.motor, supply_v=self.v_slow))
        excess = path.envelope_excess(env_v)
        if excess <= 1e-9:
            return path, ""
        new = path.reprofiled(replace(path.limits, envelope=env_v), 0)
        note = (f"the path asked up to {excess:.1%} beyond the motors at the measured {self.v_slow:.2f} V "
                f"(profiled for {env.motor.supply_v:g} V): re-profiled ({path.duration:.2f} -> "
                f"{new.duration:.2f} s)")
        log.info("follow: %s", note)
        return new, note

    # ------------------------------------------------------------------ commands

    def start_guard(self) -> str:
        """Why the robot may not start moving now (a low battery), or ''."""
        return self.reason

    def started(self) -> None:
        """The robot moves again (the mode machine allowed it): what the low battery stopped is
        no longer resumable."""
        self.stopped_ref = None

    def reset_guard(self) -> str:
        """Why a reset is refused now (the hardware estop input is open), or ''."""
        return f"{HW_ESTOP_REASON}: close it (release the button), then reset" if self.hw_estop else ""

    def resumable(self, ref: Reference | None) -> bool:
        """`ref` was stopped by a low battery (and may now be resumed from where it stopped)."""
        return ref is not None and ref is self.stopped_ref

    def status(self) -> dict[str, Any]:
        """For `ddrt ctl status`."""
        return {"measured": self.measured, "v": self.v, "v_slow": self.v_slow, "config_v": self.config_v,
                "limits_v": self.limits_v, "rejected": self.rejected,
                "min_v": self.min_v, "low": self.low, "reason": self.reason, "low_stops": self.low_stops,
                "hw_estop_wired": self.hw_estop_wired, "hw_estop_open": self.hw_estop}
