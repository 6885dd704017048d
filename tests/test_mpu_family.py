"""The MPU-6050 family: each part told apart by WHO_AM_I and driven by its own facts
(ddrt/params/mpu_parts.py, hal/mpu6050.py, sim_hal/mpu_emulator.py)."""

from __future__ import annotations

import math
import random

import pytest

from ddrt.config import ConfigError, load_config
from ddrt.params.mpu_parts import MPU_PARTS, part_by_name, part_by_who_am_i, part_names
from hal.base import HalInitError
from hal.mpu6050 import FIFO_SIZE_MAX, TEMP_OUT_H, Mpu6050
from sim_hal.mpu_emulator import ConstantGyro, MpuEmulator, SineGyro
from tests.support.clocks import ManualClock as Clock
from tests.support.repo import REPO

DEG = math.pi / 180.0
BY_NAME = {p.name: p for p in MPU_PARTS}


def test_the_table_holds_each_parts_datasheet_facts() -> None:
    six050, six500, nine250, icm = (BY_NAME[n] for n in ("MPU-6050", "MPU-6500", "MPU-9250", "ICM-20689"))
    assert [p.who_am_i for p in MPU_PARTS] == [0x68, 0x70, 0x71, 0x98]
    # temperature: at TEMP_OUT 0 and per LSB
    assert (six050.temp_c(0), six050.temp_c(340)) == (36.53, pytest.approx(37.53))
    assert (six500.temp_c(0), six500.temp_c(334)) == (21.0, pytest.approx(22.0, abs=0.001))
    assert (icm.temp_c(0), icm.temp_c(-3268)) == (25.0, pytest.approx(15.0))
    assert nine250.temp_c(1000) == six500.temp_c(1000)
    # the FIFOs
    assert (six050.fifo_bytes, six500.fifo_bytes, nine250.fifo_bytes, icm.fifo_bytes) == (1024, 512, 512, 4096)
    assert icm.fifo_size_register == 0x1D and six050.fifo_size_register is None
    # the low-pass's delays at DLPF_CFG 2 (the default) and 6
    assert (six050.dlpf_delay_s[2], six500.dlpf_delay_s[2], icm.dlpf_delay_s[2]) == (0.0028, 0.0039, 0.0039)
    assert (six050.dlpf_delay_s[6], six500.dlpf_delay_s[6]) == (0.0186, 0.03348)
    # asleep after a reset, or not
    assert (six050.pwr_mgmt_1_reset, six500.pwr_mgmt_1_reset, icm.pwr_mgmt_1_reset) == (0x40, 0x01, 0x40)
    for p in MPU_PARTS:
        assert len(p.dlpf_delay_s) == len(p.dlpf_bandwidth_hz) == 7
        assert list(p.dlpf_delay_s) == sorted(p.dlpf_delay_s)  # narrower low-pass, longer delay
        assert list(p.dlpf_bandwidth_hz) == sorted(p.dlpf_bandwidth_hz, reverse=True)


def test_temperature_round_trips_through_each_parts_formula() -> None:
    rng = random.Random(3)
    for p in MPU_PARTS:
        for _ in range(50):
            t = rng.uniform(-40.0, 85.0)
            assert p.temp_c(p.temp_raw(t)) == pytest.approx(t, abs=0.5 / p.temp_lsb_per_c)


def test_parts_are_found_by_who_am_i_and_by_name() -> None:
    for p in MPU_PARTS:
        assert part_by_who_am_i(p.who_am_i) is p
        assert part_by_name(p.name) is p and part_by_name(p.name.lower().replace("-", "")) is p
    for who in (0x00, 0x12, 0x69, 0xAF, 0xFF):
        assert part_by_who_am_i(who) is None
    with pytest.raises(ValueError, match=r"MPU-6050 \(0x68\).*ICM-20689 \(0x98\)"):
        part_by_name("BMI160")


