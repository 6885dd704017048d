"""The InvenSense gyros ddrt drives, one row each, told apart by WHO_AM_I (register 0x75).

They share the MPU-6050's register map where ddrt touches it (SMPLRT_DIV, CONFIG's DLPF_CFG,
GYRO_CONFIG's FS_SEL, TEMP_OUT, GYRO_ZOUT, FIFO_EN's ZG bit, USER_CTRL, FIFO_COUNT, FIFO_R_W,
PWR_MGMT_1) and the same output rate (8 kHz at DLPF_CFG 0, else 1 kHz, over 1 + SMPLRT_DIV),
and differ in what a driver must get right per part: the temperature formula, the low-pass's
bandwidths and delays, the FIFO's size, PWR_MGMT_1's value after a reset, the gyro's start-up
time. The figures are the parts' register maps and datasheets (MPU-6000/6050 register map rev
4.2, MPU-6500 register map rev 2.1, MPU-9250 register map rev 1.6, ICM-20689 datasheet rev 1.x);
start-up times are the longer of the datasheet's and what Linux's inv_mpu6050 driver waits.

This is a leaf (ddrt/params): the config validates `sim.gyro.part` against it, hal/ drives by
it and sim_hal/ emulates it, without importing one another.
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["MPU_PARTS", "MpuPart", "known_parts", "part_by_name", "part_by_who_am_i", "part_names"]


@dataclass(frozen=True)
class MpuPart:
    """One part's facts. Temperature: degC = TEMP_OUT / temp_lsb_per_c + temp_offset_c."""

    name: str
    who_am_i: int
    temp_lsb_per_c: float
    temp_offset_c: float
    dlpf_bandwidth_hz: tuple[float, ...]  # gyro 3-dB bandwidth by DLPF_CFG 0..6
    dlpf_delay_s: tuple[float, ...]  # gyro group delay by DLPF_CFG 0..6
    fifo_bytes: int  # the FIFO's size as ddrt configures it; full, its oldest data are overwritten
    pwr_mgmt_1_reset: int  # PWR_MGMT_1 after power-on or a reset (0x40: asleep)
    startup_s: float  # after waking, how long before the gyro's samples are valid
    # A register whose bits 7:6 select the FIFO's size (0: 512 bytes ... 3: 4096), written 0xC0;
    # None: the size is fixed.
    fifo_size_register: int | None = None
    same_map: str = ""  # other parts that answer this WHO_AM_I with this register map
    note: str = ""  # what the row takes from elsewhere than the part's own documents

    def temp_c(self, raw: int) -> float:
        """Die temperature (degC) of a TEMP_OUT reading."""
        return raw / self.temp_lsb_per_c + self.temp_offset_c

    def temp_raw(self, temp_c: float) -> int:
        """The int16 TEMP_OUT holds at die temperature `temp_c`."""
        return max(-32768, min(32767, round((temp_c - self.temp_offset_c) * self.temp_lsb_per_c)))

    @property
    def label(self) -> str:
        """Name and WHO_AM_I, as errors and reports print it."""
        return f"{self.name} (WHO_AM_I 0x{self.who_am_i:02x})"


_6500_BANDWIDTH = (250.0, 184.0, 92.0, 41.0, 20.0, 10.0, 5.0)
_6500_DELAY = (0.00097, 0.0029, 0.0039, 0.0059, 0.0099, 0.01785, 0.03348)

MPU_PARTS: tuple[MpuPart, ...] = (
    MpuPart("MPU-6050", 0x68, 340.0, 36.53,
            (256.0, 188.0, 98.0, 42.0, 20.0, 10.0, 5.0),
            (0.00098, 0.0019, 0.0028, 0.0048, 0.0083, 0.0134, 0.0186),
            fifo_bytes=1024, pwr_mgmt_1_reset=0x40, startup_s=0.060, same_map="MPU-6000, MPU-9150"),
    MpuPart("MPU-6500", 0x70, 333.87, 21.0, _6500_BANDWIDTH, _6500_DELAY,
            fifo_bytes=512, pwr_mgmt_1_reset=0x01, startup_s=0.070),
    MpuPart("MPU-9250", 0x71, 333.87, 21.0, _6500_BANDWIDTH, _6500_DELAY,
            fifo_bytes=512, pwr_mgmt_1_reset=0x01, startup_s=0.070,
            note="the MPU-6500's gyro, temperature sensor and FIFO, plus a magnetometer ddrt does not use"),
    MpuPart("ICM-20689", 0x98, 326.8, 25.0, (250.0, 176.0, 92.0, 41.0, 20.0, 10.0, 5.0), _6500_DELAY,
            fifo_bytes=4096, pwr_mgmt_1_reset=0x40, startup_s=0.070, fifo_size_register=0x1D,
            note="its register map gives the low-pass's bandwidths, not its delays: the MPU-6500's, "
                 "whose bandwidths it shares"),
)


def part_names() -> tuple[str, ...]:
    return tuple(p.name for p in MPU_PARTS)


def known_parts() -> str:
    """The table in one line, for errors: 'MPU-6050 (0x68), MPU-6500 (0x70), ...'."""
    return ", ".join(f"{p.name} (0x{p.who_am_i:02x})" for p in MPU_PARTS)


def part_by_who_am_i(who_am_i: int) -> MpuPart | None:
    for p in MPU_PARTS:
        if p.who_am_i == who_am_i:
            return p
    return None


def part_by_name(name: str) -> MpuPart:
    """The part called `name` (case and a missing hyphen forgiven); ValueError listing the known ones."""
    key = name.replace("-", "").upper() if isinstance(name, str) else None
    for p in MPU_PARTS:
        if p.name.replace("-", "") == key:
            return p
    raise ValueError(f"unknown gyro part {name!r}: known parts are {known_parts()}")
