"""`SimHal`: the `Hal` backend over a `SimRobot`, and the control loop's clock.

Its time is sim_hal.simtime's: unpaced (the default, for CI) the loop's computation takes no
sim time and a run goes as fast as the CPU allows; paced, sim time follows the wall clock, so
the daemon can run against the simulator in real time.

Like the robot's microcontroller, the simulated motor driver has a DRIVE watchdog: when no
command arrives for `drive_timeout_s` (100 ms, `hal.bridge.drive_timeout_ms`'s default) it
zeroes both motors, so a stalled or stopped loop leaves the simulated robot as it would the
real one. A loop that writes every tick never trips it.

Like a protocol-v2 microcontroller, it measures the driver's supply (`SimRobot.battery_v`,
in every sample's `battery_v`; `battery_measured=False`, `sim.battery_measured: false`, is a
v1 MCU that does not) and has a hardware emergency-stop input, closed unless a test opens it
(`estop_input_open`).

Like the real driver, it reads the gyro's die temperature (TEMP_OUT's 1/340 degC steps) at
`gyro_temp_hz` (`sensors.gyro_temp_hz`; 0: never), and reports the reading's age as the
low-pass's lag plus half the output register's hold (`sim.gyro.register_hold`).

With `sensors.gyro_fifo` the gyro is read as through the MPU's FIFO (`SimRobot.read_gyro_fifo`):
every sample it produced since the last read, their count and sum in the sample (`gyro_n`,
`gyro_sum_raw`), the newest as `gyro_z_raw`; a FIFO that overflowed is dropped, the sample
flagged not fresh ("imu_fifo_overflow"), as the real driver does. The reading's age is then
the low-pass's lag only (`HalInfo.gyro_fifo_period_s` the nominal sample period).

With `sensors.wheel_counts_per_rev` > 0 every sample carries the drive wheels' counts
(`count_left`/`count_right`, `SimRobot.read_wheel_counts`), as a v2 MCU counting them does.

Fault injection: `wiring` (sim_hal/wiring.py, `sim.wiring`) miswires the motors and sensors;
`freeze(at, duration)` makes the sensors repeat their last reading, flagged
not fresh, from sim time `at` for `duration` s (None: for good); `sim.sensors_freeze_after_s`
with `sim.sensors_freeze_for_s` does it from the config.
"""

from __future__ import annotations

import math

from ddrt.params.robot import RobotParams
from ddrt.params.motor import MotorParams
from hal.base import Hal, HalInfo, HalIOError, HalValueError, Sample
from sim_hal.plant import PlantConfig, SimRobot
from sim_hal.simtime import SimTime
from sim_hal.mpu_emulator import temp_out_c, temp_out_raw
from sim_hal.wiring import WiringFaults


