"""The velocity mode (`drive`) in process on the simulated robot (configs/sim.yaml), in simulated time.

- Tick cost: the real `ControlLoop.tick`, stage-stamped as in section 2 (bench/tick_cost.py),
  while driving a cycle of commands re-sent at 10 Hz (the ramps always at work), against the
  same number of ticks following the config's path.
- The stop after the last command at 1 m/s, on the plant's true state (as tests/test_drive.py
  measures it): the time until the robot stands still and the distance it travelled, against
  the bound daemon.command_timeout_s + the braking time at limits.accel with the jerk ramps
  (v / a + a / j), and the distance that allows, for drive.jerk_max as configured and none.
"""

from __future__ import annotations

import math
from array import array
from dataclasses import dataclass

import numpy as np

from bench import tick_cost
from ddrt.config import Config, with_overrides
from ddrt.loop import ControlLoop
from hal.registry import open_hal

# Drive commands (v m/s, omega rad/s), each held for 2 s and re-sent every 20 ticks.
COMMANDS = ((0.6, 1.5), (-0.4, -2.5), (0.0, 3.0), (0.8, 0.0), (0.3, -1.0))


@dataclass(frozen=True)
class Stop:
    jerk_max: float | None
    still_s: float  # from the last command to standing still (|v| <= 5 mm/s, |omega| <= 0.01 rad/s)
    bound_s: float  # timeout + v / accel + accel / jerk
    travel_m: float
    bound_m: float  # v * timeout + v^2 / (2 accel) + v * (accel / jerk) / 2


@dataclass(frozen=True)
class VelocityMode:
    ticks: int
    repeats: int
    drive: tick_cost.Percentiles  # whole tick while driving
    follow: tick_cost.Percentiles  # whole tick while following (section 2's measurement)
    stops: tuple[Stop, ...]


def _calibrated(cfg: Config, seed: int | None) -> tuple[ControlLoop, object]:
    hal = open_hal(cfg, start=(0.0, 0.0, 0.0), seed=seed)
    loop = ControlLoop(cfg, hal)
    loop.calibrate(hal.sleep_until, hal.now)  # type: ignore[attr-defined]
    return loop, hal


def drive_tick_cost(cfg: Config, ticks: int, seed: int | None = 1) -> tick_cost.Percentiles:
    """Whole-tick durations over `ticks` timed ticks in the velocity mode."""
    loop, hal = _calibrated(cfg, seed)
    try:
        out = [array("q", bytes(8 * ticks)) for _ in tick_cost.STAGES]
        stamps = tick_cost.StageStamps()
        hold = int(round(2.0 / loop.period))
        for i in range(ticks):
            if i % 20 == 0:
                loop.drive(*COMMANDS[(i // hold) % len(COMMANDS)])
            hal.sleep_until(hal.now() + loop.period)  # type: ignore[attr-defined]
            tick_cost.timed_tick(loop, out, i, stamps)
    finally:
        hal.close()  # type: ignore[attr-defined]
    return tick_cost.Percentiles.of_ns(np.sum([np.asarray(o, dtype=np.int64) for o in out], axis=0))


def stop_after_last_command(cfg: Config, jerk_max: float | None, v: float = 1.0) -> Stop:
    cfg = with_overrides(cfg, {"drive": {"jerk_max": jerk_max}, "estimator": {"calibration_s": 0.2}})
    loop, hal = _calibrated(cfg, seed=1)
    plant = hal.robot  # type: ignore[attr-defined]
    try:
        for k in range(500):  # 2.5 s at 10 Hz: up to speed
            if k % 20 == 0:
                loop.drive(v, 0.0)
            hal.sleep_until(hal.now() + loop.period)  # type: ignore[attr-defined]
            loop.tick()
        loop.drive(v, 0.0)  # the last command
        t0, (x0, y0, _) = hal.now(), plant.pose  # type: ignore[attr-defined]
        timeout, a = cfg.daemon.command_timeout_s, loop.drive_limits().accel
        ramps = a / jerk_max if jerk_max else 0.0
        bound_s = timeout + v / a + ramps
        still, travel = None, 0.0
        while hal.now() - t0 < bound_s + 1.0:  # type: ignore[attr-defined]
            hal.sleep_until(hal.now() + loop.period)  # type: ignore[attr-defined]
            loop.tick()
            x, y, _ = plant.pose
            travel = math.hypot(x - x0, y - y0)
            tv, tw = plant.velocity
            if abs(tv) > 0.005 or abs(tw) > 0.01:
                still = None
            elif still is None:
                still = hal.now() - t0  # type: ignore[attr-defined]
    finally:
        hal.close()  # type: ignore[attr-defined]
    return Stop(jerk_max, still if still is not None else math.nan, bound_s, travel,
                v * timeout + v * v / (2 * a) + v * ramps / 2)


def measure(cfg: Config, ticks: int, repeats: int = 2) -> VelocityMode:
    """Drive and follow alternately, `repeats` runs each; per mode the run with the lowest p99
    (on a shared machine, preemption only ever adds)."""
    drives, follows = [], []
    for _ in range(repeats):
        drives.append(drive_tick_cost(cfg, ticks))
        follows.append(tick_cost.measure_tick_cost(cfg, ticks, seed=1).tick)
    drive, follow = (min(runs, key=lambda p: p.p99_us) for runs in (drives, follows))
    return VelocityMode(ticks, repeats, drive, follow, (stop_after_last_command(cfg, cfg.drive.jerk_max),
                                               stop_after_last_command(cfg, None)))


def render(r: VelocityMode) -> list[str]:
    d, f = r.drive, r.follow
    lines = [
        f"In process on the simulated robot (configs/sim.yaml, bench/velocity_mode.py), {r.ticks} ticks a run, "
        f"timed as in section 2 (whole tick, back to back; {r.repeats} runs of each mode, alternately, the one "
        "with the lower p99 shown): driving a cycle of commands re-sent at 10 Hz "
        f"({', '.join(f'{v:g} m/s {w:g} rad/s' for v, w in COMMANDS)}, 2 s each) against following the "
        "config's path.",
        "",
        "| mode | tick p50 (us) | p99 (us) | max (us) |",
        "|---|---|---|---|",
        f"| drive | {d.p50_us:.1f} | {d.p99_us:.1f} | {d.max_us:.0f} |",
        f"| follow | {f.p50_us:.1f} | {f.p99_us:.1f} | {f.max_us:.0f} |",
        "",
        "The stop after the last command at 1 m/s, on the plant's true state (still: |v| <= 5 mm/s and "
        "|omega| <= 0.01 rad/s); bound: daemon.command_timeout_s + braking at limits.accel with the jerk "
        "ramps (v / a + a / j), and the distance that allows:",
        "",
        "| drive.jerk_max (m/s^3) | still after (s) | bound (s) | travelled (m) | bound (m) |",
        "|---|---|---|---|---|",
    ]
    for s in r.stops:
        ok_t = "" if s.still_s <= s.bound_s + 0.05 else " **x**"
        ok_m = "" if s.travel_m <= s.bound_m + 0.01 else " **x**"
        lines.append(f"| {s.jerk_max if s.jerk_max is not None else 'none'} | {s.still_s:.3f}{ok_t} | "
                     f"{s.bound_s:.3f} | {s.travel_m:.3f}{ok_m} | {s.bound_m:.3f} |")
    lines += ["", "**x** would mark a stop beyond its bound by more than the plant's lag (50 ms, 1 cm), as "
              "tests/test_drive.py allows."]
    return lines
