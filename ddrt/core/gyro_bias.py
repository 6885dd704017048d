"""The gyro's zero-rate bias against its die temperature, re-learnt at every stop.

An MPU-6050's zero-rate output moves with its die's temperature (by degrees per second while
it warms up). While the robot turns the bias cannot be seen, so between stops it is predicted
from the temperature (TEMP_OUT, read a few times a second, `Sample.gyro_temp_c`):
b(T) = b0 + k (T - t_ref), t_ref the first temperature read. At a stop the mean of the gyro's
readings at rest measures the bias at the stop's temperature; those (bias, temperature) pairs
teach the line with a 2-state Kalman filter on (b0, k): recursive least squares whose
forgetting is a random walk per second (b0 by `estimator.gyro_bias_walk`, k by SLOPE_WALK), so
a bias that moves for other reasons (a drift, ageing) is followed too. A slope set by
commissioning (`estimator.gyro_bias_per_c_dps`) is held fixed; b0 is still learnt.

Gating: a stop whose readings spread more than `estimator.calibration_max_std_dps` (the robot
moved) is dropped; a pair beyond `gate_sigma` of the line re-syncs b0 to it (at rest the
readings are the measurement to trust; the line is the model that failed), counted.

When a pair is fused, the heading turned since the previous pair is corrected once: it was
integrated with the bias in use then (`b_used`), and the line learnt now, with b0 taken
linearly in time between its values at the two pairs (the smoothed random walk), says what the
bias was at every tick of the way. The heading moves by -(integral of (b_smoothed - b_used) dt),
which four running sums give without a history.

`TemperatureBias` is the estimator's fusion step for the die temperature's channel
(Sample.gyro_temp_c, read when HalInfo.gyro_temp_hz > 0); `StopsOnly` the step without it, where
the bias is re-learnt at stops only (by the yaw filters themselves).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

from ddrt.config import EstimatorConfig
from ddrt.core.types import Sample
from ddrt.errors import DdrtError

if TYPE_CHECKING:
    from ddrt.core.estimator import Estimator

DEG = math.pi / 180.0
SLOPE_PRIOR_DPS_PER_C = 0.2  # 1 sigma of an unknown slope (deg/s per degC; the MPU-6050's +-20 deg/s over 125 degC is 0.16)
SLOPE_WALK = 2e-6  # rad/s per degC per sqrt(s): how fast a learnt slope is forgotten
WINDOW_S = 1.0  # a stop's readings are averaged this long into one pair
MIN_WINDOW_S = 0.3  # a shorter rest gives no pair
NOISE_FLOOR = 1e-4 * DEG  # rad/s: the least a pair's 1 sigma is taken to be (quantisation, vibration)


class CalibrationError(DdrtError, ValueError):
    """The gyro could not be calibrated: too few samples, or the robot was moving."""


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


class GyroBias:
    """The (b0, k) line and the sums of the stretch since the last pair (module doc)."""

    __slots__ = ("period", "fixed_k", "b0_walk_var", "gate2", "max_std", "t_ref", "temp", "b0", "k",
                 "p00", "p01", "p11", "t_fused", "t_pair", "b0_pair", "n", "sz", "szz", "st", "stime",
                 "m1", "mt", "mtemp", "mb", "pairs", "resyncs", "dropped", "last_correction")

    def __init__(self, period_s: float, bias_per_c_dps: float | None, bias_walk: float, gate_sigma: float,
                 max_std_dps: float) -> None:
        self.period = period_s
        self.t_ref = self.temp = math.nan  # not started: no temperature read yet
        self.b0 = self.k = 0.0
        self.p00 = self.p01 = self.p11 = 0.0
        self.t_fused = self.t_pair = self.b0_pair = 0.0
        self.n = 0
        self.sz = self.szz = self.st = self.stime = 0.0  # the open window at rest: sums of z, z^2, temperature, time
        self.m1 = self.mt = self.mtemp = self.mb = 0.0  # the stretch since the last pair: sums of dt, t dt, T dt, b dt
        self.pairs = self.resyncs = self.dropped = 0
        self.last_correction = 0.0  # rad: the heading correction of the last pair
        self._tune(bias_per_c_dps, bias_walk, gate_sigma, max_std_dps)  # the slope is taken at the start

    def configure(self, bias_per_c_dps: float | None, bias_walk: float, gate_sigma: float,
                  max_std_dps: float) -> None:
        """A new tuning (a reload): a commissioned slope replaces the learnt one."""
        self._tune(bias_per_c_dps, bias_walk, gate_sigma, max_std_dps)
        if self.fixed_k is not None:
            self.k, self.p01, self.p11 = self.fixed_k, 0.0, 0.0

    def _tune(self, bias_per_c_dps: float | None, bias_walk: float, gate_sigma: float, max_std_dps: float) -> None:
        self.fixed_k = None if bias_per_c_dps is None else bias_per_c_dps * DEG
        self.b0_walk_var = bias_walk * bias_walk
        self.gate2 = gate_sigma * gate_sigma
        self.max_std = max_std_dps * DEG

    @property
    def started(self) -> bool:
        return self.t_ref == self.t_ref

    def line(self, temp: float) -> float:
        """The bias (rad/s) the line predicts at `temp` (degC)."""
        return self.b0 + self.k * (temp - self.t_ref)

    def rescale(self, ratio: float) -> None:
        """The gyro's scale changed (a reload): biases are readings times it."""
        self.b0 *= ratio
        self.k *= ratio
        self.b0_pair *= ratio
        self.mb *= ratio
        self.p00 *= ratio * ratio
        self.p01 *= ratio * ratio
        self.p11 *= ratio * ratio
        if self.fixed_k is not None:
            self.fixed_k *= ratio
        self.n = 0  # the open window's readings were at the old scale
        self.sz = self.szz = self.st = self.stime = 0.0

    def tick(self, t: float, dt: float, temp: float, rest: bool, z: float, b_used: float) -> tuple[float, float]:
        """One estimator tick: `temp` the die temperature read now (NaN: none), `rest` whether the
        robot is at rest with `z` the raw rate (rad/s; NaN: no fresh reading), `b_used` the bias
        the heading is integrated with. Returns (the change to make to the filters' bias, the
        heading correction in rad), both 0.0 on most ticks."""
        db = 0.0
        if temp == temp:
            if not self.started:
                self._start(t, temp, b_used)
            else:
                db = self.k * (temp - self.temp)
            self.temp = temp
        if not self.started:
            return 0.0, 0.0
        dth = 0.0
        if rest:
            if z == z:
                self.n += 1
                self.sz += z
                self.szz += z * z
                self.st += self.temp
                self.stime += t
                if self.n * self.period >= WINDOW_S - 1e-9:
                    db2, dth = self._close(t, b_used + db)
                    db += db2
        else:
            if self.n:  # the stop ended
                db2, dth = self._close(t, b_used + db)
                db += db2
            self.m1 += dt
            self.mt += t * dt
            self.mtemp += self.temp * dt
            self.mb += b_used * dt  # what this tick's heading was integrated with
        return db, dth

    def _start(self, t: float, temp: float, b_used: float) -> None:
        self.t_ref = self.temp = temp
        self.b0 = self.b0_pair = b_used
        self.p00 = (0.05 * DEG) ** 2  # the start-up calibration's bias, loosely
        if self.fixed_k is None:
            self.k, self.p01, self.p11 = 0.0, 0.0, (SLOPE_PRIOR_DPS_PER_C * DEG) ** 2
        else:
            self.k, self.p01, self.p11 = self.fixed_k, 0.0, 0.0
        self.t_fused = self.t_pair = t

    def _close(self, t: float, b_now: float) -> tuple[float, float]:
        """Fuse the window at rest as a pair (if long and still enough); (bias change, heading correction)."""
        n, sz, szz, st, t_mid = self.n, self.sz, self.szz, self.st, self.stime / max(self.n, 1)
        self.n = 0
        self.sz = self.szz = self.st = self.stime = 0.0
        if n * self.period < MIN_WINDOW_S or n < 2:
            return 0.0, 0.0
        mean = sz / n
        var = max(0.0, (szz - n * mean * mean) / (n - 1))
        if var > self.max_std * self.max_std:
            self.dropped += 1  # it moved: no bias from this stop
            return 0.0, 0.0
        r = max(var / n, NOISE_FLOOR * NOISE_FLOOR)
        elapsed = max(0.0, t_mid - self.t_fused)  # the pair measures the bias at the window's middle
        self.t_fused = max(self.t_fused, t_mid)
        self.p00 += self.b0_walk_var * elapsed
        if self.fixed_k is None:
            self.p11 += SLOPE_WALK * SLOPE_WALK * elapsed
        h = st / n - self.t_ref
        y = mean - (self.b0 + self.k * h)
        hp0 = self.p00 + h * self.p01  # P H'
        hp1 = self.p01 + h * self.p11
        s = hp0 + h * hp1 + r
        if y * y / s > self.gate2:
            self.resyncs += 1  # the model failed, the stop did not: re-sync b0 to it
            self.p00 += y * y
            hp0 += y * y
            s += y * y
        k0, k1 = hp0 / s, hp1 / s
        self.b0 += k0 * y
        self.k += k1 * y
        self.p00 -= k0 * hp0
        self.p01 -= k0 * hp1
        self.p11 -= k1 * hp1
        self.pairs += 1
        dth = 0.0
        if self.m1 > 0.0:
            span = t_mid - self.t_pair
            drift = (self.b0 - self.b0_pair) / span if span > 0.0 else 0.0
            smoothed = (self.b0_pair * self.m1 + drift * (self.mt - self.t_pair * self.m1)
                        + self.k * (self.mtemp - self.t_ref * self.m1))
            dth = -(smoothed - self.mb)
        self.m1 = self.mt = self.mtemp = self.mb = 0.0
        self.t_pair = t_mid
        self.b0_pair = self.b0
        self.last_correction = dth
        return self.line(self.temp) - b_now, dth

    def counters(self) -> dict[str, float | int]:
        """For status: pairs fused, re-synced and dropped; the slope (deg/s per degC); the last correction (deg)."""
        return {"bias_pairs": self.pairs, "bias_resyncs": self.resyncs, "bias_dropped": self.dropped,
                "bias_per_c_dps": self.k / DEG, "bias_correction_deg": self.last_correction / DEG}


