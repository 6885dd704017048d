"""The drive wheels' encoders in the estimator: distance, the gyro's bias on the move, slip.

A robot built the common way counts its drive wheels (sensors.wheel_counts_per_rev > 0), with
or without the seed's front omni-wheel encoder. Their increments dl, dr (m) give, at A,

    ds = (R dl + L dr) / (L + R)       dth = (dr - dl) / (L + R)

so they measure both the distance (what the front encoder does; without one, `ds` is the
travel filters' position measurement) and the turn, which the gyro also measures. The two
turns differ by the gyro's bias, so while the robot moves straight-ish and no wheel slips, a
window of `BIAS_WINDOW_S` gives a measurement of the bias (gyro turn - wheel turn) / window,
fused into both yaw filters (YawFilter.update_bias): the bias is tracked on the move, not only
at stops. Its random walk while moving is `estimator.wheel_bias_walk`, small, so the 0.1 deg/s
the wheels' quantisation gives a window does not wander the heading; a step is caught apart:
a window beyond 3 sigma is not fused, and `BIAS_RESYNC` of them in a row that agree mean the
bias moved, which is then re-synced (the bias's variance widened by the innovation).

Slip: over the last `SLIP_WINDOW_S` the wheels' turn is held against the pose's (the gyro's)
and, with a front encoder, the wheels' distance against the omni wheel's, each against the
noise it should have (quantisation, the parts' scale errors, the bias's uncertainty). Beyond
`estimator.gate_sigma` the wheels are slipping (the gyro and the omni wheel see the ground;
a driven wheel under traction does not): the tick is flagged (`Estimator.wheel_slip`, the
`wheel_slip` telemetry column, `wheel_slips` in status' faults) and the wheels are
down-weighted for that tick: their distance increment is replaced by the model's prediction,
and their window is not used for the bias. A flag that lasts beyond `MAX_SLIP_S` stops
down-weighting (a disagreement that persists is not slip but a wrong parameter; distance
from the wheels is then better than none) until it clears.

A difference between the wheels' radii reads as a bias proportional to speed: driving
straight, (gyro turn - wheel turn) / window = b + delta v / (L + R), delta = the right wheel's
relative radius error less the left's (the seed's plant has 4 %: r_L 0.049, r_R 0.051 where the
config says 0.050). So each window is two scalar measurements: of b (with the learnt delta
taken off and its variance added) into the yaw filters, and of delta (with the bias taken
off and its variance added) into `delta`, which starts at 0 with 2 x wheel_scale_std and
then barely walks (`DELTA_WALK`): it is learnt in the first metres, and a later change of
the difference goes to the bias, whose walk is much larger. Stops tell the two apart for good
(the bias is learnt at rest). The bias is only learnt while nearly straight, where the
gyro's scale error and the track width do not matter.

As the estimator's fusion step (ddrt/core/fusion.py): `take` reads the sample's wheel counts
before anything is fused (without a front encoder they say whether the robot moved), `fuse`
runs after the gyro's step; a robot without them has `NoWheels`.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING

from ddrt.config import EstimatorConfig
from ddrt.core.types import Sample
from ddrt.core.uncertainty import ErrorModel
from ddrt.core.wrap import wrap_i32

if TYPE_CHECKING:
    from ddrt.core.estimator import Estimator

SLIP_WINDOW_S = 0.1  # the slip check compares turns and distances over this long
BIAS_WINDOW_S = 0.5  # one bias measurement per this much straight-ish motion
MAX_SLIP_S = 0.5  # a slip flag longer than this stops down-weighting the wheels
MIN_SPEED = 0.01  # m/s: slower than this the window is left to the stops
MIN_BIAS_SPEED = 0.05  # m/s: slower, delta u is too small to tell delta (the bias is left to the stops)
MAX_TURN = 0.3  # rad/s: turning faster, the gyro's scale error would pass for bias (delta is still learnt)
BIAS_RESYNC = 3  # rejected bias windows in a row that agree: the bias moved, re-sync
BIAS_GATE2 = 3.0 ** 2  # a bias window this many sigma off is not fused (a step: re-synced instead)
DELTA_WALK = 1e-4  # per sqrt(s): how fast the wheels' radius difference may change
_BIAS_FLOOR = (0.01 * math.pi / 180.0) ** 2  # (rad/s)^2: the gyro's lag and what else is not modelled


def error_model(cfg: EstimatorConfig, period_s: float, wheels_give_distance: bool) -> ErrorModel:
    """The pose's error model (ddrt/core/uncertainty.py); when the wheels give the distance its
    scale error is theirs (estimator.wheel_scale_std, if larger than the encoder's)."""
    model = ErrorModel.from_config(cfg, period_s)
    if not wheels_give_distance:
        return model
    return replace(model, encoder_scale_std=max(cfg.wheel_scale_std, cfg.encoder_scale_std))


class WheelOdometry:
    """The estimator's wheel-encoder step (module doc). `gives_distance`: no front encoder, so
    the wheels' distance `z` (m, cumulative) is the travel filters' measurement. Configured by
    the estimator (`configure`), started by its reset."""

    def __init__(self, counts_per_rev: int, period_s: float, gives_distance: bool) -> None:
        self.cpr = counts_per_rev
        self.gives_distance = gives_distance
        n = max(4, int(round(SLIP_WINDOW_S / period_s)))
        self.n = n
        self._ring_w = [0.0] * n  # per tick: the wheels' turn, the pose's turn, the two distances
        self._ring_g = [0.0] * n
        self._ring_s = [0.0] * n
        self._ring_f = [0.0] * n
        self._ring_a = [0.0] * n  # the wheels' mean absolute travel (their scale errors act on it)
        self.delta0_var = self.position_var = 0.0  # until configured
        self.reset(Sample(0.0, 0, 0))

    def configure(self, est: "Estimator") -> None:
        """Scales and noises from the estimator's model, config and period."""
        dyn, cfg = est.dyn, est.cfg
        self.m_l = 2.0 * math.pi * dyn.r_L / self.cpr
        self.m_r = 2.0 * math.pi * dyn.r_R / self.cpr
        self.track_w = dyn.L + dyn.R
        self.a_l = dyn.R / self.track_w  # ds = a_l dl + a_r dr
        self.a_r = dyn.L / self.track_w
        q_l2, q_r2 = self.m_l * self.m_l, self.m_r * self.m_r
        # A distance over a window is a difference of two quantised counts: var q^2 / 6 each wheel.
        self.turn_q_var = (q_l2 + q_r2) / 6.0 / (self.track_w * self.track_w)
        self.dist_q_var = (self.a_l * self.a_l * q_l2 + self.a_r * self.a_r * q_r2) / 6.0
        self.front_q_var = est.metres_per_count * est.metres_per_count / 6.0
        self.gyro_var_dt = est.gyro_var * est.period  # (rad)^2 per second of integrated gyro noise
        self.gate2 = est.gate2
        self.scale_var = cfg.wheel_scale_std * cfg.wheel_scale_std
        self.gyro_scale_var = cfg.gyro_scale_std * cfg.gyro_scale_std
        self.enc_scale_var = cfg.encoder_scale_std * cfg.encoder_scale_std
        self.walk_var = cfg.wheel_bias_walk * cfg.wheel_bias_walk
        self.delta0_var = 2.0 * self.scale_var
        self.max_slip_ticks = max(1, int(round(MAX_SLIP_S / est.period)))
        # as the travel filters' position measurement (no front encoder): the wheels' quantisation
        self.position_var = (self.a_l * self.a_l * q_l2 + self.a_r * self.a_r * q_r2) / 12.0

    def reset(self, sample: Sample) -> None:
        """Start counting from `sample` (a reset, or the first sample after a gap)."""
        self.last_l, self.last_r = sample.count_left, sample.count_right
        self.z = 0.0
        self.dl = self.dr = self.ds = 0.0
        self.moved = False
        self.slip_ticks = 0
        self.delta = 0.0  # the right wheel's relative radius error less the left's (module doc)
        self.delta_var = self.delta0_var
        self._clear_windows()

    def _clear_windows(self) -> None:
        for ring in (self._ring_w, self._ring_g, self._ring_s, self._ring_f, self._ring_a):
            for i in range(self.n):
                ring[i] = 0.0
        self.i = 0
        self.filled = 0
        self.sum_w = self.sum_g = self.sum_s = self.sum_f = self.sum_a = 0.0
        self.bias_t = self.bias_g = self.bias_w = self.bias_s = 0.0
        self.bias_clean = True
        self.bias_rejects = 0
        self.bias_last_y = 0.0
        self.since_bias_s = 0.0

    def rebase(self) -> None:
        """Count the distance from zero again (a reload)."""
        self.z = 0.0

    # ------------------------------------------------------------------ per fresh sample

    def take(self, sample: Sample) -> None:
        """Take the wheels' increments of this sample (before the filters are fused): `moved`,
        and `ds`, the distance at A they give as configured."""
        cl, cr = sample.count_left, sample.count_right
        dcl, dcr = wrap_i32(cl - self.last_l), wrap_i32(cr - self.last_r)
        self.last_l, self.last_r = cl, cr
        self.moved = dcl != 0 or dcr != 0
        self.dl = dcl * self.m_l
        self.dr = dcr * self.m_r
        self.ds = self.a_l * self.dl + self.a_r * self.dr

    def fuse(self, est: "Estimator", sample: Sample, dt: float, still: bool, front_ds: float) -> bool:
        """After the gyro's step, so the wheels are checked against its turn before their distance
        (without a front encoder) is fused, down-weighted to the model's prediction where they
        slip. `front_ds`: the front encoder's distance this sample (m; 0 without one). Returns
        True while the wheels slip (and are down-weighted)."""
        gyro_z = sample.gyro_z_raw * est.rad_s_per_lsb
        slip = self.check(est, dt, front_ds, gyro_z, est.heading.w * dt, not still)
        if self.gives_distance:
            # The learnt radius difference split evenly (their mean is what the config says).
            h = 0.5 * self.delta
            ds = self.a_l * self.dl * (1.0 - h) + self.a_r * self.dr * (1.0 + h)
            self.z += est.travel.v * dt if slip else ds
            est.fuse_travel(self.moved, self.z, dt)
        return slip

    def catch_up(self, sample: Sample) -> None:
        """The first sample after a gap (Estimator._reanchor): `ds` the distance the wheels
        counted over it (m); the windows restart, as nothing compares across a gap."""
        self.take(sample)
        self.z += self.ds
        self.slip_ticks = 0
        self._clear_windows()

    def check(self, est: "Estimator", dt: float, front_ds: float, gyro_z: float, dth: float,
              moving: bool) -> bool:
        """After the gyro (and front encoder) are fused: compare, flag slip, and learn the bias.
        `front_ds` the omni wheel's distance this tick (m), `gyro_z` the gyro's reading (rad/s,
        bias included), `dth` the pose's turn this tick. Returns True while the wheels slip
        (and are down-weighted)."""
        d_w = (self.dr - self.dl) / self.track_w
        ds = self.ds
        i = self.i
        self.sum_w += d_w - self._ring_w[i]
        self.sum_g += dth - self._ring_g[i]
        self.sum_s += ds - self._ring_s[i]
        self.sum_f += front_ds - self._ring_f[i]
        a = 0.5 * (abs(self.dl) + abs(self.dr))
        self.sum_a += a - self._ring_a[i]
        self._ring_w[i], self._ring_g[i], self._ring_s[i], self._ring_f[i], self._ring_a[i] = d_w, dth, ds, front_ds, a
        self.i = i + 1 if i + 1 < self.n else 0
        slip = False
        if self.filled < self.n:
            self.filled += 1
        else:
            win = self.n * dt
            u = self.sum_s / self.track_w
            e = self.sum_w + self.delta * u - self.sum_g
            b_var = est.heading.p11 * win * win
            var = (self.turn_q_var + self.gyro_var_dt * win + b_var + _BIAS_FLOOR * win * win + self.delta_var * u * u
                   + (self.gyro_scale_var + self.scale_var) * self.sum_g * self.sum_g)
            slip = e * e > self.gate2 * var
            if not self.gives_distance:
                e = self.sum_s - self.sum_f
                var = (self.dist_q_var + self.front_q_var + self.scale_var * self.sum_a * self.sum_a
                       + self.enc_scale_var * self.sum_f * self.sum_f)
                slip = slip or e * e > self.gate2 * var
        if slip:
            if self.slip_ticks == 0:
                est.health.count_slip()
            self.slip_ticks += 1
        else:
            self.slip_ticks = 0
        down = slip and self.slip_ticks <= self.max_slip_ticks
        self._bias(est, dt, gyro_z, d_w, ds, moving and not slip)
        return down

    def _bias(self, est: "Estimator", dt: float, gyro_z: float, d_w: float, ds: float, clean: bool) -> None:
        """Accumulate a bias window; at its end, fuse (gyro turn - wheel turn) / window."""
        self.since_bias_s += dt
        self.bias_clean = self.bias_clean and clean
        self.bias_t += dt
        self.bias_g += gyro_z * dt
        self.bias_w += d_w
        self.bias_s += ds
        if self.bias_t < BIAS_WINDOW_S:
            return
        t = self.bias_t
        ok = self.bias_clean and abs(self.bias_s) > MIN_SPEED * t
        straight = abs(self.bias_w) < MAX_TURN * t and abs(self.bias_s) > MIN_BIAS_SPEED * t
        y = (self.bias_g - self.bias_w) / t  # = b + delta u
        turn = self.bias_w / t
        u = self.bias_s / t / self.track_w
        self.bias_t = self.bias_g = self.bias_w = self.bias_s = 0.0
        self.bias_clean = True
        if not ok:
            return
        r = (self.turn_q_var / (t * t) + self.gyro_var_dt / t + _BIAS_FLOOR
             + (self.gyro_scale_var + self.scale_var) * turn * turn)
        grow = self.walk_var * self.since_bias_s
        self.delta_var += DELTA_WALK * DELTA_WALK * self.since_bias_s
        self.since_bias_s = 0.0
        est.widen_bias(grow)
        heading = est.heading
        b0, b0_var = heading.b, heading.p11
        z = y - self.delta * u  # the bias, the radius difference taken off
        r_b = r + self.delta_var * u * u
        y = z - b0
        s = b0_var + r_b
        if not straight:
            pass  # the bias is not fused turning or slow: the radius difference is, with its variance
        elif y * y > BIAS_GATE2 * s:
            # An outlier; several in a row that agree mean the bias itself moved: re-sync.
            agree = self.bias_rejects > 0 and (y - self.bias_last_y) ** 2 <= BIAS_GATE2 * 2.0 * r_b
            self.bias_rejects = self.bias_rejects + 1 if agree or self.bias_rejects == 0 else 1
            self.bias_last_y = y
            if self.bias_rejects < BIAS_RESYNC:
                return
            est.health.count_resync()
            est.widen_bias(y * y)
            self._fuse_b(est, z, r_b)
            return  # the step was the bias's, not the radii's
        else:
            self._fuse_b(est, z, r_b)
        # The radius difference: (y - b) / u, with the bias's variance (before this update).
        if u * u < 1e-6:
            return
        d_var = (r + b0_var) / (u * u)
        k = self.delta_var / (self.delta_var + d_var)
        self.delta += k * ((y + self.delta * u) / u - self.delta)
        self.delta_var *= 1.0 - k

    def _fuse_b(self, est: "Estimator", z: float, var: float) -> None:
        self.bias_rejects = 0
        est.fuse_bias(z, var)


class NoWheels:
    """The drive wheels are not counted: nothing taken, fused or flagged."""

    __slots__ = ()
    moved = False
    ds = 0.0
    z = 0.0
    position_var = 0.0

    def configure(self, est: "Estimator") -> None:
        pass

    def reset(self, sample: Sample) -> None:
        pass

    def rebase(self) -> None:
        pass

    def take(self, sample: Sample) -> None:
        pass

    def fuse(self, est: "Estimator", sample: Sample, dt: float, still: bool, front_ds: float) -> bool:
        return False

    def catch_up(self, sample: Sample) -> None:
        pass
