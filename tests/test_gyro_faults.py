"""A gyro that stops answering is a fault, whatever the path (hal/mpu_watch.py, hal/mpu6050.py,
sim_hal/faults.py; the loop's reaction through bench/gyro_faults.py)."""

from __future__ import annotations

import errno
import math
import random

import pytest

from ddrt.params.mpu_parts import MPU_PARTS
from hal.base import HalIOError, HalSensorFault, HalTimeoutError
from hal.mpu6050 import CONFIG_CHECK_S, MAX_REINITS, Mpu6050
from hal.mpu_watch import FALSE_ALARMS_PER_S, NOISE_FLOOR_DPS_RTHZ, OutputWatch, stuck_bound
from sim_hal.faults import FaultyI2cBus, inject_gyro_fault
from sim_hal.mpu_emulator import MpuEmulator
from tests.support.clocks import ManualClock as Clock

DEG = math.pi / 180.0
BY_NAME = {p.name: p for p in MPU_PARTS}


class NoisyGyro:
    """A rate with white noise of `sigma_dps` per reading (a live part at rest)."""

    def __init__(self, rate_dps: float, sigma_dps: float, seed: int = 0) -> None:
        self.rate = rate_dps * DEG
        self.sigma = sigma_dps * DEG
        self.rng = random.Random(seed)

    def gyro_z_rad_s(self) -> float:
        return self.rate + self.rng.gauss(0.0, self.sigma)


def rig(part=MPU_PARTS[0], fifo: bool = False, sigma_dps: float = 0.05, **kw):
    clock = Clock()
    mpu = MpuEmulator(NoisyGyro(1.5, sigma_dps), part=part, clock=clock)
    bus = FaultyI2cBus(mpu)
    return clock, mpu, bus, Mpu6050(bus, fifo=fifo, clock=clock, **kw)


def tick(clock: Clock, imu: Mpu6050, fifo: bool, dt: float = 0.005):
    clock.t += dt
    return imu.read_gyro_fifo() if fifo else imu.read_gyro_z_raw()


# ------------------------------------------------------------------ the bound and its argument

def test_the_default_bound_is_short_and_meets_its_false_alarm_rate() -> None:
    b = stuck_bound(131.0, 98.0, 200.0)  # MPU-6050, 250 deg/s, DLPF_CFG 2, 200 Hz
    assert b.sigma_lsb == pytest.approx(NOISE_FLOOR_DPS_RTHZ * math.sqrt(98.0) * 131.0)
    assert b.looks == 11 and b.after_s == pytest.approx(11 / 98.0) and b.usable
    assert b.looks_per_s * b.p_same ** b.looks <= FALSE_ALARMS_PER_S  # m meets it ...
    assert b.looks_per_s * b.p_same ** (b.looks - 1) > FALSE_ALARMS_PER_S  # ... and is the least that does
    assert 0.3 - 0.4 * b.after_s > 0.2  # at 0.4 m/s the detection leaves most of 0.3 m for braking


@pytest.mark.parametrize("lsb, bw, rate", [(131.0, 98.0, 200.0), (65.5, 42.0, 100.0), (16.4, 188.0, 1000.0),
                                           (32.8, 5.0, 1000.0), (131.0, 256.0, 8000.0)])
def test_a_bound_is_the_least_count_meeting_the_false_alarm_rate(lsb: float, bw: float, rate: float) -> None:
    b = stuck_bound(lsb, bw, rate)
    if b.p_same < 1.0:
        assert b.looks_per_s * b.p_same ** b.looks <= FALSE_ALARMS_PER_S
        assert b.looks == 2 or b.looks_per_s * b.p_same ** (b.looks - 1) > FALSE_ALARMS_PER_S
    assert b.samples >= b.looks and b.looks_per_s == min(bw, rate)


