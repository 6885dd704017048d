"""State estimation: forward speed, yaw rate and gyro bias from the encoder and the gyro.

Prediction uses the robot's dynamic model driven by the torque the motors actually give
(the motor model at the applied duty and the estimated wheel speeds), so the filter knows
about accelerations before the sensors see them. Measurements: the front encoder's
travelled distance (a position, so quantisation stays white) and the raw gyro. The gyro's
zero-rate bias is calibrated at rest before the robot moves and re-tracked whenever it
stands still; outliers are gated; a sensor that stops changing or arriving is reported.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ddrt.config import EstimatorConfig
from ddrt.core.kalman import TravelFilter, YawFilter
from ddrt.core.model import Dynamics
from ddrt.core.motor import Motor
from ddrt.core.types import HalInfo, Sample
from ddrt.core.wrap import wrap_i32

NOISE_STEP_S = 0.005  # the step the configured process noises are given for
DEG = math.pi / 180.0


class CalibrationError(ValueError):
    """The gyro could not be calibrated: too few samples, or the robot was moving."""


@dataclass(slots=True)
class EstimatorHealth:
    """Counters and the latest fault; the loop turns a fault into a safe stop."""

    gyro_rejects: int = 0
    encoder_rejects: int = 0
    resyncs: int = 0
    stale_ticks: int = 0
    fault: str = ""


def calibrate_gyro(raw: list[int], lsb_per_rad_s: float, scale: float, max_std_dps: float) -> tuple[float, float]:
    """Mean and std (rad/s) of gyro readings taken at rest; refuse if the robot moved."""
    if len(raw) < 10:
        raise CalibrationError(f"gyro calibration needs at least 10 samples, got {len(raw)}")
    values = [r / (lsb_per_rad_s * scale) for r in raw]
    mean = sum(values) / len(values)
    std = math.sqrt(sum((v - mean) ** 2 for v in values) / (len(values) - 1))
    if std > max_std_dps * DEG:
        raise CalibrationError(
            f"gyro calibration refused: noise {std / DEG:.3f} deg/s exceeds "
            f"estimator.calibration_max_std_dps={max_std_dps} (is the robot moving?)")
    return mean, std


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
        self._configure(cfg, r_3)
        self._last_gyro_z: float | None = None
        self._last_gyro_t = 0.0
        self._travel_counts = 0  # unwrapped encoder counts since reset (or the last re-base)
        self.health = EstimatorHealth()
        self.x = self.y = self.theta = 0.0
        self.dt = period_s  # the time step of the last update (what the reference advances by)
        self._last_t: float | None = None
        self._last_count = 0
        self._enc_rejects_row = 0
        self._gyro_rejects_row = 0
        self._last_raw_gyro: int | None = None
        self._same_gyro = 0
        self._count_still_s = 0.0  # time without counts while the filter says we move
        self._still_ticks = 0  # ticks in a row without a single encoder count

    # ------------------------------------------------------------------ configuration

    def _configure(self, cfg: EstimatorConfig, r_3: float) -> None:
        """Derive the scales, noises and bounds from `cfg` and the encoder wheel's radius."""
        info, period_s = self.info, self.period
        self.cfg = cfg
        self.metres_per_count = 2.0 * math.pi * r_3 / info.encoder_counts_per_rev
        self.rad_s_per_lsb = 1.0 / (info.gyro_lsb_per_rad_s * cfg.gyro_scale)
        self.gyro_full_scale = info.gyro_full_scale_rad_s / cfg.gyro_scale
        # The filters' noise is per step; scaled so that their bandwidth, i.e. how much they
        # trust the model, is the same at every loop rate (the configured values are per 5 ms).
        k = math.sqrt(NOISE_STEP_S / period_s)
        enc_var = self.metres_per_count * self.metres_per_count / 12.0
        for filt, noise in ((self.travel, cfg.odometry_accel_noise), (self.speed, cfg.accel_noise)):
            filt.accel_var = (k * noise) ** 2
            filt.meas_var = enc_var
        gyro_var = (cfg.gyro_noise_dps * DEG) ** 2
        for filt, noise in ((self.yaw, cfg.yaw_accel_noise), (self.heading, cfg.odometry_yaw_accel_noise)):
            filt.yaw_accel_var = (k * noise) ** 2
            filt.bias_walk_var = cfg.gyro_bias_walk * cfg.gyro_bias_walk
            filt.meas_var = gyro_var
        self._gyro_var = gyro_var
        # The gyro's low-pass makes it lag the encoder; a heading that lags the distance
        # bends the dead-reckoned path. The lead z + tau dz/dt undoes a lag tau.
        self.gyro_lead = info.gyro_delay_s if cfg.gyro_delay_s is None else cfg.gyro_delay_s
        self.gate2 = cfg.gate_sigma * cfg.gate_sigma
        # A gap in the samples while moving is a fault: ten ticks, but never less than
        # max_gap_s, so a fast loop does not fault on a host's scheduling hiccup.
        self.max_gap = max(10.0 * period_s, cfg.max_gap_s)

    def reconfigure(self, cfg: EstimatorConfig, r_3: float, dyn: Dynamics, motor: Motor) -> None:
        """Take a new tuning, encoder radius (a calibrated r_3), gyro scale or model between
        two ticks, without a jump in the estimate.

        The travelled distance is re-based at the new metres per count, so the position
        measurement stays continuous; the yaw rate and the gyro bias, which are raw readings
        times the gyro's scale, are rescaled with it.
        """
        old_lsb = self.rad_s_per_lsb
        travelled = self._travel_counts * self.metres_per_count
        self._configure(cfg, r_3)
        self.dyn = dyn
        self.motor = motor
        for f in (self.travel, self.speed):
            f.p -= travelled
        self._travel_counts = 0
        ratio = self.rad_s_per_lsb / old_lsb
        if ratio != 1.0:
            for f in (self.yaw, self.heading):
                f.w *= ratio
                f.b *= ratio
            if self._last_gyro_z is not None:
                self._last_gyro_z *= ratio

    # ------------------------------------------------------------------ set-up

    def reset(self, sample: Sample, pose: tuple[float, float, float], bias: float) -> None:
        """Start from a known pose at rest, with a calibrated gyro bias (rad/s)."""
        self.x, self.y, self.theta = pose
        self._last_t = sample.t
        self._last_count = sample.encoder_count
        self._travel_counts = 0
        for f in (self.travel, self.speed):
            f.p = 0.0
            f.v = 0.0
        for f in (self.yaw, self.heading):
            f.w = 0.0
            f.b = bias
        self._last_raw_gyro = sample.gyro_z_raw
        self._last_gyro_z = None

    def set_pose(self, pose: tuple[float, float, float]) -> None:
        self.x, self.y, self.theta = pose

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
        if not sample.fresh or dt <= 0.0:
            # No new measurement: a repeated value (dead-reckon through the time that
            # passed), or a repeated timestamp (no time passed: nothing to predict).
            health.stale_ticks += 1
            if health.stale_ticks >= self.cfg.stale_ticks:
                health.fault = f"sensors stale for {health.stale_ticks} ticks"
            fresh = False
            if dt <= 0.0:
                dt = 0.0
                new_anchor = last_t
            else:
                new_anchor = sample.t
        else:
            health.stale_ticks = 0
            fresh = True
            new_anchor = sample.t
            if dt > self.max_gap:
                if commanded_still:
                    dt = self.period  # standing still: a pause in the loop endangers nothing
                else:
                    health.fault = f"sensor gap of {dt * 1000:.1f} ms"
        self._last_t = new_anchor
        self.dt = dt

        # Predict with the model and the torque the motors give at the applied duty.
        dyn = self.dyn
        v = self.speed.v
        w = self.yaw.w
        wl = (v - dyn.L * w) / dyn.r_L
        wr = (v + dyn.R * w) / dyn.r_R
        tau_l = self.motor.electromagnetic_torque(duty_l, wl) - self.motor.friction(wl)
        tau_r = self.motor.electromagnetic_torque(duty_r, wr) - self.motor.friction(wr)
        a, alpha = dyn.forward(v, w, tau_l, tau_r)
        self.travel.predict(dt, a)
        self.speed.predict(dt, a)
        self.yaw.predict(dt, alpha)
        self.heading.predict(dt, alpha)

        if fresh:
            self._fuse_encoder(sample.encoder_count, dt)
            self._fuse_gyro(sample.gyro_z_raw, sample.t, commanded_still)

        # Dead reckoning of A with the odometry filters' velocities (midpoint heading).
        v = self.travel.v
        w = self.heading.w
        half = self.theta + 0.5 * w * dt
        self.x += v * dt * math.cos(half)
        self.y += v * dt * math.sin(half)
        self.theta += w * dt

    def _fuse_encoder(self, count: int, dt: float) -> None:
        delta = wrap_i32(count - self._last_count)
        self._last_count = count
        self._travel_counts += delta
        health = self.health
        self._still_ticks = self._still_ticks + 1 if delta == 0 else 0
        if delta == 0 and abs(self.speed.v) > 0.05:
            self._count_still_s += dt
            if self._count_still_s > self.cfg.encoder_stuck_s:
                health.fault = (f"encoder stuck: no counts for {self._count_still_s:.2f} s "
                                f"while moving at {self.speed.v:.2f} m/s")
        else:
            self._count_still_s = 0.0
        z = self._travel_counts * self.metres_per_count
        row = self._fuse_pair(self.travel, self.speed, z, self._enc_rejects_row)
        if row > self._enc_rejects_row:
            health.encoder_rejects += 1
        self._enc_rejects_row = row

    def _fuse_gyro(self, raw: int, t: float, commanded_still: bool) -> None:
        health = self.health
        if raw == self._last_raw_gyro:
            self._same_gyro += 1
            if self._same_gyro >= self.cfg.stuck_gyro_ticks:
                health.fault = f"gyro stuck at raw {raw} for {self._same_gyro} samples"
        else:
            self._same_gyro = 0
        self._last_raw_gyro = raw
        z = raw * self.rad_s_per_lsb
        if abs(z) >= self.gyro_full_scale * 0.999:
            health.fault = "gyro saturated"
        if commanded_still and self._still_ticks >= 20:  # ~0.1 s without a count: at rest
            self.yaw.update_at_rest(1e-10)
            self.heading.update_at_rest(1e-10)
        z = self._lead(z, t)
        row = self._fuse_pair(self.heading, self.yaw, z, self._gyro_rejects_row)
        if row > self._gyro_rejects_row:
            health.gyro_rejects += 1
        self._gyro_rejects_row = row

    def _lead(self, z: float, t: float) -> float:
        """Undo the gyro's lag: z + tau (z - z_prev) / dt, with the variance that implies."""
        prev = self._last_gyro_z
        dt = t - self._last_gyro_t
        self._last_gyro_z = z
        self._last_gyro_t = t
        if prev is None or dt <= 0.0 or self.gyro_lead <= 0.0:
            self.yaw.meas_var = self.heading.meas_var = self._gyro_var
            return z
        c = self.gyro_lead / dt
        self.yaw.meas_var = self.heading.meas_var = self._gyro_var * ((1.0 + c) * (1.0 + c) + c * c)
        return z + c * (z - prev)

    def _fuse_pair(self, sharp: TravelFilter | YawFilter, smooth: TravelFilter | YawFilter, z: float,
                   row: int) -> int:
        """Fuse `z` into the odometry filter (which decides on outliers) and, if it was
        accepted, into the feedback filter on the same sensor."""
        resyncs = self.health.resyncs
        row = self._gated_update(sharp, z, row)
        if row == 0:
            if self.health.resyncs > resyncs:
                y, _ = smooth.innovation(z)
                smooth.p00 += y * y
            smooth.update(z)
        return row

    def _gated_update(self, filt: TravelFilter | YawFilter, z: float, row: int) -> int:
        """Fuse `z` unless it is an outlier; returns how many outliers came in a row.

        After `max_rejects` outliers in a row the sensor is trusted again: the filter's
        variance is widened by the innovation (a re-sync) and the measurement is fused.
        """
        y, s = filt.innovation(z)
        if y * y / s > self.gate2 and row < self.cfg.max_rejects:
            return row + 1
        if row >= self.cfg.max_rejects:
            self.health.resyncs += 1
            filt.p00 += y * y
        filt.update(z)
        return 0
