"""InvenSense gyro driver (z axis only: the robot's yaw rate) for the MPU-6050 family, over any SMBus.

The part is told by its WHO_AM_I (ddrt/params/mpu_parts.py: MPU-6050, MPU-6500, MPU-9250,
ICM-20689), and its row gives what differs between them: the temperature formula, the
low-pass's delays, the FIFO's size. An unknown WHO_AM_I is refused with the value read and the
known parts.

The bus is handed in (anything with smbus2.SMBus's `read_byte_data`, `write_byte_data`,
`read_i2c_block_data`), so a dict-backed register file tests it completely. Each sample is
ONE 2-byte block read, so the high and low bytes cannot come from different samples. A
transfer that fails with EIO/EREMOTEIO/ETIMEDOUT is retried once, then raised; a fake value
is never returned.

The die temperature (TEMP_OUT, one more 2-byte block read) is read only when asked, a few
times a second: the estimator compensates the gyro's zero-rate bias for it. A reading's age
is the low-pass's group delay plus the output register's hold, 0 to one sample period
(`register_hold_s`), which `sample_age_s` takes at its mean.

With `fifo=True` (`sensors.gyro_fifo`) the part also writes every gyro z sample into its FIFO
(FIFO_EN's ZG_FIFO_EN; 1024 bytes on the MPU-6050, 512 on the MPU-6500, 4096 on the ICM-20689
once its FIFO_SIZE bits are set), and `read_gyro_fifo()` is the per-tick call: FIFO_COUNT (one
2-byte read), then that many whole samples from FIFO_R_W (block reads of at most 32 bytes), so
every sample the gyro produced is delivered exactly once, as a count, a sum and the newest
(`FifoBatch`). Its age is then the low-pass's delay only: which sample is newest is known. A
FIFO that is full (it may have lost samples), a count that cannot be (odd, beyond the FIFO's
size), a short or failed data read: the FIFO is reset and the batch says `lost`, never a
traceback and never a misaligned sample (a failed FIFO transfer is not retried: it may have
popped bytes).

A part that stops answering is a fault whatever the path (hal/mpu_watch.py for the bounds):
an output word repeated longer than the part's noise allows (frozen, or all zeros), a FIFO that
stops filling, a WHO_AM_I that no longer reads right: HalSensorFault naming the part and what
it saw. The configuration registers are read back every CONFIG_CHECK_S and whenever the output
looks dead: a part that reset itself (PWR_MGMT_1 asleep, or its configuration gone) is
re-initialised when that is safe (it still answers as itself, at most MAX_REINITS times in
REINIT_WINDOW_S, and the writes read back), its readings held as missing (HalTimeoutError)
until its gyro has started (the part's `startup_s`): the loop holds the robot and resumes.
Otherwise HalSensorFault. Each is counted (`fault_counts`).
"""

from __future__ import annotations

import errno
import logging
import math
import time
from dataclasses import dataclass
from typing import Any, Callable, Protocol

from collections import deque

from ddrt.params.gyro_scale import GYRO_LSB_PER_DPS, GYRO_RANGES_DPS, gyro_lsb_per_rad_s
from ddrt.params.mpu_parts import MPU_PARTS, MpuPart, known_parts, part_by_who_am_i
from hal.base import GyroCaps, HalInitError, HalIOError, HalSensorFault, HalTimeoutError, HalValueError
from hal.mpu_watch import ALIVE, MAX_STUCK_S, OutputWatch, StuckBound, Symptom, stuck_bound

log = logging.getLogger("ddrt.hal.mpu")

__all__ = [
    "DEFAULT_ADDRESS", "FIFO_BYTES", "FIFO_COUNTH", "FIFO_EN", "FIFO_R_W", "FifoBatch", "GYRO_CONFIG", "GYRO_DELAY_S", "GYRO_FS_SEL", "GYRO_ZOUT_H", "PWR_MGMT_1",
    "SMPLRT_DIV", "CONFIG", "TEMP_OUT_H", "USER_CTRL", "WHO_AM_I", "WHO_AM_I_VALUE", "Mpu6050", "MpuPart", "SmbusLike",
    "gyro_scale", "open_i2c_bus",
]

