"""`ddrt sim`: the closed loop on the simulated robot, as fast as the CPU allows.

The same `ControlLoop.tick` as on the robot; the simulated HAL is also the clock, so
sleeping until the next deadline just advances the plant. Writes telemetry.csv (one row per
controller tick, true state beside the estimate and the reference) and metrics.json.
"""

from __future__ import annotations

import csv
import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path as FsPath
from typing import Any, Callable

import numpy as np

from ddrt.config import Config
from ddrt.core.wrap import wrap_angle
from ddrt.loop import COLUMNS, ControlLoop
from ddrt.simrun.metrics import tracking_metrics
from ddrt.path import Path
from hal.registry import open_hal

TRUTH_COLUMNS = ("x", "y", "theta", "v", "omega")
SIM_COLUMNS = ("t",) + TRUTH_COLUMNS + COLUMNS[1:]


@dataclass
class SimResult:
    """What a run produced: per-tick rows (SIM_COLUMNS), metrics, and the path followed."""

    rows: list[tuple[float, ...]]
    metrics: dict[str, Any]
    path: Path
    columns: tuple[str, ...] = SIM_COLUMNS
    extra: dict[str, Any] = field(default_factory=dict)

    def column(self, name: str) -> np.ndarray:
        i = self.columns.index(name)
        return np.array([r[i] for r in self.rows])


def run_sim(cfg: Config, path: Path, *, duration: float | None = None, seed: int | None = None,
            start: tuple[float, float, float] | None = None,
            progress: Callable[[float, float], None] | None = None) -> SimResult:
    """Calibrate at rest, follow `path` to its end (or `duration` s), return rows and metrics."""
    pose = start or cfg.start or path.start_pose
    hal = open_hal(cfg, start=pose, seed=seed)
    robot = hal.robot  # the truth, for telemetry only
    loop = ControlLoop(cfg, hal)
    rows: list[tuple[float, ...]] = []
    wall0 = time.perf_counter()
    loop.calibrate(hal.sleep_until, hal.now)
    # Stand still a little longer, as a robot does between power-on and its first command:
    # the estimator keeps refining the gyro bias at rest.
    t_idle = hal.now()
    for i in range(int(round(cfg.sim.start_delay_s / loop.period))):
        hal.sleep_until(t_idle + (i + 1) * loop.period)
        loop.tick()
    if loop.state not in ("estop", "fault"):  # a fault at rest: one tick records it, below
        loop.follow(path, pose)
    t0 = hal.now()
    limit = duration if duration is not None else 1.5 * path.duration + 10.0
    period = loop.period
    n_ticks = int(math.ceil(limit / period))
    report_every = max(1, int(5.0 / period))
    wall_loop0 = time.perf_counter()
    for i in range(n_ticks):
        deadline = t0 + (i + 1) * period
        hal.sleep_until(deadline)
        loop.tick()
        x, y, th = robot.pose
        v, w = robot.velocity
        r = loop.row
        rows.append((r[0] - t0, x, y, th, v, w) + tuple(r[1:]))
        if loop.state in ("stopped", "fault"):
            break
        if progress is not None and i % report_every == 0:
            progress(hal.now() - t0, limit)
    wall_loop = time.perf_counter() - wall_loop0
    hal.close()
    metrics = summarise(rows, path, loop)
    metrics["wall_s"] = time.perf_counter() - wall0
    metrics["realtime_factor"] = metrics["sim_duration_s"] / wall_loop if wall_loop > 0 else float("inf")
    metrics["controller"] = cfg.controller.mode
    return SimResult(rows=rows, metrics=metrics, path=path)


def summarise(rows: list[tuple[float, ...]], path: Path, loop: ControlLoop) -> dict[str, Any]:
    """metrics.json's content from the per-tick rows."""
    idx = {name: i for i, name in enumerate(SIM_COLUMNS)}
    arr = np.array(rows) if rows else np.zeros((0, len(SIM_COLUMNS)))
    true_xy = arr[:, [idx["x"], idx["y"]]]
    est_xy = arr[:, [idx["x_est"], idx["y_est"]]]
    heading = np.array([wrap_angle(a - b) for a, b in zip(arr[:, idx["theta_ref"]], arr[:, idx["theta"]])])
    m: dict[str, Any] = tracking_metrics(path, true_xy, est_xy, heading, arr[:, idx["saturated"]],
                                                 arr[:, idx["sigma"]])
    m.update({
        "completed": loop.state == "stopped",
        "state": loop.state,
        "fault": loop.fault,
        "ticks": len(rows),
        "sim_duration_s": float(arr[-1, 0]) if len(arr) else 0.0,
        "path_length_m": path.length,
        "path_duration_s": path.duration,
        "rms_velocity_err_mps": float(np.sqrt(np.mean((arr[:, idx["v_ref"]] - arr[:, idx["v"]]) ** 2))) if len(arr) else 0.0,
        "estimator": {"gyro_rejects": loop.estimator.health.gyro_rejects,
                      "encoder_rejects": loop.estimator.health.encoder_rejects},
    })
    return m


def write_outputs(result: SimResult, out_dir: str | FsPath) -> None:
    """telemetry.csv and metrics.json into `out_dir`."""
    out = FsPath(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "telemetry.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(result.columns)
        for r in result.rows:
            w.writerow([f"{v:.9g}" for v in r])
    with open(out / "metrics.json", "w") as fh:
        json.dump(result.metrics, fh, indent=2, sort_keys=True)
        fh.write("\n")


def summary_text(m: dict[str, Any]) -> str:
    """One screen: what happened and how well."""
    lines = [
        f"controller        {m['controller']}",
        f"completed         {m['completed']}  (state {m['state']}{', ' + m['fault'] if m['fault'] else ''})",
        f"simulated         {m['sim_duration_s']:.2f} s in {m['ticks']} ticks, wall {m['wall_s']:.2f} s "
        f"({m['realtime_factor']:.0f}x real time)",
        f"cross-track true  rms {m['rms_cross_track_m'] * 1000:.3f} mm   max {m['max_cross_track_m'] * 1000:.3f} mm",
        f"cross-track est   rms {m['rms_tracking_m'] * 1000:.3f} mm   max {m['max_tracking_m'] * 1000:.3f} mm",
        f"heading           rms {math.degrees(m['rms_heading_err_rad']):.3f} deg",
        f"final position    {m['final_pos_err_m'] * 1000:.2f} mm from the end",
        f"saturated         {m['saturated_fraction'] * 100:.1f}% of ticks",
    ]
    return "\n".join(lines)


def stderr_progress(t: float, limit: float) -> None:
    sys.stderr.write(f"\r  simulated {t:7.1f} s of at most {limit:.0f} s")
    sys.stderr.flush()
