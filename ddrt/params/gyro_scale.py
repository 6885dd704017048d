"""The gyro's full-scale ranges and sensitivities (MPU-6050 datasheet), in one table.

The config validates `sensors.gyro_range_dps` against these ranges, the driver sets FS_SEL
and scales by them (hal/mpu6050.py), and the simulated gyro quantises with them. It lives
here, below all three, so the config and computation never import a driver.
"""

from __future__ import annotations

import math

__all__ = ["GYRO_LSB_PER_DPS", "GYRO_RANGES_DPS", "gyro_lsb_per_rad_s"]

# Full-scale range (deg/s) -> sensitivity (LSB per deg/s), in ascending range order.
GYRO_LSB_PER_DPS: dict[int, float] = {250: 131.0, 500: 65.5, 1000: 32.8, 2000: 16.4}
GYRO_RANGES_DPS: tuple[int, ...] = tuple(GYRO_LSB_PER_DPS)


def gyro_lsb_per_rad_s(gyro_range_dps: int) -> float:
    """Raw units per rad/s at a full-scale range; ValueError naming gyro_range_dps otherwise."""
    lsb = None if isinstance(gyro_range_dps, bool) else GYRO_LSB_PER_DPS.get(gyro_range_dps)  # type: ignore[call-overload]
    if lsb is None:
        raise ValueError(f"gyro_range_dps: expected one of {list(GYRO_RANGES_DPS)}, got {gyro_range_dps!r}")
    return lsb * (180.0 / math.pi)
