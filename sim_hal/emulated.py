"""The real drivers on emulated devices: MPU-6050 register file + protocol-v2 MCU, both
backed by the simulated robot (`hal.backend: real`, `hal.imu.bus: sim`,
`hal.bridge.url: ddrtsim://NAME`).

The simulated robot is also the loop's clock here, as with the sim backend: sleeping until a
deadline integrates the plant and lets the emulated MCU run (stream STATE, run its DRIVE
watchdog) up to it. Paced, it follows the wall clock instead.
"""

from __future__ import annotations

import itertools
from dataclasses import replace
from typing import Any, Callable

from ddrt.config import Config
from ddrt.params.mpu_parts import MpuPart, part_by_name
from hal.base import Hal, Sample
from hal.wire import PROTOCOL_V1, PROTOCOL_VERSION
from hal.mpu_watch import NOISE_FLOOR_DPS_RTHZ
from hal.real import RealHal
from sim_hal.serial_urls import protocol_ddrtsim
from sim_hal.factory import plant_config
from sim_hal.faults import FaultyI2cBus
from sim_hal.mcu_emulator import McuEmulator
from sim_hal.mpu_emulator import MpuEmulator
from sim_hal.plant import SimRobot
from sim_hal.simtime import SimTime

_names = itertools.count()


class _PlantMotorsAndEncoder:
    """What the emulated MCU drives and counts: the simulated robot's motors and encoder."""

    def __init__(self, robot: SimRobot) -> None:
        self.robot = robot

    def set_duty(self, duty_l: float, duty_r: float) -> None:
        self.robot.command(duty_l, duty_r)

    def encoder_count(self) -> int:
        return self.robot.read_encoder()


class _PlantGyro:
    """What the emulated MPU-6050 measures: the simulated robot's gyro (noise, bias, lag)."""

    def __init__(self, robot: SimRobot) -> None:
        self.robot = robot

    def gyro_z_rad_s(self) -> float:
        return self.robot.read_gyro_raw() / self.robot.gyro_lsb_per_rad_s


def plant_mpu(robot: SimRobot, part: MpuPart, *, clock: Callable[[], float] | None = None, clock_ppm: float = 0.0,
              temperature_c: Callable[[], float] | None = None) -> MpuEmulator:
    """The emulated MPU on the simulated robot's gyro; with the plant's own FIFO
    (sensors.gyro_fifo) the emulator's FIFO takes each of its samples once."""
    return MpuEmulator(_PlantGyro(robot), part=part, clock=clock, clock_ppm=clock_ppm, temperature_c=temperature_c,
                       fifo_samples=robot.read_gyro_fifo if robot.gyro_fifo else None)


class EmulatedDevices:
    """The simulated robot, its two emulated devices, and the clock that drives them (`time`).

    The MCU is the reference firmware's model: protocol v2, measuring the robot's battery,
    with a hardware estop input (closed until `set_estop(True)`), counting the drive wheels
    when `sensors.wheel_counts_per_rev` > 0. `protocol_version=1`: an MCU of the old protocol
    (no battery, no estop input, no wheel counts).

    The MCU runs on its own crystal, `sim.mcu_clock_ppm` off: its time (the t_us it stamps,
    its STATE period, its DRIVE watchdog) is the plant's scaled by 1 + ppm 1e-6. With
    `sim.gyro.register_hold`, the emulated MPU-6050 refreshes its registers at its sample rate.
    """

    def __init__(self, cfg: Config, start: tuple[float, float, float], seed: int | None = None,
                 paced: bool = False, state_rate_hz: int | None = None,
                 protocol_version: int = PROTOCOL_VERSION) -> None:
        self.robot = SimRobot(cfg.plant, cfg.plant_motor_l, cfg.plant_motor_r, plant_config(cfg, seed), start=start)
        self._mcu_scale = 1.0 + cfg.sim.mcu_clock_ppm * 1e-6
        rate = state_rate_hz or int(round(cfg.controller.rate_hz))
        robot = self.robot
        v2: dict[str, Any] = {}
        if protocol_version != PROTOCOL_V1:
            v2 = dict(battery_v=lambda: robot.battery_v, estop_wired=True)
            if cfg.sensors.wheel_counts_per_rev > 0:
                v2.update(wheel_counts=robot.read_wheel_counts,
                          wheel_counts_per_rev=cfg.sensors.wheel_counts_per_rev)
        self.mcu = McuEmulator(_PlantMotorsAndEncoder(self.robot), now=self.mcu_time(self.robot.t),
                               counts_per_rev=cfg.sensors.encoder_counts_per_rev, state_rate_hz=rate,
                               protocol_version=protocol_version, **v2)
        url = (cfg.hal.bridge.url or "ddrtsim://robot").partition("?")[0]
        self.name = f"{url.split('://', 1)[-1].strip('/') or 'robot'}-{next(_names)}"
        self.url = f"ddrtsim://{self.name}"
        self.link = protocol_ddrtsim.register(self.name, self.mcu, self.mcu_time(self.robot.t))
        robot = self.robot
        g = cfg.sim.gyro
        self.mpu = plant_mpu(robot, part_by_name(g.part), clock=(lambda: robot.t) if g.register_hold else None,
                             clock_ppm=g.clock_ppm, temperature_c=lambda: robot.gyro_die_temp_c)
        self.i2c = FaultyI2cBus(self.mpu)  # the bus the driver is given: faults injectable (sim_hal/faults.py)
        self.time = SimTime(lambda: robot.t, self._advance, paced)  # the real drivers' Clock
        self.link.pump(self.mcu_time(robot.t))

    def mcu_time(self, t: float) -> float:
        """The MCU's own time at plant time `t` (its crystal's error applied)."""
        return t * self._mcu_scale if self._mcu_scale != 1.0 else t

    def set_estop(self, open_: bool) -> None:
        """Open (True) or close the robot's hardware estop input now (tests, fault drills);
        the in-process link is pumped from the caller's thread, at the plant's steps."""
        self.mcu.set_estop(open_, self.mcu_time(self.robot.t))

    def _advance(self, t: float) -> None:
        """Integrate in plant steps, letting the MCU run at each, so STATE frames carry the
        count of the moment they were sent and the DRIVE watchdog fires on time."""
        robot = self.robot
        step = robot.step_s
        while robot.t < t - 1e-12:
            robot.advance_to(min(t, robot.t + step))
            self.link.pump(self.mcu_time(robot.t))

    def close(self) -> None:
        protocol_ddrtsim.unregister(self.name)


