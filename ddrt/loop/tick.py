"""`ControlLoop`: one control tick, the same on the robot and in simulation:
read -> estimate -> reference -> control -> write -> record.

It owns the estimator, the reference stage and the controller and knows nothing of where the
samples come from (a `hal.base.Hal`). Transient faults (a gap in the samples while moving)
put it in `holding`, whose rules are ddrt/loop/hold.py's; faults that cannot wait latch at
once, motors to zero: any other HAL error, a motor write that fails, a stuck or saturated
gyro, a stuck encoder, a non-finite number, a robot farther than `limits.max_path_error_m`
from its path. `estop` latches until `reset` (docs/design.md, "Faults").

Velocity mode (`drive`, ddrt/core/drive.py): the state `driving`, whose reference is a
`DriveReference`; it ends `stopped` once it has braked to rest after a stop or a timeout.
"""

from __future__ import annotations

import logging
import math
from dataclasses import replace
from typing import Callable

from ddrt.config import Config
from ddrt.errors import DdrtError
from ddrt.config.sections import LimitsConfig
from ddrt.core.adapt import DynamicsAdapter
from ddrt.core.control import Command, DynamicController, KinematicController, make_controller
from ddrt.core.drive import DriveReference, check_command
from ddrt.core.envelope import ResolvedLimits, resolve_limits
from ddrt.core.estimator import Estimator, calibrate_gyro
from ddrt.core.model import Dynamics
from ddrt.core.motor import Motor
from ddrt.core.reference import Reference
from ddrt.core.types import Setpoint
from ddrt.loop.hold import HoldBounds, HoldMachine, RecoveryCounters
from ddrt.loop.modes import NOTHING_TO_RESUME, Event, ModeMachine, Transition
from ddrt.loop.power import Power
from ddrt.loop.record import COLUMNS, fill_row
from ddrt.loop.reload import Reprofile, drive_limits, limits_plan, prepare_reload, reprofile
from ddrt.loop.states import MOVING, LoopState
from ddrt.path import Path
from ddrt.path.frame import Transform, in_map
from ddrt.path.reference import PathReference
from ddrt.path.start import JOIN_APPROACH_RAD, StartReference, needs_join, start_heading_offset
from hal.base import Hal, HalError, HalTimeoutError, Sample

log = logging.getLogger("ddrt.loop")

AT_REST_V = 2e-3  # m/s and rad/s below which the robot counts as at rest
AT_REST_W = 5e-3

# The states the tick tests every tick, as module names: on Python 3.11 a member looked up on
# its Enum class costs about 0.1 us, five times a module global.
FOLLOWING, STOPPED = LoopState.FOLLOWING, LoopState.STOPPED
ESTOP, FAULT, HOLDING, DRIVING = LoopState.ESTOP, LoopState.FAULT, LoopState.HOLDING, LoopState.DRIVING


class StartTooFar(DdrtError, ValueError):
    """A path refused because its start is farther from the robot than limits.max_path_error_m
    (a caller that can place the path at the robot says how)."""


def _no_stamp() -> None:
    """The tick's stage stamp outside benchmarks: nothing."""


