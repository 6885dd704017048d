"""`python -m bench.gyro_warmup`: the heading after ten minutes of driving while the gyro warms up.

Gyro warm-up: the seed robot (configs/sim.yaml) on the realistic plant
whose gyro's die warms by RISE_C with a TAU_S time constant and whose zero-rate output follows
at SLOPE_DPS_PER_C, so that it moves 1 deg/s over the first 5 minutes (1.04 in all); the output
register holds each sample for a period of the MPU's own 200 Hz clock, 0.5 % fast. The robot
drives a figure-eight of about 28 s again and again, with a 2 s stop after each (a stop every
30 s), until it has driven 10 minutes.

How it drives: paths cannot pause part way, so each lap pair is one path, followed through a
ControlLoop in-process (as `ddrt sim` does, no daemon): `follow` from where the robot believes
it is, tick until it stops at the end, tick 2 s at rest, again. Reported per setting: the
heading error (estimate minus truth, deg) at the end (after the last stop) and its largest
magnitude at the end of any stop, and the position error at the end (mm).

Settings: TEMP_OUT not read (`sensors.gyro_temp_hz: 0`: the bias re-learnt at the stops only); read at
5 Hz with the slope learnt at the stops (`estimator.gyro_bias_per_c_dps: null`); read with the
slope set by commissioning (the true one); that again with the register read at the tick
(`sim.gyro.register_hold: false`), which shows what the hold's tick-to-tick age costs; and the
two TEMP_OUT settings with the gyro read through its FIFO (`sensors.gyro_fifo: true`: every
sample once, at the part's own period, learnt). "wheels too": the same robot with its drive
wheels' encoders counted (`sensors.wheel_counts_per_rev`), with and without the front encoder:
the wheels' difference observes the yaw rate, so the bias is tracked on the move as well as
at the stops (ddrt/core/wheel_odometry.py).

`--shipped`: configs/robot.yaml as shipped (its defaults included) through the real drivers
on the emulated devices (`shipped_config`), 3 minutes of one-lap figure-eights with a 2 s stop
after each while the die warms 8 degC and the zero-rate output moves 0.76 deg/s; its settings
(SHIPPED_SETTINGS) set the gyro's two keys over the file's to show what each does.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
from dataclasses import dataclass
from typing import Any, Sequence

from bench.common import REPO, SIM_CONFIG
from bench.wheel_encoders import WHEEL_CPR  # the drive wheels' encoders where they are counted
from ddrt.config import load_config
from ddrt.loop import ControlLoop, LoopState
from ddrt.path.spec import load_path, speed_limits
from hal.registry import open_hal

RISE_C = 8.0
TAU_S = 120.0
SLOPE_DPS_PER_C = 1.0 / (RISE_C * (1.0 - math.exp(-300.0 / TAU_S)))  # 1 deg/s over the first 5 minutes
DRIVE_S = 600.0
STOP_S = 2.0
LAP_S = 28.0  # a path of about this long, then a stop: a stop every 30 s
TEMP_HZ = 5.0
FRONT_CPR = None  # the front encoder as configs/sim.yaml has it
SETTINGS = (  # (label, gyro_temp_hz, estimator.gyro_bias_per_c_dps, register held, FIFO read, (front, wheels) counts)
    ("TEMP_OUT not read (before)", 0.0, None, True, False, (FRONT_CPR, 0)),
    ("TEMP_OUT at 5 Hz, slope learnt at stops", TEMP_HZ, None, True, False, (FRONT_CPR, 0)),
    ("TEMP_OUT at 5 Hz, slope commissioned", TEMP_HZ, SLOPE_DPS_PER_C, True, False, (FRONT_CPR, 0)),
    ("the same, register read at the tick (no hold)", TEMP_HZ, SLOPE_DPS_PER_C, False, False, (FRONT_CPR, 0)),
    ("FIFO, TEMP_OUT at 5 Hz, slope learnt at stops", TEMP_HZ, None, True, True, (FRONT_CPR, 0)),
    ("FIFO, TEMP_OUT at 5 Hz, slope commissioned", TEMP_HZ, SLOPE_DPS_PER_C, True, True, (FRONT_CPR, 0)),
    ("wheels too: FIFO, slope learnt, drive wheels counted as well as the front encoder", TEMP_HZ, None, True, True,
     (FRONT_CPR, WHEEL_CPR)),
    ("wheels too: FIFO, slope learnt, drive wheels and gyro, no front encoder", TEMP_HZ, None, True, True,
     (0, WHEEL_CPR)),
)
SEEDS = (1, 2, 3)

# The shipped config's case: configs/robot.yaml through the real drivers on emulated devices,
# 3 minutes of one-lap figure-eights (about SHIPPED_LAP_S each) with a 2 s stop after each,
# while the die warms SHIPPED_RISE_C (most of it within the 3 minutes) and the zero-rate
# output moves SHIPPED_MOVE_DPS with it.
ROBOT_CONFIG = REPO / "configs" / "robot.yaml"
SHIPPED_RISE_C = 8.0
SHIPPED_TAU_S = 60.0
SHIPPED_MOVE_DPS = 0.76
SHIPPED_DRIVE_S = 180.0
SHIPPED_LAP_S = 14.0
SHIPPED_SETTINGS = (  # (label, sensors keys set over configs/robot.yaml's)
    ("configs/robot.yaml as shipped", {}),
    ("TEMP_OUT not read, register at the tick (`gyro_temp_hz: 0, gyro_fifo: false`)",
     {"gyro_temp_hz": 0.0, "gyro_fifo": False}),
    ("TEMP_OUT at 5 Hz, register at the tick (`gyro_temp_hz: 5, gyro_fifo: false`)",
     {"gyro_temp_hz": 5.0, "gyro_fifo": False}),
    ("TEMP_OUT at 5 Hz, FIFO (`gyro_temp_hz: 5, gyro_fifo: true`)", {"gyro_temp_hz": 5.0, "gyro_fifo": True}),
)


@dataclass
class Run:
    heading_end_deg: float
    heading_worst_deg: float
    position_end_mm: float
    driven_s: float
    stops: int
    slope_dps_per_c: float
    fault: str


def config(temp_hz: float, slope: float | None, seed: int, hold: bool = True, fifo: bool = False,
           counts: tuple[int | None, int] = (FRONT_CPR, 0)) -> Any:
    front, wheels = counts
    sensors: dict[str, Any] = {"gyro_temp_hz": temp_hz, "gyro_fifo": fifo, "wheel_counts_per_rev": wheels}
    if front is not None:
        sensors["encoder_counts_per_rev"] = front
    over = {"sim": {"seed": seed, "gyro": {"warmup_rise_c": RISE_C, "warmup_tau_s": TAU_S,
                                           "bias_per_c_dps": SLOPE_DPS_PER_C, "register_hold": hold,
                                           "clock_ppm": 5000.0}},
            "sensors": sensors, "estimator": {"gyro_bias_per_c_dps": slope}}
    return load_config(SIM_CONFIG, over)


def shipped_config(seed: int, sensors: dict[str, Any] | None = None) -> Any:
    """configs/robot.yaml as shipped on the emulated devices (`hal.imu.bus: sim`, the bridge on
    `ddrtsim://`), the real drivers in between; the truth behind them is configs/sim.yaml's
    plant with the MPU warming SHIPPED_RISE_C (its zero-rate output moving SHIPPED_MOVE_DPS),
    held at its own clock, 0.5 % fast. `sensors`: keys set over the shipped file's."""
    plant = load_config(SIM_CONFIG).raw["plant"]
    over: dict[str, Any] = {
        "hal": {"imu": {"bus": "sim"}, "bridge": {"url": "ddrtsim://robot"}},
        "plant": plant,
        "sim": {"seed": seed, "gyro": {"warmup_rise_c": SHIPPED_RISE_C, "warmup_tau_s": SHIPPED_TAU_S,
                                       "bias_per_c_dps": SHIPPED_MOVE_DPS / SHIPPED_RISE_C,
                                       "register_hold": True, "clock_ppm": 5000.0}}}
    if sensors:
        over["sensors"] = sensors
    return load_config(ROBOT_CONFIG, over)


