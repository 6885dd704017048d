"""What the closed-loop tests on one backend share: a calibrated loop already following the
config's path, and ticking it in the backend's own time while keeping the telemetry rows."""

from __future__ import annotations

from typing import Any

from ddrt.config import Config
from ddrt.loop import COLUMNS, ControlLoop, LoopState
from ddrt.path.spec import resolve_path
from hal.registry import open_hal


def following(cfg: Config) -> tuple[Any, ControlLoop]:
    """(hal, loop): the backend opened at the path's start, calibrated, following the path."""
    path = resolve_path(cfg)
    hal = open_hal(cfg, start=path.start_pose)
    loop = ControlLoop(cfg, hal)
    loop.calibrate(hal.sleep_until, hal.now)
    loop.follow(path, path.start_pose)
    return hal, loop


def tick_rows(hal: Any, loop: ControlLoop, n: int) -> list[dict[str, float]]:
    """Up to n ticks at the loop's period (fewer if it faults); each tick's row by column."""
    rows = []
    t = hal.now()
    for _ in range(n):
        t += loop.period
        hal.sleep_until(t)
        loop.tick()
        rows.append(dict(zip(COLUMNS, loop.row)))
        if loop.state == LoopState.FAULT:
            break
    return rows
