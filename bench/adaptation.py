"""Adaptive dynamics and calibration: the rows and verdicts of BENCHMARKS.md section 7.

Three measurements on the simulated robot:
- every scenario with `controller.adaptation` off and on, at the default 200 Hz and at 1 kHz,
  over the noise seeds (medians);
- `ddrt calibrate identify` on the nominal and the offset-mass robot against the plant's true
  lumped parameters;
- `ddrt calibrate odometry` (from the simulator's truth) on the 4% encoder-radius error, then
  the seed's circle before, after, and with the exact radius.
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass
from pathlib import Path as FsPath
from typing import Sequence

from bench.common import REPO, pooled_by_key
from ddrt import calibrate as cal
from ddrt.config import load_config
from ddrt.path.spec import resolve_path
from ddrt.simrun.runner import run_sim
from hal.registry import open_hal

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
LONG_PATH = REPO / "configs" / "paths" / "figure8_fast_5laps.yaml"
LONG_LAPS = 5


@dataclass(frozen=True)
class Cell:
    """Median over seeds of one (scenario, rate, adaptation) combination, in metres."""

    est: float
    true: float


@dataclass(frozen=True)
class LongRun:
    """Five laps: whole-run est/true RMS and the worst lap after the first (medians over seeds)."""

    est: float
    true: float
    est_after_first_lap: float


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
    long: dict[tuple[str, float, bool], LongRun]
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


def _medians(rows: list[tuple[float, ...]]) -> list[float]:
    return [statistics.median(r[i] for r in rows) for i in range(len(rows[0]))]


def measure_grid(scenarios: Sequence[str], seeds: Sequence[int], workers: int,
                 rates: Sequence[float] = RATES_HZ) -> dict[tuple[str, float, bool], Cell]:
    jobs = [(s, r, on, seed) for s in scenarios for r in rates for on in (False, True) for seed in seeds]
    return {k: Cell(*_medians(v)) for k, v in pooled_by_key(_job, jobs, workers).items()}


def _long_job(args: tuple[str, float, bool, int]) -> tuple[tuple[str, float, bool], float, float, float]:
    import numpy as np

    from ddrt.path.sampled import distances_to_polyline
    from ddrt.simrun.metrics import path_polyline

    name, rate, on, seed = args
    cfg = load_config(REPO / "configs" / "scenarios" / f"{name}.yaml",
                      {"controller": {"mode": "dynamic", "rate_hz": rate, "adaptation": {"enabled": on}}})
    r = run_sim(cfg, resolve_path(cfg, str(LONG_PATH)), seed=seed)
    d = distances_to_polyline(path_polyline(r.path), np.c_[r.column("x_est"), r.column("y_est")])
    lap = np.minimum((r.column("sigma") / (r.path.length / LONG_LAPS)).astype(int), LONG_LAPS - 1)
    later = max(float(np.sqrt(np.mean(d[lap == i] ** 2))) for i in range(1, LONG_LAPS))
    return (name, rate, on), float(r.metrics["rms_tracking_m"]), float(r.metrics["rms_cross_track_m"]), later


def measure_long(seeds: Sequence[int], workers: int,
                 rates: Sequence[float] = RATES_HZ) -> dict[tuple[str, float, bool], LongRun]:
    """Both figure-eights of TARGET_CASE over five laps, adaptation off and on."""
    jobs = [(s, r, on, seed) for s in TARGET_CASE for r in rates for on in (False, True) for seed in seeds]
    return {k: LongRun(*_medians(v)) for k, v in pooled_by_key(_long_job, jobs, workers).items()}


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


def verdicts(grid: dict[tuple[str, float, bool], Cell], long: dict[tuple[str, float, bool], LongRun],
             scenarios: Sequence[str], rates: Sequence[float], identify: list[IdentifyRow],
             odo: OdometryRows) -> list[str]:
    out = []
    hidden, nominal = TARGET_CASE
    for rate in rates:
        if (hidden, rate, False) in long:
            off, on = long[(hidden, rate, False)], long[(hidden, rate, True)]
            nom, nom_on = long[(nominal, rate, False)], long[(nominal, rate, True)]
            gain = off.est / on.est
            vs_nom = on.est_after_first_lap / nom.est_after_first_lap
            vs_nom_on = on.est_after_first_lap / nom_on.est_after_first_lap
            out.append(
                f"{rate:.0f} Hz, {hidden}, five laps: est RMS {off.est * 1e3:.4f} -> {on.est * 1e3:.4f} mm with "
                f"adaptation, {gain:.2f}x (target >= {GAIN_TARGET:g}x: {'met' if gain >= GAIN_TARGET else 'NOT met'}); "
                f"after the learning lap its worst lap is {vs_nom:.2f}x the nominal robot's without adaptation and "
                f"{vs_nom_on:.2f}x with it (target <= {NOMINAL_TARGET:g}x: "
                f"{'met' if max(vs_nom, vs_nom_on) <= NOMINAL_TARGET else 'NOT met'}); true RMS "
                f"{off.true * 1e3:.3f} -> {on.true * 1e3:.3f} mm.")
        if (hidden, rate, False) in grid:
            a, b = grid[(hidden, rate, False)], grid[(hidden, rate, True)]
            out.append(f"{rate:.0f} Hz, {hidden}, the one-lap scenario (learning included): est RMS "
                       f"{a.est * 1e3:.4f} -> {b.est * 1e3:.4f} mm ({a.est / b.est:.2f}x).")
        changes = [(grid[(s, rate, True)].est / grid[(s, rate, False)].est - 1.0,
                    grid[(s, rate, True)].true / grid[(s, rate, False)].true - 1.0, s)
                   for s in scenarios if (s, rate, False) in grid]
        if changes:
            worst = max(changes, key=lambda c: c[0])
            worst_true = max(changes, key=lambda c: c[1])
            ok = max(worst[0], worst_true[1]) <= HARM_LIMIT
            out.append(f"{rate:.0f} Hz, worst change with adaptation over {len(changes)} scenarios: est "
                       f"{worst[0]:+.0%} ({worst[2]}), true {worst_true[1]:+.0%} ({worst_true[2]}) (target: never "
                       f"more than {HARM_LIMIT:.0%} worse: {'met' if ok else 'NOT met'}).")
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
    long = measure_long(seeds, workers) if not scenarios or set(TARGET_CASE) <= set(names) else {}
    ident = measure_identify()
    odo = measure_odometry()
    return AdaptationResult(tuple(seeds), names, grid, long, ident, odo, time.perf_counter() - t0,
                            verdicts(grid, long, names, RATES_HZ, ident, odo))


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
    if r.long:
        lines += ["", f"Five laps of the 0.8 m/s figure-eight (`{LONG_PATH.relative_to(REPO)}`; the first lap is "
                  "the adapter's learning lap): est / true RMS over the run (mm), and the est RMS of the worst lap "
                  "after the first.", "",
                  "| robot | rate | off: run est / true | off: worst later lap | on: run est / true | "
                  "on: worst later lap |", "|---|---|---|---|---|---|"]
        for name in TARGET_CASE:
            for rate in RATES_HZ:
                a, b = r.long[(name, rate, False)], r.long[(name, rate, True)]
                lines.append(f"| {name} | {rate:.0f} Hz | {a.est * 1e3:.4f} / {a.true * 1e3:.3f} | "
                             f"{a.est_after_first_lap * 1e3:.4f} | {b.est * 1e3:.4f} / {b.true * 1e3:.3f} | "
                             f"{b.est_after_first_lap * 1e3:.4f} |")
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
    lines += ["", "Verdicts against the targets of adaptation.md (\"Against the targets\"):", ""]
    lines += [f"- {v}" for v in r.verdict]
    return lines


# --------------------------------------------------------------------------- events

EVENT_CONFIGS = ("realistic/actuators_events.yaml", "realistic/payload_floor_fast.yaml")


def _event_job(args: tuple[str, bool, int]) -> tuple[tuple[str, bool], float, float, float]:
    """One run: est and true RMS over the run, and est RMS from the first payload on."""
    import numpy as np

    name, on, seed = args
    cfg = load_config(REPO / "configs" / "scenarios" / name, {"controller": {"adaptation": {"enabled": on}}})
    r = run_sim(cfg, resolve_path(cfg), seed=seed)
    t = r.column("t") - r.column("t")[0]
    at = min((p.at_s for p in cfg.sim.events.payloads), default=0.0)
    after = float(np.sqrt(np.mean(r.column("cross_track_est")[t >= at] ** 2)))
    return (name, on), float(r.metrics["rms_tracking_m"]), float(r.metrics["rms_cross_track_m"]), after


def measure_events(seeds: Sequence[int], workers: int = 1,
                   names: Sequence[str] = EVENT_CONFIGS) -> dict[tuple[str, bool], tuple[float, float, float]]:
    """The realistic scenarios with a payload put on mid-run and a draggy floor, adaptation off
    and on (medians over `seeds`)."""
    jobs = [(n, on, s) for n in names for on in (False, True) for s in seeds]
    return {k: tuple(_medians(v)) for k, v in pooled_by_key(_event_job, jobs, workers).items()}


def render_events(cells: dict[tuple[str, bool], tuple[float, float, float]], seeds: Sequence[int]) -> list[str]:
    lines = [f"Payload and floor events, adaptation off and on (medians over seeds {', '.join(map(str, seeds))}; "
             "mm; \"after\": est RMS from the payload on):", "",
             "| scenario | off: est / true / after | on: est / true / after |", "|---|---|---|"]
    for name in dict.fromkeys(n for n, _ in cells):
        a, b = cells[(name, False)], cells[(name, True)]
        lines.append(f"| {name} | {a[0] * 1e3:.4f} / {a[1] * 1e3:.3f} / {a[2] * 1e3:.4f} | {b[0] * 1e3:.4f} "
                     f"({b[0] / a[0] - 1:+.0%}) / {b[1] * 1e3:.3f} / {b[2] * 1e3:.4f} ({b[2] / a[2] - 1:+.0%}) |")
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m bench.adaptation",
                                 description="adaptation off and on where it should help: payload and floor events "
                                             "(the rest of this module is section 7 of `python -m bench.run`)")
    ap.add_argument("--seeds", default="1,2,3", help="comma-separated noise seeds (default 1,2,3)")
    ap.add_argument("--workers", type=int, default=1)
    args = ap.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",") if s]
    print("\n".join(render_events(measure_events(seeds, args.workers), seeds)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
