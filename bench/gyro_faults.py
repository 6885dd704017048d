"""`python -m bench.gyro_faults`: a gyro that stops answering mid-path, and the MPU family on the figure-eight.

Both run the real drivers on emulated devices (`hal.backend: real`, `hal.imu.bus: sim`: hal/
mpu6050.py and hal/bridge.py against sim_hal's register file and microcontroller), the seed
robot of configs/sim.yaml.

Faults: the robot follows a figure-eight at 0.4 m/s; FAULT_AT_S into the path the emulated gyro
fails as one of sim_hal.faults.GYRO_FAULTS (its output frozen, stalled so that its FIFO stops
filling, a bus that reads all zeros, NAKs, a reset of the part). Reported for each, with the
FIFO on and off: the true travel from the fault to rest (m), the loop's state and its fault
text, and the driver's counters (status's imu.<name>). A reset is re-initialised (the loop holds,
the robot stops, then resumes); every other fault stops the robot for good.

Family: the fast figure-eight (configs/scenarios/figure8_fast.yaml, 0.8 m/s) driven with the
emulated gyro as each part of ddrt.params.mpu_parts (`sim.gyro.part`): the true cross-track
RMS (mm) and whether the path completed.

`--before`: the faults again with the driver's liveness checks off (hal/mpu6050.py's `_alive`
a no-op: what a driver without them does; the estimator's `estimator.stuck_gyro_ticks` and the
path-error limit are then what stops the robot). Before the family, only 0x68 was accepted.
"""

from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass
from typing import Any, Sequence

from bench.common import SIM_CONFIG
from ddrt.config import load_config
from ddrt.loop import ControlLoop, LoopState
from ddrt.params.mpu_parts import part_names
from ddrt.path.spec import resolve_path
from hal.registry import open_hal
from sim_hal.faults import GYRO_FAULTS, inject_gyro_fault

FAULT_AT_S = 3.0
SPEED = 0.4
AFTER_S = 4.0  # ticks after the fault (a reset: the hold, the stop and the resume)
EMULATED = {"hal": {"backend": "real", "imu": {"bus": "sim"},
                    "bridge": {"url": "ddrtsim://robot", "drive_timeout_ms": 100, "state_stale_s": 0.05}}}
FIGURE8_04 = {"shape": "figure_eight", "width": 1.2, "height": 0.6, "speed": SPEED}


@dataclass
class FaultRun:
    fault: str
    fifo: bool
    travel_m: float  # true distance driven from the fault until first at rest
    state: str  # the loop's state then (and at the end of the run, when it moved on: a reset resumes)
    message: str  # the loop's fault text, or the hold's cause
    counters: dict[str, int]


def _config(fifo: bool, **over: Any):
    return load_config(SIM_CONFIG, {**EMULATED, "path": FIGURE8_04, "sensors": {"gyro_fifo": fifo}, **over})


def fault_run(fault: str, fifo: bool, seed: int = 1) -> FaultRun:
    """Follow the 0.4 m/s figure-eight; FAULT_AT_S in, the gyro fails as `fault`."""
    cfg = _config(fifo, sim={"seed": seed})
    path = resolve_path(cfg)
    hal = open_hal(cfg, start=path.start_pose, seed=seed)
    try:
        loop = ControlLoop(cfg, hal)
        loop.calibrate(hal.sleep_until, hal.now)
        loop.follow(path, path.start_pose)
        t0 = t = hal.now()
        robot = hal.robot
        devices = hal.devices
        travel = 0.0
        stopped: tuple[float, str, str] | None = None  # travel, state and message at the first rest
        last = None
        while t - t0 < FAULT_AT_S + AFTER_S:
            t += loop.period
            hal.sleep_until(t)
            if last is None and t - t0 >= FAULT_AT_S:
                inject_gyro_fault(fault, devices.mpu, devices.i2c)
                last = robot.pose
            loop.tick()
            if last is not None:
                x, y, _ = robot.pose
                travel += math.hypot(x - last[0], y - last[1])
                last = robot.pose
                if stopped is None and abs(robot.velocity[0]) < 1e-3 and abs(robot.velocity[1]) < 1e-2:
                    stopped = (travel, loop.state.name.lower(), loop.fault or loop.recovery.last_cause)
            if loop.state in (LoopState.FAULT, LoopState.STOPPED) and stopped is not None:
                break
        if stopped is None:
            stopped = (travel, loop.state.name.lower(), loop.fault or loop.recovery.last_cause)
        counters = {k: v for k, v in (hal.fault_counters or {}).items() if k.startswith("imu") and v}
        end = loop.state.name.lower()
        state = stopped[1] if end == stopped[1] else f"{stopped[1]}, then {end}"
        message = loop.fault or hal.real.imu.last_event or stopped[2]
        return FaultRun(fault, fifo, stopped[0], state, message, counters)
    finally:
        hal.close()


@dataclass
class FamilyRun:
    part: str
    fifo: bool
    rms_mm: float
    completed: bool
    seen: str  # the part the driver identified


def family_run(part: str, fifo: bool, seed: int = 1) -> FamilyRun:
    """The fast figure-eight with the emulated gyro as `part`: true cross-track RMS (mm)."""
    from ddrt.simrun.runner import run_sim

    cfg = load_config(SIM_CONFIG.parent / "scenarios" / "figure8_fast.yaml",
                      {**EMULATED, "sim": {"gyro": {"part": part}}, "sensors": {"gyro_fifo": fifo}})
    hal = open_hal(cfg, seed=seed)
    try:
        seen = hal.info.gyro_part  # what the driver identified by WHO_AM_I
    finally:
        hal.close()
    res = run_sim(cfg, resolve_path(cfg), seed=seed)
    return FamilyRun(part, fifo, res.metrics["rms_cross_track_m"] * 1e3, bool(res.metrics["completed"]), seen)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--faults", nargs="*", default=list(GYRO_FAULTS), choices=GYRO_FAULTS)
    ap.add_argument("--parts", nargs="*", default=list(part_names()))
    ap.add_argument("--before", action="store_true", help="the driver's liveness checks off")
    args = ap.parse_args(argv)
    if args.before:
        from hal.mpu6050 import Mpu6050

        Mpu6050._alive = lambda self, symptom=None: None  # type: ignore[method-assign]
    print(f"# a gyro that stops answering at {SPEED} m/s (real drivers, emulated devices"
          + (", the driver's liveness checks off)" if args.before else ")"))
    print("| fault | FIFO | travel after the fault (m) | state | counters | error |")
    print("|---|---|---|---|---|---|")
    worst = 0.0
    for fault in args.faults:
        for fifo in (False, True):
            r = fault_run(fault, fifo)
            worst = max(worst, r.travel_m)
            counters = ", ".join(f"{k} {v}" for k, v in sorted(r.counters.items()))
            print(f"| {fault} | {'on' if fifo else 'off'} | {r.travel_m:.3f} | {r.state} | {counters} | "
                  f"{r.message[:160]} |")
            sys.stdout.flush()
    print(f"\nworst travel after a fault: {worst:.3f} m")
    if args.before:
        return 0
    print("\n# the MPU family on the fast figure-eight (0.8 m/s)")
    print("| emulated part | driver found | FIFO | true cross-track RMS (mm) | completed |")
    print("|---|---|---|---|---|")
    for part in args.parts:
        for fifo in (False, True):
            r = family_run(part, fifo)
            print(f"| {r.part} | {r.seen} | {'on' if fifo else 'off'} | {r.rms_mm:.2f} | {r.completed} |")
            sys.stdout.flush()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
