"""A daemon's parts as `ddrt run` builds them (its own HAL, loop and telemetry) following a
circle on the simulated robot, ticked in simulated time and reloaded from its config file:
what the reload tests and the reload fuzz drive."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from ddrt.loop import ControlLoop
from ddrt.path import load_path
from ddrt.path.spec import speed_limits
from ddrt.runtime.clock import MonotonicClock
from ddrt.service.daemon import Daemon
from hal.registry import open_hal
from tests.support.repo import SIM_YAML
from ddrt.loop import COLUMNS
from ddrt.service.telemetry import open_csv_telemetry

PATH = {"shape": "circle", "radius": 0.5, "speed": 0.2, "laps": 3}


def write_config(path: Path, tmp: Path, over: dict[str, Any]) -> None:
    """configs/sim.yaml with a short calibration and telemetry in `tmp`, merged with `over`."""
    base: dict[str, Any] = {
        "extends": str(SIM_YAML),
        "estimator": {"calibration_s": 0.05},
        "daemon": {"telemetry_dir": str(tmp / "tel"), "socket": ""},
    }
    path.write_text(yaml.safe_dump(_merge(base, over)), encoding="utf-8")


def _merge(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    out = dict(a)
    for k, v in b.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


class Rig:
    """A daemon's parts as `ddrt run` builds them, driven tick by tick in simulated time."""

    def __init__(self, tmp: Path) -> None:
        self.file = tmp / "ddrt.yaml"
        self.tmp = tmp
        write_config(self.file, tmp, {})
        d = Daemon(str(self.file))
        self.d = d
        d.hal = open_hal(d.cfg, start=(0.0, 0.0, 0.0))
        d.clock = MonotonicClock(spin_s=d.cfg.daemon.spin_us * 1e-6)
        d.loop = ControlLoop(d.cfg, d.hal)
        d.ring, d.telemetry = open_csv_telemetry(d.cfg.daemon, COLUMNS)
        d.loop.calibrate(d.hal.sleep_until, d.hal.now)
        self.path = load_path(PATH, speed_limits(d.cfg))
        d.loop.follow(self.path)
        self.ticks(20)

    def ticks(self, n: int) -> None:
        loop, hal = self.d.loop, self.d.hal
        for _ in range(n):
            hal.sleep_until(hal.now() + loop.period)
            loop.tick()

    def reload(self, over: dict[str, Any]) -> dict[str, Any]:
        write_config(self.file, self.tmp, over)
        return self.d.reload()

    def close(self) -> None:
        self.d._shutdown()
