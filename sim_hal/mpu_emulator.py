"""An MPU-6050 register file behind the three smbus2 calls the driver uses.

The rate it reports comes from a `GyroSource` (later the simulated robot's yaw rate),
quantised to int16 at the FS_SEL written to GYRO_CONFIG, with the part's power-on state:
asleep (PWR_MGMT_1 = 0x40), data registers frozen until SLEEP is cleared. Every call is
recorded in `calls` so tests can count bus transactions.

Given a `clock` (seconds), the part samples as the real one does: its output registers are
refreshed at the sample rate, the gyro output rate (1 kHz with the DLPF on, 8 kHz with
DLPF_CFG 0 or 7) / (1 + SMPLRT_DIV), on its own oscillator (`clock_ppm` off), and hold between
refreshes; without one, every read samples anew (as before). TEMP_OUT reports the die
temperature from `temperature_c` (36.53 degC, a register of 0, without it) by the datasheet's
T = TEMP_OUT / 340 + 36.53.
"""

from __future__ import annotations

import errno
import math
from collections import Counter
from typing import Callable, Protocol

from ddrt.params.gyro_scale import GYRO_LSB_PER_DPS
from hal.mpu6050 import (
    CONFIG, GYRO_CONFIG, GYRO_FS_SEL, GYRO_ZOUT_H, PWR_MGMT_1, PWR_SLEEP, SMPLRT_DIV, WHO_AM_I, WHO_AM_I_VALUE,
)

__all__ = ["ConstantGyro", "GyroSource", "MpuEmulator", "SineGyro", "temp_out_c", "temp_out_raw"]

TEMP_OUT_H = 0x41  # TEMP_OUT_L follows at 0x42
TEMP_OFFSET_C = 36.53
TEMP_LSB_PER_C = 340.0


def temp_out_raw(temp_c: float) -> int:
    """The int16 TEMP_OUT holds at die temperature `temp_c` (MPU-6050 register map, 4.18)."""
    return max(-32768, min(32767, round((temp_c - TEMP_OFFSET_C) * TEMP_LSB_PER_C)))


def temp_out_c(raw: int) -> float:
    """Die temperature (degC) from a TEMP_OUT reading."""
    return raw / TEMP_LSB_PER_C + TEMP_OFFSET_C

_DEVICE_RESET = 0x80
_DPS_PER_RAD_S = 180.0 / math.pi
_FS_LSB = {GYRO_FS_SEL[rng]: lsb for rng, lsb in GYRO_LSB_PER_DPS.items()}  # FS_SEL -> LSB per deg/s


class GyroSource(Protocol):
    """The true yaw rate the part measures."""

    def gyro_z_rad_s(self) -> float: ...


class ConstantGyro:
    """A fixed rate (rad/s): the robot at rest has only the bias."""

    def __init__(self, rate_rad_s: float = 0.0) -> None:
        self.rate_rad_s = rate_rad_s

    def gyro_z_rad_s(self) -> float:
        return self.rate_rad_s


class SineGyro:
    """offset + amplitude * sin(2 pi f t), with t from `time_source` (a moving robot)."""

    def __init__(self, amplitude_rad_s: float, freq_hz: float, time_source: Callable[[], float],
                 offset_rad_s: float = 0.0) -> None:
        self.amplitude_rad_s = amplitude_rad_s
        self.freq_hz = freq_hz
        self.offset_rad_s = offset_rad_s
        self._now = time_source

    def gyro_z_rad_s(self) -> float:
        return self.offset_rad_s + self.amplitude_rad_s * math.sin(
            2.0 * math.pi * self.freq_hz * self._now())


