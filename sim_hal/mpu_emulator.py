"""An InvenSense gyro's register file (the MPU-6050 family of ddrt.params.mpu_parts) behind
the three smbus2 calls the driver uses.

`part` chooses which one (`sim.gyro.part`): its WHO_AM_I, its temperature formula, its FIFO's
size (the ICM-20689's as its FIFO_SIZE bits say: 512 bytes after a reset, 4096 at 0xC0) and
PWR_MGMT_1 after a reset (the MPU-6050 and ICM-20689 wake asleep, 0x40; the MPU-6500 and
MPU-9250 awake, 0x01). The rate it reports comes from a `GyroSource` (the simulated robot's yaw
rate), quantised to int16 at the FS_SEL written to GYRO_CONFIG; while asleep the data registers
hold. Every call is recorded in `calls` so tests can count bus transactions.

Given a `clock` (seconds), the part samples as the real one does: its output registers are
refreshed at the sample rate, the gyro output rate (1 kHz with the DLPF on, 8 kHz with
DLPF_CFG 0 or 7) / (1 + SMPLRT_DIV), on its own oscillator (`clock_ppm` off), and hold between
refreshes; without one, every read samples anew. TEMP_OUT reports the die temperature from
`temperature_c` (a register of 0 without it) by the part's formula.

The FIFO (USER_CTRL's FIFO_EN, FIFO_EN's ZG_FIFO_EN, FIFO_COUNT, FIFO_R_W): each gyro z sample
2 bytes big-endian; full, the oldest sample is overwritten and INT_STATUS's FIFO_OFLOW_INT set
(cleared when INT_STATUS is read). Where the samples come from: a source with its own FIFO
(`fifo_samples()`, the simulated robot's every sample, exactly once); else with a clock,
the source's rate at each sample instant passed (the rate now, for every instant since the last
access: exact for a constant rate); else one sample per FIFO_COUNT read.

Faults of the part itself (sim_hal/faults.py injects them, with the bus's): `freeze()` (its
output repeats the word it holds, in the register and into the FIFO), `stall()` (it stops
sampling: the register holds, the FIFO stops filling, everything else answers), `brown_out()`
(it resets itself: registers to their power-on values), `recover()` (live again).
`fifo_garbage(count)` makes the next FIFO_COUNT read report `count`.
"""

from __future__ import annotations

import errno
import math
from collections import Counter
from typing import Callable, Protocol

from ddrt.params.gyro_scale import GYRO_LSB_PER_DPS
from ddrt.params.mpu_parts import MPU_PARTS, MpuPart
from hal.mpu6050 import (
    CONFIG, FIFO_COUNTH, FIFO_EN, FIFO_R_W, GYRO_CONFIG, GYRO_FS_SEL, GYRO_ZOUT_H, PWR_MGMT_1, PWR_SLEEP,
    SMPLRT_DIV, USER_CTRL, USER_FIFO_EN, USER_FIFO_RESET, WHO_AM_I, ZG_FIFO_EN,
)

__all__ = ["ConstantGyro", "GyroSource", "MpuEmulator", "SineGyro", "temp_out_c", "temp_out_raw"]

TEMP_OUT_H = 0x41  # TEMP_OUT_L follows at 0x42
MPU_6050 = MPU_PARTS[0]


def temp_out_raw(temp_c: float, part: MpuPart = MPU_6050) -> int:
    """The int16 TEMP_OUT holds at die temperature `temp_c` (the part's formula)."""
    return part.temp_raw(temp_c)


def temp_out_c(raw: int, part: MpuPart = MPU_6050) -> float:
    """Die temperature (degC) from a TEMP_OUT reading."""
    return part.temp_c(raw)

