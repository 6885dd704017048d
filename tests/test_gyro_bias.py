"""The gyro's temperature-compensated bias (ddrt/core/gyro_bias.py), TEMP_OUT read at a low
rate by both backends, and a reading's age with the register's hold."""

from __future__ import annotations

import math
import random

import pytest

from ddrt.core.gyro_bias import DEG, WINDOW_S, GyroBias
from ddrt.params.robot import RobotParams
from ddrt.params.motor import MotorParams
from hal.mpu6050 import CONFIG_CHECK_S, GYRO_DELAY_S, Mpu6050
from sim_hal import PlantConfig, SimHal, SimRobot
from sim_hal.mpu_emulator import ConstantGyro, MpuEmulator
from sim_hal.plant_config import Realism
from tests.support.seed_robot import TABLE_5_1

PERIOD = 0.005
NOISE = 0.06 * DEG  # rad/s per sample, about the simulated MPU's after its low-pass


def drive(gb: GyroBias, bias, temp, t0: float, t1: float, rest: bool, rng: random.Random,
          b_used: list[float], heading: list[float]) -> float:
    """Tick `gb` from t0 to t1 with the true bias(t) and temperature(t), moving or at rest;
    b_used[0] is the estimator's bias (the filter's), heading[0] the heading error the
    estimator would integrate ((true - used) bias while moving, nothing at rest)."""
    t = t0
    k = 0
    while t < t1 - 1e-9:
        t += PERIOD
        temp_now = temp(t) if k % 40 == 0 else math.nan  # TEMP_OUT at 5 Hz
        k += 1
        z = bias(t) + rng.gauss(0.0, NOISE)
        if not rest:
            heading[0] += (bias(t) - b_used[0]) * PERIOD  # integrating w = z - b_used
        db, dth = gb.tick(t, PERIOD, temp_now, rest, z, b_used[0])
        b_used[0] += db
        heading[0] += dth  # the estimator adds dth to its heading (error = estimate - truth)
    return t


def new(slope: float | None = None) -> GyroBias:
    return GyroBias(PERIOD, slope, 1e-5, 5.0, 0.5)


def warm(t: float) -> float:
    return 25.0 + 8.0 * (1.0 - math.exp(-t / 120.0))


@pytest.mark.parametrize("slope", [None, 0.136])
def test_bias_follows_the_temperature_between_stops_and_the_heading_is_corrected(slope):
    """A warm-up bias, 0.136 deg/s per degC: with the slope learnt at the stops (or given),
    the bias the estimator uses follows the truth within hundredths of a deg/s, and the
    heading error after 5 minutes of 28 s drives and 2 s stops stays small, where with the
    start's bias held it would be tens of degrees."""
    rng = random.Random(3)

    def bias(t: float) -> float:
        return (1.5 + 0.136 * (warm(t) - 25.0)) * DEG

    gb = new(slope)
    b_used = [bias(0.0)]
    heading = [0.0]
    t = drive(gb, bias, warm, 0.0, 1.0, True, rng, b_used, heading)
    held = 0.0
    worst = 0.0
    while t < 300.0:
        t1 = drive(gb, bias, warm, t, t + 28.0, False, rng, b_used, heading)
        held += sum((bias(t + i * PERIOD) - bias(0.0)) * PERIOD for i in range(int(28.0 / PERIOD)))
        t = drive(gb, bias, warm, t1, t1 + 2.0, True, rng, b_used, heading)
        worst = max(worst, abs(b_used[0] - bias(t)))
        assert gb.pairs >= 2
    assert abs(held) / DEG > 50.0  # what holding the start's bias would cost
    assert worst / DEG < 0.01
    assert abs(heading[0]) / DEG < 0.2
    assert gb.k / DEG == pytest.approx(0.136, abs=0.004)
    assert gb.resyncs == 0 and gb.dropped == 0


def test_a_drift_the_temperature_does_not_explain_is_re_synced_at_the_stop():
    """A bias that ramps 0.01 deg/s per s at a constant temperature: each stop's mean is far
    off the line, so b0 re-syncs to it (counted), and the heading between the stops is
    corrected with b0 taken linearly in time: a linear drift is undone almost exactly."""
    rng = random.Random(5)

    def bias(t: float) -> float:
        return (1.0 + 0.01 * t) * DEG

    gb = new()
    b_used = [bias(0.0)]
    heading = [0.0]
    t = drive(gb, bias, lambda t: 30.0, 0.0, 1.0, True, rng, b_used, heading)
    for _ in range(4):
        t = drive(gb, bias, lambda t: 30.0, t, t + 20.0, False, rng, b_used, heading)
        t = drive(gb, bias, lambda t: 30.0, t, t + 2.0, True, rng, b_used, heading)
        assert abs(b_used[0] - bias(t)) / DEG < 0.02  # the drift since the window's middle
    assert gb.resyncs >= 3
    assert abs(heading[0]) / DEG < 0.5  # about 2 deg per stretch uncorrected


def test_a_stop_where_the_robot_turned_gives_no_pair():
    rng = random.Random(1)
    gb = new()
    b_used = [0.01]
    heading = [0.0]
    drive(gb, lambda t: 0.01, lambda t: 25.0, 0.0, 0.5, False, rng, b_used, heading)
    pairs = gb.pairs
    t = 0.5
    for i in range(int(WINDOW_S / PERIOD) + 1):  # 'at rest', but the readings swing by 2 deg/s
        t += PERIOD
        db, dth = gb.tick(t, PERIOD, math.nan, True, 0.01 + 2.0 * DEG * math.sin(7.0 * t), b_used[0])
        assert db == 0.0 and dth == 0.0
    assert gb.pairs == pairs and gb.dropped == 1


