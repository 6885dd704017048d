"""`python -m bench.uncertainty [--quick | --trace PLANT SEED]`: is the reported uncertainty
honest, and do pose fixes hold a robot with a wrong gyro on its path? (docs/BENCHMARKS.md,
section 15.)

1. Honest uncertainty: every scenario (configs/sim.yaml, configs/scenarios/*.yaml) as
   `ddrt sim` runs it, and a population of robots whose encoder radius and gyro scale are off
   by amounts drawn from the estimator's own error model (estimator.encoder_scale_std,
   gyro_scale_std): on what share of ticks the true position lies within the reported 2 sigma
   (|true - estimate| <= 2 sqrt(std_x^2 + std_y^2)) and the heading within 2 std_theta, and
   how tight the figure is (the median of |error| / sigma).
2. Pose fixes: a 1 m circle at 0.4 m/s for 60 s with an uncalibrated
   2 % gyro scale error, followed in `map`, with and without a fix every second (the true pose
   plus 5 mm and 1 degree of noise, 0.1 s late), on the plain and the realistic plant, seeds
   1 to 5; and a gyro without scale error, its scale unknown or known to the model (what the
   first seconds cost). `--trace PLANT SEED` prints one run's fixes one by one.
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
            plant: dict[str, Any] | None = None, estimator: dict[str, Any] | None = None,
            trace: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """Follow `spec` in map on the simulated robot with a gyro scale error (and `plant`'s sim:
    keys), fed fixes of its true pose every second (or none); the true cross-track and the
    duty steps at the fixes. `trace`, if given, gets a row per fix: the map's true error at the
    fix's moment, the fix's innovation and d^2, and the learnt gyro scale with its 1 sigma."""
    sim = {"gyro": {"scale_error": scale_error}, "seed": seed}
    for key, value in (plant or {}).items():
        sim[key] = {**sim.get(key, {}), **value} if isinstance(value, dict) else value
    cfg = load_config(SIM_CONFIG, {"sim": sim, "estimator": estimator or {}})
    path = load_path(spec, speed_limits(cfg), paths=cfg.paths)
    hal = open_hal(cfg, start=path.start_pose, seed=seed)
    rng = np.random.default_rng(seed)
    true_xy: list[tuple[float, float]] = []
    duty, fix_ticks, replies = [], [], []

    def ct_of(xy: list[tuple[float, float]]) -> np.ndarray:
        return cross_track(np.asarray(path.x), np.asarray(path.y), np.array(xy)) if xy else np.zeros(1)

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
        pending: list[tuple[int, PoseFix, tuple[float, ...]]] = []
        t0 = hal.now()  # type: ignore[attr-defined]
        for i in range(int(round(duration_s / loop.period))):
            if pending and pending[0][0] <= i:
                _, fix, err = pending.pop(0)
                replies.append(est.fuse_fix(fix))
                fix_ticks.append(i)
                if trace is not None:
                    trace.append(_trace_row(fix.stamp - t0, err, replies[-1], est, float(ct_of(true_xy).max())))
            hal.sleep_until(t0 + (i + 1) * loop.period)  # type: ignore[attr-defined]
            loop.tick()
            x, y, th = robot.pose
            if fixes and i % every == every - 1:
                mx, my, mth = est.map_pose()
                err = (x - mx, y - my, math.remainder(th - mth, 2 * math.pi))
                pending.append((i + late, PoseFix(x + rng.normal(0, sx), y + rng.normal(0, sy), th + rng.normal(0, sth),
                                                  cov, est.t_est), (*err, _nees(err, est.track.p_map))))
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
    # A fix fused before tick i acts on the step into tick i, or (the realistic plant's
    # held gyro register and late samples) on the next one: both count as at the fix.
    near = [j for i in fix_ticks for j in (i - 1, i) if 0 <= j < len(d)]
    at = [d[j] for j in near]
    mask = np.ones(len(d), bool)
    mask[near] = False
    mask[: int(2.0 / loop.period)] = False
    t_settle = int(6.0 / loop.period)
    return {"state": state, "seconds": len(ct) * loop.period, "max_mm": ct.max() * 1e3,
            "max_after_6s_mm": ct[t_settle:].max() * 1e3 if len(ct) > t_settle else math.nan,
            "rms_mm": float(np.sqrt(np.mean(ct ** 2))) * 1e3, "t_max_s": float(np.argmax(ct)) * loop.period,
            "fixes": sum(1 for r in replies if r["fused"]), "outliers": sum(1 for r in replies if r.get("outlier")),
            "learnt_gyro_scale": learnt if replies else math.nan, "reanchors": reanchors,
            "duty_step_at_fix": max(at) if at else math.nan, "duty_step_steady": float(d[mask].max())}


def _nees(err: tuple[float, float, float], p: list[float]) -> float:
    """e' P^-1 e of the map pose's true error and its covariance: 3 on average if it is honest."""
    e = np.array(err)
    return float(e @ np.linalg.solve(np.array(p).reshape(6, 6)[:3, :3], e))


def consistency(seeds: int, duration_s: float = 8.0) -> list[tuple[float, float, float]]:
    """Per fix time: the mean NEES of the map pose just before the fix, over `seeds` runs with
    the 2 % scale error and with none; is the filter's covariance what its errors are?"""
    spec = {"shape": "circle", "radius": 1.0, "laps": 4, "speed": 0.4}
    by: dict[float, list[list[float]]] = {}
    for k, scale_error in enumerate((0.02, 0.0)):
        for seed in range(1, seeds + 1):
            rows: list[dict[str, Any]] = []
            fix_run(spec, duration_s, True, seed, scale_error=scale_error, trace=rows)
            for w in rows:
                by.setdefault(round(w["t"]), [[], []])[k].append(w["error"][3])
    return [(t, float(np.mean(v[0])), float(np.mean(v[1]))) for t, v in sorted(by.items())]