def test_a_noise_below_one_lsb_gives_a_bound_too_long_to_use() -> None:
    b = stuck_bound(16.4, 5.0, 1000.0)  # 2000 deg/s behind a 5 Hz low-pass: sigma 0.09 LSB
    assert b.p_same == 1.0 and not b.usable


def test_a_live_part_at_its_noise_floor_never_trips_in_an_hour_of_reads() -> None:
    """Readings as noisy as the floor the bound assumes, at rest, 200 a second for an hour of
    simulated time: no false alarm (expected: 3.6e3 * 2.8e-8, about 1e-4)."""
    b = stuck_bound(131.0, 98.0, 200.0)
    watch = OutputWatch(b, 200.0)
    rng = random.Random(7)
    sigma = b.sigma_lsb
    for k in range(200 * 3600):
        # readings 5 ms apart behind a 98 Hz low-pass: a fresh draw each look
        assert not watch.word(round(250.3 + rng.gauss(0.0, sigma)), k * 0.005)


# ------------------------------------------------------------------ the driver, fault by fault

@pytest.mark.parametrize("fifo", [False, True], ids=["register", "fifo"])
def test_a_frozen_output_is_a_fault_naming_the_part_within_the_bound(fifo: bool) -> None:
    clock, mpu, bus, imu = rig(BY_NAME["MPU-6500"], fifo)
    for _ in range(40):
        tick(clock, imu, fifo)
    mpu.freeze()
    t0 = clock.t
    with pytest.raises(HalSensorFault) as ei:
        for _ in range(200):
            tick(clock, imu, fifo)
    msg = str(ei.value)
    assert msg.startswith("MPU-6500 at 0x68: its gyro z output repeated 0x") and "frozen" in msg
    assert clock.t - t0 <= imu.stuck.after_s + 0.015
    assert imu.fault_counts["frozen"] == 1
    with pytest.raises(HalSensorFault, match="frozen"):  # it stands, counted once
        tick(clock, imu, fifo)
    assert imu.fault_counts["frozen"] == 1


@pytest.mark.parametrize("fifo", [False, True], ids=["register", "fifo"])
def test_a_bus_that_reads_all_zeros_is_a_fault_naming_what_it_saw(fifo: bool) -> None:
    clock, mpu, bus, imu = rig(fifo=fifo)
    for _ in range(40):
        tick(clock, imu, fifo)
    bus.read_zeros()
    t0 = clock.t
    with pytest.raises(HalSensorFault, match=r"MPU-6050 at 0x68: WHO_AM_I now reads 0x00, expected 0x68 .*all zeros"):
        for _ in range(100):
            tick(clock, imu, fifo)
    assert clock.t - t0 <= 0.03  # two zero readings, or the FIFO's silence
    assert imu.fault_counts["gone"] == 1


def test_a_fifo_that_stops_filling_is_a_fault() -> None:
    clock, mpu, bus, imu = rig(fifo=True)
    for _ in range(40):
        assert tick(clock, imu, True).n >= 1
    mpu.stall()
    t0 = clock.t
    with pytest.raises(HalSensorFault, match=r"MPU-6050 at 0x68: its FIFO stopped filling: no sample for 0\.0[23]"):
        for _ in range(100):
            tick(clock, imu, True)
    assert clock.t - t0 <= 0.03 and imu.fault_counts["fifo_stopped"] == 1


def test_a_stalled_register_is_a_frozen_output() -> None:
    clock, mpu, bus, imu = rig()
    for _ in range(40):
        tick(clock, imu, False)
    mpu.stall()
    with pytest.raises(HalSensorFault, match="frozen"):
        for _ in range(100):
            tick(clock, imu, False)


