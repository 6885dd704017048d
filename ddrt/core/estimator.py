"""State estimation: forward speed, yaw rate and gyro bias from the encoder and the gyro.

Prediction uses the robot's dynamic model driven by the torque the motors actually give
(the motor model at the applied duty and the estimated wheel speeds), so the filter knows
about accelerations before the sensors see them. Measurements: the front encoder's
travelled distance (a position, so quantisation stays white) and the raw gyro. The gyro's
zero-rate bias is calibrated at rest before the robot moves and re-tracked whenever it
stands still; outliers are gated; a sensor that stops changing or arriving is reported.

Gaps: while no fresh sample arrives the estimate dead-reckons on the model (`blind_s` says for
how long); the first fresh sample after a gap longer than `max_gap` (the loop stalled, or the
sensors were stale) re-anchors the estimate instead of fusing across the gap: the time base
and the count are re-synced, the distance the encoder counted meanwhile is put into the pose
(less what dead reckoning already put there), the speeds are re-learnt from the next samples,
and no motion is invented for the time nobody looked. Whether a gap stops the robot is the
loop's decision (ddrt/loop/hold.py: the `holding` state); `health.fault` is only set for faults
that must latch at once (a stuck or saturated gyro, a stuck encoder).

Uncertainty and pose fixes (docs/estimation.md): every step of the dead reckoning also goes
to the map frame (ddrt/core/pose_fix.py), whose history and covariances
(ddrt/core/uncertainty.py) give the pose's 1-sigma and let a late fix be fused.

Sensors: each is one fusion step (ddrt/core/fusion.py), composed here once from what HalInfo
says the robot delivers; a sensor that is not there is a step that does nothing, so every tick
runs the same calls. A fresh sample goes, in order: the drive wheels take their counts, the
front encoder fuses the distance, the gyro's step the yaw rate, the drive wheels check the turn
and the bias and (without a front encoder) fuse the distance; then, every tick, the temperature
step moves the bias and the gyro's step says how far the heading turned.
- The distance: the front encoder (ddrt/core/front_encoder.py), or the drive wheels' without one.
- The yaw rate: the register read at the tick (ddrt/core/gyro_register.py), or through the FIFO
  (HalInfo.gyro_fifo_period_s > 0, ddrt/core/gyro_fifo.py): each fresh sample's batch is fused
  at its mean rate and the heading turns over its span, so every gyro sample is integrated once.
- Temperature (HalInfo.gyro_temp_hz > 0): the bias follows the die's temperature between stops
  and is re-learnt at every stop, which also corrects the heading turned since the last one
  (ddrt/core/gyro_bias.py); without it, the bias is re-learnt at stops only.
- Drive-wheel encoders (HalInfo.wheel_counts_per_rev > 0, ddrt/core/wheel_odometry.py): the
  distance when there is no front encoder, the gyro's bias on the move, and wheel slip.
`fifo`, `wheels` and `gyro_bias` are those steps' state for reports (None without the sensor).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ddrt.config import EstimatorConfig
from ddrt.core.front_encoder import FrontEncoder, NoFront
from ddrt.core.fusion import BiasStep, DistanceStep, RateStep
from ddrt.core.gyro_bias import CalibrationError, GyroBias, StopsOnly, TemperatureBias, calibrate_gyro
from ddrt.core.gyro_fifo import FifoRate, GyroFifo, mean_rate
from ddrt.core.gyro_register import GyroRegister
from ddrt.core.kalman import TravelFilter, YawFilter
from ddrt.core.model import Dynamics
from ddrt.core.motor import Motor
from ddrt.core.pose_fix import MapFrame, PoseFix
from ddrt.core.uncertainty import ErrorModel, Tracker
from ddrt.core.types import HalInfo, Sample
from ddrt.core.wheel_odometry import NoWheels, WheelOdometry, error_model

__all__ = ["CalibrationError", "Estimator", "EstimatorHealth", "calibrate_gyro"]  # the first and last from gyro_bias.py

NOISE_STEP_S = 0.005  # the step the configured process noises are given for
_RESYNC_V_VAR = 0.01  # (m/s)^2: speed variance after a re-anchor, so the next samples set it
_RESYNC_W_VAR = 0.01  # (rad/s)^2: likewise for the yaw rate
DEG = math.pi / 180.0
UNCERTAINTY_EVERY_S = 0.02  # the map covariance is propagated this often (the odometry's every 0.1 s)


@dataclass(slots=True)
class EstimatorHealth:
    """Counters and the latest fault; the loop turns a fault into a safe stop."""

    gyro_rejects: int = 0
    encoder_rejects: int = 0
    resyncs: int = 0
    stale_ticks: int = 0  # stale samples in a row, now
    gaps: int = 0  # gaps beyond max_gap that ended while commanded to move (each re-anchored)
    longest_gap_s: float = 0.0
    wheel_slips: int = 0  # times the drive wheels began to slip (ddrt/core/wheel_odometry.py)
    fault: str = ""

    def count_slip(self) -> None:
        self.wheel_slips += 1

    def count_resync(self) -> None:
        self.resyncs += 1

    def counters(self) -> dict[str, float | int]:
        return {"gyro_rejects": self.gyro_rejects, "encoder_rejects": self.encoder_rejects,
                "resyncs": self.resyncs, "stale_ticks": self.stale_ticks, "gaps": self.gaps,
                "longest_gap_ms": self.longest_gap_s * 1000.0, "wheel_slips": self.wheel_slips}


class Estimator:
    """Kalman-filtered (v, omega), gyro bias, and a dead-reckoned pose of point A."""

    def __init__(self, dyn: Dynamics, motor: Motor, cfg: EstimatorConfig, info: HalInfo,
                 r_3: float, period_s: float) -> None:
        self.dyn = dyn
        self.motor = motor
        self.cfg = cfg
        self.period = period_s
        self.info = info
        self.metres_per_count = self.rad_s_per_lsb = 0.0
        # Two filters on the same encoder: `speed` (smooth) is what the controller feeds back,
        # `travel` (trusting the encoder over the model) is what the pose integrates. One filter
        # cannot do both: a smooth one lets a wrong model bend the dead-reckoned path, a sharp
        # one makes the PID chatter on quantisation noise. Their noises are set by _configure.
        self.travel = TravelFilter(0.0, 0.0)
        self.speed = TravelFilter(0.0, 0.0)
        # Likewise for yaw: `yaw` is fed back, `heading` (trusting the gyro) is integrated.
        self.yaw = YawFilter(0.0, 0.0, 0.0)
        self.heading = YawFilter(0.0, 0.0, 0.0)
        self.at_rest, self.rest_rate = False, math.nan  # at rest at the last fresh gyro reading, and its rate
        # The sensors' fusion steps (module doc), from what the HAL says it delivers.
        self._front: FrontEncoder | NoFront = FrontEncoder() if info.encoder_counts_per_rev > 0 else NoFront()
        self._gyro: RateStep = (FifoRate(info.gyro_fifo_period_s) if info.gyro_fifo_period_s > 0.0
                                else GyroRegister())
        self._temperature: BiasStep = TemperatureBias(period_s, cfg) if info.gyro_temp_hz > 0.0 else StopsOnly()
        counted = info.wheel_counts_per_rev > 0
        self.wheels = (WheelOdometry(info.wheel_counts_per_rev, period_s, info.encoder_counts_per_rev <= 0)
                       if counted else None)
        self._wheels: WheelOdometry | NoWheels = self.wheels if self.wheels is not None else NoWheels()
        self._distance: DistanceStep = self._front if info.encoder_counts_per_rev > 0 else self._wheels
        self.fifo: GyroFifo | None = self._gyro.fifo
        self.wheel_slip = False  # the drive wheels slip this tick (telemetry)
        self._configure(cfg, r_3)
        self.t_est = 0.0  # the time the estimate is for (the loop's clock)
        self.track = self._tracker(cfg)
        self.frame = MapFrame(cfg.fix_gate_chi2)
        self._last_gyro_z: float | None = None  # the previous rate fused (the lead's)
        self.health = EstimatorHealth()
        self.x = self.y = self.theta = 0.0
        self.dt = period_s  # the time step of the last update (what the reference advances by)
        self._last_t: float | None = None
        self._enc_rejects_row = 0
        self._gyro_rejects_row = 0
        self._count_still_s = 0.0  # time without counts while the filter says we move
        self._still_ticks = 0  # fresh samples in a row without a count of what gives the distance
        # Gaps: the newest fresh sample's time, how long the estimate has been blind, what
        # dead reckoning added to the pose meanwhile, and the gap that ended this update.
        self._last_fresh_t = 0.0
        self._blind_ticks = 0
        self._blind_travel = 0.0
        self._blind_moving = False
        self._ahead_of_anchor = 0.0  # time dead-reckoned past the anchor (repeated timestamps)
        self.blind_s = 0.0
        self.gap_s = 0.0
        self.stall_s = 0.0  # of that gap, the last interval between two updates (the loop did not run)

    # ------------------------------------------------------------------ configuration

    def _configure(self, cfg: EstimatorConfig, r_3: float) -> None:
        """Derive the scales, noises and bounds from `cfg` and the encoder wheel's radius."""
        info, period_s = self.info, self.period
        self.cfg = cfg
        cpr = info.encoder_counts_per_rev  # 0: no front encoder (the wheels give the distance)
        self.metres_per_count = 2.0 * math.pi * r_3 / cpr if cpr > 0 else 0.0
        self.rad_s_per_lsb = 1.0 / (info.gyro_lsb_per_rad_s * cfg.gyro_scale)
        self.gyro_full_scale = info.gyro_full_scale_rad_s / cfg.gyro_scale
        # The filters' noise is per step; scaled so that their bandwidth, i.e. how much they
        # trust the model, is the same at every loop rate (the configured values are per 5 ms).
        k = math.sqrt(NOISE_STEP_S / period_s)
        for filt, noise in ((self.travel, cfg.odometry_accel_noise), (self.speed, cfg.accel_noise)):
            filt.accel_var = (k * noise) ** 2
        gyro_var = (cfg.gyro_noise_dps * DEG) ** 2
        for filt, noise in ((self.yaw, cfg.yaw_accel_noise), (self.heading, cfg.odometry_yaw_accel_noise)):
            filt.yaw_accel_var = (k * noise) ** 2
            filt.bias_walk_var = cfg.gyro_bias_walk * cfg.gyro_bias_walk
            filt.meas_var = gyro_var
        self.gyro_var = gyro_var  # (rad/s)^2: one gyro reading's noise
        # The gyro's low-pass makes it lag the encoder; a heading that lags the distance
        # bends the dead-reckoned path. The lead z + tau dz/dt undoes a lag tau.
        self.gyro_lead = info.gyro_delay_s if cfg.gyro_delay_s is None else cfg.gyro_delay_s
        self.gate2 = cfg.gate_sigma * cfg.gate_sigma
        # How long the estimate may go without a fresh sample while moving: ten ticks, but
        # never less than max_gap_s, so a fast loop does not stop on a host's hiccup.
        self.max_gap = max(10.0 * period_s, cfg.max_gap_s)
        self._front.configure(self.metres_per_count)
        self._temperature.configure(cfg)
        self._wheels.configure(self)
        # The travel filters' position noise: the quantisation of what gives the distance.
        self.travel.meas_var = self.speed.meas_var = self._distance.position_var

    def _tracker(self, cfg: EstimatorConfig) -> Tracker:
        """The pose's uncertainty and history at this config (ddrt/core/uncertainty.py)."""
        per = self.period
        return Tracker(self._error_model(cfg), int(math.ceil(cfg.fix_history_s / per)) + 2,
                       max(1, int(round(UNCERTAINTY_EVERY_S / per))), max(1, int(round(5 * UNCERTAINTY_EVERY_S / per))))

    def _error_model(self, cfg: EstimatorConfig) -> ErrorModel:
        return error_model(cfg, self.period, self.metres_per_count <= 0.0)

    def reconfigure(self, cfg: EstimatorConfig, r_3: float, dyn: Dynamics, motor: Motor) -> None:
        """Take a new tuning, encoder radius (a calibrated r_3), gyro scale or model between
        two ticks, without a jump in the estimate.

        The travelled distance is re-based at the new metres per count, so the position
        measurement stays continuous; the yaw rate and the gyro bias, which are raw readings
        times the gyro's scale, are rescaled with it.
        """
        old_lsb = self.rad_s_per_lsb
        old_cfg = self.cfg
        travelled = self._distance.z
        self.dyn = dyn
        self.motor = motor
        self._configure(cfg, r_3)
        self._retrack(old_cfg, cfg)
        for f in (self.travel, self.speed):
            f.p -= travelled
        self._front.rebase()
        self._wheels.rebase()
        ratio = self.rad_s_per_lsb / old_lsb
        if ratio != 1.0:
            for f in (self.yaw, self.heading):
                f.w *= ratio
                f.b *= ratio
            if self._last_gyro_z is not None:
                self._last_gyro_z *= ratio
            self._temperature.rescale(ratio)

    def _retrack(self, old: EstimatorConfig, cfg: EstimatorConfig) -> None:
        """A reload's uncertainty figures: the scale errors' rows rescaled (so the covariance
        stays positive), a new history length takes a fresh history at the present pose."""
        self.track.rescale(self._error_model(cfg))
        self.frame.regate(cfg.fix_gate_chi2)
        if cfg.fix_history_s != old.fix_history_s:
            track = self._tracker(cfg)
            track.reset(self.t_est, self.map_pose())
            track.carry(self.track)
            self.track = track
            self.frame.history_restarted(self.t_est)

    # ------------------------------------------------------------------ set-up

    def reset(self, sample: Sample, pose: tuple[float, float, float], bias: float) -> None:
        """Start from a known pose at rest, with a calibrated gyro bias (rad/s)."""
        self.x, self.y, self.theta = pose
        self._last_t = sample.t
        self._front.reset(sample)
        for f in (self.travel, self.speed):
            f.p = 0.0
            f.v = 0.0
        for f in (self.yaw, self.heading):
            f.w = 0.0
            f.b = bias
        self._last_gyro_z = None
        self._gyro.reset(sample)
        self._wheels.reset(sample)
        self._last_fresh_t = sample.t
        self._blind_ticks = 0
        self._blind_travel = 0.0
        self._blind_moving = False
        self._ahead_of_anchor = 0.0
        self.blind_s = self.gap_s = 0.0
        self.health.stale_ticks = 0
        self.t_est = sample.t
        self.track.reset(sample.t, pose)
        self.frame.reset(pose, anchored=False)  # nothing says where map is yet
        self._temperature.reset(self.cfg)  # a new calibration: a temperature's line starts again from it

    def set_pose(self, pose: tuple[float, float, float], cov: list[float] | None = None,
                 anchored: bool = True) -> None:
        """The robot is at `pose` (in both frames: the map correction is cleared), known to
        `cov` (a 3x3 covariance, 9 floats row by row; None: exactly). `anchored`: this is
        where it is in map (a pose set); False for a convention (a reset's origin), which
        leaves the first fix to say where map is."""
        self.x, self.y, self.theta = pose
        self.track.reset(self.t_est, pose, cov)
        self.frame.reset(pose, anchored)

    # ------------------------------------------------------------------ frames and fixes

    def map_pose(self) -> tuple[float, float, float]:
        """The pose in `map` (the same as odom's until a fix)."""
        f = self.frame
        return f.x, f.y, f.th

    def fuse_fix(self, fix: PoseFix) -> dict[str, object]:
        """Gate and fuse a pose fix (ddrt/core/pose_fix.py); FixError (naming the field) for a
        fix that cannot be used, which changes nothing."""
        return self.frame.fuse(self.track, fix)

    @property
    def v(self) -> float:
        """Forward speed for feedback (the smooth filter)."""
        return self.speed.v

    @property
    def omega(self) -> float:
        return self.yaw.w

    @property
    def bias(self) -> float:
        return self.yaw.b

    @property
    def gyro_bias(self) -> GyroBias | None:
        """The die temperature's bias line (ddrt/core/gyro_bias.py); None when TEMP_OUT is not read."""
        return self._temperature.line

    def set_dynamics(self, dyn: Dynamics) -> None:
        """Predict with `dyn` from the next tick on (an adapted model); nothing else changes."""
        self.dyn = dyn

    # ------------------------------------------------------------------ per tick

    def update(self, sample: Sample, duty_l: float, duty_r: float, commanded_still: bool) -> None:
        """Advance to `sample` given the duties applied since the previous one.

        `commanded_still` is True when the controller asks for no motion: with the encoder
        also still, the robot is at rest and the gyro bias is re-tracked (w = 0 exactly).
        """
        health = self.health
        last_t = self._last_t
        if last_t is None:
            raise RuntimeError("Estimator.update before reset")
        dt = sample.t - last_t
        self.gap_s = self.stall_s = 0.0
        if not sample.fresh or dt <= 0.0:
            # No new measurement: a repeated value with the time of the read (dead-reckon
            # through the time that passed), or a repeated sample with its own timestamp
            # (the loop ticked, so a period passed; the anchor stays at the sample's time,
            # so the next fresh sample measures the whole gap).
            health.stale_ticks += 1
            self._blind_ticks += 1
            self._blind_moving = self._blind_moving or not commanded_still
            fresh = False
            if dt <= 0.0:
                dt = self.period if not sample.fresh else 0.0
                new_anchor = last_t
                self._ahead_of_anchor += dt
            else:
                new_anchor = sample.t
                self._ahead_of_anchor = 0.0
            self.blind_s = max(sample.t - self._last_fresh_t, self._blind_ticks * self.period)
        else:
            health.stale_ticks = 0
            fresh = True
            new_anchor = sample.t
            self.blind_s = 0.0
            if dt > self.max_gap or sample.t - self._last_fresh_t > self.max_gap:
                self._reanchor(sample, dt, commanded_still)
                return
        self._last_t = new_anchor
        self.dt = dt

        # Predict with the model and the torque the motors give at the applied duty.
        dyn = self.dyn
        v = self.speed.v
        w = self.yaw.w
        wl = (v - dyn.L * w) / dyn.r_L
        wr = (v + dyn.R * w) / dyn.r_R
        tau_l, tau_r = self.motor.net_torques(duty_l, wl, duty_r, wr)
        a, alpha = dyn.forward(v, w, tau_l, tau_r)
        self.travel.predict(dt, a)
        self.speed.predict(dt, a)
        self.yaw.predict(dt, alpha)
        self.heading.predict(dt, alpha)

        if fresh:  # the sensors' fusion steps, in the order the module doc gives
            wheels, front = self._wheels, self._front
            wheels.take(sample)
            front.fuse(self, sample, dt)
            self._still_ticks = 0 if self._distance.moved else self._still_ticks + 1
            self._gyro.fuse(self, sample, commanded_still)
            self.wheel_slip = wheels.fuse(self, sample, dt, commanded_still, front.ds)

        # Dead reckoning of A with the odometry filters' velocities (midpoint heading), plus
        # the heading's correction when a stop re-learnt the bias (temperature model only).
        dth = self._temperature.fuse(self, sample, fresh, dt)
        v = self.travel.v
        w = self.heading.w
        if dth:
            self.theta += dth
        turn = self._gyro.turn(w, dt, fresh)
        half = self.theta + 0.5 * turn
        ds = v * dt
        dx = ds * math.cos(half)
        dy = ds * math.sin(half)
        self.x += dx
        self.y += dy
        self.theta += turn
        t_est = sample.t if fresh else self._last_t + self._ahead_of_anchor
        if t_est > self.t_est:  # the history's times never go back
            self.t_est = t_est
        self.frame.step(self.track, self.t_est, dt, ds, turn + dth if dth else turn, self.x, self.y, self.theta)
        if fresh:
            self._last_fresh_t = sample.t
            if self._blind_ticks:
                self._ahead_of_anchor = 0.0
                self._blind_ticks = 0
                self._blind_travel = 0.0
                self._blind_moving = False
        else:
            self._blind_travel += v * dt

    def _reanchor(self, sample: Sample, dt: float, commanded_still: bool) -> None:
        """The first fresh sample after a gap beyond max_gap: re-sync instead of fusing.

        The time base and the count restart at this sample. The pose gets the distance the
        encoder counted since the last fresh sample, less what dead reckoning already put
        in; its heading keeps what dead reckoning integrated through stale samples, and
        where nothing ran (the loop itself stalled) the gyro's readings either side of the
        gap give it (their mean). The speeds restart from what was measured, with wide
        variances, so the next samples set them: no motion is invented for the gap.
        """
        health = self.health
        gap = sample.t - self._last_fresh_t
        self._front.catch_up(sample)
        self._wheels.catch_up(sample)  # their windows restart
        measured = self._distance.ds
        w_now = mean_rate(sample, self.rad_s_per_lsb) - self.heading.b
        self._gyro.restart(sample.t)  # a FIFO batch's samples are the gap's: counted from here on
        stalled = self._blind_ticks == 0  # nothing was dead-reckoned through this gap
        # The heading turns through the time dead reckoning did not cover (all of a stall,
        # the last interval otherwise) at the mean of the rates either side of it.
        uncovered = max(0.0, dt - self._ahead_of_anchor)
        turn = 0.5 * (self.heading.w + w_now) * uncovered
        extra = measured - self._blind_travel
        half = self.theta + 0.5 * turn
        dx = extra * math.cos(half)
        dy = extra * math.sin(half)
        self.x += dx
        self.y += dy
        self.theta += turn
        self.t_est = max(self.t_est, sample.t)
        self.frame.step(self.track, self.t_est, gap, extra, turn, self.x, self.y, self.theta)
        z = self._distance.z
        v_new = measured / gap if stalled and gap > 0.0 else self.travel.v
        for f in (self.travel, self.speed):
            f.p = z
            f.v = v_new
            f.p00 = f.meas_var
            f.p01 = 0.0
            f.p11 = max(f.p11, _RESYNC_V_VAR)
        for f in (self.yaw, self.heading):
            f.w = w_now
            f.p00 = max(f.p00, _RESYNC_W_VAR)
            f.p01 = 0.0
        self._last_gyro_z = None  # no lead across the gap
        self._still_ticks = 0 if self._distance.moved else 1
        self._count_still_s = 0.0
        self._enc_rejects_row = self._gyro_rejects_row = 0
        self._last_t = sample.t
        self._last_fresh_t = sample.t
        self._ahead_of_anchor = 0.0
        self._blind_ticks = 0
        self._blind_travel = 0.0
        self.dt = self.period
        self.gap_s = gap
        self.stall_s = dt if dt > self.max_gap else 0.0
        moving = not commanded_still or self._blind_moving
        self._blind_moving = False
        if moving:  # a pause while standing still endangers nothing: not counted
            health.gaps += 1
            if gap > health.longest_gap_s:
                health.longest_gap_s = gap
        raw = sample.gyro_z_raw * self.rad_s_per_lsb
        if abs(raw) >= self.gyro_full_scale * 0.999:
            health.fault = "gyro saturated"

    # ------------------------------------------------------------------ for the fusion steps

    def set_fault(self, text: str) -> None:
        """A sensor's step saw a fault that must latch (the loop stops the robot)."""
        self.health.fault = text

    def clear_fault(self) -> None:
        """The operator reset the loop: a latched sensor fault is cleared (it latches again if it persists)."""
        self.health.fault = ""

    def fuse_travel(self, moved: bool, z: float, dt: float) -> None:
        """Fuse the distance `z` (m since the reset) into the travel filters; `moved`: a count
        came this tick (no count for encoder_stuck_s while the filter says it moves: a fault)."""
        health = self.health
        if not moved and abs(self.speed.v) > 0.05:
            self._count_still_s += dt
            if self._count_still_s > self.cfg.encoder_stuck_s:
                health.fault = (f"encoder stuck: no counts for {self._count_still_s:.2f} s "
                                f"while moving at {self.speed.v:.2f} m/s")
        else:
            self._count_still_s = 0.0
        row = self._fuse_pair(self.travel, self.speed, z, self._enc_rejects_row)
        if row > self._enc_rejects_row:
            health.encoder_rejects += 1
        self._enc_rejects_row = row

    def fuse_rate(self, z: float, lead_dt: float, commanded_still: bool) -> None:
        """Fuse a gyro rate `z` (rad/s, bias included) into the yaw filters, `lead_dt` (s) after
        the previous one. At rest (commanded still, and no count for ~0.1 s) the filters also
        learn that the robot does not turn, which is how the bias is learnt at a stop."""
        self.at_rest, self.rest_rate = commanded_still and self._still_ticks >= 20, z
        if self.at_rest:
            self.yaw.update_at_rest(1e-10)
            self.heading.update_at_rest(1e-10)
            track = self.track
            if self.heading.p11 < track.at_rest_var:
                track.at_rest_var = self.heading.p11  # the bias is learnt: its error shrinks
        z = self._lead(z, lead_dt)
        row = self._fuse_pair(self.heading, self.yaw, z, self._gyro_rejects_row)
        if row > self._gyro_rejects_row:
            self.health.gyro_rejects += 1
        self._gyro_rejects_row = row

    def fuse_no_rate(self) -> None:
        """A fresh sample that brought no gyro sample (an empty or junk FIFO batch)."""
        self.rest_rate = math.nan

    def fuse_bias(self, z: float, var: float) -> None:
        """Fuse a measurement `z` of the gyro's bias itself (rad/s, variance `var`) into both yaw filters."""
        self.yaw.update_bias(z, var)
        self.heading.update_bias(z, var)

    def widen_bias(self, var: float) -> None:
        """Widen both yaw filters' bias variance by `var` ((rad/s)^2)."""
        self.yaw.widen_bias(var)
        self.heading.widen_bias(var)

    def shift_bias(self, db: float) -> None:
        """Move both yaw filters' bias by `db` (rad/s)."""
        self.yaw.shift_bias(db)
        self.heading.shift_bias(db)

    def _lead(self, z: float, dt: float) -> float:
        """Undo the gyro's lag: z + tau (z - z_prev) / dt, with the variance that implies."""
        prev = self._last_gyro_z
        self._last_gyro_z = z
        if prev is None or dt <= 0.0 or self.gyro_lead <= 0.0:
            self.yaw.meas_var = self.heading.meas_var = self.gyro_var
            return z
        c = self.gyro_lead / dt
        self.yaw.meas_var = self.heading.meas_var = self.gyro_var * ((1.0 + c) * (1.0 + c) + c * c)
        return z + c * (z - prev)

    def _fuse_pair(self, sharp: TravelFilter | YawFilter, smooth: TravelFilter | YawFilter, z: float,
                   row: int) -> int:
        """Fuse `z` into the odometry filter unless it is an outlier (the odometry filter decides)
        and, if it was fused, into the feedback filter on the same sensor; returns how many
        outliers came in a row.

        After `max_rejects` outliers in a row the sensor is trusted again: each filter's
        variance is widened by its innovation (a re-sync) and the measurement is fused.
        """
        y, s = sharp.innovation(z)
        max_rejects = self.cfg.max_rejects
        if y * y / s > self.gate2 and row < max_rejects:
            return row + 1
        if row >= max_rejects:
            self.health.resyncs += 1
            sharp.widen(y * y)
            sharp.update(z)
            y, _ = smooth.innovation(z)
            smooth.widen(y * y)
        else:
            sharp.update(z)
        smooth.update(z)
        return 0