class EmulatedRealHal(Hal):
    """RealHal (the real drivers) over EmulatedDevices; also the clock, like SimHal."""

    owns_time = True
    robot: SimRobot  # Hal's optional capability: the truth behind the readings

    def __init__(self, real: RealHal, devices: EmulatedDevices) -> None:
        self.real = real
        self.devices = devices
        self.robot = devices.robot
        self.info = real.info

    def now(self) -> float:
        return self.devices.time.now()

    def advance_to_wall_clock(self) -> None:
        """Paced: run the plant and the emulated MCU up to the wall clock now."""
        self.devices.time.catch_up()

    def sleep_until(self, deadline: float) -> float:
        return self.devices.time.sleep_until(deadline)

    def read(self) -> Sample:
        return self.real.read()

    def _write(self, duty_l: float, duty_r: float) -> None:
        self.real.write(duty_l, duty_r)

    def stop(self) -> None:
        self.real.stop()

    @property
    def fault_counters(self) -> dict[str, int]:
        return self.real.fault_counters

    def _close(self) -> None:
        # Both are set before anything in the constructor can fail.
        try:
            self.real.close()
        finally:
            self.devices.close()


def real_hal_on(cfg: Config, devices: Any) -> RealHal:
    """The real backend built from the same config, its bridge on the devices' link (`url`),
    its clock and I2C bus theirs; the devices are closed if it cannot be built."""
    hal = replace(cfg.hal, bridge=replace(cfg.hal.bridge, url=devices.url))
    try:
        # A simulated gyro quieter than any real part (noise-free, or below the floor the
        # driver's bound assumes) repeats its word at rest, which no live part does: the
        # repeated-word check is for real parts (the driver's other checks stay on).
        return RealHal.from_config(replace(cfg, hal=hal), clock=devices.time, i2c_bus=devices.i2c,
                                   watch_repeats=cfg.sim.gyro.noise_dps_rthz >= NOISE_FLOOR_DPS_RTHZ)
    except BaseException:
        devices.close()
        raise


def mcu_protocol(url: str | None) -> int:
    """The emulated MCU's protocol version from `hal.bridge.url`: `ddrtsim://NAME?v1` is an
    MCU of protocol v1 (to try the host's fallback), anything else the reference firmware's."""
    query = (url or "").partition("?")[2]
    return PROTOCOL_V1 if "v1" in query.split("&") else PROTOCOL_VERSION


def open_emulated_real_hal(cfg: Config, start: tuple[float, float, float] = (0.0, 0.0, 0.0),
                           seed: int | None = None, paced: bool = False, **_: Any) -> EmulatedRealHal:
    devices = EmulatedDevices(cfg, start, seed, paced, protocol_version=mcu_protocol(cfg.hal.bridge.url))
    real = real_hal_on(cfg, devices)
    real.encoder.byte_time_s = 0.0  # the in-process link has no line: bytes arrive as sent
    return EmulatedRealHal(real, devices)