class SimHal(Hal):
    """A HAL whose sensors and motors are those of a simulated robot; its own clock."""

    owns_time = True
    robot: SimRobot  # Hal's optional capability: the truth behind the readings

    def __init__(self, robot: SimRobot, paced: bool = False, drive_timeout_s: float | None = 0.1,
                 battery_measured: bool = True, wiring: WiringFaults | None = None,
                 gyro_temp_hz: float = 0.0) -> None:
        if drive_timeout_s is not None and not (math.isfinite(drive_timeout_s) and drive_timeout_s > 0):
            raise ValueError(f"drive_timeout_s: expected None or a positive number, got {drive_timeout_s!r}")
        self.robot = robot
        self.time = SimTime(lambda: robot.t, self._advance, paced)
        self.drive_timeout_s = drive_timeout_s
        self.info = HalInfo(
            encoder_counts_per_rev=robot.encoder_counts_per_rev,
            gyro_lsb_per_rad_s=robot.gyro_lsb_per_rad_s,
            gyro_full_scale_rad_s=robot.gyro_full_scale_rad_s,
            gyro_delay_s=robot.gyro_delay_s + (0.0 if robot.gyro_fifo else 0.5 * robot.gyro_hold_s),
            drive_timeout_s=drive_timeout_s,
            battery_measured=battery_measured,
            hw_estop_wired=True,
            gyro_temp_hz=gyro_temp_hz,
            wheel_counts_per_rev=robot.wheel_counts_per_rev,
            # nominal: the host does not know the part's clock error (the estimator learns it)
            gyro_fifo_period_s=1.0 / robot.cfg.realism.gyro_odr_hz if robot.gyro_fifo else 0.0,
        )
        self.fifo_overflows = 0
        self._temp_next_t = -math.inf  # sim time of the next TEMP_OUT read
        self.estop_input_open = False  # the robot's emergency-stop button, pressed (tests)
        self._freezes: list[tuple[float, float]] = []  # fault injection: [start, end) in sim time
        self._last_sample: Sample | None = None
        self._last_drive_t = robot.t
        self._driving = False  # a nonzero command is in force (the watchdog can trip)
        self.watchdog_trips = 0
        self.wiring = wiring if wiring is not None and wiring.faulty else None  # None: wired right

    @classmethod
    def from_params(cls, params: RobotParams, motor_l: MotorParams | None = None,
                    motor_r: MotorParams | None = None, cfg: PlantConfig | None = None,
                    start: tuple[float, float, float] = (0.0, 0.0, 0.0),
                    paced: bool = False) -> "SimHal":
        """Build the robot too; motors default to `MotorParams()`, the plant to `PlantConfig()`."""
        robot = SimRobot(params, motor_l or MotorParams(), motor_r or MotorParams(), cfg, start)
        return cls(robot, paced=paced)

    # --- fault injection -------------------------------------------------------------------

    def freeze(self, at: float, duration: float | None = None) -> None:
        """From sim time `at`, for `duration` s (None: for good), every read repeats the last
        sample (its own timestamp, `fresh=False`): sensors that stopped updating."""
        if not math.isfinite(at) or (duration is not None and not (math.isfinite(duration) and duration >= 0)):
            raise ValueError(f"freeze: expected a finite start and None or a duration >= 0, got {at!r}, {duration!r}")
        self._freezes.append((float(at), math.inf if duration is None else float(at) + float(duration)))

    @property
    def freeze_after(self) -> float | None:
        """Start of the first injected freeze (None: none)."""
        return self._freezes[0][0] if self._freezes else None

    @freeze_after.setter
    def freeze_after(self, at: float | None) -> None:
        self._freezes = [] if at is None else [(float(at), math.inf)]

    def _frozen(self, t: float) -> bool:
        for start, end in self._freezes:
            if start <= t < end:
                return True
        return False

    @property
    def fault_counters(self) -> dict[str, int]:
        """For status: how often the simulated driver's watchdog zeroed the motors."""
        return {"watchdog_trips": self.watchdog_trips, "imu_fifo_overflows": self.fifo_overflows}

    # --- clock (sim_hal.simtime) ------------------------------------------------------------

    def _advance(self, t: float) -> None:
        """Integrate the plant to `t`, zeroing the motors on the way if the watchdog trips."""
        robot = self.robot
        if self._driving and self.drive_timeout_s is not None:
            trip = self._last_drive_t + self.drive_timeout_s
            if trip < t:
                robot.advance_to(trip)
                robot.command(0.0, 0.0)
                self._driving = False
                self.watchdog_trips += 1
        robot.advance_to(t)

    @property
    def paced(self) -> bool:
        return self.time.paced

    def now(self) -> float:
        """Sim time (s). Paced, the plant is first brought up to the wall clock."""
        return self.time.now()

    def advance_to_wall_clock(self) -> None:
        """Paced: integrate the plant up to the wall clock now (unpaced, sim time waits)."""
        self.time.catch_up()

    def sleep_until(self, deadline: float) -> float:
        """Advance the plant to `deadline` (and, paced, wait for the wall clock); return now."""
        if self.time.paced:
            return self.time.sleep_until(deadline)
        # Unpaced (`ddrt sim`, every tick): SimTime.sleep_until's own steps, two calls fewer.
        if not math.isfinite(deadline):
            raise HalValueError(f"deadline={deadline!r} is not finite")
        robot = self.robot
        timeout = self.drive_timeout_s
        if self._driving and timeout is not None and self._last_drive_t + timeout < deadline:
            self._advance(deadline)  # the watchdog trips on the way
        else:
            robot.advance_to(deadline)  # _advance's common case, one call fewer
        return robot.t

    # --- Hal ------------------------------------------------------------------------------

    def read(self) -> Sample:
        if self._closed:
            raise HalIOError("SimHal.read: the HAL is closed")
        robot = self.robot
        t = self.time.now() if self.time.paced else robot.t
        last = self._last_sample
        if self._freezes and last is not None and self._frozen(t):
            return Sample(t=last.t, encoder_count=last.encoder_count, gyro_z_raw=last.gyro_z_raw,
                          fresh=False, faults="sensors frozen (injected)", battery_v=last.battery_v,
                          hw_estop=self.estop_input_open, count_left=last.count_left, count_right=last.count_right)
        count, gyro = robot.read_sensors()
        # Positional (t, encoder_count, gyro_z_raw, fresh, faults, battery_v, hw_estop): every tick.
        s = self._last_sample = Sample(t, count, gyro, True, "",
                                       robot.battery_v if self.info.battery_measured else math.nan,
                                       self.estop_input_open)
        info = self.info
        if info.gyro_temp_hz > 0.0 and t >= self._temp_next_t:
            nxt = self._temp_next_t + 1.0 / info.gyro_temp_hz
            self._temp_next_t = nxt if nxt > t else t + 1.0 / info.gyro_temp_hz
            s.gyro_temp_c = temp_out_c(temp_out_raw(robot.gyro_die_temp_c))
        if info.wheel_counts_per_rev > 0:  # the drive wheels' encoders (sensors.wheel_counts_per_rev)
            s.count_left, s.count_right = robot.read_wheel_counts()
        if self.wiring is not None:
            s.encoder_count, s.gyro_z_raw = self.wiring.encoder(s.encoder_count), self.wiring.gyro(s.gyro_z_raw)
            s.count_left, s.count_right = self.wiring.wheels(s.count_left, s.count_right)
        if info.gyro_fifo_period_s > 0.0:
            return self._read_fifo(s, last)
        return s

    def _read_fifo(self, s: Sample, last: Sample | None) -> Sample:
        """The gyro through its FIFO: its samples since the last read into `s` (module doc); after
        an overflow, the last sample again (its own time, not fresh), as a frozen read: the next
        fresh one then measures the whole gap."""
        samples, lost = self.robot.read_gyro_fifo()
        if self.wiring is not None:
            samples = [self.wiring.gyro(r) for r in samples]
        if lost:  # what is left no longer joins the last read's samples: drop it, say so
            self.fifo_overflows += 1
            if last is not None:
                self._last_sample = last
                return Sample(t=last.t, encoder_count=last.encoder_count, gyro_z_raw=last.gyro_z_raw, fresh=False,
                              faults="imu_fifo_overflow", battery_v=last.battery_v, hw_estop=s.hw_estop,
                              count_left=last.count_left, count_right=last.count_right)
            s.fresh, s.faults = False, "imu_fifo_overflow"
            samples = []
        s.gyro_n = len(samples)
        s.gyro_sum_raw = sum(samples)
        if samples:
            s.gyro_z_raw = samples[-1]
        elif last is not None:
            s.gyro_z_raw = last.gyro_z_raw
        return s

    def write(self, duty_l: float, duty_r: float) -> None:
        """Hal.write, its checks first on the common path: both duties in range go straight to
        the motors; anything else is Hal.write's (the HalValueError naming the duty)."""
        dl = float(duty_l)
        dr = float(duty_r)
        if not (-1.0 <= dl <= 1.0 and -1.0 <= dr <= 1.0):
            super().write(duty_l, duty_r)
        elif self._closed or self.wiring is not None:
            self._write(dl, dr)
        else:  # _write's common case, written out (one call fewer): every tick
            robot = self.robot
            robot.command(dl, dr)
            self._last_drive_t = robot.t
            self._driving = dl != 0.0 or dr != 0.0

    def _write(self, duty_l: float, duty_r: float) -> None:
        if self._closed:
            raise HalIOError("SimHal.write: the HAL is closed")
        if self.wiring is not None:
            duty_l, duty_r = self.wiring.motors(duty_l, duty_r)
        robot = self.robot
        robot.command(duty_l, duty_r)
        self._last_drive_t = robot.t
        self._driving = duty_l != 0.0 or duty_r != 0.0

    def stop(self) -> None:
        if not self._closed:
            self.robot.command(0.0, 0.0)
            self._driving = False

    def _close(self) -> None:
        robot = self.robot  # None (Hal's default) on a half-built object
        if robot is not None:
            robot.command(0.0, 0.0)