DEFAULT_ADDRESS = 0x68
# Register map (MPU-6000/6050 Register Map rev 4.2)
SMPLRT_DIV = 0x19
CONFIG = 0x1A  # DLPF_CFG in bits 2:0
GYRO_CONFIG = 0x1B  # FS_SEL in bits 4:3
GYRO_ZOUT_H = 0x47  # GYRO_ZOUT_L follows at 0x48
TEMP_OUT_H = 0x41  # TEMP_OUT_L follows at 0x42; degC by the part's formula (ddrt.params.mpu_parts)
PWR_MGMT_1 = 0x6B
WHO_AM_I = 0x75
WHO_AM_I_VALUE = 0x68  # the MPU-6050's; the family's values are ddrt.params.mpu_parts'
FIFO_EN = 0x23  # which data go into the FIFO: ZG_FIFO_EN is bit 4
USER_CTRL = 0x6A  # FIFO_EN bit 6 (the FIFO runs), FIFO_RESET bit 2 (self-clearing)
FIFO_COUNTH = 0x72  # FIFO_COUNTL follows at 0x73: bytes in the FIFO, big-endian
FIFO_R_W = 0x74  # each read pops one byte
ZG_FIFO_EN = 0x10
USER_FIFO_EN = 0x40
USER_FIFO_RESET = 0x04
FIFO_BYTES = 1024  # the MPU-6050's FIFO size; each part's is its row's fifo_bytes
FIFO_SIZE_MAX = 0xC0  # FIFO_SIZE bits 7:6 = 3: the largest FIFO, where a part can choose
_SMBUS_BLOCK = 32  # the most one SMBus block read returns

PWR_SLEEP = 0x40
PWR_CLKSEL_PLL_XGYRO = 0x01  # steadier than the internal 8 MHz oscillator
FS_SEL_SHIFT = 3
# Full-scale range (deg/s) -> FS_SEL: the ranges of ddrt.params.gyro_scale in ascending order are
# FS_SEL 0..3 (register 27); their sensitivities are that module's table.
GYRO_FS_SEL: dict[int, int] = {rng: fs_sel for fs_sel, rng in enumerate(GYRO_RANGES_DPS)}
# Gyro group delay (s) by DLPF_CFG 0..6 (Register Map rev 4.2, register 26): the
# estimator compensates it so the heading does not lag the encoder's distance.
GYRO_DELAY_S: tuple[float, ...] = MPU_PARTS[0].dlpf_delay_s  # the MPU-6050's; a part's: part.dlpf_delay_s
CONFIG_CHECK_S = 0.1  # how often the configuration registers are read back (two short reads)
MAX_REINITS = 2  # re-initialisations after a reset allowed within ...
REINIT_WINDOW_S = 60.0  # ... this long; a part that keeps resetting is a fault
_RETRY_ERRNOS = frozenset({errno.EIO, errno.EREMOTEIO, errno.ETIMEDOUT})
_DEG = math.pi / 180.0


@dataclass(slots=True)
class FifoBatch:
    """What one FIFO read delivered: `n` samples (0: none since the last read) with raw sum
    `sum_raw`, the newest `last_raw` (None when n is 0); `lost`: samples were lost since the last
    read (the FIFO was full, garbled or unreadable, and was reset), so this batch does not join
    the previous one."""

    n: int
    sum_raw: int
    last_raw: int | None
    lost: bool = False


class SmbusLike(Protocol):
    """The three smbus2.SMBus calls this driver uses."""

    def read_byte_data(self, i2c_addr: int, register: int) -> int: ...
    def write_byte_data(self, i2c_addr: int, register: int, value: int) -> None: ...
    def read_i2c_block_data(self, i2c_addr: int, register: int, length: int) -> list[int]: ...


