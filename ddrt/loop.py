"""One control tick, the same on the robot and in simulation:
read -> estimate -> reference -> control -> write -> record.

`ControlLoop` owns the estimator, the reference and the controller and knows nothing of
where the samples come from (a `hal.base.Hal`).

Transient faults degrade, persistent ones latch (docs/design.md, "Faults"):
- A gap in the samples while moving (the loop stalled, the sensors went stale for longer
  than `estimator.max_gap_s` or `estimator.stale_ticks`, a HAL read timed out) puts the
  loop in `holding`: a controlled stop along the path, or the motors to zero at once when
  the robot has been blind for longer than the motors' own watchdog
  (`estimator.zero_motors_after_s`, default the HAL's DRIVE timeout). When fresh samples are
  back and the robot is at rest, the path resumes from where the robot is
  (`daemon.on_recover: resume`) or the loop stops and waits for a command (`wait`).
- Such a fault latches `fault` only if it persists: no fresh sample for
  `estimator.fault_latch_s`, more than `estimator.max_holds` holds within
  `estimator.hold_window_s`, or a hold that does not end.
- Latched at once, motors to zero: any other HAL error, a motor write that fails, a stuck
  or saturated gyro, a stuck encoder, a non-finite number, a robot farther than
  `limits.max_path_error_m` from its path. `estop` latches until `reset`.

Velocity mode (`drive`, ddrt/core/drive.py): the state `driving`, whose reference is a
`DriveReference`; it ends `stopped` once it has braked to rest after a stop or a timeout.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass, replace
from typing import Callable

from ddrt.core.adapt import DynamicsAdapter
from ddrt.config import Config
from ddrt.config.sections import LimitsConfig
from ddrt.core.control import Command, DynamicController, KinematicController, make_controller
from ddrt.core.drive import DriveReference, check_command
from ddrt.core.types import Setpoint
from ddrt.core.envelope import ResolvedLimits, resolve_limits
from ddrt.core.estimator import Estimator, calibrate_gyro
from ddrt.core.model import Dynamics
from ddrt.core.motor import Motor
from ddrt.path import Path
from ddrt.path.reference import PathReference
from ddrt.path.start import JOIN_APPROACH_RAD, StartReference, needs_join, start_heading_offset
from hal.base import Hal, HalError, HalTimeoutError, Sample

log = logging.getLogger("ddrt.loop")

# A path with more samples left than this keeps its profile when a reload changes the robot
# (re-profiling 20 000 samples, 40 m at 2 mm, takes 0.05-0.1 s: ten to twenty ticks at 200 Hz).
REPROFILE_MAX_SAMPLES = 20_000

# Codes are the index (telemetry's `state` column): new states go at the end.
STATES = ("idle", "following", "stopping", "stopped", "estop", "fault", "holding", "driving")
MOVING = ("following", "stopping", "driving")
RECOVER_FRESH_TICKS = 10  # fresh samples in a row before a hold may end
AT_REST_V = 2e-3  # m/s and rad/s below which the robot counts as at rest
AT_REST_W = 5e-3
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
class _Hold:
    """The hold in progress."""

    cause: str
    resume_to: str  # the state it interrupted: "following" resumes, "stopping" ends stopped
    zeroed: bool = False
    ticks: int = 0
    fresh: int = 0  # fresh samples in a row

COLUMNS = (
    "t", "x_est", "y_est", "theta_est", "v_est", "omega_est", "gyro_bias",
    "x_ref", "y_ref", "theta_ref", "v_ref", "omega_ref", "v_cmd", "omega_cmd",
    "tau_l", "tau_r", "duty_l", "duty_r", "sigma", "cross_track_est", "saturated", "state",
    "fresh", "hal_fault_ticks",
    "ad_m_k", "ad_mbar", "ad_I", "ad_m_x", "ad_fric_l", "ad_fric_r", "ad_active",
)
STATE_CODE = {name: float(i) for i, name in enumerate(STATES)}


def _drive_limits(resolved: ResolvedLimits) -> LimitsConfig:
    """ControlLoop.drive_limits for given resolved limits."""
    return replace(resolved.limits, v_max=resolved.profile_v_max)


def _no_stamp() -> None:
    """The tick's stage stamp outside benchmarks: nothing."""


