"""Mpu6050 driver against the register-file emulator (hal/mpu6050.py, sim_hal/mpu_emulator.py)."""

from __future__ import annotations

import errno
import math
from pathlib import Path

import pytest

from hal.base import HalInitError, HalIOError, HalTimeoutError, HalValueError
from hal.mpu6050 import (
    CONFIG, GYRO_CONFIG, GYRO_ZOUT_H, PWR_MGMT_1, SMPLRT_DIV, Mpu6050, gyro_scale, open_i2c_bus,
)
from sim_hal.faults import FaultyI2cBus
from sim_hal.mpu_emulator import ConstantGyro, MpuEmulator, SineGyro

DEG = math.pi / 180.0


@pytest.mark.parametrize("who", [0x00, 0x12, 0x69, 0x72, 0xFF])
def test_an_unknown_who_am_i_is_refused_with_the_value_and_the_known_parts(who: int) -> None:
    bus = MpuEmulator(ConstantGyro(), who_am_i=who)
    with pytest.raises(HalInitError) as ei:
        Mpu6050(bus)
    msg = str(ei.value)
    assert f"read 0x{who:02x}" in msg and "0x68" in msg
    for name, value in (("MPU-6050", "0x68"), ("MPU-6500", "0x70"), ("MPU-9250", "0x71"), ("ICM-20689", "0x98")):
        assert f"{name} ({value})" in msg


def test_no_device_at_address_is_init_error() -> None:
    bus = MpuEmulator(ConstantGyro(), address=0x68)
    with pytest.raises(HalInitError, match="0x69"):
        Mpu6050(bus, address=0x69)


@pytest.mark.parametrize("rng, fs_sel, lsb_dps", [(250, 0, 131.0), (500, 1, 65.5),
                                                   (1000, 2, 32.8), (2000, 3, 16.4)])
def test_range_registers_and_scale(rng: int, fs_sel: int, lsb_dps: float) -> None:
    bus = MpuEmulator(ConstantGyro(10.0 * DEG))  # 10 deg/s
    imu = Mpu6050(bus, gyro_range_dps=rng, dlpf_cfg=3, sample_rate_div=9)
    assert bus.regs[GYRO_CONFIG] == fs_sel << 3
    assert bus.regs[CONFIG] == 3
    assert bus.regs[SMPLRT_DIV] == 9
    assert bus.regs[PWR_MGMT_1] == 0x01  # awake, PLL on gyro X
    assert imu.read_gyro_z_raw() == round(10.0 * lsb_dps)
    assert imu.read_gyro_z() == pytest.approx(10.0 * DEG, rel=2e-3)
    assert imu.lsb_per_rad_s == pytest.approx(lsb_dps / DEG)
    assert imu.full_scale_rad_s == pytest.approx(rng * DEG)


def test_scale_at_250_is_131_lsb_per_dps() -> None:
    lsb, full = gyro_scale(250)
    assert lsb * DEG == pytest.approx(131.0)
    assert full == pytest.approx(250 * DEG)


@pytest.mark.parametrize("bad", [300, 0, True, "250"])
def test_bad_range_is_value_error_naming_field(bad) -> None:
    with pytest.raises(ValueError, match="gyro_range_dps"):
        Mpu6050(MpuEmulator(ConstantGyro()), gyro_range_dps=bad)


def test_bad_dlpf_is_value_error() -> None:
    with pytest.raises(ValueError, match="dlpf_cfg"):
        Mpu6050(MpuEmulator(ConstantGyro()), dlpf_cfg=7)


def test_negative_rate_and_saturation_twos_complement() -> None:
    src = ConstantGyro(-1.0 * DEG)
    imu = Mpu6050(MpuEmulator(src))
    assert imu.read_gyro_z_raw() == -131
    src.rate_rad_s = -1000 * DEG  # beyond +-250 dps
    assert imu.read_gyro_z_raw() == -32768
    src.rate_rad_s = 1000 * DEG
    assert imu.read_gyro_z_raw() == 32767


def test_one_block_read_per_sample() -> None:
    bus = MpuEmulator(ConstantGyro(0.2))
    imu = Mpu6050(bus)
    before = dict(bus.calls)
    for _ in range(5):
        imu.read_gyro_z()
    assert bus.calls["read_i2c_block_data"] - before.get("read_i2c_block_data", 0) == 5
    assert bus.calls["read_byte_data"] == before.get("read_byte_data", 0)
    assert bus.calls["write_byte_data"] == before.get("write_byte_data", 0)


def test_emulator_asleep_until_woken() -> None:
    bus = MpuEmulator(ConstantGyro(1.0))
    assert bus.read_i2c_block_data(0x68, GYRO_ZOUT_H, 2) == [0, 0]  # power-on: asleep
    Mpu6050(bus)
    assert bus.read_i2c_block_data(0x68, GYRO_ZOUT_H, 2) != [0, 0]
    bus.write_byte_data(0x68, PWR_MGMT_1, 0x40)  # back to sleep: output frozen
    frozen = bus.read_i2c_block_data(0x68, GYRO_ZOUT_H, 2)
    bus.source = ConstantGyro(-1.0)
    assert bus.read_i2c_block_data(0x68, GYRO_ZOUT_H, 2) == frozen