class ControlLoop(ModeMachine):
    """The controller around one HAL: calibrate, follow a path, stop safely. Its state changes
    only by its mode machine's table (ddrt/loop/modes.py)."""

    def __init__(self, cfg: Config, hal: Hal) -> None:
        super().__init__()  # the mode machine: idle
        self.cfg = cfg
        self.hal = hal
        self.period = 1.0 / cfg.controller.rate_hz
        self.dyn = Dynamics.from_params(cfg.robot)
        self.seed_dyn = Dynamics.from_params(cfg.robot, seed_report=True)
        self.motor = Motor(cfg.robot_motor)
        # The limits in numbers: the config's caps, null ones from what the motors give.
        self.limits = resolve_limits(cfg.limits, cfg.robot, cfg.robot_motor)
        self.estimator = Estimator(self.dyn, self.motor, cfg.estimator, hal.info, cfg.robot.r_3, self.period)
        self.controller: DynamicController | KinematicController = make_controller(
            cfg.controller.mode, self.dyn, self.seed_dyn, self.motor, cfg.controller, self.limits.limits, self.period)
        self.reference: Reference | None = None
        self.path: Path | None = None
        self.setpoint = Setpoint()
        self.idle_cmd = Command()
        self.cmd = self.idle_cmd
        self.fault = ""
        self.ticks = 0
        self.saturated_ticks = 0
        self._starting = False
        self.hal_fault_ticks = 0  # ticks whose sample reported a fault (retry, hold, lost packets)
        self.sample: Sample | None = None
        self.duty_l = 0.0
        self.duty_r = 0.0
        self.row = [0.0] * len(COLUMNS)
        # The adaptive law drives the dynamic controller's compensator and the estimator's
        # prediction; the seed's method keeps its own (deliberately reproduced) model.
        self.adapter: DynamicsAdapter | None = None
        if cfg.controller.adaptation.enabled and cfg.controller.mode == "dynamic":
            self.adapter = DynamicsAdapter(self.dyn, self.motor, cfg.controller.adaptation, self.period)
        self.adapt_active = False  # the adapter's model is in use
        self.reprofiled = ""  # what the last reload did to the path being followed
        self._on_tick: Callable[["ControlLoop"], None] | None = None  # each_tick
        self.holds = HoldMachine(HoldBounds.of(cfg, hal.info.drive_timeout_s, self.period))
        # A reload's lower top speeds for the controller, once a drive has braked within them.
        self.limits_after_braking: LimitsConfig | None = None
        self.power = Power(cfg, hal.info, self.period)  # the supply voltage, the hardware estop

    def each_tick(self, callback: Callable[["ControlLoop"], None] | None) -> None:
        """Call `callback(loop)` at the end of every tick from now on (None: no more); a tool
        that records or identifies along a run (calibration, commissioning) watches it so."""
        self._on_tick = callback

    @property
    def recovery(self) -> RecoveryCounters:
        """What the loop did about transient faults so far (status, stats)."""
        return self.holds.counters

    def reconfigure(self, cfg: Config) -> None:
        """Put a config in force between two ticks: every part that holds a copy gets it. All
        that is new is built first (ddrt/loop/reload.py), so a part that refuses leaves all as
        it was."""
        t = self.allow(Event.RELOAD)
        plan = prepare_reload(cfg, self.cfg, self.period, self.adapter is not None)
        m = plan.model
        # Swap (nothing below raises for values that passed validation).
        self.estimator.reconfigure(cfg.estimator, cfg.robot.r_3, self.estimator.dyn if m is None else m.dyn,
                                   self.motor if m is None else m.motor)
        self.controller.retune(cfg.controller, self.put_limits(plan.limits, cfg))
        if m is not None:
            self.dyn, self.seed_dyn, self.motor = m.dyn, m.seed_dyn, m.motor
            self.controller.set_model(m.seed_dyn if cfg.controller.mode == "seed" else m.dyn, m.motor)
            self.adapter, self.adapt_active = m.adapter, False  # what it learnt was about the old robot
        self.cfg = cfg
        self.holds.rebound(HoldBounds.of(cfg, self.hal.info.drive_timeout_s, self.period))
        self.power.reconfigure(self, cfg)  # the measured supply into the new motor model and limits
        if m is not None:
            self._reprofile()
        self.enter(t)

    def put_limits(self, limits: ResolvedLimits, cfg: Config | None = None) -> LimitsConfig:
        """Make `limits` (of `cfg`, the loop's by default) the loop's, the velocity mode's ramp
        included; returns the limits the controller takes now (the caller sets them)."""
        plan = limits_plan(limits, self.reference, cfg or self.cfg)
        self.limits, self.limits_after_braking = limits, plan.after_braking
        return plan.now

    def _reprofile(self) -> None:
        """A new robot model: the rest of the path being followed re-profiled when it asks more
        than the new motors give (ddrt/loop/reload.py); what was done goes in `reprofiled`."""
        ref = self.reference
        r = (reprofile(ref, self.path, self.dyn, replace(self.motor.params, supply_v=self.power.limits_v))
             if self.state == FOLLOWING else Reprofile())
        self.reprofiled = r.note
        if r.path is not None and isinstance(ref, PathReference):
            ref.reprofiled(r.path)
            self.path = r.path
            log.info("reload: %s", r.note)
        elif r.note:
            log.warning("reload: %s", r.note)

    # ------------------------------------------------------------------ start-up

    def calibrate(self, sleep_until: Callable[[float], float], now: Callable[[], float]) -> tuple[float, float]:
        """Hold the motors at zero and measure the gyro bias at rest; returns (bias, std)."""
        self.fire(Event.CALIBRATE)
        self.hal.stop()
        est_cfg = self.cfg.estimator
        n = max(10, int(round(est_cfg.calibration_s / self.period)))
        raw: list[int] = []
        t = now() + self.period
        sleep_until(t)  # a device may need one period after opening to deliver a sample
        sample = self.hal.read()
        for _ in range(n):
            t += self.period
            sleep_until(t)
            sample = self.hal.read()
            self.power.step(self, sample)  # the supply known before the first path; the estop input
            if sample.fresh:  # a value the HAL held through a pause would count twice
                raw.append(sample.gyro_z_raw)
        bias, std = calibrate_gyro(raw, self.hal.info.gyro_lsb_per_rad_s, est_cfg.gyro_scale,
                                   est_cfg.calibration_max_std_dps)
        self.estimator.reset(sample, self.estimator_pose(), bias)
        self.sample = sample
        log.info("gyro bias %.4f deg/s (noise %.4f deg/s) from %d samples",
                 math.degrees(bias), math.degrees(std), n)
        return bias, std

    def estimator_pose(self) -> tuple[float, float, float]:
        e = self.estimator
        return e.x, e.y, e.theta

    @property
    def at_rest(self) -> bool:
        """The estimated speeds are below AT_REST_V and AT_REST_W."""
        est = self.estimator
        return abs(est.v) < AT_REST_V and abs(est.omega) < AT_REST_W

    # ------------------------------------------------------------------ commands

    def follow(self, path: Path, pose: tuple[float, float, float] | None = None,
               built: Transform | None = None) -> None:
        """Start following `path`; `pose` (if given) resets the dead-reckoned pose; `built`
        (a path in map, built in odom as the correction map -> odom stood then) steers it in
        odom as the map frame moves (ddrt/path/frame.py).

        A start the robot cannot make as it stands is made a start it can (ddrt/path/start.py):
        a start heading more than `pursuit.max_start_heading_deg` from the robot's is turned
        to in place first (or refused, with `pursuit.start_turn: refuse`), and a start off
        the path or off its heading is joined at no more than the path's speed."""
        self._check_start(path, pose)  # refused before any work
        path, note = self.power.fit_path(path)  # under the motors at the measured supply
        if note:
            self.reprofiled = note
        p = self.cfg.pursuit
        ref: PathReference | StartReference = PathReference(
            path, p.lookahead_m, p.search_window_m, self.period,
            time_indexed=(p.mode == "time" or self.cfg.controller.mode == "seed"))
        x, y, theta = pose if pose is not None else self.estimator_pose()
        start = path.at(0.0)
        offset = start_heading_offset(start.theta, theta)
        turn = abs(offset) > math.radians(p.max_start_heading_deg)
        if turn and p.start_turn == "refuse":
            raise ValueError(f"the path starts {math.degrees(abs(offset)):.0f} deg from the robot's heading, more "
                             f"than pursuit.max_start_heading_deg = {p.max_start_heading_deg:g} deg "
                             f"(pursuit.start_turn: refuse): turn the robot or the path")
        join = needs_join(math.hypot(start.x - x, start.y - y), offset)
        if turn or join:
            outer = self.cfg.controller.outer
            ref = StartReference(ref, (x, y, theta), path.limits, self.period, turn=turn, join=join,
                                 y_cap=outer.k_theta * math.sin(JOIN_APPROACH_RAD) / outer.k_y)
        if built is None:
            self.follow_reference(ref, pose, path)
        else:
            self.follow_reference(in_map(ref, self.estimator.frame, built, self.cfg.estimator.map_blend_s,
                                         self.period), pose, path)

    def follow_reference(self, reference: Reference, pose: tuple[float, float, float] | None = None,
                         path: Path | None = None) -> None:
        """Start following any reference stage (calibration's turn in place is one)."""
        self.enter(self._check_start(path, pose))
        self._start_reference(reference, pose, path)

    def _start_reference(self, reference: Reference, pose: tuple[float, float, float] | None,
                         path: Path | None) -> None:
        """Make `reference` the loop's, from rest (the caller makes the state change)."""
        if pose is not None:
            self.estimator.set_pose(pose)
        self._take_deferred_limits()
        self.reference = reference
        self.path = path
        sp = self.setpoint
        sp.v_cap = sp.omega_cap = sp.y_cap = math.inf  # a previous start's caps end here
        self.controller.reset()
        self.holds.cancel()
        self._starting = True  # the robot stood still until now: a pause before this is no gap

    def _check_start(self, path: Path | None, pose: tuple[float, float, float] | None) -> Transition | None:
        """The follow's transition, or ModeRefused; StartTooFar for a path that starts far away."""
        t = self.allow(Event.FOLLOW)
        if path is not None:
            x, y, _ = pose if pose is not None else self.estimator_pose()
            start = path.at(0.0)
            why = self._off_path(x, y, start.x, start.y)
            if why:
                raise StartTooFar(f"the path's start is {why}: move the robot or the path")
        self.power.started()
        return t

    # The table's guards (ddrt/loop/modes.py): why a change is refused now, or ''.

    def start_guard(self) -> str:
        """A low battery keeps the robot still."""
        return self.power.start_guard()

    def drive_guard(self) -> str:
        if self.cfg.controller.mode == "seed":
            # Its weak fixed inner gains hold a speed only with the outer law's pose feedback
            # (measured: 0.17 m/s for a 0.3 m/s command); it is there to compare paths.
            return ("controller.mode seed (the report's method, for comparison on paths) does not "
                    "drive: use dynamic or kinematic")
        return ""

    def resume_guard(self) -> str:
        ref = self.reference
        if ref is None or (ref.done and not self.power.resumable(ref)) or not ref.resumable:
            return NOTHING_TO_RESUME
        return ""

    def reset_guard(self) -> str:
        return self.power.reset_guard()

    def _off_path(self, x: float, y: float, px: float, py: float) -> str:
        """'' while (x, y) is within limits.max_path_error_m of the path point (px, py), else why."""
        limit = self.cfg.limits.max_path_error_m
        gap = math.hypot(px - x, py - y)
        return "" if gap <= limit else f"{gap:.3f} m from the robot, beyond limits.max_path_error_m = {limit:g} m"

    @property
    def path_completed(self) -> bool:
        """Stopped at the end of the path, not stopped part way (a hold that ended waiting
        under daemon.on_recover: wait, or a stop that was asked)."""
        ref = self.reference
        return self.state == STOPPED and ref is not None and ref.done and not ref.stopping

    def drive_limits(self) -> LimitsConfig:
        """The velocity mode's limits in numbers: the config's, null ones from the motors;
        its top speed the one the profile plans to (within limits.feedback_headroom), so the
        inner loop keeps room to correct at full speed."""
        return drive_limits(self.limits)

    def drive(self, v: object, omega: object, source: str = "") -> tuple[float, float, tuple[str, ...]]:
        """Hold the velocities (v, omega) until the next command, a stop, or
        daemon.command_timeout_s without one (ddrt/core/drive.py); returns them as limited
        and the fields that were clamped. Changes nothing when it refuses: ValueError for a
        value that is no plausible velocity (naming it); ModeRefused where the mode machine
        refuses it (ddrt/loop/modes.py: controller.mode seed, holding, following or stopping a
        path, estop, fault, a low battery)."""
        v_lim, w_lim, clamped = check_command(v, omega, self.drive_limits())
        t = self.allow(Event.DRIVE)
        self.power.started()
        ref = self.reference
        if self.state != DRIVING or not isinstance(ref, DriveReference):
            d = self.cfg
            ref = DriveReference(self.drive_limits(), d.drive, d.daemon.command_timeout_s, self.period)
            self._start_reference(ref, None, None)
            self.enter(t)
            log.info("driving (%s): v %.3f m/s, omega %.3f rad/s", source or "a command", v_lim, w_lim)
        ref.command(v_lim, w_lim, (float(v), float(omega)), source)  # type: ignore[arg-type]
        return v_lim, w_lim, clamped

    def stop(self) -> None:
        """Controlled stop along the path (in a hold: end it stopped, do not resume); in
        the velocity mode, braking to rest within its limits as on a timeout."""
        state = self.state
        t = self.allow(Event.STOP)
        if state == FOLLOWING and self.reference is not None:
            self.reference.request_stop(self.cfg.daemon.stop_decel)
        elif state == DRIVING and self.reference is not None:
            self.reference.request_stop(self.limits.limits.accel)
        elif state == HOLDING:
            self.holds.stop_when_over()
        self.enter(t)

    def resume(self) -> None:
        """Resume an interrupted path from where the robot stands (after a hold ended
        stopped, with daemon.on_recover: wait)."""
        t = self.allow(Event.RESUME)
        self.power.started()
        assert self.reference is not None  # the guard saw to it
        self.resume_reference(self.reference, t)

    def resume_reference(self, ref: Reference, t: Transition | None = None) -> None:
        """Restart `ref` from where the robot stands and follow it (by `t`, else a hold's end)."""
        if t is None:
            t = self.allow(Event.RECOVER)
        est = self.estimator
        ref.resume(est.x, est.y, est.theta)
        self.controller.reset()
        self.enter(t)
        self._starting = True

    def estop(self, reason: str = "estop requested") -> None:
        """Motors to zero now, latched until reset()."""
        self.fire(Event.ESTOP)
        self.fault = reason

    def reset(self) -> None:
        """Leave estop/fault (or whatever runs): back to idle, motors at zero; ModeRefused while
        the hardware estop input is open."""
        t = self.allow(Event.RESET)  # the motors go to zero on entering idle
        self.controller.reset()
        self._take_deferred_limits()
        self.reference = None
        self.estimator.clear_fault()
        self.fault = ""
        self.holds.cancel()
        self.enter(t)

    def shutdown(self) -> None:
        """The process is stopping: motors to zero, and a last row that shows it."""
        self.fire(Event.SHUTDOWN)
        fill_row(self.row, self, self.sample.t if self.sample is not None else 0.0)

    def enter_fault(self, reason: str) -> None:
        was = self.state
        self.fire(Event.FAULT)
        if was != FAULT:
            log.error("fault: %s; motors zeroed", reason)
        self.fault = reason

    def zero_motors(self) -> None:
        self.duty_l = self.duty_r = 0.0
        self.cmd = self.idle_cmd
        try:
            self.hal.stop()
        except Exception as exc:  # the device may be gone; the MCU's watchdog stops it then
            log.error("stop failed: %s", exc)

    # ------------------------------------------------------------------ the tick

    def tick(self, stamp: Callable[[], None] = _no_stamp) -> None:
        """read -> estimate -> reference -> control -> write -> record.

        `stamp` (benchmarks only; a no-op by default) is called at the start and after each
        stage that ran, so the cost of each stage can be measured on the real tick.
        """
        self.ticks += 1
        stamp()
        holds = self.holds
        read_error = ""  # the HAL's timeout this tick: a transient fault until it persists
        try:
            sample = self.hal.read()
        except HalTimeoutError as exc:
            # The device stopped answering within its bound: a transient fault until it
            # persists. The estimator dead-reckons through a stale copy of the last sample.
            if self.sample is None:
                self.enter_fault(f"sensor read failed: {exc}")
                fill_row(self.row, self, 0.0)
                return
            read_error = str(exc)
            last = self.sample
            sample = Sample(t=last.t + self.period, encoder_count=last.encoder_count,
                            gyro_z_raw=last.gyro_z_raw, fresh=False, faults="read_timeout")
        except HalError as exc:
            self.enter_fault(f"sensor read failed: {exc}")
            fill_row(self.row, self, self.sample.t + self.period if self.sample else 0.0)
            return
        stamp()
        self.sample = sample
        if sample.faults:
            self.hal_fault_ticks += 1
        self.power.step(self, sample)
        state = self.state
        moving = state in MOVING or (state == HOLDING and holds.braking)
        est = self.estimator
        est.update(sample, self.duty_l, self.duty_r, commanded_still=not moving or self._starting)
        self._starting = False
        ad = self.adapter
        if ad is not None and state in MOVING:
            self._adapt(ad)
        if state != FAULT and state != ESTOP:
            if est.health.fault:
                self.enter_fault(est.health.fault)
            elif est.blind_s or est.gap_s or read_error:  # a sample missed or late: the hold's rules
                if why := holds.persistent(est, read_error):
                    self.enter_fault(why)
                elif state in MOVING and (why := holds.transient(est, read_error)):
                    holds.enter(self, why, sample.t, stall=est.stall_s > 0.0)
            state = self.state
        ref = self.reference
        if state == HOLDING:
            holds.step(self, sample, stamp)
        elif state in MOVING and ref is not None:
            self.steer(ref, stamp)
        elif state != FAULT:
            # Standing still is a command too: one write per tick keeps a serial bridge's
            # watchdog fed and re-asserts zero if anything else touched the motors.
            self.write_zero()
        stamp()
        fill_row(self.row, self, sample.t)
        stamp()
        if self._on_tick is not None:
            self._on_tick(self)

    def steer(self, ref: Reference, stamp: Callable[[], None] = _no_stamp) -> None:
        """Reference -> control -> checks -> write, for a robot that moves along its reference."""
        est = self.estimator
        sp = self.setpoint
        stamp()
        ref.update(est.x, est.y, est.theta, sp, est.dt)
        if (after := self.limits_after_braking) is not None and not (
                isinstance(ref, DriveReference) and ref.over(after.v_max, after.omega_max)):
            self._take_deferred_limits()  # braked down to a reload's lower top speeds
        stamp()
        cmd = self.controller.update(est.x, est.y, est.theta, est.v, est.omega, sp)
        stamp()
        if ref.done and self.at_rest:
            if self.state == HOLDING:
                self.zero_motors()  # at rest at the end of the stop: the hold decides what next
                return
            self.fire(Event.ARRIVE)
        elif not (math.isfinite(cmd.duty_l) and math.isfinite(cmd.duty_r)
                  and math.isfinite(est.x) and math.isfinite(est.y) and math.isfinite(est.theta)):
            self.enter_fault("non-finite value in the controller")
        elif why := self._off_path(est.x, est.y, sp.x_d, sp.y_d):
            # Pushed, stuck, slipping or a wrong model: never chase a path from afar.
            self.enter_fault(f"the path's reference point is {why}")
        else:
            try:
                self.hal.write(cmd.duty_l, cmd.duty_r)
            except HalError as exc:
                self.enter_fault(f"motor write failed: {exc}")
            else:
                self.duty_l = cmd.duty_l
                self.duty_r = cmd.duty_r
                self.cmd = cmd
                if cmd.saturated:
                    self.saturated_ticks += 1

    def _take_deferred_limits(self) -> None:
        if self.limits_after_braking is not None:
            self.controller.set_limits(self.limits_after_braking)
            self.limits_after_braking = None

    def write_zero(self) -> None:
        try:
            self.hal.write(0.0, 0.0)
        except HalError as exc:
            self.enter_fault(f"motor write failed: {exc}")

    def _adapt(self, ad: DynamicsAdapter) -> None:
        """Feed the adapter; every 10th tick move the model in use towards its estimate."""
        est = self.estimator
        ad.update(est.v, est.yaw.w, self.duty_l, self.duty_r)
        if self.ticks % 10 == 0:
            active = ad.trusted
            if active or self.adapt_active:
                dyn = ad.blend(10 * self.period)
                self.controller.set_dynamics(dyn)
                if self.cfg.controller.adaptation.update_estimator:
                    est.set_dynamics(dyn)
            self.adapt_active = active or ad.used != ad.theta0
