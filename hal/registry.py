"""Backends by name: the config chooses one; nothing else imports a driver or the simulator.

The config's choice resolves to a name in `BACKENDS` (`backend_name`): `hal.backend: sim` is
the simulated robot, `hal.backend: real` the drivers on the robot's buses, and `real` with
`hal.imu.bus: sim` the same drivers on emulated devices, whose entry lives in sim_hal: the
Python model of the microcontroller, or with `hal.bridge.url: simavr://...` the reference
firmware (firmware/) in the simavr simulator. Each
backend module is imported only when chosen (by its "module:function" string, never by an
import statement here), so the simulated robot needs no I2C or serial library, the robot
never loads the simulator, and hal/ imports nothing from sim_hal/.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from hal.base import Hal, HalInitError

if TYPE_CHECKING:
    from ddrt.config import Config

# name -> "module:function". The function takes (cfg, **options) and returns a Hal; it uses
# the options it knows and ignores the rest. The daemon passes all of: `start` (pose where a
# simulated robot starts), `paced` (simulated time follows the wall clock), `seed` (noise)
# and `clock` (the Clock that times hardware devices).
BACKENDS = {
    "sim": "sim_hal.factory:open_sim_hal",
    "real": "hal.real_factory:open_real_hal",
    "emulated": "sim_hal.emulated:open_emulated_real_hal",
    "firmware-sim": "sim_hal.firmware_sim:open_firmware_sim_hal",
}


def backend_name(cfg: "Config") -> str:
    """The BACKENDS entry the config's `hal:` section chooses."""
    name = cfg.hal.backend
    if name == "real" and cfg.hal.imu.bus == "sim":
        if _bridge_url(cfg).startswith("simavr:"):
            return "firmware-sim"  # the real drivers and the reference firmware in simavr
        return "emulated"  # the real drivers, byte for byte, on devices backed by the simulator
    return name


def _bridge_url(cfg: "Config") -> str:
    """hal.bridge.url, or "" when none is given."""
    return cfg.hal.bridge.url or ""


def open_hal(cfg: "Config", **options: Any) -> Hal:
    """Open the backend the config chooses (see `backend_name`)."""
    name = backend_name(cfg)
    try:
        target = BACKENDS[name]
    except KeyError:
        raise HalInitError(f"hal.backend: unknown backend {name!r} (known: {', '.join(BACKENDS)})") from None
    module_name, func_name = target.split(":")
    module = importlib.import_module(module_name)
    hal = getattr(module, func_name)(cfg, **options)
    # The one place the robot's wiring (hal.wiring) is fixed, for every backend alike.
    from hal.wiring import wire

    return wire(hal, cfg.hal.wiring)
