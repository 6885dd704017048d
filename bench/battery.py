"""`python -m bench.battery`: what measuring the supply voltage buys on a low battery.

The seed robot (configs/sim.yaml) with its limits taken from the motors (v_max, accel and
torque_max_nm null), its config saying 12 V, on the simulated robot in three settings: the
supply really at 12 V (the reference), at 9.3 V and not measured (the loop believes 12 V, as
with a protocol-v1 MCU: `sim.battery_measured: false`), and at 9.3 V measured (ddrt/loop/power.py).
Two paths: a 5 m lane change at 0.9 m/s (an S-curve, 0.8 m across) and the fast figure-eight
(configs/paths/figure8_fast.yaml, 0.8 m/s). Reported: the true cross-track RMS, the distance
between the estimated and the true position at the end (at rest), the estimate's own
tracking RMS and how long the run took, the median over the seeds and each seed's.

A constant 9.3 V supply has no internal resistance: the sag under load of a real pack is the
plant's (another section), this one isolates what the measurement corrects.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
from dataclasses import dataclass, field
from typing import Any, Sequence

from bench.common import SIM_CONFIG
from ddrt.config import load_config
from ddrt.path.spec import load_path, speed_limits
from ddrt.simrun.runner import run_sim

CONFIG_V = 12.0
LOW_V = 9.3
PATHS: dict[str, dict[str, Any] | str] = {
    "lane change 5 m, 0.9 m/s": {"shape": "s_curve", "length": 5.0, "offset": 0.8, "speed": 0.9},
    "figure-eight fast, 0.8 m/s": "paths/figure8_fast.yaml",
}
SETTINGS = (  # (label, true supply, measured)
    (f"{CONFIG_V:g} V (config {CONFIG_V:g} V)", CONFIG_V, True),
    (f"{LOW_V:g} V, not measured", LOW_V, False),
    (f"{LOW_V:g} V, measured", LOW_V, True),
)
SEEDS = (1, 2, 3)


@dataclass
class Run:
    cross_track_mm: float
    end_error_mm: float
    tracking_mm: float
    duration_s: float
    completed: bool


@dataclass
class BatteryResult:
    seeds: tuple[int, ...]
    runs: dict[tuple[str, str], list[Run]] = field(default_factory=dict)  # (path, setting) -> per seed


def one_run(path_key: str, supply_v: float, measured: bool, seed: int) -> Run:
    over = {"limits": {"v_max": None, "accel": None, "torque_max_nm": None},
            "plant": {"motor": {"supply_v": supply_v}}, "sim": {"battery_measured": measured, "seed": seed}}
    cfg = load_config(SIM_CONFIG, over)
    spec = PATHS[path_key]
    source = str(SIM_CONFIG.parent / spec) if isinstance(spec, str) else spec
    path = load_path(source, speed_limits(cfg), paths=cfg.paths)
    res = run_sim(cfg, path, keep_rows=True)
    rows, cols = res.rows_array(), res.columns
    last = rows[-1]
    end = math.hypot(last[cols.index("x_est")] - last[cols.index("x")], last[cols.index("y_est")] - last[cols.index("y")])
    m = res.metrics
    return Run(1e3 * m["rms_cross_track_m"], 1e3 * end, 1e3 * m["rms_tracking_m"], m["sim_duration_s"],
               bool(m["completed"]))


def measure(seeds: Sequence[int] = SEEDS) -> BatteryResult:
    out = BatteryResult(tuple(seeds))
    for path_key in PATHS:
        for label, volts, measured in SETTINGS:
            out.runs[(path_key, label)] = [one_run(path_key, volts, measured, s) for s in seeds]
    return out


def render(r: BatteryResult) -> list[str]:
    lines = [
        "The seed robot with its limits from the motors and its config at 12 V; the simulated supply at 12 V, "
        "or at 9.3 V with and without the measured voltage (`sim.battery_measured`; ddrt/loop/power.py puts the "
        "filtered measurement into the inverse motor model, the estimator's prediction, the controller's limits "
        "and the starting path's profile). True cross-track RMS, the estimate's distance from the true position "
        "at the end (at rest), the estimate's own tracking RMS, the run's duration: median over seeds "
        f"{', '.join(map(str, r.seeds))} (each seed in brackets). `python -m bench.battery`.",
        "",
        "| path | supply | true cross-track RMS (mm) | end estimate error (mm) | estimated tracking RMS (mm) | duration (s) |",
        "|---|---|---|---|---|---|",
    ]
    for (path_key, label), runs in r.runs.items():
        def cell(values: list[float], fmt: str = ".2f") -> str:
            return f"{statistics.median(values):{fmt}} ({', '.join(f'{v:{fmt}}' for v in values)})"

        done = "" if all(x.completed for x in runs) else " (not all completed)"
        lines.append(f"| {path_key} | {label}{done} | {cell([x.cross_track_mm for x in runs])} | "
                     f"{cell([x.end_error_mm for x in runs])} | {cell([x.tracking_mm for x in runs], '.3f')} | "
                     f"{statistics.median(x.duration_s for x in runs):.2f} |")
    lines += ["", "Without the measurement the model takes every duty to give 12/9.3 = 1.29 times the torque it "
              "gives: the estimator's speed prediction runs ahead of the encoder between samples and the "
              "feed-forward falls short, which the feedback makes up from the error. With it, the duty for a "
              "torque is scaled by 12/9.3 (tests/test_power.py checks that ratio and the forward model), and a "
              "path profiled for 12 V is re-profiled for the measured 9.3 V when it starts (the longer duration)."]
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.battery", description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=len(SEEDS), help="seeds 1..N (default: 3)")
    args = ap.parse_args(argv)
    print("\n".join(render(measure(tuple(range(1, args.seeds + 1))))))
    return 0


if __name__ == "__main__":
    sys.exit(main())
