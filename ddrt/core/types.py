"""The small types that cross the boundaries between the stages of one tick: what the
hardware delivers (Sample, with the static facts in HalInfo), what the reference stage hands
the controller (Setpoint), and the Clock that paces the loop and times the drivers. They live
here, below both the HAL and the controllers, so computation never imports a driver and a
driver never imports a controller."""

from __future__ import annotations

import math

from dataclasses import dataclass
from typing import Protocol


class Clock(Protocol):
    """What the loop and the drivers need from a clock: seconds on a monotonic time base, and a
    sleep to an ABSOLUTE deadline that returns the time it woke (never before the deadline).

    ddrt.runtime.clock.MonotonicClock is the wall clock; a backend whose robot runs in
    simulated time is its own clock (hal.base.Hal.owns_time)."""

    def now(self) -> float: ...

    def sleep_until(self, deadline: float) -> float: ...


@dataclass(frozen=True, slots=True)
class HalInfo:
    """Static facts about the sensors that the estimator needs to turn raw values into SI."""

    encoder_counts_per_rev: int  # counts per revolution of the front wheel (lines x 4)
    gyro_lsb_per_rad_s: float  # raw gyro z units per rad/s (131 LSB per deg/s at +-250 dps)
    gyro_full_scale_rad_s: float  # magnitude at which the raw reading saturates
    # How old the gyro's reading is at the read, against the encoder's (s): its low-pass's group
    # delay plus, for a part that holds its output register one sample period (an MPU-6050 at
    # 1 kHz / (1 + SMPLRT_DIV)), half that period, the hold's mean (its phase to the loop's
    # ticks is not known, and wanders with the two clocks).
    gyro_delay_s: float = 0.0
    # The motor driver's own watchdog: it zeroes the motors when no command arrived for this
    # long (the microcontroller's DRIVE timeout); None when the motors have none (sysfs PWM).
    drive_timeout_s: float | None = None
    wheel_counts_per_rev: int = 0  # counts per revolution of each drive wheel; 0: not counted
    battery_measured: bool = False  # Sample.battery_v is the driver's measured supply voltage
    hw_estop_wired: bool = False  # Sample.hw_estop reports a hardware emergency-stop input
    gyro_temp_hz: float = 0.0  # how often Sample.gyro_temp_c is read (TEMP_OUT); 0: never
    # The gyro's nominal sample period (s) when it is read through its FIFO (sensors.gyro_fifo):
    # every sample arrives once, Sample.gyro_n of them with the sum Sample.gyro_sum_raw; the
    # estimator learns the true period (the part's own clock) from their count. 0: no FIFO, the
    # output register is read at the tick.
    gyro_fifo_period_s: float = 0.0
    gyro_part: str = ""  # the gyro the driver identified ("MPU-6500 (WHO_AM_I 0x70)"); "": not told (the simulator)


@dataclass(slots=True)
class Sample:
    """One reading of every sensor, as the hardware delivers it.

    `t` is on the monotonic clock of the loop (seconds): when the value was read (a backend
    that repeats a value may stamp it with the time of the read, or keep the value's own). `encoder_count` is the raw front
    encoder counter (wraps like a signed 32-bit integer). `gyro_z_raw` is the raw int16 from
    the gyro at its configured range (bias not removed). `fresh` is False when a backend had
    no new data and repeated its last value; `faults` is a short text when the backend saw a
    fault on this read (retried I/O, lost packets), else "". `battery_v` is the supply voltage
    measured at the motor driver (V; NaN when not measured), `hw_estop` True while the robot's
    hardware emergency-stop input is open, `count_left`/`count_right` the raw drive-wheel
    counters (signed 32-bit, wrapping; meaningful only when HalInfo.wheel_counts_per_rev > 0).
    `gyro_temp_c` is the gyro's die temperature (degC, its TEMP_OUT), read now and then
    (HalInfo.gyro_temp_hz): NaN on the ticks it was not read. Read through the gyro's FIFO
    (HalInfo.gyro_fifo_period_s > 0), `gyro_n` is how many samples the gyro produced since the
    last fresh sample (0: none yet, possible on any tick) and `gyro_sum_raw` their raw sum, so
    their mean rate is gyro_sum_raw / gyro_n; `gyro_z_raw` is then the newest of them (or the
    last one's again when gyro_n is 0). Without a FIFO both stay 0.
    """

    t: float
    encoder_count: int
    gyro_z_raw: int
    fresh: bool = True
    faults: str = ""
    battery_v: float = math.nan
    hw_estop: bool = False
    count_left: int = 0
    count_right: int = 0
    gyro_temp_c: float = math.nan
    gyro_n: int = 0
    gyro_sum_raw: int = 0


@dataclass(slots=True)
class Setpoint:
    """What the reference stage hands the controller each tick (SI units).

    q_d = (x_d, y_d, theta_d) is the reference pose; (v_d, omega_d) and (a_d, alpha_d) the
    reference speeds and their derivatives; `along_err` the path distance by which the
    schedule leads the robot (path-following mode; 0 when time-indexed); `kappa` the path's
    curvature at q_d and `pp_curvature` pure pursuit's curvature to its lookahead point.
    `v_cap` and `omega_cap` bound the commanded speeds below the config's limits for this
    tick, `y_cap` the lateral error the outer law acts on (the start of a path the robot
    joins from off it: ddrt/path/start.py); inf: none.
    """

    x_d: float = 0.0
    y_d: float = 0.0
    theta_d: float = 0.0
    v_d: float = 0.0
    omega_d: float = 0.0
    a_d: float = 0.0
    alpha_d: float = 0.0
    along_err: float = 0.0
    kappa: float = 0.0
    pp_curvature: float = 0.0
    pivot: bool = False
    pivot_radius: float = 0.1
    path_frame: bool = False  # errors in the path's frame at q_d (path-following mode)
    active: bool = False  # False: hold still (no path, or finished)

    def turn_in_place(self, x: float, y: float, theta: float, omega: float, alpha: float) -> None:
        """A pivot at (x, y): heading theta, yaw rate omega and its derivative, no travel."""
        self.x_d, self.y_d = x, y
        self.theta_d = theta
        self.v_d = self.a_d = self.along_err = self.kappa = self.pp_curvature = 0.0
        self.omega_d = omega
        self.alpha_d = alpha
        self.pivot = True
        self.path_frame = False
        self.active = True
    v_cap: float = math.inf  # |v_c| at most this (m/s), besides limits.v_max
    y_cap: float = math.inf  # the outer law sees at most this lateral error (m)
    omega_cap: float = math.inf  # |omega_c| at most this (rad/s), besides limits.omega_max
