"""In-process rigs on the unpaced simulated robot, ticked in simulated time: a calibrated loop
at rest (`Robot`), and a Daemon's loop without its socket whose requests go to handle()
(`DaemonRig`). The velocity-mode and viewer tests drive them."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ddrt.config import load_config, with_overrides
from ddrt.loop import ControlLoop
from ddrt.service.daemon import Daemon
from hal.registry import open_hal
from tests.support.repo import SIM_YAML


class Robot:
    """A calibrated loop at rest on the unpaced simulated robot, ticked in simulated time."""

    def __init__(self, **overrides: Any) -> None:
        cfg = load_config(SIM_YAML, {"estimator": {"calibration_s": 0.2}})
        if overrides:
            cfg = with_overrides(cfg, overrides)
        self.cfg = cfg
        self.hal = open_hal(cfg, start=(0.0, 0.0, 0.0))
        self.plant = self.hal.robot
        self.loop = ControlLoop(cfg, self.hal)
        self.loop.calibrate(self.hal.sleep_until, self.hal.now)
        self.ticks(20)

    def ticks(self, n: int, drive: tuple[float, float] | None = None, every: int = 20) -> None:
        """n ticks; with `drive`, the command re-sent every `every` ticks (10 Hz at 200 Hz)."""
        loop, hal = self.loop, self.hal
        for k in range(n):
            if drive is not None and k % every == 0:
                loop.drive(*drive)
            hal.sleep_until(hal.now() + loop.period)
            loop.tick()

    def until(self, cond: Any, limit_s: float) -> float:
        """Tick until cond(); the simulated seconds it took."""
        t0 = self.hal.now()
        while not cond():
            assert self.hal.now() - t0 < limit_s, f"not within {limit_s} s: {self.loop.state} {self.loop.fault}"
            self.ticks(1)
        return self.hal.now() - t0

    def true_v(self) -> tuple[float, float]:
        return self.plant.velocity

    def close(self) -> None:
        self.hal.close()


class DaemonRig:
    """A Daemon's loop on the simulated robot without its socket (requests go to handle())."""

    def __init__(self, tmp: Path) -> None:
        cfg = tmp / "d.yaml"
        cfg.write_text(f"extends: {SIM_YAML}\nestimator: {{calibration_s: 0.2}}\n"
                       f"daemon: {{telemetry_dir: {tmp}, socket: null}}\n")
        self.d = d = Daemon(str(cfg))
        d.hal = open_hal(d.cfg, start=(0.0, 0.0, 0.0))
        d.loop = ControlLoop(d.cfg, d.hal)
        d.loop.calibrate(d.hal.sleep_until, d.hal.now)

    def ticks(self, n: int) -> None:
        loop, hal = self.d.loop, self.d.hal
        for _ in range(n):
            hal.sleep_until(hal.now() + loop.period)
            loop.tick()

    def snapshot(self) -> tuple[Any, ...]:
        loop = self.d.loop
        ref = loop.reference
        drive = (ref.commanded, ref.target, ref.age_s, ref.braking, ref.commands) if hasattr(ref, "commanded") else None
        return loop.state, loop.fault, ref, drive, self.d.follows.pending