def _trace_row(t: float, err: tuple[float, ...], reply: dict[str, Any], est: Any, ct_max: float) -> dict[str, Any]:
    p = est.track.p_map
    return {"t": t, "fused": reply["fused"], "d2": reply["d2"], "innovation": reply.get("innovation", [math.nan] * 3),
            "error": err, "g": est.frame.g, "g_std": math.sqrt(p[4 * 6 + 4]), "b": est.frame.b,
            "b_std": math.sqrt(p[5 * 6 + 5]), "ct_max": ct_max}


def print_trace(plant_name: str, seed: int, scale_error: float, est_keys: dict[str, Any]) -> None:
    """Per fix of one run: why the first seconds peak (the map's true error at the fix, what
    the fix said, how much of the gyro's scale error has been learnt, and how surely)."""
    rows: list[dict[str, Any]] = []
    spec = {"shape": "circle", "radius": 1.0, "laps": 4, "speed": 0.4}
    r = fix_run(spec, 60.0, True, seed, scale_error=scale_error, plant=REALISTIC if plant_name == "realistic" else None,
                estimator=est_keys, trace=rows)
    truth = 1.0 / (1.0 + scale_error) - 1.0
    print(f"### {plant_name} plant, seed {seed}, gyro scale error {scale_error * 100:g} % (learnt should reach {truth:+.4f})"
          f"{', estimator ' + str(est_keys) if est_keys else ''}\n")
    print("| fix at (s) | map error then: x, y (mm), theta (deg) | its NEES | innovation: x, y (mm), theta (deg) | d2 | "
          "fused | learnt gyro scale | its 1 sigma | learnt bias (mrad/s) | its 1 sigma | max cross-track so far (mm) |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for w in rows:
        e, y = w["error"], w["innovation"]
        d2 = "-" if w["d2"] is None else f"{w['d2']:.2f}"
        print(f"| {w['t']:.1f} | {e[0] * 1e3:+.1f}, {e[1] * 1e3:+.1f}, {math.degrees(e[2]):+.2f} | {e[3]:.2f} | "
              f"{y[0] * 1e3:+.1f}, {y[1] * 1e3:+.1f}, {math.degrees(y[2]):+.2f} | {d2} | {'yes' if w['fused'] else 'no'} | "
              f"{w['g']:+.4f} | {w['g_std']:.4f} | {w['b'] * 1e3:+.3f} | {w['b_std'] * 1e3:.3f} | {w['ct_max'] * 1e3:.1f} |")
    print(f"\nmax cross-track {r['max_mm']:.1f} mm at {r['t_max_s']:.1f} s, after 6 s {r['max_after_6s_mm']:.1f} mm\n")


def _num(v: float, fmt: str) -> str:
    return "-" if math.isnan(v) else format(v, fmt)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="3 scenarios, 6 robots, one seed: a smoke run")
    ap.add_argument("--trace", nargs=2, metavar=("PLANT", "SEED"),
                    help="only the per-fix trace of one 60 s fix run: PLANT plain, realistic or exact (no scale error)")
    args = ap.parse_args(argv)
    t0 = time.time()
    if args.trace:
        name, seed = args.trace[0], int(args.trace[1])
        if name not in ("plain", "realistic", "exact"):
            ap.error(f"--trace: PLANT is plain, realistic or exact, got {name!r}")
        print_trace("plain" if name == "exact" else name, seed, 0.0 if name == "exact" else 0.02, {})
        return 0
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
    print("\n### Pose fixes: 2 % gyro scale error (unless said), 1 m circle at 0.4 m/s, 60 s in map\n")
    print("Plain plant, and the realistic plant (a bias drifting 0.01 deg/s per s, the register held, "
          "the MCU's clock off, a slipping omni wheel); default estimator settings unless said.\n")
    print("| plant, seed | fixes | state | s | max (mm) | at (s) | max after 6 s (mm) | RMS (mm) | fused | outliers | "
          "re-anchors | learnt gyro scale | duty step at a fix | steady max step |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    spec = {"shape": "circle", "radius": 1.0, "laps": 4, "speed": 0.4}
    seeds = (1,) if args.quick else (1, 2, 3, 4, 5)
    # (label, sim plant keys, estimator keys, gyro scale error, with a run without fixes)
    runs: list[tuple[str, Any, Any, float, bool]] = [("plain", None, None, 0.02, True)]
    runs += [("realistic", REALISTIC, None, 0.02, True)]
    # What the first seconds cost: a gyro with no scale error, its scale still unknown to the
    # model (the default gyro_scale_std), and known (a calibrated gyro, 0.3 %).
    runs += [("plain, no scale error", None, None, 0.0, False)]
    runs += [("plain, no scale error, gyro_scale_std 0.003", None, {"gyro_scale_std": 0.003}, 0.0, False)]
    summary: dict[str, list[float]] = {}
    for label, plant, est_keys, scale_error, free in runs:
        for seed in seeds:
            for fixes in ((False, True) if free else (True,)):
                r = fix_run(spec, 60.0, fixes, seed, scale_error=scale_error, plant=plant, estimator=est_keys)
                print(f"| {label}, {seed} | {'every 1 s' if fixes else 'none'} | {r['state']} | {r['seconds']:.1f} | "
                      f"{r['max_mm']:.1f} | {r['t_max_s']:.1f} | {r['max_after_6s_mm']:.1f} | {r['rms_mm']:.2f} | "
                      f"{r['fixes']} | {r['outliers']} | {r['reanchors']} | {_num(r['learnt_gyro_scale'], '+.4f')} | "
                      f"{_num(r['duty_step_at_fix'], '.4f')} | {r['duty_step_steady']:.4f} |")
                sys.stdout.flush()
                if fixes:
                    summary.setdefault(label, []).append(r)
    print()
    for label, rs in summary.items():
        peaks, late = [r["max_mm"] for r in rs], [r["max_after_6s_mm"] for r in rs]
        print(f"- {label}, with fixes: largest cross-track over the whole run {min(peaks):.1f} to {max(peaks):.1f} mm "
              f"({sum(p > 10.0 for p in peaks)} of {len(peaks)} seeds beyond 10 mm), after 6 s {min(late):.1f} to "
              f"{max(late):.1f} mm ({sum(p > 10.0 for p in late)} beyond 10 mm); outliers {sum(r['outliers'] for r in rs)}; "
              f"the duty step at a fix above the run's steady max in {sum(r['duty_step_at_fix'] > r['duty_step_steady'] for r in rs)} "
              f"of {len(rs)} runs.")
    n = 5 if args.quick else 30
    print(f"\n### Pose fixes: is the map's covariance honest in the first seconds? ({n} seeds, 8 s)\n")
    print("Mean NEES (e' P^-1 e of the map pose's true error, x, y, theta) just before each fix: 3 when the "
          "covariance is what the errors are; the 2 % error is 1.16 sigma of the model's gyro_scale_std, "
          "so a little above 3 is expected there, and below 3 with no scale error.\n")
    print("| fix at (s) | 2 % scale error | no scale error |")
    print("|---|---|---|")
    for t, a, b in consistency(n):
        print(f"| {t:.0f} | {a:.2f} | {b:.2f} |")
    print(f"\n({time.time() - t0:.0f} s wall)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
