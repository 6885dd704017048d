"""SimHal: the simulated robot behind the Hal interface, and the loop's clock."""

from __future__ import annotations

import math
import time

import pytest

from ddrt.params.robot import RobotParams
from ddrt.params.motor import MotorParams
from hal.base import Hal, HalError, HalIOError, HalValueError, Sample
from sim_hal import PlantConfig, SimHal, SimRobot
from tests.support.cpu_queue import Stopwatch
from tests.support.seed_robot import TABLE_5_1


def make_hal(paced: bool = False, **cfg) -> SimHal:
    return SimHal.from_params(RobotParams(**TABLE_5_1), cfg=PlantConfig(**cfg), paced=paced)


def test_is_a_hal_with_the_sensor_facts():
    hal = make_hal(gyro_range_dps=500, encoder_counts_per_rev=2048)
    assert isinstance(hal, Hal)
    assert hal.info.encoder_counts_per_rev == 2048
    assert hal.info.gyro_lsb_per_rad_s == pytest.approx(65.5 * 180 / math.pi)
    assert hal.info.gyro_full_scale_rad_s == pytest.approx(math.radians(32767 / 65.5))
    assert isinstance(hal.robot.motor_l, MotorParams)


def test_read_reports_the_robots_sensors_at_sim_time():
    hal = make_hal()
    hal.write(0.6, 0.4)
    assert hal.sleep_until(0.5) == pytest.approx(0.5, abs=1e-12)
    s = hal.read()
    assert isinstance(s, Sample)
    assert s.t == hal.now() == pytest.approx(0.5, abs=1e-12)
    assert s.encoder_count == hal.robot.read_encoder() > 1000
    assert s.gyro_z_raw == hal.robot.read_gyro_raw()
    assert s.fresh and s.faults == ""


def test_sleep_until_advances_the_plant_and_not_backwards():
    hal = make_hal()
    assert hal.now() == 0.0
    assert hal.sleep_until(0.0125) == pytest.approx(0.013, abs=1e-12)  # whole plant steps
    assert hal.sleep_until(0.005) == pytest.approx(0.013, abs=1e-12)
    with pytest.raises(HalValueError):
        hal.sleep_until(math.nan)


@pytest.mark.parametrize("bad", [1.5, -1.0001, math.nan, math.inf])
def test_write_rejects_bad_duty_without_moving(bad):
    hal = make_hal(slip=False)  # slip torque alone would jiggle the robot
    with pytest.raises(HalValueError, match="duty_l"):
        hal.write(bad, 0.0)
    with pytest.raises(ValueError, match="duty_r"):  # HalValueError is also a ValueError
        hal.write(0.2, bad)
    hal.sleep_until(0.1)
    assert hal.robot.applied_duty == (0.0, 0.0)
    assert hal.robot.velocity == (0.0, 0.0)


def test_write_takes_effect_after_the_command_latency():
    hal = make_hal(command_latency_s=0.004)
    hal.sleep_until(0.010)
    hal.write(0.5, -0.5)
    hal.sleep_until(0.013)
    assert hal.robot.applied_duty == (0.0, 0.0)
    hal.sleep_until(0.015)
    assert hal.robot.applied_duty == (0.5, -0.5)


def test_stop_and_close():
    hal = make_hal()
    hal.write(0.8, 0.8)
    hal.sleep_until(0.5)
    hal.stop()
    hal.sleep_until(0.51)
    assert hal.robot.applied_duty == (0.0, 0.0)
    hal.write(0.8, 0.8)
    hal.close()
    hal.close()  # idempotent
    hal.stop()  # must not raise on a closed device
    hal.sleep_until(0.52)
    assert hal.robot.applied_duty == (0.0, 0.0)  # close stopped the motors last
    with pytest.raises(HalIOError):
        hal.read()
    with pytest.raises(HalError):
        hal.write(0.1, 0.1)


def test_context_manager_stops_the_robot():
    with make_hal() as hal:
        hal.write(0.5, 0.5)
        hal.sleep_until(0.1)
    hal.robot.advance_to(0.2)
    assert hal.robot.applied_duty == (0.0, 0.0)


