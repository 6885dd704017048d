"""Wheel encoders fused in the estimator: `python -m bench.wheel_encoders [--robots N]`.

1. Seed scenarios (configs/scenarios/*.yaml): each run as configured (front omni encoder and
   gyro) and with the drive wheels' encoders and the gyro but no front encoder
   (`sensors.encoder_counts_per_rev: 0`, `wheel_counts_per_rev: WHEEL_CPR`). Passes when the
   wheel-only run completes without a fault, as the front-encoder run does, with a true RMS
   cross-track within SCENARIO_SLACK of it.
2. Population (bench/population.py's robots and paths, the dynamic controller): the same
   two sensor sets, the wheels' with their radii as the population draws them (2 % off) and
   calibrated like the omni wheel's (0.05 %); each counted against population's own pass rule.
3. Bias step: all three sensors on the rectangle (straight sides, pivots at the corners, no
   stop), the gyro's zero-rate bias stepping by BIAS_STEP_DPS mid-run
   (`sim.gyro.bias_step_dps`): how long until the estimated bias is within BIAS_TOL_DPS of
   the truth, for good (target: 10 s).
"""

from __future__ import annotations

import argparse
import dataclasses as dc
import math
import random
import sys
import time
from pathlib import Path as FsPath
from typing import Any, Sequence

import numpy as np

from ddrt.config import load_config
from ddrt.path.spec import resolve_path
from ddrt.simrun.runner import run_sim

REPO = FsPath(__file__).resolve().parent.parent
WHEEL_CPR = 1440  # a 12-line motor encoder x 4 behind a 30:1 gearbox
SCENARIO_SLACK = (1.5, 2e-3)  # wheel-only true RMS <= 1.5 x front-only + 2 mm
BIAS_STEP_DPS = 0.5
BIAS_STEP_AT_S = 8.0  # sim time: 3 s of calibration and start delay, then 5 s of driving
BIAS_TOL_DPS = 0.1
BIAS_TARGET_S = 10.0


def with_sensors(cfg: Any, front: int, wheels: int) -> Any:
    return dc.replace(cfg, sensors=dc.replace(cfg.sensors, encoder_counts_per_rev=front, wheel_counts_per_rev=wheels))


def run(cfg: Any) -> dict[str, Any]:
    res = run_sim(cfg, resolve_path(cfg), keep_rows=True)
    m = res.metrics
    c = res.column
    err = np.hypot(c("x_map") - c("x"), c("y_map") - c("y"))  # the estimate's position error (no fixes: odom)
    within = float(np.mean(err <= 2.0 * np.hypot(c("std_x"), c("std_y"))))
    return {"completed": bool(m["completed"]), "fault": m["fault"], "true": m["rms_cross_track_m"],
            "est": m["rms_tracking_m"], "slip": int(c("wheel_slip").sum()), "within": within}


def scenarios() -> list[tuple[str, dict[str, Any], dict[str, Any], bool]]:
    out = []
    for f in sorted((REPO / "configs/scenarios").glob("*.yaml")):
        cfg = load_config(str(f))
        front = run(cfg)
        wheels = run(with_sensors(cfg, 0, WHEEL_CPR))
        ok = (wheels["completed"] and not wheels["fault"]
              and wheels["true"] <= SCENARIO_SLACK[0] * front["true"] + SCENARIO_SLACK[1])
        out.append((f.stem, front, wheels, ok))
        print(f"  {f.stem}: front {front['true'] * 1e3:.3f} mm, wheels {wheels['true'] * 1e3:.3f} mm "
              f"({'ok' if ok else 'FAIL'})", file=sys.stderr)
    return out


def wheels_config(cfg: Any, case_id: str, calibrated: bool) -> Any:
    """No front encoder, the drive wheels counted; `calibrated`: the belief's r_L and r_R within
    N(0, 0.05 %) of the truth, as population draws the omni wheel's (`ddrt calibrate odometry`
    measures them the same way); else as drawn (N(0, 2 %) off, ddrt/sweep/population.py)."""
    cfg = with_sensors(cfg, 0, WHEEL_CPR)
    if not calibrated:
        return cfg
    rng = random.Random(f"wheels/{case_id}")
    robot = dc.replace(cfg.robot, r_L=cfg.plant.r_L * (1.0 + rng.gauss(0.0, 5e-4)),
                       r_R=cfg.plant.r_R * (1.0 + rng.gauss(0.0, 5e-4)))
    return dc.replace(cfg, robot=robot)


def population(robots: int, workers: int) -> dict[str, tuple[int, int, float, float]]:
    """Passes of population's rule, of runs, median true and est RMS, per sensor set."""
    from bench import population as pop
    from ddrt.sweep.cases import expand
    from ddrt.sweep.driver import run_plan

    plan = expand(pop.campaign(robots, ("dynamic",)))
    out = {}
    sets = (("front encoder + gyro", None, False), ("wheel encoders + gyro, drive wheels' radii as drawn", 0, False),
            ("wheel encoders + gyro, drive wheels' radii calibrated", 0, True))
    for name, front, calibrated in sets:
        cases = tuple(c if front is None else dc.replace(c, config=wheels_config(c.config, c.case_id, calibrated),
                                                         case_id=c.case_id + f"-wheels{int(calibrated)}")
                      for c in plan.cases)
        p = dc.replace(plan, cases=cases, fingerprint=plan.fingerprint + ("" if front is None else f"-w{int(calibrated)}"))
        runs = [pop._record(r) for r in run_plan(p, workers)]
        passed = sum(pop._passes(r) for r in runs)
        out[name] = (passed, len(runs), float(np.median([r.true for r in runs])), float(np.median([r.est for r in runs])))
    return out


