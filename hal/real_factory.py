"""`hal.backend: real`: the drivers on the robot's buses, or on emulated devices.

With `hal.imu.bus: sim` the drivers talk to emulated devices backed by the simulated robot
(sim_hal.emulated), byte for byte as they would to the hardware; that module is imported
only then, so the robot never loads the simulator.
"""

from __future__ import annotations

from typing import Any

from ddrt.config import Config
from hal.base import Hal
from hal.real import RealHal


def open_real_hal(cfg: Config, clock: Any = None, **options: Any) -> Hal:
    if cfg.hal.imu.bus == "sim":
        from sim_hal.emulated import open_emulated_real_hal

        return open_emulated_real_hal(cfg, **options)
    return RealHal.from_config(cfg, clock=clock)
