"""A closed-loop run on the simulated robot fed pose fixes taken from its true pose: what the
map-frame and fix tests drive (the bench has its own, bench/uncertainty.py)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ddrt.config import load_config
from ddrt.core.pose_fix import PoseFix
from ddrt.loop import ControlLoop
from ddrt.path import load_path
from ddrt.path.frame import in_map
from ddrt.path.spec import speed_limits
from ddrt.simrun.metrics import cross_track as polyline_cross_track
from hal.registry import open_hal
from tests.support.repo import REPO


@dataclass
class FixRun:
    t: list[float] = field(default_factory=list)
    true_xy: list[tuple[float, float]] = field(default_factory=list)
    map_xy: list[tuple[float, float]] = field(default_factory=list)
    duty: list[tuple[float, float]] = field(default_factory=list)
    fix_ticks: list[int] = field(default_factory=list)  # the ticks a fix was fused before
    replies: list[dict[str, Any]] = field(default_factory=list)
    path: Any = None
    state: str = ""


def cross_track(path: Any, xy: np.ndarray) -> np.ndarray:
    """Distance of each point to the path's sampled polyline (the bench's measure)."""
    return polyline_cross_track(np.asarray(path.x), np.asarray(path.y), xy)


def run_with_fixes(path_spec: dict[str, Any], duration_s: float, overrides: dict[str, Any] | None = None,
                   fix_every_s: float = 1.0, fix_std: tuple[float, float, float] = (0.005, 0.005, math.radians(1.0)),
                   latency_s: float = 0.1, fixes: bool = True, seed: int = 1, offset: tuple[float, float, float] | None = None,
                   ) -> FixRun:
    """Follow `path_spec` in map for `duration_s`, with a fix of the true pose (plus noise of
    `fix_std`, plus `offset` if given: a fix that disagrees) every `fix_every_s`, arriving
    `latency_s` after the moment it describes."""
    cfg = load_config(REPO / "configs" / "sim.yaml", {"estimator": {"calibration_s": 0.2}, **(overrides or {})})
    path = load_path(path_spec, speed_limits(cfg), paths=cfg.paths)
    hal = open_hal(cfg, start=path.start_pose, seed=seed)
    rng = np.random.default_rng(seed)
    run = FixRun(path=path)
    try:
        loop = ControlLoop(cfg, hal)
        loop.calibrate(hal.sleep_until, hal.now)  # type: ignore[attr-defined]
        loop.follow(path, path.start_pose)
        est = loop.estimator
        loop.reference = in_map(loop.reference, est.frame, (0.0, 0.0, 0.0), cfg.estimator.map_blend_s, loop.period)
        robot = hal.robot
        every = int(round(fix_every_s / loop.period))
        late = int(round(latency_s / loop.period))
        pending: list[tuple[int, PoseFix]] = []
        t0 = hal.now()  # type: ignore[attr-defined]
        sx, sy, sth = fix_std
        cov = (sx * sx, 0.0, 0.0, 0.0, sy * sy, 0.0, 0.0, 0.0, sth * sth)
        off = offset or (0.0, 0.0, 0.0)
        for i in range(int(round(duration_s / loop.period))):
            if pending and pending[0][0] <= i:
                run.replies.append(est.fuse_fix(pending.pop(0)[1]))
                run.fix_ticks.append(i)
            hal.sleep_until(t0 + (i + 1) * loop.period)  # type: ignore[attr-defined]
            loop.tick()
            x, y, th = robot.pose
            if fixes and i % every == every - 1:
                pending.append((i + late, PoseFix(x + rng.normal(0, sx) + off[0], y + rng.normal(0, sy) + off[1],
                                                  th + rng.normal(0, sth) + off[2], cov, est.t_est)))
            run.t.append(est.t_est)
            run.true_xy.append((x, y))
            run.map_xy.append(est.map_pose()[:2])
            run.duty.append((loop.duty_l, loop.duty_r))
            if loop.state.label not in ("following",):
                break
        run.state = loop.state.label
    finally:
        hal.close()
    return run