def test_a_commissioned_slope_is_held_and_nothing_happens_before_a_temperature():
    gb = new(0.2)
    assert gb.tick(0.005, PERIOD, math.nan, True, 0.0, 0.0) == (0.0, 0.0)
    assert not gb.started and gb.n == 0
    gb.tick(0.01, PERIOD, 30.0, False, 0.0, 0.0)
    db, _ = gb.tick(0.015, PERIOD, 31.0, False, 0.0, 0.0)
    assert db == pytest.approx(0.2 * DEG)  # 1 degC warmer: the bias moves by the slope
    gb.rescale(2.0)
    assert gb.k == pytest.approx(0.4 * DEG) and gb.fixed_k == pytest.approx(0.4 * DEG)


# ---------------------------------------------------------------------------- the drivers


def test_mpu_reads_temp_out_and_reports_the_age_with_the_hold():
    temp = [41.3]
    bus = MpuEmulator(ConstantGyro(), temperature_c=lambda: temp[0])
    imu = Mpu6050(bus, dlpf_cfg=2, sample_rate_div=4)
    assert imu.read_temp_c() == pytest.approx(41.3, abs=1.0 / 340.0)
    temp[0] = -5.0
    assert imu.read_temp_c() == pytest.approx(-5.0, abs=1.0 / 340.0)
    assert imu.register_hold_s == pytest.approx(0.005)
    assert imu.sample_age_s == pytest.approx(GYRO_DELAY_S[2] + 0.0025)


def test_real_hal_reads_the_temperature_at_its_rate_and_ages_the_gyro():
    """RealHal over the real driver on the emulated part: TEMP_OUT 5 times a second, one
    2-byte block read each (the gyro's own read is one per tick); a failed read is NaN and
    counted, not a fault; the gyro's age is the low-pass's plus half the hold."""
    from hal.base import HalIOError
    from hal.real import RealHal
    from tests.support.fake_bridge import FakeClock, FakeEncoder

    bus = MpuEmulator(ConstantGyro(), temperature_c=lambda: 30.0)
    clock = FakeClock()
    # noise-free: its repeated word is not a frozen part here (watch_repeats=False)
    imu = Mpu6050(bus, dlpf_cfg=2, sample_rate_div=4, clock=clock.now, watch_repeats=False)
    hal = RealHal(imu, FakeEncoder(), clock, temp_hz=5.0)
    assert hal.info.gyro_temp_hz == 5.0
    assert hal.info.gyro_delay_s == pytest.approx(GYRO_DELAY_S[2] + 0.0025)
    before = bus.calls["read_i2c_block_data"]
    temps = []
    for _ in range(200):  # 1 s at 200 Hz
        clock.t += 0.005
        temps.append(hal.read().gyro_temp_c)
    read = [x for x in temps if x == x]
    assert len(read) == 5 and read[0] == pytest.approx(30.0, abs=0.003)
    # the gyro once a tick, TEMP_OUT 5 times, and the driver's read-back of its configuration
    # (two block reads every CONFIG_CHECK_S)
    checks = (bus.calls["read_i2c_block_data"] - before - 200 - 5) / 2
    assert checks in (round(1.0 / CONFIG_CHECK_S) - 1, round(1.0 / CONFIG_CHECK_S))

    def broken(*_a):
        raise HalIOError("nack")

    imu.read_temp_c = broken  # type: ignore[method-assign]
    clock.t += 0.5
    s = hal.read()
    assert math.isnan(s.gyro_temp_c) and s.fresh and hal.fault_counters["temp_errors"] == 1
    off = RealHal(Mpu6050(MpuEmulator(ConstantGyro())), FakeEncoder(), FakeClock())
    assert off.info.gyro_temp_hz == 0.0 and math.isnan(off.read().gyro_temp_c)


def _sim(realism: Realism, temp_hz: float) -> SimHal:
    robot = SimRobot(RobotParams(**TABLE_5_1), MotorParams(), MotorParams(), PlantConfig(realism=realism))
    return SimHal(robot, gyro_temp_hz=temp_hz)


def test_sim_hal_reads_the_temperature_at_its_rate():
    hal = _sim(Realism(gyro_warmup_rise_c=8.0, gyro_warmup_tau_s=10.0), 5.0)
    temps = []
    t = 0.0
    for _ in range(400):  # 2 s at 200 Hz
        t += 0.005
        hal.sleep_until(t)
        temps.append(hal.read().gyro_temp_c)
    read = [x for x in temps if x == x]
    assert 9 <= len(read) <= 11  # 5 Hz, NaN in between
    assert read[-1] == pytest.approx(hal.robot.gyro_die_temp_c, abs=0.2)  # read up to 0.2 s ago, warming 0.8 degC/s
    assert read[-1] > read[0]  # warming
    assert hal.info.gyro_temp_hz == 5.0
    off = _sim(Realism(gyro_warmup_rise_c=8.0), 0.0)
    off.sleep_until(0.5)
    assert math.isnan(off.read().gyro_temp_c) and off.info.gyro_temp_hz == 0.0


def test_sim_hal_ages_the_gyro_by_half_the_hold_like_the_driver():
    held = _sim(Realism(gyro_odr_hz=200.0), 0.0)
    tick = _sim(Realism(), 0.0)
    assert held.info.gyro_delay_s - tick.info.gyro_delay_s == pytest.approx(0.0025)
    assert tick.info.gyro_delay_s == pytest.approx(tick.robot.gyro_delay_s)  # the low-pass's alone