@pytest.mark.parametrize("part", MPU_PARTS, ids=lambda p: p.name)
@pytest.mark.parametrize("fifo", [False, True], ids=["register", "fifo"])
def test_a_part_that_reset_itself_is_re_initialised_and_its_start_up_held(part, fifo: bool) -> None:
    """Asleep after a reset (MPU-6050, ICM-20689) or awake at its power-on settings (MPU-6500,
    MPU-9250): found within a periodic read-back at most, re-initialised, held as missing for the
    part's start-up, then read again as configured."""
    clock, mpu, bus, imu = rig(part, fifo)
    for _ in range(40):
        tick(clock, imu, fifo)
    mpu.brown_out()
    t0 = clock.t
    with pytest.raises(HalTimeoutError, match=rf"{part.name} at 0x68: the part reset itself: PWR_MGMT_1 "
                                              rf"0x{part.pwr_mgmt_1_reset:02x}.*re-initialised"):
        for _ in range(100):
            tick(clock, imu, fifo)
    assert clock.t - t0 <= CONFIG_CHECK_S + 0.006
    held_until = clock.t + part.startup_s
    while clock.t < held_until - 0.006:
        with pytest.raises(HalTimeoutError, match="still starting"):
            tick(clock, imu, fifo)
    for _ in range(3):
        tick(clock, imu, fifo)
    got = [tick(clock, imu, fifo) for _ in range(20)]
    if fifo:
        assert all(b.n >= 1 and not b.lost for b in got)
    else:
        assert len(set(got)) > 1  # live again
    assert mpu.regs[0x1B] == 0 and mpu.regs[0x1A] == 2 and mpu.regs[0x19] == 4  # configured again
    assert imu.fault_counts["resets"] == 1 and imu.fault_counts["reinits"] == 1


def test_a_part_that_keeps_resetting_is_a_fault() -> None:
    clock, mpu, bus, imu = rig()
    for n in range(MAX_REINITS + 1):
        for _ in range(40):
            try:
                tick(clock, imu, False)
            except HalTimeoutError:
                pass
        mpu.brown_out()
        if n < MAX_REINITS:
            with pytest.raises(HalTimeoutError, match="re-initialised"):
                for _ in range(40):
                    tick(clock, imu, False)
    with pytest.raises(HalSensorFault, match=r"the part reset itself.*3 times within 60 s: not re-initialised again"):
        for _ in range(40):
            tick(clock, imu, False)
    assert imu.fault_counts["resets"] == MAX_REINITS + 1 and imu.fault_counts["reinits"] == MAX_REINITS


def test_a_re_initialisation_that_does_not_take_is_a_fault() -> None:
    clock, mpu, bus, imu = rig()
    for _ in range(20):
        tick(clock, imu, False)
    mpu.brown_out()
    real_write = mpu.write_byte_data
    mpu.write_byte_data = lambda a, r, v, force=None: None if r == 0x1A else real_write(a, r, v)  # CONFIG lost
    with pytest.raises(HalSensorFault, match="re-initialising it did not take"):
        for _ in range(40):
            tick(clock, imu, False)


def test_naks_are_io_errors_naming_the_part() -> None:
    clock, mpu, bus, imu = rig()
    tick(clock, imu, False)
    bus.stop_answering(errno.EREMOTEIO)
    with pytest.raises(HalIOError, match="MPU-6050 at 0x68: read_i2c_block_data failed twice"):
        tick(clock, imu, False)


def test_a_noise_free_gyro_may_turn_off_only_the_repeat_check() -> None:
    clock, mpu, bus, imu = rig(sigma_dps=0.0, watch_repeats=False)
    for _ in range(400):
        tick(clock, imu, False)  # a constant word for 2 s: not a fault
    mpu.brown_out()
    with pytest.raises(HalTimeoutError, match="re-initialised"):  # the other checks stay on
        for _ in range(40):
            tick(clock, imu, False)


def test_inject_gyro_fault_refuses_an_unknown_kind() -> None:
    clock, mpu, bus, imu = rig()
    with pytest.raises(ValueError, match="expected one of frozen, stalled, zeros, nak, reset"):
        inject_gyro_fault("smoke", mpu, bus)