def _line(period_s: float, cfg: EstimatorConfig) -> GyroBias:
    return GyroBias(period_s, cfg.gyro_bias_per_c_dps, cfg.gyro_bias_walk, cfg.gate_sigma, cfg.calibration_max_std_dps)


class TemperatureBias:
    """The fusion step of the die temperature (module doc): each tick the line's change to the
    bias goes into both yaw filters (Estimator.shift_bias), and a stop's pair returns the
    heading's correction."""

    __slots__ = ("period", "line")

    def __init__(self, period_s: float, cfg: EstimatorConfig) -> None:
        self.period = period_s
        self.line: GyroBias = _line(period_s, cfg)

    def configure(self, cfg: EstimatorConfig) -> None:
        self.line.configure(cfg.gyro_bias_per_c_dps, cfg.gyro_bias_walk, cfg.gate_sigma, cfg.calibration_max_std_dps)

    def reset(self, cfg: EstimatorConfig) -> None:
        """A new calibration: the line starts again from it."""
        self.line = _line(self.period, cfg)

    def rescale(self, ratio: float) -> None:
        self.line.rescale(ratio)

    def fuse(self, est: "Estimator", sample: Sample, fresh: bool, dt: float) -> float:
        """`fresh`: the sample is new (its time and its rest reading count); returns the heading's
        correction (rad), 0.0 on most ticks."""
        db, dth = self.line.tick(sample.t if fresh else est.t_est, dt, sample.gyro_temp_c, est.at_rest,
                                 est.rest_rate if fresh else math.nan, est.heading.b)
        if db:
            est.shift_bias(db)
        return dth


class StopsOnly:
    """No die temperature: the bias is re-learnt at stops only (the yaw filters at rest)."""

    __slots__ = ()
    line: GyroBias | None = None

    def configure(self, cfg: EstimatorConfig) -> None:
        pass

    def reset(self, cfg: EstimatorConfig) -> None:
        pass

    def rescale(self, ratio: float) -> None:
        pass

    def fuse(self, est: "Estimator", sample: Sample, fresh: bool, dt: float) -> float:
        return 0.0