def test_a_loop_over_the_hal_sees_the_robot_move():
    """A 100 Hz loop that only uses the Hal and the clock: counts rise with the wheel."""
    hal = make_hal()
    cpr = hal.info.encoder_counts_per_rev
    counts = []
    deadline = hal.now()
    for _ in range(100):
        s = hal.read()
        counts.append(s.encoder_count)
        hal.write(0.5, 0.5)
        deadline += 0.01
        hal.sleep_until(deadline)
    assert hal.now() == pytest.approx(1.0, abs=1e-9)
    assert all(b >= a for a, b in zip(counts, counts[1:]))
    distance = counts[-1] * 2 * math.pi / cpr * hal.robot.params.r_3
    assert distance == pytest.approx(hal.robot.pose[0], rel=0.05)


def test_paced_mode_follows_the_wall_clock():
    hal = make_hal(paced=True)
    step = hal.robot.step_s
    a0 = time.monotonic()
    sim0 = hal.now()
    b0 = time.monotonic()
    deadline = sim0
    for _ in range(6):
        deadline += 0.02
        assert hal.sleep_until(deadline) >= deadline - 1e-12
    a1 = time.monotonic()
    sim = hal.now() - sim0
    b1 = time.monotonic()
    assert a1 - a0 >= 0.12 - 0.002  # it did wait
    # And sim time is wall time: each reading lies between the wall-clock readings around it
    # (less a plant step: the plant integrates in whole steps), however long this process
    # waited for a CPU in between.
    assert a1 - b0 - step - 1e-9 <= sim <= b1 - a0 + step + 1e-9, (a1 - b0, sim, b1 - a0)
    time.sleep(0.03)
    assert hal.now() - sim0 >= sim + 0.03 - 0.002  # the plant keeps up with the wall clock


def test_unpaced_mode_runs_faster_than_real_time():
    """5 s of simulated time in well under 1 s of wall time where the thread ran (the wall
    time less its wait for a CPU): it never waits for the wall clock."""
    hal = make_hal()
    deadline = 0.0
    with Stopwatch() as watch:
        for _ in range(500):  # 5 s at 100 Hz
            hal.read()
            hal.write(0.3, 0.35)
            deadline += 0.01
            hal.sleep_until(deadline)
    assert watch.running_s < 1.0, (watch.wall, watch.queued)


def test_wraps_an_existing_robot():
    robot = SimRobot(RobotParams(**TABLE_5_1), MotorParams(), MotorParams(), PlantConfig(seed=7),
                     start=(1.0, 2.0, 0.5))
    hal = SimHal(robot)
    assert hal.robot is robot and hal.now() == 0.0
    assert robot.pose == (1.0, 2.0, 0.5)


def test_reported_gyro_delay_is_the_measured_lag_of_the_simulated_gyro():
    """The HAL's gyro_delay_s equals the lag found by matching the reading to the true yaw rate."""
    hal = make_hal(slip=False, sensor_latency_s=0.0, gyro_noise_dps_rthz=0.0, gyro_bias_dps=0.0,
                   gyro_range_dps=2000)
    robot = hal.robot
    h = robot.step_s
    truth, gyro = [], []
    for k in range(1, 1500):
        d = 0.5 * math.sin(2 * math.pi * 1.5 * k * h)
        robot.command(-d, d)  # a smooth turn back and forth
        robot.advance_to(k * h)
        truth.append(robot.velocity[1])
        gyro.append(robot.read_gyro_raw() / hal.info.gyro_lsb_per_rad_s)

    def mismatch(lag: float) -> float:
        # true rate `lag` seconds ago, linearly interpolated between plant steps
        n = lag / h
        i, frac = int(n), n - int(n)
        return sum((gyro[k] - ((1 - frac) * truth[k - i] + frac * truth[k - i - 1])) ** 2
                   for k in range(200, len(gyro)))

    lags = [j * 1e-4 for j in range(0, 40)]
    best = min(lags, key=mismatch)
    assert 0.0005 < hal.info.gyro_delay_s < 0.003
    assert best == pytest.approx(hal.info.gyro_delay_s, abs=2e-4)