def one_run(temp_hz: float, slope: float | None, seed: int, drive_s: float = DRIVE_S, hold: bool = True,
            fifo: bool = False, counts: tuple[int | None, int] = (FRONT_CPR, 0)) -> Run:
    return drive(config(temp_hz, slope, seed, hold, fifo, counts), seed, drive_s)


def drive(cfg: Any, seed: int, drive_s: float, laps: int = 2, lap_s: float = LAP_S) -> Run:
    """`cfg`'s robot drives a figure-eight of `laps` laps (about `lap_s` long), then stands
    STOP_S, again, until it has driven `drive_s` (module doc)."""
    probe = load_path({"shape": "figure_eight", "width": 1.6, "height": 0.8, "speed": 0.4, "laps": laps},
                      speed_limits(cfg), paths=cfg.paths)
    speed = 0.4 * probe.duration / lap_s
    path = load_path({"shape": "figure_eight", "width": 1.6, "height": 0.8, "speed": speed, "laps": laps},
                     speed_limits(cfg), paths=cfg.paths)
    hal = open_hal(cfg, start=path.start_pose, seed=seed)
    try:
        loop = ControlLoop(cfg, hal)
        robot = hal.robot
        loop.calibrate(hal.sleep_until, hal.now)
        period = loop.period
        t = hal.now()

        def tick() -> None:
            nonlocal t
            t += period
            hal.sleep_until(t)
            loop.tick()

        for _ in range(int(round(cfg.sim.start_delay_s / period))):
            tick()
        driven = 0.0
        stops = 0
        worst = 0.0
        first = True
        while driven < drive_s and loop.state not in (LoopState.FAULT, LoopState.ESTOP):
            loop.follow(path, path.start_pose if first else None)
            first = False
            t0 = t
            while loop.state != LoopState.STOPPED and loop.state not in (LoopState.FAULT, LoopState.ESTOP):
                tick()
                if t - t0 > 3.0 * path.duration + 10.0:
                    break
            driven += t - t0
            for _ in range(int(round(STOP_S / period))):
                tick()
            stops += 1
            err = _heading_err(loop, robot)
            worst = max(worst, abs(err))
        x, y, _ = robot.pose
        est = loop.estimator
        gb = est.gyro_bias
        return Run(_heading_err(loop, robot), worst, 1e3 * math.hypot(est.x - x, est.y - y), driven, stops,
                   gb.k * 180.0 / math.pi if gb is not None else math.nan, loop.fault)
    finally:
        hal.close()


