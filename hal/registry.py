"""Backends by name: the config says `hal.backend: sim | real`; nothing else imports a driver.

Each backend module is imported only when chosen, so the simulated robot needs no I2C or
serial library and the robot needs no simulator.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from hal.base import Hal, HalInitError

if TYPE_CHECKING:
    from ddrt.config import Config

# name -> "module:function"; the function takes (cfg, **options) and returns a Hal that is
# also a clock (now(), sleep_until()) or is paired with one by the caller.
BACKENDS = {
    "sim": "sim_hal.factory:open_sim_hal",
    "real": "hal.real_factory:open_real_hal",
}


def open_hal(cfg: "Config", **options: Any) -> Hal:
    """Open the backend named by `cfg.hal.backend`."""
    name = cfg.hal.backend
    try:
        target = BACKENDS[name]
    except KeyError:
        raise HalInitError(f"hal.backend: unknown backend {name!r} (known: {', '.join(BACKENDS)})") from None
    module_name, func_name = target.split(":")
    module = importlib.import_module(module_name)
    return getattr(module, func_name)(cfg, **options)
