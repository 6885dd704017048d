"""Adaptive dynamics and calibration (issue 7): the rows and verdicts of BENCHMARKS.md section 7.

Three measurements on the simulated robot:
- every scenario with `controller.adaptation` off and on, at the default 200 Hz and at 1 kHz,
  over the noise seeds (medians);
- `ddrt calibrate identify` on the nominal and the offset-mass robot against the plant's true
  lumped parameters;
- `ddrt calibrate odometry` (from the simulator's truth) on the 4% encoder-radius error, then
  the seed's circle before, after, and with the exact radius.
"""

from __future__ import annotations

import math
import multiprocessing
import statistics
import time
from dataclasses import dataclass
from pathlib import Path as FsPath
from typing import Sequence

from ddrt import calibrate as cal
from ddrt.config import load_config, with_overrides
from ddrt.simrun import resolve_path, run_sim
from hal.registry import open_hal

REPO = FsPath(__file__).resolve().parents[1]
RATES_HZ = (200.0, 1000.0)
TARGET_CASE = ("figure8_fast_offset_mass", "figure8_fast")  # (hidden mass, same path nominal)
SLOW_CASES = ("figure8_slow", "figure8_slow_offset_mass")
GAIN_TARGET = 2.0
NOMINAL_TARGET = 1.2
HARM_LIMIT = 0.10
PARAM_TARGET = 0.05
IDENTIFY_CONFIGS = ("sim.yaml", "sim-offset-mass.yaml")
IDENTIFY_AREA_M = (2.0, 1.2)
UNCALIBRATED = "figure8_slow_r3_uncalibrated"
CIRCLE_PATH = REPO / "configs" / "paths" / "seed_circle.yaml"


@dataclass(frozen=True)
class Cell:
    """Median over seeds of one (scenario, rate, adaptation) combination, in metres."""

    est: float
    true: float


@dataclass(frozen=True)
class IdentifyRow:
    config: str
    values: dict[str, float]
    truth: dict[str, float]
    r2: float
    duration_s: float


@dataclass(frozen=True)
class OdometryRows:
    r_3_before: float
    r_3_after: float
    r_3_true: float
    gyro_scale_after: float
    circle: dict[str, Cell]  # "uncalibrated", "calibrated", "exact r_3"


@dataclass(frozen=True)
class AdaptationResult:
    seeds: tuple[int, ...]
    scenarios: tuple[str, ...]
    grid: dict[tuple[str, float, bool], Cell]
    identify: list[IdentifyRow]
    odometry: OdometryRows
    wall_s: float
    verdict: list[str]


def _job(args: tuple[str, float, bool, int]) -> tuple[tuple[str, float, bool], float, float]:
    name, rate, on, seed = args
    cfg = load_config(REPO / "configs" / "scenarios" / f"{name}.yaml",
                      {"controller": {"mode": "dynamic", "rate_hz": rate, "adaptation": {"enabled": on}}})
    m = run_sim(cfg, resolve_path(cfg), seed=seed).metrics
    return (name, rate, on), float(m["rms_tracking_m"]), float(m["rms_cross_track_m"])


def measure_grid(scenarios: Sequence[str], seeds: Sequence[int], workers: int,
                 rates: Sequence[float] = RATES_HZ) -> dict[tuple[str, float, bool], Cell]:
    jobs = [(s, r, on, seed) for s in scenarios for r in rates for on in (False, True) for seed in seeds]
    if workers > 1:
        with multiprocessing.get_context("fork").Pool(workers) as pool:
            out = pool.map(_job, jobs, chunksize=1)
    else:
        out = [_job(j) for j in jobs]
    acc: dict[tuple[str, float, bool], list[tuple[float, float]]] = {}
    for key, est, true in out:
        acc.setdefault(key, []).append((est, true))
    return {k: Cell(statistics.median(e for e, _ in v), statistics.median(t for _, t in v)) for k, v in acc.items()}