def gyro_scale(gyro_range_dps: int) -> tuple[float, float]:
    """(LSB per rad/s, full scale in rad/s) for a range; ValueError naming gyro_range_dps."""
    return gyro_lsb_per_rad_s(gyro_range_dps), gyro_range_dps * _DEG


def open_i2c_bus(spec: int | str) -> Any:
    """Open /dev/i2c-N for an int N. "sim" is not opened here: the caller wires an emulator."""
    if isinstance(spec, bool) or not isinstance(spec, int):
        if spec == "sim":
            raise ValueError("bus 'sim': the emulated bus must be built by the caller "
                             "(sim_hal.mpu_emulator.MpuEmulator) and passed in")
        raise ValueError(f"bus: expected an I2C bus number or 'sim', got {spec!r}")
    if spec < 0:
        raise ValueError(f"bus: expected a non-negative bus number, got {spec!r}")
    import smbus2  # lazy: only needed on the robot

    try:
        return smbus2.SMBus(spec)
    except OSError as e:
        raise HalInitError(f"/dev/i2c-{spec}: cannot open I2C bus: {e}") from e


class Mpu6050:
    """Configures the part on construction; `read_gyro_z_raw()` (or `read_gyro_fifo()`) is the
    per-tick call. `clock` (seconds) times the liveness checks; `watch_repeats=False` turns off
    only the repeated-word check (for a noise-free emulated gyro, which no real part is)."""

    def __init__(self, bus: SmbusLike, address: int = DEFAULT_ADDRESS, gyro_range_dps: int = 250,
                 dlpf_cfg: int = 2, sample_rate_div: int = 4, fifo: bool = False, *,
                 clock: Callable[[], float] = time.monotonic, watch_repeats: bool = True) -> None:
        self.lsb_per_rad_s, self.full_scale_rad_s = gyro_scale(gyro_range_dps)
        if isinstance(address, bool) or not isinstance(address, int) or not 0x03 <= address <= 0x77:
            raise ValueError(f"address: expected a 7-bit I2C address, got {address!r}")
        if isinstance(dlpf_cfg, bool) or not isinstance(dlpf_cfg, int) or not 0 <= dlpf_cfg <= 6:
            raise ValueError(f"dlpf_cfg: expected an int in 0..6, got {dlpf_cfg!r}")
        if (isinstance(sample_rate_div, bool) or not isinstance(sample_rate_div, int)
                or not 0 <= sample_rate_div <= 255):
            raise ValueError(f"sample_rate_div: expected an int in 0..255, got {sample_rate_div!r}")
        self.bus = bus
        self.address = address
        self.gyro_range_dps = gyro_range_dps
        self.dlpf_cfg = dlpf_cfg
        self.sample_rate_div = sample_rate_div
        self.fifo = bool(fifo)
        self._clock = clock
        self._watch_repeats = bool(watch_repeats)
        self.fifo_resets = 0  # FIFO resets after a full, garbled or failed read
        self._fifo_reset_due = False  # a FIFO transfer failed: its contents are suspect
        self._rad_per_lsb = 1.0 / self.lsb_per_rad_s
        self.retries = 0  # transfers that failed once and were retried
        self.errors = 0  # transfers that failed after the retry
        # what the liveness checks saw: outputs frozen or all zeros, FIFOs that stopped, resets
        # seen and re-initialised, a WHO_AM_I gone wrong
        self.counts = {"frozen": 0, "zeros": 0, "fifo_stopped": 0, "resets": 0, "reinits": 0, "gone": 0}
        self._where = f"gyro at 0x{address:02x}"
        self.part: MpuPart = self._identify()
        self._where = f"{self.part.name} at 0x{address:02x}"
        self.stuck: StuckBound = stuck_bound(GYRO_LSB_PER_DPS[gyro_range_dps],
                                             self.part.dlpf_bandwidth_hz[dlpf_cfg], self.sample_rate_hz)
        self._watch = OutputWatch(self.stuck, self.sample_rate_hz)
        if watch_repeats and not self.stuck.usable:
            log.warning("%s: at %d deg/s behind DLPF_CFG %d its noise (%.2f LSB) is too small to tell a frozen "
                        "output within %.2f s: the repeat check is too slow to stop the robot in time "
                        "(docs/hardware.md)", self._where, gyro_range_dps, dlpf_cfg, self.stuck.sigma_lsb, MAX_STUCK_S)
        self._reinit_t: deque[float] = deque()
        self._dead: str = ""  # once a fault is seen, every read raises it again (counted once)
        self._prev_raw: int | None = None  # the last register reading
        self.last_event = ""  # what the liveness checks last saw (a re-initialisation, a fault)
        self._starting_until = -math.inf  # after a re-initialisation: no valid sample before
        try:
            self._configure()
        except HalIOError as e:
            raise HalInitError(f"{self._where}: no answer during set-up: {e}") from e
        self._check_due = self._clock() + CONFIG_CHECK_S

    @property
    def gyro_part(self) -> str:
        """The part found, as reports print it: "MPU-6500 (WHO_AM_I 0x70)"."""
        return self.part.label

    @property
    def fifo_bytes(self) -> int:
        return self.part.fifo_bytes

    @property
    def fault_counts(self) -> dict[str, int]:
        """Every fault this driver counted, by name (status shows them as imu.<name>)."""
        return {"retries": self.retries, "errors": self.errors, "fifo_resets": self.fifo_resets, **self.counts}

    @property
    def gyro_delay_s(self) -> float:
        """The datasheet's group delay of the configured digital low-pass."""
        return self.part.dlpf_delay_s[self.dlpf_cfg]

    @property
    def register_hold_s(self) -> float:
        """How long the output register holds one sample: one sample period."""
        return 1.0 / self.sample_rate_hz

    @property
    def sample_age_s(self) -> float:
        """The mean age of a reading: the low-pass's delay plus half the register's hold (the
        low-pass's only through the FIFO, whose newest sample is known)."""
        return self.gyro_delay_s + (0.0 if self.fifo else 0.5 * self.register_hold_s)

    @property
    def fifo_period_s(self) -> float:
        """The nominal time between two FIFO samples (the part's clock may be 1 % off); 0
        without the FIFO."""
        return 1.0 / self.sample_rate_hz if self.fifo else 0.0

    @property
    def caps(self) -> GyroCaps:
        """What this part delivers as configured (hal.base.GyroCaps): the age of a reading, the
        FIFO's period when read through it, and the die temperature (every member has TEMP_OUT)."""
        return GyroCaps(age_s=self.sample_age_s, fifo_period_s=self.fifo_period_s, die_temp=True)

    @property
    def sample_rate_hz(self) -> float:
        """Gyro output rate: 1 kHz with the DLPF on (cfg 1..6), 8 kHz off, over 1 + div."""
        base = 8000.0 if self.dlpf_cfg == 0 else 1000.0
        return base / (1 + self.sample_rate_div)

    # -- set-up -----------------------------------------------------------------------------

    def _identify(self) -> MpuPart:
        try:
            who = self._xfer(self.bus.read_byte_data, self.address, WHO_AM_I)
        except HalIOError as e:
            raise HalInitError(f"{self._where}: no answer during set-up: {e}") from e
        part = part_by_who_am_i(who)
        if part is None:
            raise HalInitError(f"{self._where}: WHO_AM_I (0x{WHO_AM_I:02x}) read 0x{who:02x}, not a part "
                               f"ddrt knows ({known_parts()}): wrong part or address?")
        return part

    def _expected(self) -> tuple[list[int], list[int]]:
        """What the configuration registers hold once set: SMPLRT_DIV, CONFIG, GYRO_CONFIG, and
        USER_CTRL, PWR_MGMT_1."""
        return ([self.sample_rate_div, self.dlpf_cfg, GYRO_FS_SEL[self.gyro_range_dps] << FS_SEL_SHIFT],
                [USER_FIFO_EN if self.fifo else 0, PWR_CLKSEL_PLL_XGYRO])

    def _configure(self) -> None:
        rates, _ = self._expected()
        for reg, value in ((PWR_MGMT_1, PWR_CLKSEL_PLL_XGYRO),  # SLEEP cleared
                           (SMPLRT_DIV, rates[0]), (CONFIG, rates[1]), (GYRO_CONFIG, rates[2])):
            self._xfer(self.bus.write_byte_data, self.address, reg, value)
        if self.part.fifo_size_register is not None:
            self._xfer(self.bus.write_byte_data, self.address, self.part.fifo_size_register, FIFO_SIZE_MAX)
        if self.fifo:
            self._xfer(self.bus.write_byte_data, self.address, FIFO_EN, ZG_FIFO_EN)
            self._fifo_restart()
        else:
            self._xfer(self.bus.write_byte_data, self.address, USER_CTRL, 0)

    def _xfer(self, fn: Callable[..., Any], *args: Any) -> Any:
        try:
            return fn(*args)
        except OSError as e:
            if e.errno not in _RETRY_ERRNOS:
                self.errors += 1
                raise HalIOError(f"{self._where}: {fn.__name__} failed: {e}") from e
        self.retries += 1
        try:
            return fn(*args)
        except OSError as e:
            self.errors += 1
            cls = HalTimeoutError if e.errno == errno.ETIMEDOUT else HalIOError
            raise cls(f"{self._where}: {fn.__name__} failed twice: {e}") from e

    # -- liveness ---------------------------------------------------------------------------

    def _config_seen(self) -> tuple[list[int], list[int]]:
        rates = self._xfer(self.bus.read_i2c_block_data, self.address, SMPLRT_DIV, 3)
        power = self._xfer(self.bus.read_i2c_block_data, self.address, USER_CTRL, 2)
        return [b & 0xFF for b in rates], [b & 0xFF for b in power]

    def _check_part(self, symptom: Symptom, now: float) -> None:
        """Read the part back: WHO_AM_I, then its configuration. A part that reset itself is
        re-initialised if safe (HalTimeoutError: no sample until its gyro has started); a part
        that no longer answers as itself, or keeps resetting, or shows `symptom` while
        configured as set, is a fault. Returns when all is well and `symptom` is ''."""
        self._check_due = now + CONFIG_CHECK_S
        who = self._xfer(self.bus.read_byte_data, self.address, WHO_AM_I)
        if who != self.part.who_am_i:
            self.counts["gone"] += 1
            seen = f"; {symptom.text}" if symptom else ""
            raise HalSensorFault(f"{self._where}: WHO_AM_I now reads 0x{who:02x}, expected 0x{self.part.who_am_i:02x} "
                                 f"(the part no longer answers as itself{', all zeros' if who == 0 else ''}){seen}")
        (rates, power), (want_rates, want_power) = self._config_seen(), self._expected()
        if rates != want_rates or power != want_power:
            self._reinit(rates, power, symptom, now)
        if symptom:
            self.counts[symptom.kind] += 1
            raise HalSensorFault(f"{self._where}: {symptom.text}; it answers as itself, configured as set "
                                 f"(PWR_MGMT_1 0x{power[1]:02x}): its output has stopped")

    def _reinit(self, rates: list[int], power: list[int], symptom: Symptom, now: float) -> None:
        self.counts["resets"] += 1
        asleep = " (asleep)" if power[1] & PWR_SLEEP else ""
        saw = (f"the part reset itself: PWR_MGMT_1 0x{power[1]:02x}{asleep}, USER_CTRL 0x{power[0]:02x}, "
               f"SMPLRT_DIV/CONFIG/GYRO_CONFIG {' '.join(f'0x{b:02x}' for b in rates)}"
               + (f"; {symptom.text}" if symptom else ""))
        while self._reinit_t and now - self._reinit_t[0] > REINIT_WINDOW_S:
            self._reinit_t.popleft()
        if len(self._reinit_t) >= MAX_REINITS:
            raise HalSensorFault(f"{self._where}: {saw}; it did so {len(self._reinit_t) + 1} times within "
                                 f"{REINIT_WINDOW_S:g} s: not re-initialised again (check its supply)")
        self._reinit_t.append(now)
        self._configure()
        if self._config_seen() != self._expected():
            raise HalSensorFault(f"{self._where}: {saw}; re-initialising it did not take (its registers do not read "
                                 "back): not restarted")
        self.counts["reinits"] += 1
        self._watch.reset()
        self._starting_until = now + self.part.startup_s
        self.last_event = (f"{self._where}: {saw}; re-initialised, no sample for its "
                           f"{self.part.startup_s * 1e3:.0f} ms start-up")
        log.warning("%s", self.last_event)
        raise HalTimeoutError(self.last_event)

    def _alive(self, symptom: Symptom = ALIVE) -> None:
        """Per read: the periodic read-back, and a look at the part when the output looks dead.
        A fault found once stands: the part is not trusted again until it is opened anew."""
        if self._dead:
            raise HalSensorFault(self._dead)
        try:
            self._look(symptom)
        except HalSensorFault as e:
            self._dead = self.last_event = str(e)
            raise

    def _look(self, symptom: Symptom) -> None:
        now = self._clock()
        if self._starting_until > -math.inf:
            if now < self._starting_until:
                raise HalTimeoutError(f"{self._where}: re-initialised after a reset, its gyro still starting "
                                      f"({(self._starting_until - now) * 1e3:.0f} ms left)")
            self._starting_until = -math.inf
            if self.fifo:  # what it wrote while starting is not a valid sample
                self._fifo_restart()
        if symptom or now >= self._check_due:
            self._check_part(symptom, now)

    # -- the FIFO -----------------------------------------------------------------------------

    def _fifo_restart(self) -> None:
        """Stop, empty and restart the FIFO (FIFO_RESET acts while USER_CTRL's FIFO_EN is 0)."""
        for value in (0, USER_FIFO_RESET, USER_FIFO_EN):
            self._xfer(self.bus.write_byte_data, self.address, USER_CTRL, value)
        self._watch.fifo_restarted(self._clock())  # an empty FIFO is new, not silent

    def _fifo_lost(self) -> FifoBatch:
        """Reset the FIFO after a full, garbled or failed read; the batch says samples were lost.
        If even the reset fails, it is due again next read (HalIOError now)."""
        self.fifo_resets += 1
        self._fifo_reset_due = True
        self._fifo_restart()
        self._fifo_reset_due = False
        return FifoBatch(0, 0, None, lost=True)

    def read_gyro_fifo(self) -> FifoBatch:
        """Every z sample the part produced since the last call (module doc). HalIOError when
        the bus fails; the FIFO is then reset at the next call, whose batch says `lost`.
        HalSensorFault / HalTimeoutError: the part stopped answering (module doc)."""
        if not self.fifo:
            raise HalValueError(f"{self._where}: read_gyro_fifo needs fifo=True")
        self._alive()
        if self._fifo_reset_due:
            return self._fifo_lost()
        data = self._xfer(self.bus.read_i2c_block_data, self.address, FIFO_COUNTH, 2)
        if not isinstance(data, (list, tuple, bytes, bytearray)) or len(data) != 2:
            self.errors += 1
            return self._fifo_lost()
        count = ((data[0] & 0xFF) << 8) | (data[1] & 0xFF)
        if count >= self.part.fifo_bytes or count % 2:  # full (samples were lost), or no count it can hold
            return self._fifo_lost()
        words: list[int] = []
        left = count
        while left:
            size = min(left, _SMBUS_BLOCK)
            try:
                chunk = self.bus.read_i2c_block_data(self.address, FIFO_R_W, size)
            except OSError as e:  # not retried: the failed transfer may have popped bytes
                self.errors += 1
                self._fifo_reset_due = True
                raise HalIOError(f"{self._where}: FIFO read failed: {e}") from e
            if not isinstance(chunk, (list, tuple, bytes, bytearray)) or len(chunk) != size:
                self.errors += 1
                return self._fifo_lost()
            for i in range(0, size, 2):
                raw = ((chunk[i] & 0xFF) << 8) | (chunk[i + 1] & 0xFF)
                words.append(raw - 0x10000 if raw & 0x8000 else raw)
            left -= size
        symptom = self._watch.batch(words, self._clock())
        if symptom and (self._watch_repeats or symptom.kind == "fifo_stopped"):
            self._alive(symptom)
        return FifoBatch(len(words), sum(words), words[-1] if words else None)

    # -- the register ---------------------------------------------------------------------------

    def read_gyro_z_raw(self) -> int:
        """Raw int16 z rate at the configured range (bias not removed)."""
        self._alive()
        data = self._xfer(self.bus.read_i2c_block_data, self.address, GYRO_ZOUT_H, 2)
        if len(data) != 2:
            self.errors += 1
            raise HalIOError(f"{self._where}: block read returned {len(data)} bytes, expected 2")
        raw = (data[0] << 8) | data[1]
        raw = raw - 0x10000 if raw & 0x8000 else raw
        if self._watch_repeats and not self.fifo:  # with the FIFO, its own samples are watched
            symptom = self._watch.word(raw, self._clock())
            if symptom:
                self._alive(symptom)
        if raw == 0 and self._prev_raw == 0 and self._watch_repeats:
            # A reset zeroes the output registers: read the part back now, not at the next
            # periodic check, so that few zeros are taken for a rate (a live part reads exactly
            # 0 twice in a row rarely, and then this costs three short reads).
            self._check_due = -math.inf
            self._alive()
        self._prev_raw = raw
        return raw

    def read_temp_c(self) -> float:
        """The die temperature (degC) from TEMP_OUT: one 2-byte block read."""
        data = self._xfer(self.bus.read_i2c_block_data, self.address, TEMP_OUT_H, 2)
        if len(data) != 2:
            self.errors += 1
            raise HalIOError(f"{self._where}: TEMP_OUT read returned {len(data)} bytes, expected 2")
        raw = (data[0] << 8) | data[1]
        return self.part.temp_c(raw - 0x10000 if raw & 0x8000 else raw)

    def read_gyro_z(self) -> float:
        """z rate in rad/s (bias not removed)."""
        return self.read_gyro_z_raw() * self._rad_per_lsb

    def calibrate_bias(self, samples: int = 200, max_std_rad_s: float = 0.01,
                       sleep: Callable[[float], None] | None = time.sleep) -> tuple[float, float]:
        """Mean and standard deviation of the z rate over `samples` readings at rest (rad/s).

        Spaced one output period apart (pass sleep=None to read back to back). Raises
        HalValueError when the spread exceeds `max_std_rad_s` or a reading saturates: the
        robot is moving, and a bias taken now would be wrong.
        """
        if isinstance(samples, bool) or not isinstance(samples, int) or samples < 2:
            raise ValueError(f"samples: expected an int >= 2, got {samples!r}")
        if not (math.isfinite(max_std_rad_s) and max_std_rad_s > 0):
            raise ValueError(f"max_std_rad_s: expected a positive number, got {max_std_rad_s!r}")
        period = 1.0 / self.sample_rate_hz
        total = 0.0
        total_sq = 0.0
        for i in range(samples):
            raw = self.read_gyro_z_raw()
            if raw in (-32768, 32767):
                raise HalValueError(f"calibrate_bias: gyro saturated (raw {raw}); robot moving?")
            total += raw
            total_sq += raw * raw
            if sleep is not None and i + 1 < samples:
                sleep(period)
        mean = total / samples
        var = max(0.0, (total_sq - samples * mean * mean) / (samples - 1))
        bias = mean * self._rad_per_lsb
        std = math.sqrt(var) * self._rad_per_lsb
        if std > max_std_rad_s:
            raise HalValueError(
                f"calibrate_bias: gyro spread {std:.4f} rad/s exceeds max_std_rad_s="
                f"{max_std_rad_s:g}; is the robot moving?")
        return bias, std