_DEVICE_RESET = 0x80
INT_STATUS = 0x3A
FIFO_OFLOW_INT = 0x10
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
    """smbus2-compatible fake bus holding one part of the family at `address` (`who_am_i`
    overrides the part's own, to try a part ddrt does not know)."""

    def __init__(self, source: GyroSource, address: int = 0x68,
                 who_am_i: int | None = None, *, part: MpuPart = MPU_6050,
                 clock: Callable[[], float] | None = None,
                 clock_ppm: float = 0.0, temperature_c: Callable[[], float] | None = None,
                 fifo_samples: Callable[[], tuple[list[int], int]] | None = None) -> None:
        self.source = source
        self.fifo_samples = fifo_samples  # the source's own FIFO: (raw samples since the last call, lost)
        self.address = address
        self.part = part
        self._who_am_i = part.who_am_i if who_am_i is None else who_am_i
        self.output = "live"  # the part's own faults: "live", "frozen", "stalled" (module doc)
        self.brown_outs = 0
        self._last_raw = 0  # the last sample it produced (register or FIFO)
        self._frozen_raw = 0
        self._clock = clock
        self._clock_scale = 1.0 + clock_ppm * 1e-6  # its oscillator runs this much fast
        self._temperature_c = temperature_c
        self.calls: Counter[str] = Counter()
        self.regs = bytearray(128)
        self.refreshes = 0  # sample instants at which the output registers were written
        self.fifo_pushed = 0  # samples written into the FIFO (tests)
        self._garbage: int | None = None
        self._power_on()

    def _power_on(self) -> None:
        self.regs[:] = bytes(128)
        self._latched = -1  # index of the sample period the output registers hold
        self.fifo = bytearray()
        self._fifo_instant: int | None = None  # with a clock: the last sample instant pushed
        self.regs[PWR_MGMT_1] = self.part.pwr_mgmt_1_reset
        self.regs[WHO_AM_I] = self._who_am_i

    # --- the part's own faults ------------------------------------------------------------------

    def freeze(self) -> None:
        """Its output repeats its last sample (the register, and every FIFO sample)."""
        self._frozen_raw = self._last_raw
        self.output = "frozen"

    def stall(self) -> None:
        """It stops sampling: the register holds, the FIFO stops filling; the rest answers."""
        self.output = "stalled"

    def brown_out(self) -> None:
        """It resets itself, as after a dip in its supply: every register to its power-on value."""
        self.brown_outs += 1
        self.output = "live"
        self._power_on()

    def recover(self) -> None:
        self.output = "live"

    @property
    def fifo_bytes(self) -> int:
        """The FIFO's size now: the part's, or as its FIFO_SIZE bits (7:6) choose."""
        reg = self.part.fifo_size_register
        return self.part.fifo_bytes if reg is None else 512 << ((self.regs[reg] >> 6) & 0x03)


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
        if self.asleep or self.output == "stalled":
            return
        if self._clock is not None:
            n = math.floor(self._clock() / self.sample_period_s + 1e-9)
            if n == self._latched:
                return
            self._latched = n
        self.refreshes += 1
        if self._temperature_c is not None:
            t_raw = self.part.temp_raw(self._temperature_c()) & 0xFFFF
            self.regs[TEMP_OUT_H] = t_raw >> 8
            self.regs[TEMP_OUT_H + 1] = t_raw & 0xFF
        raw = self._raw_now()
        raw = max(-32768, min(32767, raw)) & 0xFFFF
        self.regs[GYRO_ZOUT_H] = raw >> 8
        self.regs[GYRO_ZOUT_H + 1] = raw & 0xFF

    # --- the FIFO -----------------------------------------------------------------------------

    @property
    def fifo_running(self) -> bool:
        return (not self.asleep and bool(self.regs[USER_CTRL] & USER_FIFO_EN)
                and bool(self.regs[FIFO_EN] & ZG_FIFO_EN))

    def fifo_garbage(self, count: int) -> None:
        """Fault injection: the next FIFO_COUNT read reports `count` (0..0xFFFF)."""
        self._garbage = count & 0xFFFF

    def _push(self, raw: int) -> None:
        raw = max(-32768, min(32767, raw)) & 0xFFFF
        self.fifo += bytes((raw >> 8, raw & 0xFF))
        self.fifo_pushed += 1
        size = self.fifo_bytes
        if len(self.fifo) > size:
            del self.fifo[:len(self.fifo) - size]
            self.regs[INT_STATUS] |= FIFO_OFLOW_INT

    def _fill_fifo(self, on_count_read: bool) -> None:
        """Bring the FIFO up to now (module doc); samples are dropped while it does not run."""
        drain = self.fifo_samples
        if drain is not None:
            samples, lost = drain()
            if self.fifo_running and self.output != "stalled":
                if lost:
                    self.regs[INT_STATUS] |= FIFO_OFLOW_INT
                frozen = self.output == "frozen"
                for r in samples:
                    if frozen:
                        r = self._frozen_raw
                    self._last_raw = r
                    self._push(r)
            return
        if self.output == "stalled":
            return
        if not self.fifo_running:
            self._fifo_instant = None
            return
        if self._clock is None:
            if on_count_read:
                self._push(self._raw_now())
            return
        n = math.floor(self._clock() / self.sample_period_s + 1e-9)
        if self._fifo_instant is None:
            self._fifo_instant = n  # starts filling from the next instant
            return
        if n > self._fifo_instant:
            raw = self._raw_now()
            for _ in range(min(n - self._fifo_instant, self.fifo_bytes // 2 + 1)):
                self._push(raw)
            self._fifo_instant = n

    def _raw_now(self) -> int:
        if self.output == "frozen":
            return self._frozen_raw
        self._last_raw = round(self.source.gyro_z_rad_s() * _DPS_PER_RAD_S * self.lsb_per_dps)
        return self._last_raw

    def _fifo_read(self, register: int, length: int) -> list[int]:
        """Registers with side effects: FIFO_COUNT (filled first), FIFO_R_W (pops), INT_STATUS
        (clears); None for the plain ones."""
        if register in (FIFO_COUNTH, FIFO_COUNTH + 1):
            self._fill_fifo(True)
            count = len(self.fifo) if self._garbage is None else self._garbage
            self._garbage = None
            pair = [count >> 8 & 0xFF, count & 0xFF]
            return (pair if register == FIFO_COUNTH else pair[1:]) + [0] * max(0, length - 2)
        if register == FIFO_R_W:
            self._fill_fifo(False)
            out = list(self.fifo[:length])
            del self.fifo[:length]
            return out + [0xFF] * (length - len(out))  # an empty FIFO reads junk
        self._fill_fifo(False)
        value = self.regs[INT_STATUS]
        self.regs[INT_STATUS] = 0
        return [value] + [0] * (length - 1)

    def read_byte_data(self, i2c_addr: int, register: int, force: bool | None = None) -> int:
        self.calls["read_byte_data"] += 1
        self._check(i2c_addr, register)
        if register in (FIFO_COUNTH, FIFO_COUNTH + 1, FIFO_R_W, INT_STATUS):
            return self._fifo_read(register, 1)[0]
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
        if register == USER_CTRL and value & USER_FIFO_RESET:
            self._fill_fifo(False)  # what was produced until now goes with the reset
            self.fifo.clear()
            self._fifo_instant = None if self._clock is None else math.floor(self._clock() / self.sample_period_s + 1e-9)
            value &= ~USER_FIFO_RESET  # self-clearing
        self.regs[register] = value & 0xFF

    def read_i2c_block_data(self, i2c_addr: int, register: int, length: int,
                            force: bool | None = None) -> list[int]:
        self.calls["read_i2c_block_data"] += 1
        self._check(i2c_addr, register)
        if 1 <= length <= 32 and register in (FIFO_COUNTH, FIFO_R_W, INT_STATUS):
            return self._fifo_read(register, length)  # FIFO_R_W does not advance: any length
        if not 1 <= length <= 32 or register + length > len(self.regs):
            raise OSError(errno.EINVAL, f"bad block length {length}")
        if register <= GYRO_ZOUT_H + 1 and register + length > TEMP_OUT_H:
            self._sample()
        return list(self.regs[register:register + length])