class MpuEmulator:
    """smbus2-compatible fake bus holding one MPU-6050 at `address`."""

    def __init__(self, source: GyroSource, address: int = 0x68,
                 who_am_i: int = WHO_AM_I_VALUE, *, clock: Callable[[], float] | None = None,
                 clock_ppm: float = 0.0, temperature_c: Callable[[], float] | None = None) -> None:
        self.source = source
        self.address = address
        self._who_am_i = who_am_i
        self._clock = clock
        self._clock_scale = 1.0 + clock_ppm * 1e-6  # its oscillator runs this much fast
        self._temperature_c = temperature_c
        self.calls: Counter[str] = Counter()
        self.regs = bytearray(128)
        self.refreshes = 0  # sample instants at which the output registers were written
        self._power_on()

    def _power_on(self) -> None:
        self.regs[:] = bytes(128)
        self._latched = -1  # index of the sample period the output registers hold
        self.regs[PWR_MGMT_1] = PWR_SLEEP
        self.regs[WHO_AM_I] = self._who_am_i

    @property
    def asleep(self) -> bool:
        return bool(self.regs[PWR_MGMT_1] & PWR_SLEEP)

    @property
    def lsb_per_dps(self) -> float:
        return _FS_LSB[(self.regs[GYRO_CONFIG] >> 3) & 0x03]

    def _check(self, i2c_addr: int, register: int) -> None:
        if i2c_addr != self.address:
            raise OSError(errno.ENXIO, f"no device at 0x{i2c_addr:02x}")
        if not 0 <= register < len(self.regs):
            raise OSError(errno.EIO, f"register 0x{register:02x} out of range")

    @property
    def sample_period_s(self) -> float:
        """Time between refreshes of the output registers, by the part's own clock's rate."""
        dlpf = self.regs[CONFIG] & 0x07
        output_hz = 8000.0 if dlpf in (0, 7) else 1000.0
        return (1 + self.regs[SMPLRT_DIV]) / (output_hz * self._clock_scale)

    def _sample(self) -> None:
        """Latch a new measurement into GYRO_ZOUT and TEMP_OUT (only while awake); with a clock,
        only once per sample period (the registers hold in between)."""
        if self.asleep:
            return
        if self._clock is not None:
            n = math.floor(self._clock() / self.sample_period_s + 1e-9)
            if n == self._latched:
                return
            self._latched = n
        self.refreshes += 1
        if self._temperature_c is not None:
            t_raw = temp_out_raw(self._temperature_c()) & 0xFFFF
            self.regs[TEMP_OUT_H] = t_raw >> 8
            self.regs[TEMP_OUT_H + 1] = t_raw & 0xFF
        raw = round(self.source.gyro_z_rad_s() * _DPS_PER_RAD_S * self.lsb_per_dps)
        raw = max(-32768, min(32767, raw)) & 0xFFFF
        self.regs[GYRO_ZOUT_H] = raw >> 8
        self.regs[GYRO_ZOUT_H + 1] = raw & 0xFF

    def read_byte_data(self, i2c_addr: int, register: int, force: bool | None = None) -> int:
        self.calls["read_byte_data"] += 1
        self._check(i2c_addr, register)
        if register in (GYRO_ZOUT_H, GYRO_ZOUT_H + 1, TEMP_OUT_H, TEMP_OUT_H + 1):
            self._sample()
        return self.regs[register]

    def write_byte_data(self, i2c_addr: int, register: int, value: int,
                        force: bool | None = None) -> None:
        self.calls["write_byte_data"] += 1
        self._check(i2c_addr, register)
        if register == WHO_AM_I:
            return  # read-only
        if register == PWR_MGMT_1 and value & _DEVICE_RESET:
            self._power_on()
            return
        self.regs[register] = value & 0xFF

    def read_i2c_block_data(self, i2c_addr: int, register: int, length: int,
                            force: bool | None = None) -> list[int]:
        self.calls["read_i2c_block_data"] += 1
        self._check(i2c_addr, register)
        if not 1 <= length <= 32 or register + length > len(self.regs):
            raise OSError(errno.EINVAL, f"bad block length {length}")
        if register <= GYRO_ZOUT_H + 1 and register + length > TEMP_OUT_H:
            self._sample()
        return list(self.regs[register:register + length])
