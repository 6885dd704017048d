"""`hal.backend: real`: the drivers on the robot's buses (I2C gyro, serial microcontroller).

The same drivers on emulated devices (`hal.imu.bus: sim`) are another backend, registered in
hal/registry.py and built by sim_hal, so nothing here loads the simulator.
"""

from __future__ import annotations

from typing import Any

from ddrt.config import Config
from ddrt.core.types import Clock
from hal.base import Hal
from hal.real import RealHal


def open_real_hal(cfg: Config, clock: Clock | None = None, **_: Any) -> Hal:
    """RealHal from the config's `hal:` section; devices timed on `clock` (default: the wall clock)."""
    return RealHal.from_config(cfg, clock=clock)
