"""`python -m bench.uncertainty [--quick]`: is the reported uncertainty honest, and do pose fixes
hold a robot with a wrong gyro on its path? (docs/BENCHMARKS.md, section 14.)

1. Honest uncertainty: every scenario (configs/sim.yaml, configs/scenarios/*.yaml) as
   `ddrt sim` runs it, and a population of robots whose encoder radius and gyro scale are off
   by amounts drawn from the estimator's own error model (estimator.encoder_scale_std,
   gyro_scale_std): on what share of ticks the true position lies within the reported 2 sigma
   (|true - estimate| <= 2 sqrt(std_x^2 + std_y^2)) and the heading within 2 std_theta, and
   how tight the figure is (the median of |error| / sigma).
2. Pose fixes (issue 21's done-when, on the plain plant): a 1 m circle at 0.4 m/s for 60 s
   with an uncalibrated 2 % gyro scale error, followed in `map`, with and without a fix every
   second (the true pose plus 5 mm and 1 degree of noise, 0.1 s late).
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from typing import Any

import numpy as np

from bench.common import REPO, SIM_CONFIG
from ddrt.config import load_config
from ddrt.core.pose_fix import PoseFix
from ddrt.loop import ControlLoop
from ddrt.path import load_path
from ddrt.path.frame import in_map
from ddrt.path.spec import resolve_path, speed_limits
from ddrt.simrun.metrics import cross_track
from ddrt.simrun.runner import run_sim
from hal.registry import open_hal


def coverage(table: np.ndarray, columns: tuple[str, ...]) -> dict[str, float]:
    """Shares of ticks within 2 sigma (position, heading) and the median error/sigma."""
    c = {n: i for i, n in enumerate(columns)}
    ex = table[:, c["x"]] - table[:, c["x_map"]]
    ey = table[:, c["y"]] - table[:, c["y_map"]]
    eth = table[:, c["theta"]] - table[:, c["theta_map"]]
    eth = (eth + math.pi) % (2 * math.pi) - math.pi
    sp = np.hypot(table[:, c["std_x"]], table[:, c["std_y"]])
    sth = table[:, c["std_theta"]]
    e = np.hypot(ex, ey)
    live = sp > 0.0
    ratio = e[live] / sp[live]
    return {"pos_in_2s": float(np.mean(e <= 2.0 * sp + 1e-6)), "th_in_2s": float(np.mean(np.abs(eth) <= 2.0 * sth + 1e-6)),
            "median_ratio": float(np.median(ratio)) if len(ratio) else math.nan,
            "max_err_mm": float(e.max() * 1e3), "final_sigma_mm": float(sp[-1] * 1e3), "ticks": len(e)}


def scenario_rows(quick: bool) -> list[tuple[str, dict[str, float]]]:
    configs = ([SIM_CONFIG] + sorted((REPO / "configs" / "scenarios").glob("*.yaml"))
               + sorted((REPO / "configs" / "scenarios" / "realistic").glob("*.yaml")))
    if quick:
        configs = configs[:3]
    out = []
    for cfgp in configs:
        cfg = load_config(cfgp)
        res = run_sim(cfg, resolve_path(cfg), keep_rows=True)
        out.append((str(cfgp.relative_to(REPO)), coverage(res.rows_array(), res.columns)))
    # The seed's own r_3 guess (4 % off) is no 1 % measurement: said so, the figure is honest.
    cfgp = REPO / "configs" / "scenarios" / "figure8_slow_r3_uncalibrated.yaml"
    cfg = load_config(cfgp, {"estimator": {"encoder_scale_std": 0.04}})
    res = run_sim(cfg, resolve_path(cfg), keep_rows=True)
    out.append((f"{cfgp.relative_to(REPO)} with estimator.encoder_scale_std 0.04", coverage(res.rows_array(), res.columns)))
    # A warming or drifting gyro is no 1e-5 rad/s/sqrt(s) walk: told its drift, the heading is honest.
    for name in ("figure8_cheap_sensors", "everything", "gyro_warmup"):
        cfgp = REPO / "configs" / "scenarios" / "realistic" / f"{name}.yaml"
        cfg = load_config(cfgp, {"estimator": {"gyro_bias_walk": 1e-3}})
        res = run_sim(cfg, resolve_path(cfg), keep_rows=True)
        out.append((f"{cfgp.relative_to(REPO)} with estimator.gyro_bias_walk 1e-3", coverage(res.rows_array(), res.columns)))
    return out


def population_rows(n: int, seed: int) -> list[tuple[str, dict[str, float]]]:
    """Robots whose r_3 and gyro scale are off as the error model says they may be."""
    rng = np.random.default_rng(seed)
    base = load_config(SIM_CONFIG)
    est = base.estimator
    out = []
    for i in range(n):
        es = float(rng.normal(0.0, est.encoder_scale_std))
        eg = float(rng.normal(0.0, est.gyro_scale_std))
        shape = ("figure8_slow.yaml", "circle_1m.yaml", "s_curve.yaml")[i % 3]
        cfg = load_config(REPO / "configs" / "scenarios" / shape,
                          {"plant": {"r_3": base.robot.r_3 * (1.0 + es)}, "sim": {"gyro": {"scale_error": eg}, "seed": i + 1}})
        res = run_sim(cfg, resolve_path(cfg), keep_rows=True)
        out.append((f"r{i:02d} {shape[:-5]} r_3 {es * 100:+.2f} %, gyro {eg * 100:+.2f} %",
                    coverage(res.rows_array(), res.columns)))
    return out


# The realistic plant of configs/scenarios/realistic/figure8_cheap_sensors.yaml (a drifting
# bias, the gyro's register held, the MCU's clock off, a slipping omni wheel), with the 2 % scale error.
REALISTIC = {"gyro": {"drift_dps_per_s": 0.01, "register_hold": True, "clock_ppm": 5000.0},
             "encoder": {"slip": {"mean": -0.003, "sigma": 0.001, "tau_s": 20.0}}}


def fix_run(spec: dict[str, Any], duration_s: float, fixes: bool, seed: int, scale_error: float = 0.02,
            fix_std: tuple[float, float, float] = (0.005, 0.005, math.radians(1.0)), latency_s: float = 0.1,
            plant: dict[str, Any] | None = None, estimator: dict[str, Any] | None = None) -> dict[str, Any]:
    """Follow `spec` in map on the simulated robot with a gyro scale error (and `plant`'s sim:
    keys), fed fixes of its true pose every second (or none); the true cross-track and the
    duty steps at the fixes."""
    sim = {"gyro": {"scale_error": scale_error}, "seed": seed}
    for key, value in (plant or {}).items():
        sim[key] = {**sim.get(key, {}), **value} if isinstance(value, dict) else value
    cfg = load_config(SIM_CONFIG, {"sim": sim, "estimator": estimator or {}})
    path = load_path(spec, speed_limits(cfg), paths=cfg.paths)
    hal = open_hal(cfg, start=path.start_pose, seed=seed)
    rng = np.random.default_rng(seed)
    true_xy, duty, fix_ticks, replies = [], [], [], []
    try:
        loop = ControlLoop(cfg, hal)
        loop.calibrate(hal.sleep_until, hal.now)  # type: ignore[attr-defined]
        loop.follow(path, path.start_pose)
        est = loop.estimator
        loop.reference = in_map(loop.reference, est.frame, est.frame.correction(), cfg.estimator.map_blend_s, loop.period)
        robot = hal.robot
        every, late = int(round(1.0 / loop.period)), int(round(latency_s / loop.period))
        sx, sy, sth = fix_std
        cov = (sx * sx, 0.0, 0.0, 0.0, sy * sy, 0.0, 0.0, 0.0, sth * sth)
        pending: list[tuple[int, PoseFix]] = []
        t0 = hal.now()  # type: ignore[attr-defined]
        for i in range(int(round(duration_s / loop.period))):
            if pending and pending[0][0] <= i:
                replies.append(est.fuse_fix(pending.pop(0)[1]))
                fix_ticks.append(i)
            hal.sleep_until(t0 + (i + 1) * loop.period)  # type: ignore[attr-defined]
            loop.tick()
            x, y, th = robot.pose
            if fixes and i % every == every - 1:
                pending.append((i + late, PoseFix(x + rng.normal(0, sx), y + rng.normal(0, sy), th + rng.normal(0, sth),
                                                  cov, est.t_est)))
            true_xy.append((x, y))
            duty.append((loop.duty_l, loop.duty_r))
            if loop.state.label != "following":
                break
        state = loop.state.label
        learnt, reanchors = est.frame.g, est.frame.counters.reanchors
    finally:
        hal.close()
    ct = cross_track(np.asarray(path.x), np.asarray(path.y), np.array(true_xy))
    d = np.abs(np.diff(np.array(duty), axis=0)).max(axis=1)
    at = [d[i - 1] for i in fix_ticks if 0 < i <= len(d)]
    mask = np.ones(len(d), bool)
    mask[[i - 1 for i in fix_ticks if 0 < i <= len(d)]] = False
    mask[: int(2.0 / loop.period)] = False
    t_settle = int(6.0 / loop.period)
    return {"state": state, "seconds": len(ct) * loop.period, "max_mm": ct.max() * 1e3,
            "max_after_6s_mm": ct[t_settle:].max() * 1e3 if len(ct) > t_settle else math.nan,
            "rms_mm": float(np.sqrt(np.mean(ct ** 2))) * 1e3, "t_max_s": float(np.argmax(ct)) * loop.period,
            "fixes": sum(1 for r in replies if r["fused"]), "outliers": sum(1 for r in replies if r.get("outlier")),
            "learnt_gyro_scale": learnt if replies else math.nan, "reanchors": reanchors,
            "duty_step_at_fix": max(at) if at else math.nan, "duty_step_steady": float(d[mask].max())}


def _num(v: float, fmt: str) -> str:
    return "-" if math.isnan(v) else format(v, fmt)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="3 scenarios, 6 robots, one seed: a smoke run")
    args = ap.parse_args(argv)
    t0 = time.time()
    print("### Honest uncertainty: the scenarios\n")
    print("| config | ticks | position within 2 sigma | heading within 2 sigma | median error/sigma | max error (mm) | final sigma (mm) |")
    print("|---|---|---|---|---|---|---|")
    rows = scenario_rows(args.quick)
    for name, r in rows:
        print(f"| {name} | {r['ticks']} | {r['pos_in_2s'] * 100:.1f} % | {r['th_in_2s'] * 100:.1f} % | "
              f"{r['median_ratio']:.3f} | {r['max_err_mm']:.2f} | {r['final_sigma_mm']:.1f} |")
    sys.stdout.flush()
    pop = population_rows(6 if args.quick else 30, seed=21)
    print("\n### Honest uncertainty: robots drawn from the error model\n")
    print("| robot | position within 2 sigma | heading within 2 sigma | median error/sigma | max error (mm) | final sigma (mm) |")
    print("|---|---|---|---|---|---|")
    for name, r in pop:
        print(f"| {name} | {r['pos_in_2s'] * 100:.1f} % | {r['th_in_2s'] * 100:.1f} % | {r['median_ratio']:.3f} | "
              f"{r['max_err_mm']:.2f} | {r['final_sigma_mm']:.1f} |")
    ticks = sum(r["ticks"] for _, r in pop)
    pos = sum(r["pos_in_2s"] * r["ticks"] for _, r in pop) / ticks
    th = sum(r["th_in_2s"] * r["ticks"] for _, r in pop) / ticks
    worst = min(r["pos_in_2s"] for _, r in pop + rows)
    print(f"\nAll robots' ticks: position within 2 sigma {pos * 100:.1f} %, heading {th * 100:.1f} %; "
          f"the worst single run (scenarios and robots): {worst * 100:.1f} %.")
    sys.stdout.flush()
    print("\n### Pose fixes: 2 % gyro scale error, 1 m circle at 0.4 m/s, 60 s in map\n")
    print("Plain plant, and the realistic plant (a bias drifting 0.01 deg/s per s, the register held, "
          "the MCU's clock off, a slipping omni wheel).\n")
    print("| plant, seed | fixes | state | s | max (mm) | at (s) | max after 6 s (mm) | RMS (mm) | fused | outliers | "
          "re-anchors | learnt gyro scale | duty step at a fix | steady max step |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    spec = {"shape": "circle", "radius": 1.0, "laps": 4, "speed": 0.4}
    runs: list[tuple[str, Any, Any, int]] = [("plain", None, None, s) for s in ((1,) if args.quick else (1, 2, 3))]
    runs += [("realistic", REALISTIC, None, s) for s in (1, 2)]
    runs += [("realistic, gyro_bias_walk 1e-3", REALISTIC, {"gyro_bias_walk": 1e-3}, s) for s in (1, 2)]
    for label, plant, est_keys, seed in runs:
        for fixes in (False, True):
            r = fix_run(spec, 60.0, fixes, seed, plant=plant, estimator=est_keys)
            print(f"| {label}, {seed} | {'every 1 s' if fixes else 'none'} | {r['state']} | {r['seconds']:.1f} | {r['max_mm']:.1f} | "
                  f"{r['t_max_s']:.1f} | {r['max_after_6s_mm']:.1f} | {r['rms_mm']:.2f} | {r['fixes']} | {r['outliers']} | "
                  f"{r['reanchors']} | "
                  f"{_num(r['learnt_gyro_scale'], '+.4f')} | {_num(r['duty_step_at_fix'], '.4f')} | {r['duty_step_steady']:.4f} |")
            sys.stdout.flush()
    print(f"\n({time.time() - t0:.0f} s wall)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