def test_eio_retried_once_then_succeeds() -> None:
    bus = FaultyI2cBus(MpuEmulator(ConstantGyro(1.0 * DEG)))
    imu = Mpu6050(bus)
    bus.fail_next(1, errno.EIO)
    assert imu.read_gyro_z_raw() == 131
    assert imu.retries == 1 and imu.errors == 0


def test_eio_twice_raises_hal_io_error() -> None:
    bus = FaultyI2cBus(MpuEmulator(ConstantGyro(1.0 * DEG)))
    imu = Mpu6050(bus)
    bus.fail_next(2, errno.EREMOTEIO)
    with pytest.raises(HalIOError) as ei:
        imu.read_gyro_z_raw()
    assert not isinstance(ei.value, HalTimeoutError)
    assert imu.errors == 1
    assert imu.read_gyro_z_raw() == 131  # the burst is over


def test_etimedout_twice_raises_timeout() -> None:
    bus = FaultyI2cBus(MpuEmulator(ConstantGyro()))
    imu = Mpu6050(bus)
    bus.stop_answering(errno.ETIMEDOUT)
    with pytest.raises(HalTimeoutError):
        imu.read_gyro_z()


def test_other_oserror_not_retried() -> None:
    inner = MpuEmulator(ConstantGyro())
    bus = FaultyI2cBus(inner)
    imu = Mpu6050(bus)
    bus.fail_next(1, errno.ENXIO)
    n = inner.calls["read_i2c_block_data"]
    with pytest.raises(HalIOError):
        imu.read_gyro_z_raw()
    assert imu.retries == 0 and inner.calls["read_i2c_block_data"] == n


def test_init_failure_is_init_error() -> None:
    bus = FaultyI2cBus(MpuEmulator(ConstantGyro()))
    bus.stop_answering(errno.EREMOTEIO)
    with pytest.raises(HalInitError, match="0x68"):
        Mpu6050(bus)


def test_calibrate_bias_at_rest() -> None:
    bus = MpuEmulator(ConstantGyro(0.5 * DEG))  # a 0.5 deg/s bias
    imu = Mpu6050(bus)
    bias, std = imu.calibrate_bias(samples=50, sleep=None)
    assert bias == pytest.approx(0.5 * DEG, abs=1 / imu.lsb_per_rad_s)
    assert std == pytest.approx(0.0, abs=1e-9)


def test_calibrate_bias_refuses_while_moving() -> None:
    t = [0.0]

    def clock() -> float:
        t[0] += 0.005
        return t[0]

    imu = Mpu6050(MpuEmulator(SineGyro(0.5, 2.0, clock)))
    slept: list[float] = []
    with pytest.raises(HalValueError, match="moving"):
        imu.calibrate_bias(samples=50, sleep=slept.append)
    assert slept and slept[0] == pytest.approx(1 / imu.sample_rate_hz)


def test_open_i2c_bus_sim_is_left_to_caller() -> None:
    with pytest.raises(ValueError, match="sim"):
        open_i2c_bus("sim")
    with pytest.raises(ValueError, match="bus"):
        open_i2c_bus("one")


@pytest.mark.parametrize("cfg, delay_ms", [(0, 0.98), (2, 2.8), (6, 18.6)])
def test_reports_the_datasheet_delay_of_its_low_pass(cfg: int, delay_ms: float) -> None:
    imu = Mpu6050(MpuEmulator(ConstantGyro()), dlpf_cfg=cfg)
    assert imu.gyro_delay_s == pytest.approx(delay_ms * 1e-3)
    assert imu.sample_age_s == pytest.approx(delay_ms * 1e-3 + 0.5 / imu.sample_rate_hz)  # plus half the hold


def test_one_range_table_for_driver_simulator_and_config(sim_yaml: Path) -> None:
    from ddrt.config import load_config
    from ddrt.config.schema import ConfigError
    from ddrt.params.gyro_scale import GYRO_LSB_PER_DPS, GYRO_RANGES_DPS
    from hal.mpu6050 import GYRO_FS_SEL
    from sim_hal.plant import PlantConfig

    assert GYRO_RANGES_DPS == (250, 500, 1000, 2000)
    assert GYRO_FS_SEL == {250: 0, 500: 1, 1000: 2, 2000: 3}  # register 27, FS_SEL 0..3
    for rng in GYRO_RANGES_DPS:
        assert gyro_scale(rng)[0] * DEG == pytest.approx(GYRO_LSB_PER_DPS[rng])
        PlantConfig(gyro_range_dps=rng)
        assert load_config(sim_yaml, {"sensors": {"gyro_range_dps": rng}}).sensors.gyro_range_dps == rng
    with pytest.raises(ConfigError, match="gyro_range_dps"):
        load_config(sim_yaml, {"sensors": {"gyro_range_dps": 300}})