def measure_identify() -> list[IdentifyRow]:
    rows = []
    for name in IDENTIFY_CONFIGS:
        cfg = load_config(REPO / "configs" / name)
        res = cal.identify(cfg, open_hal(cfg, start=(0.0, 0.0, 0.0)), *IDENTIFY_AREA_M)
        rows.append(IdentifyRow(name, dict(res.values), cal.true_values(cfg), res.r2, res.duration_s))
    return rows


def _circle(overrides: dict) -> Cell:
    cfg = load_config(REPO / "configs" / "scenarios" / f"{UNCALIBRATED}.yaml", overrides)
    m = run_sim(cfg, resolve_path(cfg, str(CIRCLE_PATH))).metrics
    return Cell(float(m["rms_tracking_m"]), float(m["rms_cross_track_m"]))


def measure_odometry() -> OdometryRows:
    cfg = load_config(REPO / "configs" / "scenarios" / f"{UNCALIBRATED}.yaml")
    run = cal.odometry_run(cfg, open_hal(cfg, start=(0.0, 0.0, 0.0)))
    assert run.true_distance_m is not None and run.true_turn_rad is not None
    corr = cal.odometry_correction(cfg, run, run.true_distance_m, run.true_turn_rad)
    circle = {
        "uncalibrated": _circle({}),
        "calibrated": _circle({"robot": {"r_3": corr.r_3}, "estimator": {"gyro_scale": corr.gyro_scale}}),
        "exact r_3": _circle({"robot": {"r_3": cfg.plant.r_3}}),
    }
    return OdometryRows(cfg.robot.r_3, corr.r_3, cfg.plant.r_3, corr.gyro_scale, circle)


def verdicts(grid: dict[tuple[str, float, bool], Cell], scenarios: Sequence[str], rates: Sequence[float],
             identify: list[IdentifyRow], odo: OdometryRows) -> list[str]:
    out = []
    hidden, nominal = TARGET_CASE
    for rate in rates:
        if (hidden, rate, False) not in grid or (nominal, rate, False) not in grid:
            continue
        off, on = grid[(hidden, rate, False)].est, grid[(hidden, rate, True)].est
        nom = grid[(nominal, rate, False)].est
        gain, vs_nom = off / on, on / nom
        out.append(f"{rate:.0f} Hz, {hidden}: est RMS {off * 1e3:.4f} -> {on * 1e3:.4f} mm with adaptation, "
                   f"{gain:.2f}x (target >= {GAIN_TARGET:g}x: {'met' if gain >= GAIN_TARGET else 'NOT met'}); "
                   f"{vs_nom:.2f}x the nominal robot's {nom * 1e3:.4f} mm (target <= {NOMINAL_TARGET:g}x: "
                   f"{'met' if vs_nom <= NOMINAL_TARGET else 'NOT met'}).")
        worst_name, worst = "", -math.inf
        worst_true_name, worst_true = "", -math.inf
        for s in scenarios:
            a, b = grid[(s, rate, False)], grid[(s, rate, True)]
            ch, cht = b.est / a.est - 1.0, b.true / a.true - 1.0
            if ch > worst:
                worst_name, worst = s, ch
            if cht > worst_true:
                worst_true_name, worst_true = s, cht
        out.append(f"{rate:.0f} Hz, worst change with adaptation on any scenario: est {worst:+.0%} ({worst_name}), "
                   f"true {worst_true:+.0%} ({worst_true_name}) (target: never more than {HARM_LIMIT:.0%} worse: "
                   f"{'met' if max(worst, worst_true) <= HARM_LIMIT else 'NOT met'}).")
    for row in identify:
        errs = {k: row.values[k] / row.truth[k] - 1.0 for k in ("m_k", "I", "m_x", "mbar")}
        within = [k for k in ("m_k", "I", "m_x", "mbar") if abs(errs[k]) <= PARAM_TARGET]
        out.append(f"identify on {row.config} ({row.duration_s:.1f} s run): "
                   + ", ".join(f"{k} {errs[k]:+.1%}" for k in errs)
                   + f"; within {PARAM_TARGET:.0%}: {', '.join(within) or 'none'}.")
    c = odo.circle
    ratio = c["calibrated"].true / c["calibrated"].est
    out.append(f"odometry: r_3 {odo.r_3_before * 1e3:.2f} -> {odo.r_3_after * 1e3:.2f} mm (true "
               f"{odo.r_3_true * 1e3:.2f}); seed circle true RMS {c['uncalibrated'].true * 1e3:.2f} -> "
               f"{c['calibrated'].true * 1e3:.3f} mm ({c['exact r_3'].true * 1e3:.3f} mm with the exact radius). "
               f"True within 2x of estimated ({c['calibrated'].est * 1e3:.4f} mm): "
               f"{'met' if ratio <= 2.0 else f'NOT met ({ratio:.0f}x)'}.")
    return out