def bias_step(front: int) -> dict[str, Any]:
    """The rectangle with all three sensors (or wheels and gyro) and a bias step: time to learn it."""
    cfg = with_sensors(load_config(str(REPO / "configs/scenarios/rectangle.yaml")), front, WHEEL_CPR)
    gyro = dc.replace(cfg.sim.gyro, bias_step_dps=BIAS_STEP_DPS, bias_step_at_s=BIAS_STEP_AT_S)
    cfg = dc.replace(cfg, sim=dc.replace(cfg.sim, gyro=gyro))
    res = run_sim(cfg, resolve_path(cfg), keep_rows=True)
    t = res.column("t")
    bias = res.column("gyro_bias") / cfg.estimator.gyro_scale * 180.0 / math.pi  # deg/s at the part
    truth = cfg.sim.gyro.bias_dps + BIAS_STEP_DPS
    # The rows' t counts from the path's start, after the calibration and the start delay.
    step_t = BIAS_STEP_AT_S - cfg.estimator.calibration_s - cfg.sim.start_delay_s
    after = t >= step_t
    bad = np.nonzero(after & (np.abs(bias - truth) > BIAS_TOL_DPS))[0]
    learnt_at = float(t[bad[-1] + 1]) if len(bad) and bad[-1] + 1 < len(t) else (step_t if not len(bad) else math.inf)
    v_stop = np.nonzero(after & (np.abs(res.column("v")) < 1e-3) & (np.abs(res.column("omega")) < 1e-3))[0]
    first_stop = float(t[v_stop[0]]) if len(v_stop) else math.inf
    return {"learnt_s": learnt_at - step_t, "first_stop_s": first_stop - step_t,
            "end_err_dps": float(bias[-1] - truth), "run_s": float(t[-1]), "true_rms": res.metrics["rms_cross_track_m"],
            "completed": res.metrics["completed"]}


def render(sc: Sequence[tuple[str, dict[str, Any], dict[str, Any], bool]], popres: dict[str, Any] | None,
           steps: dict[str, dict[str, Any]], robots: int) -> list[str]:
    lines = [f"Drive wheels counted at {WHEEL_CPR} counts a turn (`sensors.wheel_counts_per_rev`); "
             "\"wheels\" = no front encoder (`sensors.encoder_counts_per_rev: 0`).", "",
             "| scenario | front + gyro: true RMS (mm) | wheels + gyro: true RMS (mm) | est RMS (mm) | slip ticks | "
             "position within 2 sigma | pass |",
             "|---|---|---|---|---|---|---|"]
    for name, f, w, ok in sc:
        lines.append(f"| {name} | {f['true'] * 1e3:.3f} | {w['true'] * 1e3:.3f} | {w['est'] * 1e3:.3f} | {w['slip']} | "
                     f"{w['within']:.1%} | {'yes' if ok else '**no**'} |")
    n_ok = sum(ok for *_, ok in sc)
    lines += ["", f"Seed scenarios with wheels + gyro, no front encoder: {n_ok} of {len(sc)} complete without a fault "
              f"and within {SCENARIO_SLACK[0]}x + {SCENARIO_SLACK[1] * 1e3:g} mm of the front encoder's true RMS: "
              f"**{'MET' if n_ok == len(sc) else 'NOT MET'}**."]
    if popres is not None:
        lines += ["", f"Population ({robots} robots x 2 paths, dynamic controller; population's pass rule):", "",
                  "| sensors | pass | median true RMS (mm) | median est RMS (mm) |", "|---|---|---|---|"]
        for name, (ok, n, tr, es) in popres.items():
            lines.append(f"| {name} | {ok}/{n} | {tr * 1e3:.3f} | {es * 1e3:.3f} |")
    lines += ["", f"Bias step of {BIAS_STEP_DPS} deg/s at {BIAS_STEP_AT_S:g} s on the rectangle (no stop; pivots "
              f"at the corners): learnt = the estimate within {BIAS_TOL_DPS} deg/s of the truth for good.", "",
              "| sensors | learnt after (s) | first stop after the step (s) | error at the end (deg/s) | true RMS (mm) |",
              "|---|---|---|---|---|"]
    for name, s in steps.items():
        lines.append(f"| {name} | {s['learnt_s']:.1f} | {s['first_stop_s']:.1f} | {s['end_err_dps']:+.3f} | "
                     f"{s['true_rms'] * 1e3:.3f} |")
    s3 = steps.get("all three")
    if s3 is not None:
        ok = s3["learnt_s"] <= BIAS_TARGET_S and s3["learnt_s"] < s3["first_stop_s"]
        lines += ["", f"All three sensors: the step is learnt {s3['learnt_s']:.1f} s after it, without a stop "
                  f"(target <= {BIAS_TARGET_S:g} s): **{'MET' if ok else 'NOT MET'}**."]
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=40, help="population size (0: skip the population)")
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    steps = {"all three": bias_step(8192), "wheels + gyro": bias_step(0)}
    sc = scenarios()
    popres = population(args.robots, args.workers) if args.robots > 0 else None
    print("\n".join(render(sc, popres, steps, args.robots)))
    print(f"\n({time.perf_counter() - t0:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