@pytest.mark.parametrize("part", MPU_PARTS, ids=lambda p: p.name)
def test_the_driver_identifies_each_part_and_uses_its_facts(part) -> None:
    clock = Clock()
    bus = MpuEmulator(SineGyro(0.5, 1.3, clock), part=part, clock=clock, temperature_c=lambda: 31.25)
    imu = Mpu6050(bus, dlpf_cfg=3, clock=clock)
    assert imu.part is part and imu.gyro_part == part.label
    assert imu.gyro_delay_s == part.dlpf_delay_s[3]
    assert imu.sample_age_s == pytest.approx(part.dlpf_delay_s[3] + 0.5 * 0.005)
    assert imu.read_temp_c() == pytest.approx(31.25, abs=0.5 / part.temp_lsb_per_c)
    raw = bus.regs[TEMP_OUT_H] << 8 | bus.regs[TEMP_OUT_H + 1]
    assert raw - (raw >> 15) * 65536 == part.temp_raw(31.25)  # the part's own TEMP_OUT
    assert imu.fifo_bytes == part.fifo_bytes
    if part.fifo_size_register is not None:  # the largest FIFO chosen at set-up
        assert bus.regs[part.fifo_size_register] == FIFO_SIZE_MAX and bus.fifo_bytes == 4096


@pytest.mark.parametrize("part", MPU_PARTS, ids=lambda p: p.name)
def test_each_parts_fifo_overflows_at_its_own_size(part) -> None:
    """A FIFO read that finds it full is a loss: at 1024 bytes on an MPU-6050, at 512 on an
    MPU-6500, only at 4096 on an ICM-20689 (which holds 8 times the MPU-6500's)."""
    clock = Clock()
    bus = MpuEmulator(ConstantGyro(3.0 * DEG), part=part, clock=clock)
    imu = Mpu6050(bus, fifo=True, sample_rate_div=0, clock=clock, watch_repeats=False)  # 1 kHz: 2 bytes a ms
    imu.read_gyro_fifo()
    samples = part.fifo_bytes // 2
    clock.t += (samples - 8) * 0.001  # just short of full
    b = imu.read_gyro_fifo()
    assert not b.lost and samples - 10 <= b.n <= samples - 6
    clock.t += (samples + 8) * 0.001  # beyond full
    assert imu.read_gyro_fifo().lost


def test_an_icm_20689_left_at_its_reset_fifo_size_overflows_at_512_bytes() -> None:
    """The emulated ICM-20689 follows its FIFO_SIZE bits: after a reset its FIFO is 512 bytes."""
    bus = MpuEmulator(ConstantGyro(), part=BY_NAME["ICM-20689"])
    assert bus.fifo_bytes == 512
    bus.write_byte_data(0x68, 0x1D, 0x40)
    assert bus.fifo_bytes == 1024


def test_an_unknown_who_am_i_is_refused_naming_the_value_and_every_known_part() -> None:
    with pytest.raises(HalInitError) as ei:
        Mpu6050(MpuEmulator(ConstantGyro(), who_am_i=0xAF))
    msg = str(ei.value)
    assert "read 0xaf" in msg and "gyro at 0x68" in msg
    assert all(f"{p.name} (0x{p.who_am_i:02x})" in msg for p in MPU_PARTS)


def test_sim_gyro_part_is_checked_at_load_naming_the_key() -> None:
    cfg = load_config(REPO / "configs" / "sim.yaml", {"sim": {"gyro": {"part": "MPU-6500"}}})
    assert cfg.sim.gyro.part == "MPU-6500"
    with pytest.raises(ConfigError, match=r"sim\.gyro\.part: unknown gyro part 'MPU-6000X'.*MPU-6500 \(0x70\)"):
        load_config(REPO / "configs" / "sim.yaml", {"sim": {"gyro": {"part": "MPU-6000X"}}})


def test_part_names_are_the_tables() -> None:
    assert part_names() == ("MPU-6050", "MPU-6500", "MPU-9250", "ICM-20689")