def measure_adaptation(scenario_dir: FsPath, seeds: Sequence[int], workers: int,
                       scenarios: Sequence[str] | None = None) -> AdaptationResult:
    t0 = time.perf_counter()
    names = tuple(scenarios) if scenarios else tuple(sorted(p.stem for p in scenario_dir.glob("*.yaml")))
    grid = measure_grid(names, seeds, workers)
    ident = measure_identify()
    odo = measure_odometry()
    return AdaptationResult(tuple(seeds), names, grid, ident, odo, time.perf_counter() - t0,
                            verdicts(grid, names, RATES_HZ, ident, odo))


def render(r: AdaptationResult) -> list[str]:
    lines = [
        "`controller.adaptation` off and on (`enabled`), every scenario, at the default 200 Hz and at 1 kHz "
        f"(`controller.rate_hz`), median over seeds {', '.join(map(str, r.seeds))}; est / true RMS cross-track "
        f"in mm, change with adaptation in brackets. {r.wall_s:.0f} s wall for the whole section.",
        "",
        "| scenario | " + " | ".join(f"{rate:.0f} Hz off | {rate:.0f} Hz on" for rate in RATES_HZ) + " |",
        "|---|" + "---|---|" * len(RATES_HZ),
    ]
    for s in r.scenarios:
        cells = []
        for rate in RATES_HZ:
            a, b = r.grid[(s, rate, False)], r.grid[(s, rate, True)]
            cells.append(f"{a.est * 1e3:.4f} / {a.true * 1e3:.3f}")
            cells.append(f"{b.est * 1e3:.4f} ({b.est / a.est - 1:+.0%}) / {b.true * 1e3:.3f} ({b.true / a.true - 1:+.0%})")
        lines.append(f"| {s} | " + " | ".join(cells) + " |")
    lines += ["", "`ddrt calibrate identify CONFIG --area 2x1.2` against the plant's true lumped parameters:", "",
              "| config | run (s) | R^2 | m + k | I | m_x | mbar |", "|---|---|---|---|---|---|---|"]
    for row in r.identify:
        cells = [f"{row.values[k]:.4g} (true {row.truth[k]:.4g}, {row.values[k] / row.truth[k] - 1:+.1%})"
                 for k in ("m_k", "I", "m_x", "mbar")]
        lines.append(f"| {row.config} | {row.duration_s:.1f} | {row.r2:.4f} | " + " | ".join(cells) + " |")
    o = r.odometry
    lines += ["", f"`ddrt calibrate odometry configs/scenarios/{UNCALIBRATED}.yaml --from-sim-truth`: r_3 "
              f"{o.r_3_before * 1e3:.2f} -> {o.r_3_after * 1e3:.3f} mm (true {o.r_3_true * 1e3:.2f}), gyro_scale "
              f"-> {o.gyro_scale_after:.4f}. Then the seed's circle (seed 1):", "",
              "| robot: r_3 | est RMS (mm) | true RMS (mm) |", "|---|---|---|"]
    for k, c in o.circle.items():
        lines.append(f"| {k} | {c.est * 1e3:.4f} | {c.true * 1e3:.3f} |")
    lines += ["", "Verdicts against issue 7's targets:", ""]
    lines += [f"- {v}" for v in r.verdict]
    return lines
