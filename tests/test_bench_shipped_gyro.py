"""configs/robot.yaml as shipped holds the heading of a warming MPU: the real drivers on the
emulated devices (bench/gyro_warmup.py's shipped case, shortened), with the defaults a real
MPU gets (TEMP_OUT read, the FIFO on) against TEMP_OUT not read."""

from __future__ import annotations

import pytest

from bench.gyro_warmup import SHIPPED_LAP_S, drive, shipped_config
from ddrt.config import config_from_mapping, load_config
from tests.support.repo import REPO

DRIVE_S = 60.0  # four one-lap figure-eights with a 2 s stop after each, the die warming from cold


def test_a_real_mpu_reads_temp_out_and_its_fifo_by_default() -> None:
    shipped = load_config(REPO / "configs" / "robot.yaml")
    raw = dict(shipped.raw, sensors={k: v for k, v in shipped.raw["sensors"].items() if not k.startswith("gyro_t")
                                     and k != "gyro_fifo"})
    bare = config_from_mapping(raw)
    assert "gyro_temp_hz" not in raw["sensors"] and "gyro_fifo" not in raw["sensors"]
    for cfg in (shipped, shipped_config(1)):
        assert cfg.hal.backend == "real" and cfg.sensors.gyro_temp_hz == 5.0 and cfg.sensors.gyro_fifo is True
    assert bare.sensors.gyro_temp_hz == 5.0 and bare.sensors.gyro_fifo is True  # the keys' own defaults there
    sim = load_config(REPO / "configs" / "sim.yaml")
    assert sim.sensors.gyro_temp_hz == 0.0 and sim.sensors.gyro_fifo is False


@pytest.mark.slow
def test_the_shipped_config_holds_a_warming_gyros_heading() -> None:
    shipped = drive(shipped_config(1), 1, DRIVE_S, laps=1, lap_s=SHIPPED_LAP_S)
    blind = drive(shipped_config(1, {"gyro_temp_hz": 0.0, "gyro_fifo": False}), 1, DRIVE_S, laps=1,
                  lap_s=SHIPPED_LAP_S)
    assert not shipped.fault and not blind.fault and shipped.stops == blind.stops >= 4
    assert abs(shipped.heading_end_deg) < 0.5 and shipped.heading_worst_deg < 1.0
    assert abs(blind.heading_end_deg) > 3.0  # the same drive without TEMP_OUT: the warm-up's bias left in
