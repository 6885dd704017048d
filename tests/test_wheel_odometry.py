"""Drive-wheel encoders: the plant and SimHal deliver them, hal.wiring remaps them with the
motors, config and RealHal accept a robot without a front encoder, and the estimator fuses
them (ddrt/core/wheel_odometry.py): distance, the bias on the move, slip."""

from __future__ import annotations

import dataclasses as dc
import math

import pytest

from ddrt.config import ConfigError, load_config
from ddrt.config.sections import SensorsConfig
from ddrt.config.wiring import SimWiring, WiringConfig
from ddrt.core.kalman import YawFilter
from ddrt.path.spec import resolve_path
from ddrt.simrun.runner import run_sim
from hal.wiring import WiredHal
from sim_hal.factory import open_sim_hal
from sim_hal.wiring import WiringFaults

SIM = "configs/sim.yaml"


def _cfg(front: int, wheels: int, **sim: object):
    cfg = load_config(SIM)
    cfg = dc.replace(cfg, sensors=dc.replace(cfg.sensors, encoder_counts_per_rev=front, wheel_counts_per_rev=wheels))
    if sim:
        cfg = dc.replace(cfg, sim=dc.replace(cfg.sim, gyro=dc.replace(cfg.sim.gyro, **sim)))
    return cfg


def test_sensors_config_needs_one_distance_sensor() -> None:
    SensorsConfig(encoder_counts_per_rev=0, wheel_counts_per_rev=1440).validate("sensors")
    with pytest.raises(ConfigError, match="sensors.encoder_counts_per_rev.*wheel_counts_per_rev"):
        SensorsConfig(encoder_counts_per_rev=0, wheel_counts_per_rev=0).validate("sensors")


def test_simhal_counts_the_wheels_as_they_turn_forward() -> None:
    hal = open_sim_hal(_cfg(0, 1440))
    assert hal.info.wheel_counts_per_rev == 1440 and hal.info.encoder_counts_per_rev == 0
    hal.write(0.5, 0.5)
    hal.sleep_until(hal.now() + 0.5)
    s = hal.read()
    assert s.count_left > 50 and s.count_right > 50  # both forward
    assert s.encoder_count == 0  # no front encoder
    # The count is the wheel's angle at 1440 a turn (within the sensor latency and a count).
    phi_l, phi_r, _ = hal.robot.wheel_angles
    assert abs(s.count_left - phi_l * 1440 / (2 * math.pi)) < 5
    hal.close()


@pytest.mark.parametrize("swapped,left_inv,right_inv", [(True, False, False), (False, True, False),
                                                        (True, True, True), (False, False, True)])
def test_wiring_fix_undoes_the_sim_miswiring_of_the_wheel_counts(swapped: bool, left_inv: bool, right_inv: bool) -> None:
    """A robot miswired in the sim (sim.wiring) behind the matching hal.wiring fix reads like a
    robot wired right: the left wheel's count on count_left, counting up going forward."""
    cfg = _cfg(8192, 1440)
    bad = dc.replace(cfg, sim=dc.replace(cfg.sim, wiring=SimWiring(left_motor_reversed=left_inv,
                                                                  right_motor_reversed=right_inv,
                                                                  motors_swapped=swapped)))
    raw = open_sim_hal(bad)
    assert raw.wiring == WiringFaults(left_inv, right_inv, swapped)
    fixed = WiredHal(raw, WiringConfig(motor_left_inverted=left_inv, motor_right_inverted=right_inv,
                                       motors_swapped=swapped))
    fixed.write(0.2, 0.6)  # left slow, right fast: a left turn
    fixed.sleep_until(fixed.now() + 0.5)
    s = fixed.read()
    assert 0 < s.count_left < s.count_right
    fixed.close()


def test_update_bias_matches_a_general_kalman_update() -> None:
    f = YawFilter(0.0, 0.0, 0.0)
    f.w, f.b, f.p00, f.p01, f.p11 = 0.3, 0.02, 4e-4, -1e-5, 3e-6
    P = [[f.p00, f.p01], [f.p01, f.p11]]
    x = [f.w, f.b]
    z, r = 0.025, 1e-6
    s = P[1][1] + r
    k = [P[0][1] / s, P[1][1] / s]
    y = z - x[1]
    want_x = [x[0] + k[0] * y, x[1] + k[1] * y]
    want_p = [[P[i][j] - k[i] * P[1][j] for j in range(2)] for i in range(2)]
    f.update_bias(z, r)
    assert f.w == pytest.approx(want_x[0]) and f.b == pytest.approx(want_x[1])
    assert (f.p00, f.p01, f.p11) == pytest.approx((want_p[0][0], want_p[0][1], want_p[1][1]))
    assert f.b > 0.02 and f.p11 < 3e-6  # moved towards z, more certain


def test_wheels_only_drives_a_scenario_with_no_slip_flagged() -> None:
    """No front encoder: the wheels give the distance; the run completes like the seed's, and on
    the ideal plant (no wheel slip) no slip is flagged, though the plant's wheel radii differ
    by 4 % from the config's (learnt as the radius difference)."""
    cfg = load_config("configs/scenarios/figure8_slow.yaml")
    base = run_sim(cfg, resolve_path(cfg)).metrics
    cfg = dc.replace(cfg, sensors=dc.replace(cfg.sensors, encoder_counts_per_rev=0, wheel_counts_per_rev=1440))
    res = run_sim(cfg, resolve_path(cfg), keep_rows=True)
    m = res.metrics
    assert m["completed"] and not m["fault"]
    assert m["rms_cross_track_m"] <= 1.5 * base["rms_cross_track_m"] + 2e-3
    assert res.column("wheel_slip").sum() == 0