def _heading_err(loop: ControlLoop, robot: Any) -> float:
    d = loop.estimator.theta - robot.pose[2]
    return math.degrees(math.atan2(math.sin(d), math.cos(d)))


def render(runs: dict[str, list[Run]], seeds: Sequence[int], shipped: bool = False) -> list[str]:
    head = (
        "configs/robot.yaml through the real drivers (hal/mpu6050.py, hal/bridge.py) on the emulated MPU-6050 "
        "and microcontroller (`hal.imu.bus: sim`), the truth configs/sim.yaml's plant: the gyro's die warms "
        f"{SHIPPED_RISE_C:g} degC with a {SHIPPED_TAU_S:g} s time constant and its zero-rate output moves "
        f"{SHIPPED_MOVE_DPS:g} deg/s with it, the part sampling at its own clock, 0.5 % fast. A one-lap "
        f"figure-eight (~{SHIPPED_LAP_S:g} s) then a {STOP_S:g} s stop, again, for {SHIPPED_DRIVE_S / 60:g} min "
        "of driving. Heading error (estimate minus truth) at the end and its worst at the end of a stop, position "
        f"error at the end: median over seeds {', '.join(map(str, seeds))} (each seed in brackets). "
        "`python -m bench.gyro_warmup --shipped`.")
    lines = [head] if shipped else [
        f"The seed robot on the realistic plant: the gyro's die warms {RISE_C:g} degC with a {TAU_S:g} s time "
        f"constant, its bias follows at {SLOPE_DPS_PER_C:.4f} deg/s per degC (1 deg/s over the first 5 min), "
        "its register held at its own 200 Hz (0.5 % fast). A ~28 s figure-eight (two laps) then a 2 s stop, "
        f"again, for {DRIVE_S / 60:g} min of driving, through ControlLoop in-process. Heading error (estimate "
        "minus truth) at the end and its worst at the end of a stop, position error at the end: median over "
        f"seeds {', '.join(map(str, seeds))} (each seed in brackets). `python -m bench.gyro_warmup`."]
    lines += [
        "",
        "| setting | heading error at the end (deg) | worst at a stop (deg) | position error at the end (mm) "
        "| slope learnt (deg/s/degC) | stops |",
        "|---|---|---|---|---|---|",
    ]

    def cell(values: list[float], fmt: str = ".3f") -> str:
        return f"{statistics.median(values):{fmt}} ({', '.join(f'{v:{fmt}}' for v in values)})"

    for label, rs in runs.items():
        faults = "; ".join(sorted({r.fault for r in rs if r.fault}))
        lines.append(f"| {label}{' (fault: ' + faults + ')' if faults else ''} | "
                     f"{cell([r.heading_end_deg for r in rs])} | {cell([r.heading_worst_deg for r in rs])} | "
                     f"{cell([r.position_end_mm for r in rs], '.1f')} | "
                     f"{cell([r.slope_dps_per_c for r in rs], '.4f')} | {rs[0].stops} |")
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.gyro_warmup", description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=len(SEEDS), help="seeds 1..N (default: 3)")
    ap.add_argument("--minutes", type=float, default=DRIVE_S / 60.0, help="driving time (default: 10)")
    ap.add_argument("--only", default="", help="only the settings whose label starts with this text")
    ap.add_argument("--shipped", action="store_true",
                    help="configs/robot.yaml on the emulated devices, 3 min with the die warming 8 degC")
    args = ap.parse_args(argv)
    seeds = tuple(range(1, args.seeds + 1))
    if args.shipped:
        minutes = args.minutes if args.minutes != DRIVE_S / 60.0 else SHIPPED_DRIVE_S / 60.0
        shipped = {label: [drive(shipped_config(s, keys), s, 60.0 * minutes, laps=1, lap_s=SHIPPED_LAP_S)
                           for s in seeds]
                   for label, keys in SHIPPED_SETTINGS if label.startswith(args.only)}
        print("\n".join(render(shipped, seeds, shipped=True)))
        return 0
    runs = {label: [one_run(hz, slope, s, 60.0 * args.minutes, hold, fifo, counts) for s in seeds]
            for label, hz, slope, hold, fifo, counts in SETTINGS if label.startswith(args.only)}
    print("\n".join(render(runs, seeds)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