class ControlLoop:
    """The controller around one HAL: calibrate, follow a path, stop safely."""

    def __init__(self, cfg: Config, hal: Hal) -> None:
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
        self.reference: PathReference | StartReference | DriveReference | None = None
        self.path: Path | None = None
        self.setpoint = Setpoint()
        self.idle_cmd = Command()
        self.cmd = self.idle_cmd
        self.state = "idle"
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
        self._adapt_active = False
        self.reprofiled = ""  # what the last reload did to the path being followed
        self.on_tick: Callable[["ControlLoop"], None] | None = None
        self.recovery = RecoveryCounters()
        self._hold: _Hold | None = None
        self._hold_times: deque[float] = deque()  # sample times at which holds began
        self._read_error = ""  # the HAL's timeout, while reads keep timing out
        self._limits_after_braking: LimitsConfig | None = None  # the controller's, once a drive is within them
        self._set_bounds(cfg)

    def _set_bounds(self, cfg: Config) -> None:
        """The hold's bounds from the config and the HAL."""
        e = cfg.estimator
        self._latch_s = e.fault_latch_s
        watchdog = getattr(self.hal.info, "drive_timeout_s", None)
        self.zero_after = (e.zero_motors_after_s if e.zero_motors_after_s is not None
                           else watchdog if watchdog is not None else DEFAULT_ZERO_AFTER_S)

    def reconfigure(self, cfg: Config) -> None:
        """Put a config in force between two ticks: every part that holds a copy gets it.

        `cfg` is what ddrt.config.policy.plan_reload returned (its restart-only fields are the
        running ones, so the rate, the mode and the devices never change here). Everything
        new is built before anything is swapped, so a part that refuses leaves all as it was.
        """
        model_changed = cfg.robot != self.cfg.robot or cfg.robot_motor != self.cfg.robot_motor
        if model_changed:
            dyn = Dynamics.from_params(cfg.robot)
            seed_dyn = Dynamics.from_params(cfg.robot, seed_report=True)
            motor = Motor(cfg.robot_motor)
            adapter = (DynamicsAdapter(dyn, motor, cfg.controller.adaptation, self.period)
                       if self.adapter is not None else None)
        else:
            dyn, seed_dyn, motor, adapter = self.dyn, self.seed_dyn, self.motor, self.adapter
        limits = resolve_limits(cfg.limits, cfg.robot, cfg.robot_motor)
        # Swap (nothing below raises for values that passed validation).
        self.estimator.reconfigure(cfg.estimator, cfg.robot.r_3,
                                   self.estimator.dyn if not model_changed else dyn, motor)
        ctrl = limits.limits
        self._limits_after_braking = None
        ref = self.reference
        if isinstance(ref, DriveReference):
            ref.configure(_drive_limits(limits), cfg.drive, cfg.daemon.command_timeout_s)
            if ref.over(ctrl.v_max, ctrl.omega_max):
                # Lower top speeds while the robot is faster: the ramp brakes it to them within
                # the limits; the controller's clamps, cut at once, would brake it as hard as
                # the inner loop can (5 m/s^2 from 0.8 to 0.3 m/s, measured). They take the new
                # limits once the setpoint is within them (_drive).
                self._limits_after_braking = ctrl
                ctrl = replace(ctrl, v_max=max(ctrl.v_max, abs(ref.v.value)),
                               omega_max=max(ctrl.omega_max, abs(ref.w.value)))
        self.controller.retune(cfg.controller, ctrl)
        self.limits = limits
        if model_changed:
            self.dyn, self.seed_dyn, self.motor = dyn, seed_dyn, motor
            self.controller.set_model(seed_dyn if cfg.controller.mode == "seed" else dyn, motor)
            # A new robot description invalidates what the adapter learnt about the old one.
            self.adapter = adapter
            self._adapt_active = False
        self.cfg = cfg
        self._set_bounds(cfg)
        if model_changed:
            self._reprofile()

    def _reprofile(self) -> None:
        """A new robot model: if the rest of the path being followed asks more than its motors
        give (beyond the profile's headroom), rebuild the rest of the profile for it.

        The schedule's interval and everything before it keep their speeds and times, so the
        reference does not jump; the path's own limits (and the headroom it was built with)
        stay, only the model changes. A path with more than REPROFILE_MAX_SAMPLES samples left
        keeps its profile (rebuilding it would hold up the loop); the next path uses the new
        model whatever happens here."""
        self.reprofiled = ""
        ref, path = self.reference, self.path
        if (path is None or not isinstance(ref, PathReference) or ref.path is not path or self.state != "following"
                or path.limits.envelope is None):
            return
        env = replace(path.limits.envelope, dyn=self.dyn, motor=self.motor.params)
        first = path.index(path.at_time(ref.t_sched).sigma) + 1
        left = len(path.sigma) - first
        if left < 2:
            return
        if left > REPROFILE_MAX_SAMPLES:
            self.reprofiled = (f"the path being followed has {left} samples left, more than {REPROFILE_MAX_SAMPLES} "
                               "to re-profile between two ticks: it keeps its profile; the next path uses the new model")
            log.warning("reload: %s", self.reprofiled)
            return
        excess = path.envelope_excess(env, first)
        if excess <= 1e-9:
            return
        new = path.reprofiled(replace(path.limits, envelope=env), first)
        ref.path = new
        ref.pursuit.path = new
        self.path = new
        self.reprofiled = (f"the rest of the path asked up to {excess:.1%} beyond the new robot's motors: re-profiled "
                           f"from progress {path.sigma[first]:.3f} m ({path.duration:.2f} -> {new.duration:.2f} s)")
        log.info("reload: %s", self.reprofiled)

    # ------------------------------------------------------------------ start-up

    def calibrate(self, sleep_until: Callable[[float], float], now: Callable[[], float]) -> tuple[float, float]:
        """Hold the motors at zero and measure the gyro bias at rest; returns (bias, std)."""
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

    # ------------------------------------------------------------------ commands

    def follow(self, path: Path, pose: tuple[float, float, float] | None = None) -> None:
        """Start following `path`; `pose` (if given) resets the dead-reckoned pose.

        A start the robot cannot make as it stands is made a start it can (ddrt/path/start.py):
        a start heading more than `pursuit.max_start_heading_deg` from the robot's is turned
        to in place first (or refused, with `pursuit.start_turn: refuse`), and a start off
        the path or off its heading is joined at no more than the path's speed."""
        self._check_start(path, pose)
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
        self.follow_reference(ref, pose, path)

    def follow_reference(self, reference: PathReference | StartReference | DriveReference, pose: tuple[float, float, float] | None = None,
                         path: Path | None = None) -> None:
        """Start following any reference with PathReference's interface (update, done, sigma,
        cross_track, request_stop): calibration's turn in place is one."""
        self._check_start(path, pose)
        if pose is not None:
            self.estimator.set_pose(pose)
        self._take_deferred_limits()
        self.reference = reference
        self.path = path
        sp = self.setpoint
        sp.v_cap = sp.omega_cap = sp.y_cap = math.inf  # a previous start's caps end here
        self.controller.reset()
        self.state = "following"
        self._hold = None
        self._starting = True  # the robot stood still until now: a pause before this is no gap

    def _check_start(self, path: Path | None, pose: tuple[float, float, float] | None) -> None:
        if self.state in ("estop", "fault"):
            raise RuntimeError(f"cannot follow a path in state {self.state}: reset first")
        if self.state == "holding":
            raise ValueError("holding after a sensor gap: wait until it ends (or stop)")
        if self.state == "driving":
            raise ValueError("driving: send stop first, and follow once status says 'stopped'")
        if path is not None:
            x, y, _ = pose if pose is not None else self.estimator_pose()
            start = path.at(0.0)
            why = self._off_path(x, y, start.x, start.y)
            if why:
                raise ValueError(f"the path's start is {why}: move the robot or the path")

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
        return (self.state == "stopped" and ref is not None and ref.done
                and not getattr(ref, "stopping", False))

    def drive_limits(self) -> LimitsConfig:
        """The velocity mode's limits in numbers: the config's, null ones from the motors;
        its top speed the one the profile plans to (within limits.feedback_headroom), so the
        inner loop keeps room to correct at full speed."""
        return _drive_limits(self.limits)

    def drive(self, v: object, omega: object, source: str = "") -> tuple[float, float, tuple[str, ...]]:
        """Hold the velocities (v, omega) until the next command, a stop, or
        daemon.command_timeout_s without one (ddrt/core/drive.py); returns them as limited
        and the fields that were clamped. Changes nothing when it refuses: ValueError for a
        value that is no plausible velocity (naming it), with controller.mode seed, and while holding, following or
        stopping a path (a drive does not take over a path: stop it first); RuntimeError in
        estop or fault (reset first)."""
        v_lim, w_lim, clamped = check_command(v, omega, self.drive_limits())
        if self.cfg.controller.mode == "seed":
            # Its weak fixed inner gains hold a speed only with the outer law's pose feedback
            # (measured: 0.17 m/s for a 0.3 m/s command); it is there to compare paths.
            raise ValueError("controller.mode seed (the report's method, for comparison on paths) does not "
                             "drive: use dynamic or kinematic")
        state = self.state
        if state in ("estop", "fault"):
            raise RuntimeError(f"cannot drive in state {state}: reset first")
        if state == "holding":
            raise ValueError("holding after a sensor gap: wait until it ends (or stop)")
        if state in ("following", "stopping"):
            raise ValueError(f"{state} a path: a drive does not take over a path; send stop, and drive once "
                             "status says 'stopped'")
        ref = self.reference
        if state != "driving" or not isinstance(ref, DriveReference):
            d = self.cfg
            ref = DriveReference(self.drive_limits(), d.drive, d.daemon.command_timeout_s, self.period)
            self.follow_reference(ref)
            self.state = "driving"
            log.info("driving (%s): v %.3f m/s, omega %.3f rad/s", source or "a command", v_lim, w_lim)
        ref.command(v_lim, w_lim, (float(v), float(omega)), source)  # type: ignore[arg-type]
        return v_lim, w_lim, clamped

    def stop(self) -> None:
        """Controlled stop along the path (in a hold: end it stopped, do not resume); in
        the velocity mode, braking to rest within its limits as on a timeout."""
        if self.state == "following" and self.reference is not None:
            self.reference.request_stop(self.cfg.daemon.stop_decel)
            self.state = "stopping"
        elif self.state == "driving" and self.reference is not None:
            self.reference.request_stop(self.limits.limits.accel)
        elif self.state == "holding" and self._hold is not None:
            self._hold.resume_to = "stopping"

    def resume(self) -> None:
        """Resume an interrupted path from where the robot stands (after a hold ended
        stopped, with daemon.on_recover: wait)."""
        ref = self.reference
        if self.state != "stopped" or ref is None or ref.done or not hasattr(ref, "resume"):
            raise ValueError(f"nothing to resume in state {self.state}")
        est = self.estimator
        ref.resume(est.x, est.y, est.theta)
        self.controller.reset()
        self.state = "following"
        self._starting = True

    def estop(self, reason: str = "estop requested") -> None:
        """Motors to zero now, latched until reset()."""
        self._zero_motors()
        self.state = "estop"
        self.fault = reason

    def reset(self) -> None:
        """Leave estop/fault: back to idle, motors still at zero."""
        self._zero_motors()
        self.controller.reset()
        self._take_deferred_limits()
        self.reference = None
        self.estimator.health.fault = ""
        self.fault = ""
        self._hold = None
        self.state = "idle"

    def shutdown(self) -> None:
        """The process is stopping: motors to zero, and a last row that shows it."""
        self._zero_motors()
        if self.state in ("following", "stopping", "idle", "holding", "driving"):
            self.state = "stopped"
        self._record(self.sample.t if self.sample is not None else 0.0)

    def enter_fault(self, reason: str) -> None:
        self._zero_motors()
        if self.state != "fault":
            log.error("fault: %s; motors zeroed", reason)
        self.state = "fault"
        self.fault = reason

    def _zero_motors(self) -> None:
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
        try:
            sample = self.hal.read()
            self._read_error = ""
        except HalTimeoutError as exc:
            # The device stopped answering within its bound: a transient fault until it
            # persists. The estimator dead-reckons through a stale copy of the last sample.
            if self.sample is None:
                self.enter_fault(f"sensor read failed: {exc}")
                self._record(0.0)
                return
            self._read_error = str(exc)
            last = self.sample
            sample = Sample(t=last.t + self.period, encoder_count=last.encoder_count,
                            gyro_z_raw=last.gyro_z_raw, fresh=False, faults="read_timeout")
        except HalError as exc:
            self.enter_fault(f"sensor read failed: {exc}")
            self._record(self.sample.t + self.period if self.sample else 0.0)
            return
        stamp()
        self.sample = sample
        if sample.faults:
            self.hal_fault_ticks += 1
        state = self.state
        hold = self._hold
        moving = state in MOVING or (state == "holding" and hold is not None and not hold.zeroed)
        est = self.estimator
        est.update(sample, self.duty_l, self.duty_r, commanded_still=not moving or self._starting)
        self._starting = False
        if self.adapter is not None and state in MOVING:
            self._adapt()
        if state != "fault" and state != "estop":
            if est.health.fault:
                self.enter_fault(est.health.fault)
            elif est.blind_s >= self._latch_s:
                self.recovery.latched += 1
                self.enter_fault(self._persistent())
            elif (est.blind_s or est.gap_s or self._read_error) and state in MOVING and (why := self._transient()):
                self._enter_hold(why, sample.t, stall=est.stall_s > 0.0)
            state = self.state
        if state == "holding":
            self._tick_holding(sample, stamp)
        elif state in MOVING:
            self._drive(stamp)
        elif state != "fault":
            # Standing still is a command too: one write per tick keeps a serial bridge's
            # watchdog fed and re-asserts zero if anything else touched the motors.
            self._write_zero()
        stamp()
        self._record(sample.t)
        stamp()
        if self.on_tick is not None:
            self.on_tick(self)

    def _drive(self, stamp: Callable[[], None] = _no_stamp) -> None:
        """Reference -> control -> checks -> write, for a robot that moves along its path."""
        est = self.estimator
        ref = self.reference
        sp = self.setpoint
        stamp()
        ref.update(est.x, est.y, est.theta, sp, est.dt)  # type: ignore[union-attr]
        if (after := self._limits_after_braking) is not None and not (
                isinstance(ref, DriveReference) and ref.over(after.v_max, after.omega_max)):
            self._take_deferred_limits()  # braked down to a reload's lower top speeds
        stamp()
        cmd = self.controller.update(est.x, est.y, est.theta, est.v, est.omega, sp)
        stamp()
        if ref.done and abs(est.v) < AT_REST_V and abs(est.omega) < AT_REST_W:  # type: ignore[union-attr]
            if self.state == "holding":
                self._zero_motors()  # at rest at the end of the stop: the hold decides what next
                return
            self.state = "stopped"
            self._zero_motors()
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
        if self._limits_after_braking is not None:
            self.controller.set_limits(self._limits_after_braking)
            self._limits_after_braking = None

    def _write_zero(self) -> None:
        try:
            self.hal.write(0.0, 0.0)
        except HalError as exc:
            self.enter_fault(f"motor write failed: {exc}")

    # ------------------------------------------------------------------ transient faults

    def _transient(self) -> str:
        """Why the sensors cannot be trusted this tick (a hold while moving), or ''."""
        est = self.estimator
        if self._read_error:
            return f"sensor read timed out: {self._read_error}"
        if est.gap_s > est.max_gap:
            stalled = " (the loop did not run)" if est.stall_s > 0.0 else ""
            return f"sensor gap of {est.gap_s * 1000:.1f} ms{stalled}"
        h = est.health
        if est.blind_s > est.max_gap or h.stale_ticks >= self.cfg.estimator.stale_ticks:
            return f"sensors stale for {h.stale_ticks} ticks ({est.blind_s * 1000:.0f} ms without a fresh sample)"
        return ""

    def _persistent(self) -> str:
        """Why a transient fault that has lasted estimator.fault_latch_s latches."""
        est = self.estimator
        what = (f"sensor read timed out ({self._read_error})" if self._read_error
                else f"sensors stale for {est.health.stale_ticks} ticks")
        return f"{what}: {est.blind_s:.3f} s without a fresh sample (estimator.fault_latch_s = {self._latch_s:g} s)"

    def _enter_hold(self, cause: str, t: float, stall: bool = False) -> None:
        """Stop in a controlled way (or zero the motors at once) and wait for the sensors.

        Holds on the sensors' account (stale samples, read timeouts) count towards
        estimator.max_holds: sensors that keep failing latch, and the restart that follows
        re-opens the devices. A stall of the loop itself does not: it is over when the loop
        runs again, each one is held safely, and a restart cannot cure a busy host (it would
        only lose the path)."""
        e = self.cfg.estimator
        rec = self.recovery
        rec.last_cause = cause
        if not stall:
            times = self._hold_times
            times.append(t)
            while times and times[0] < t - e.hold_window_s:
                times.popleft()
            if len(times) > e.max_holds:
                rec.latched += 1
                self.enter_fault(f"{cause}: {len(times)} holds within {e.hold_window_s:g} s "
                                 f"(estimator.max_holds = {e.max_holds})")
                return
        else:
            rec.stalls += 1
        rec.holds += 1
        self._hold = _Hold(cause=cause, resume_to=self.state)
        self.state = "holding"
        est = self.estimator
        if max(est.blind_s, est.gap_s) >= self.zero_after:
            self._zero_hold()
        elif self.reference is not None:
            self.reference.request_stop(self._hold_decel())
        log.warning("holding: %s; %s", cause,
                    "motors zeroed" if self._hold.zeroed else "decelerating to a stop along the path")

    def _hold_decel(self) -> float:
        """The hardest braking the path's limits allow (the speed profile's own)."""
        if self.path is not None:
            return self.path.limits.decel_eff  # may be inf: the stop then brakes as the motors allow
        return self.limits.limits.accel

    def _zero_hold(self) -> None:
        self._zero_motors()
        assert self._hold is not None
        self._hold.zeroed = True
        self.recovery.zeroed += 1

    def _tick_holding(self, sample: Sample, stamp: Callable[[], None]) -> None:
        h = self._hold
        assert h is not None
        est = self.estimator
        h.ticks += 1
        held_s = h.ticks * self.period
        if held_s > self.recovery.longest_hold_s:
            self.recovery.longest_hold_s = held_s
        if not h.zeroed and max(est.blind_s, est.gap_s) >= self.zero_after:
            self._zero_hold()
            log.warning("holding: blind for %.0f ms, beyond the motors' watchdog: motors zeroed",
                        max(est.blind_s, est.gap_s) * 1000)
        if h.zeroed:
            self._write_zero()
        elif self.reference is not None:
            self._drive(stamp)  # the controlled stop along the path
        else:
            self._zero_hold()
            self._write_zero()
        if self.state != "holding":
            return  # the stop itself faulted (off the path, a write failed)
        h.fresh = h.fresh + 1 if sample.fresh else 0
        at_rest = abs(est.v) < AT_REST_V and abs(est.omega) < AT_REST_W
        if h.fresh >= RECOVER_FRESH_TICKS and at_rest:
            self._end_hold()
            return
        lim = self.limits.limits  # numbers, even where the config's are null
        decel = min(self._hold_decel(), lim.accel)
        limit_s = self.cfg.estimator.fault_latch_s + 2.0 * lim.v_max / decel + 1.0
        if held_s > limit_s:
            self.recovery.latched += 1
            self.enter_fault(f"{h.cause}: the hold did not end within {limit_s:.1f} s "
                             "(sensors back and the robot at rest)")

    def _end_hold(self) -> None:
        h = self._hold
        assert h is not None
        self._hold = None
        ref = self.reference
        if (h.resume_to == "following" and self.cfg.daemon.on_recover == "resume" and ref is not None
                and hasattr(ref, "resume") and not (ref.done and not ref.stopping)):
            est = self.estimator
            ref.resume(est.x, est.y, est.theta)
            self.controller.reset()
            self.state = "following"
            self._starting = True
            self.recovery.resumes += 1
            log.info("hold ended (%s): resuming the path at %.3f m", h.cause, ref.sigma)
        else:
            self._zero_motors()
            self.state = "stopped"
            self.recovery.waits += 1
            log.info("hold ended (%s): stopped, waiting for a command", h.cause)

    def _adapt(self) -> None:
        """Feed the adapter; every 10th tick move the model in use towards its estimate."""
        ad = self.adapter
        est = self.estimator
        ad.update(est.v, est.yaw.w, self.duty_l, self.duty_r)  # type: ignore[union-attr]
        if self.ticks % 10 == 0:
            active = ad.trusted  # type: ignore[union-attr]
            if active or self._adapt_active:
                dyn = ad.blend(10 * self.period)  # type: ignore[union-attr]
                self.controller.set_dynamics(dyn)
                if self.cfg.controller.adaptation.update_estimator:
                    est.dyn = dyn
            self._adapt_active = active or ad.used != ad.theta0  # type: ignore[union-attr]

    def _record(self, t: float) -> None:
        e = self.estimator
        sp = self.setpoint
        c = self.cmd
        r = self.row
        r[0] = t
        r[1] = e.x
        r[2] = e.y
        r[3] = e.theta
        r[4] = e.v
        r[5] = e.yaw.w
        r[6] = e.yaw.b
        r[7] = sp.x_d
        r[8] = sp.y_d
        r[9] = sp.theta_d
        r[10] = sp.v_d
        r[11] = sp.omega_d
        r[12] = c.v_c
        r[13] = c.omega_c
        r[14] = c.tau_l
        r[15] = c.tau_r
        r[16] = self.duty_l
        r[17] = self.duty_r
        ref = self.reference
        r[18] = ref.sigma if ref is not None else 0.0
        r[19] = ref.cross_track if ref is not None else 0.0
        r[20] = 1.0 if c.saturated else 0.0
        r[21] = STATE_CODE[self.state]
        s = self.sample
        r[22] = 1.0 if (s is not None and s.fresh) else 0.0
        r[23] = float(self.hal_fault_ticks)
        ad = self.adapter
        if ad is not None:
            th = ad.theta
            r[24] = th[0]
            r[25] = th[1]
            r[26] = th[2]
            r[27] = th[3]
            r[28] = th[4]
            r[29] = th[5]
            r[30] = 1.0 if self._adapt_active else 0.0
