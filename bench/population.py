"""A population of robots: does one config (its `robot:` section, every other key at default) serve them all?

`python -m bench.population [--robots 40] [--workers 2]` prints the table; bench/run.py renders it as a
section of BENCHMARKS.md.

A fixed-seed generator draws physically consistent differential-drive robots:
- total mass 1-19 kg; size from the mass (the seed robot's half track 0.108 m at 4.34 kg,
  scaled by the cube root of the mass, +-20 %); drive wheels 0.3-0.55 of the half track,
  the omni-wheel 0.8-1.3 half tracks ahead of the axle;
- masses split into the two wheel assemblies (each 12-30 %), the omni-wheel (5-15 %) and the
  platform (the rest), its centre of mass -0.2..0.6 of H ahead of the axle and within 3 %
  of the half track sideways; yaw inertias of a box (the platform, 1.3 (H + r) long, 1.8 L
  wide) and of cylinders (the wheel assemblies), spin inertias of discs (35 % of each
  assembly's mass in its wheel);
- a gearmotor per robot: supply 6-24 V, full-voltage no-load ground speed 0.7-2.2 m/s, stall
  torque 0.4-1.2 x M g r / 2 (each wheel can push 20-60 % of the robot's weight), friction at
  no load 4-10 % of the stall torque (half Coulomb, half viscous);
- the truth (`plant:`) departs from the belief (`robot:`) by a few percent: every mass,
  inertia, length and the drive wheels' radii by N(0, 2 %) (clipped at 5 %), each wheel's
  motor constants by N(0, 3 %) (clipped at 8 %); the encoder wheel's radius by N(0, 0.05 %)
  (calibrated: `ddrt calibrate odometry` gets it within 0.1 %; an uncalibrated radius is a
  dead-reckoning error no controller sees, configs/scenarios/figure8_slow_r3_uncalibrated.yaml);
- latency: commands 0.5-3 ms, sensors 0.5-2 ms.

Each robot drives the figure-eight (1.2 x 0.6 m) and the rectangle (1.2 x 0.8 m, pivots at
the corners) of configs/paths/ at a speed drawn from 50-90 % of its motors' full-voltage
no-load speed (a speed the motors reach; the profile keeps within its headroom and says so
when it clamps). Controllers: dynamic (the default), dynamic with adaptation, kinematic.
"""

from __future__ import annotations

import argparse
import math
import random
import statistics
import sys
import time
from dataclasses import dataclass, field
from typing import Any, Sequence

from bench.common import pooled_by_key
from ddrt.config import config_from_mapping
from ddrt.params.robot import RobotParams
from ddrt.path.spec import resolve_path
from ddrt.simrun.runner import run_sim

SEED = 20261201
ROBOTS = 40
PATHS = {
    "figure8": {"shape": "figure_eight", "width": 1.2, "height": 0.6},
    "rectangle": {"shape": "rectangle", "width": 1.2, "height": 0.8, "direction": "ccw"},
}
VARIANTS = ("dynamic", "dynamic+adapt", "kinematic")
EST_TARGET_M = 1e-3
TRUE_TARGET_M = 5e-3
SAT_TARGET = 0.02
PASS_TARGET = 79  # of 80
ADAPT_HARM = (0.10, 0.02e-3)  # "worse" is more than 10 % and more than 0.02 mm
G = 9.81


@dataclass(frozen=True)
class Robot:
    """One drawn robot: its config sections and the figures the table shows."""

    name: str
    mass: float
    supply_v: float
    half_track: float
    wheel_r: float
    top_speed: float  # full-voltage no-load ground speed (m/s)
    speed: float  # the speed its paths ask for
    sections: dict[str, Any] = field(repr=False)


def _u(rng: random.Random, lo: float, hi: float) -> float:
    return rng.uniform(lo, hi)


def _jitter(rng: random.Random, x: float, sd: float, clip: float) -> float:
    return x * (1.0 + max(-clip, min(clip, rng.gauss(0.0, sd))))


def make_robot(rng: random.Random, i: int) -> Robot:
    """One physically consistent robot (see the module doc), with its belief and truth."""
    while True:
        mass = _u(rng, 1.0, 19.0)
        L = 0.108 * (mass / 4.34) ** (1.0 / 3.0) * _u(rng, 0.8, 1.2)
        r = L * _u(rng, 0.3, 0.55)
        H = L * _u(rng, 0.8, 1.3)
        r3 = r * _u(rng, 0.6, 1.1)
        m_w = mass * _u(rng, 0.12, 0.30)
        m_3 = mass * _u(rng, 0.05, 0.15)
        m_p = mass - 2.0 * m_w - m_3
        if m_p < 0.15 * mass:
            continue
        d_xc = H * _u(rng, -0.2, 0.6)
        d_yc = L * _u(rng, -0.03, 0.03)
        length, width = 1.3 * (H + r), 1.8 * L
        I_p = m_p * (length ** 2 + width ** 2) / 12.0 * _u(rng, 0.7, 1.3)
        I_wheel_yaw = m_w * (3.0 * (0.6 * r) ** 2 + r ** 2) / 12.0
        I_3 = m_3 * (3.0 * (0.6 * r3) ** 2 + r3 ** 2) / 12.0
        I_w = 0.5 * 0.35 * m_w * r * r
        I_w3 = 0.5 * 0.5 * m_3 * r3 * r3
        robot = dict(H=H, L=L, R=L, r_L=r, r_R=r, r_3=r3, d_xc=d_xc, d_yc=d_yc, m_p=m_p, m_L=m_w, m_R=m_w,
                     m_3=m_3, I_p=I_p, I_L=I_wheel_yaw, I_R=I_wheel_yaw, I_3=I_3, I_wL=I_w, I_wR=I_w, I_w3=I_w3)
        volts = _u(rng, 6.0, 24.0)
        v_nl = _u(rng, 0.7, 2.2)
        k = volts / (v_nl / r)
        stall = _u(rng, 0.4, 1.2) * mass * G * r / 2.0
        res = k * volts / stall
        fric = _u(rng, 0.04, 0.10) * stall
        motor = dict(supply_v=volts, resistance_ohm=res, k_nm_per_a=k, viscous_nms=0.5 * fric / (v_nl / r),
                     coulomb_nm=0.5 * fric)
        plant = {key: (_jitter(rng, v, 0.0005, 0.001) if key == "r_3" else
                       v if key == "d_yc" else _jitter(rng, v, 0.02, 0.05)) for key, v in robot.items()}
        plant["d_yc"] = robot["d_yc"] + rng.gauss(0.0, 0.01 * L)
        plant["r_L"] = _jitter(rng, r, 0.02, 0.05)
        plant["r_R"] = _jitter(rng, r, 0.02, 0.05)
        for side in ("motor_l", "motor_r"):
            plant[side] = {key: _jitter(rng, motor[key], 0.03, 0.08)
                           for key in ("resistance_ohm", "k_nm_per_a", "viscous_nms", "coulomb_nm")}
        try:
            RobotParams(**robot)
            RobotParams(**{key: v for key, v in plant.items() if not key.startswith("motor")})
        except ValueError:
            continue
        speed = v_nl * _u(rng, 0.5, 0.9)
        sections = {
            "robot": dict(robot, motor=motor),
            "plant": plant,
            "sim": {"seed": i + 1, "command_latency_s": _u(rng, 0.0005, 0.003),
                    "sensor_latency_s": _u(rng, 0.0005, 0.002)},
        }
        return Robot(f"r{i:02d}", mass, volts, L, r, v_nl, speed, sections)


def population(n: int = ROBOTS, seed: int = SEED) -> list[Robot]:
    rng = random.Random(seed)
    return [make_robot(rng, i) for i in range(n)]


def config_of(robot: Robot, path: str, variant: str):
    """The robot's config: its sections, a path, a controller; every other key at its default."""
    data: dict[str, Any] = dict(robot.sections)
    data["path"] = dict(PATHS[path], speed=round(robot.speed, 4))
    mode = "kinematic" if variant == "kinematic" else "dynamic"
    data["controller"] = {"mode": mode, "adaptation": {"enabled": variant == "dynamic+adapt"}}
    data["daemon"] = {"socket": None}
    return config_from_mapping(data, source=f"population/{robot.name}")


@dataclass(frozen=True)
class Run:
    robot: str
    path: str
    variant: str
    est: float
    true: float
    saturated: float
    completed: bool
    fault: str
    duration_s: float
    warnings: int


def _run(job: tuple[Robot, str, str]) -> tuple[tuple[str, str, str], Run]:
    import logging

    logger = logging.getLogger("ddrt")
    level = logger.level
    logger.setLevel(logging.CRITICAL)  # a run that faults logs it; the fault is in the record
    try:
        robot, path, variant = job
        cfg = config_of(robot, path, variant)
        p = resolve_path(cfg)
        m = run_sim(cfg, p).metrics
    finally:
        logger.setLevel(level)
    run = Run(robot.name, path, variant, float(m["rms_tracking_m"]), float(m["rms_cross_track_m"]),
              float(m["saturated_fraction"]), bool(m["completed"]), str(m.get("fault") or ""),
              float(m["sim_duration_s"]), len(getattr(p, "warnings", [])))
    return (robot.name, path, variant), run


@dataclass
class PopulationResult:
    robots: list[Robot]
    runs: dict[tuple[str, str, str], Run]
    variants: tuple[str, ...]
    wall_s: float
    verdict: list[str] = field(default_factory=list)


def measure_population(n: int = ROBOTS, workers: int = 2, variants: Sequence[str] = VARIANTS,
                       seed: int = SEED) -> PopulationResult:
    robots = population(n, seed)
    jobs = [(r, p, v) for v in variants for r in robots for p in PATHS]
    t0 = time.perf_counter()
    grouped = pooled_by_key(_run, jobs, workers)
    runs = {k: v[0][0] for k, v in grouped.items()}
    res = PopulationResult(robots, runs, tuple(variants), time.perf_counter() - t0)
    res.verdict = verdicts(res)
    return res


def _passes(run: Run) -> bool:
    return run.completed and run.est <= EST_TARGET_M and run.true <= TRUE_TARGET_M


def _of(res: PopulationResult, variant: str) -> list[Run]:
    return [run for (_, _, v), run in sorted(res.runs.items()) if v == variant]


def verdicts(res: PopulationResult) -> list[str]:
    out = []
    dyn = _of(res, "dynamic")
    if dyn:
        ok = sum(_passes(r) for r in dyn)
        sat = max(dyn, key=lambda r: r.saturated)
        out.append(f"dynamic: {ok} of {len(dyn)} runs complete with est RMS <= {EST_TARGET_M * 1e3:g} mm and true RMS "
                   f"<= {TRUE_TARGET_M * 1e3:g} mm (target >= {PASS_TARGET} of 80): "
                   f"**{'MET' if ok >= PASS_TARGET * len(dyn) / 80 else 'NOT MET'}**; worst saturation "
                   f"{sat.saturated:.2%} of ticks ({sat.robot} {sat.path}; target <= {SAT_TARGET:.0%}): "
                   f"**{'MET' if sat.saturated <= SAT_TARGET else 'NOT MET'}**.")
        failed = [r for r in dyn if not _passes(r)]
        if failed:
            out.append("dynamic runs that missed: " + "; ".join(
                f"{r.robot} {r.path} est {r.est * 1e3:.3f} mm true {r.true * 1e3:.3f} mm"
                f"{'' if r.completed else ' (' + (r.fault or 'time limit') + ')'}" for r in failed) + ".")
    on = {(r.robot, r.path): r for r in _of(res, "dynamic+adapt")}
    if dyn and on:
        pairs = [(r, on[(r.robot, r.path)]) for r in dyn if (r.robot, r.path) in on]
        med_off = statistics.median(a.est for a, _ in pairs)
        med_on = statistics.median(b.est for _, b in pairs)
        rel, absm = ADAPT_HARM
        worse = [(a, b) for a, b in pairs if b.est > a.est * (1 + rel) and b.est - a.est > absm]
        worse_true = [(a, b) for a, b in pairs if b.true > a.true * (1 + rel) and b.true - a.true > absm]
        qualifies = med_on < med_off and not worse
        out.append(f"adaptation: median est RMS {med_off * 1e3:.4f} -> {med_on * 1e3:.4f} mm; runs worse by more than "
                   f"{rel:.0%} and {absm * 1e3:g} mm: {len(worse)} on the estimated pose, {len(worse_true)} on the "
                   f"true pose (the criterion for on by default: better median and none worse on the estimated pose): "
                   f"**{'qualifies' if qualifies else 'does not qualify'}**"
                   + (" (" + "; ".join(f"{a.robot} {a.path} {a.est * 1e3:.3f} -> {b.est * 1e3:.3f} mm"
                                       for a, b in worse[:8]) + ")" if worse else "") + ".")
    kin = {(r.robot, r.path): r for r in _of(res, "kinematic")}
    if dyn and kin:
        pairs = [(r, kin[(r.robot, r.path)]) for r in dyn if (r.robot, r.path) in kin]
        ok = sum(_passes(b) for _, b in pairs)
        out.append(f"kinematic baseline: {ok} of {len(pairs)} pass; median est RMS "
                   f"{statistics.median(b.est for _, b in pairs) * 1e3:.4f} mm against dynamic "
                   f"{statistics.median(a.est for a, _ in pairs) * 1e3:.4f} mm; dynamic better on "
                   f"{sum(a.est < b.est for a, b in pairs)} of {len(pairs)} runs.")
    return out


def _stats(runs: list[Run]) -> str:
    est = [r.est for r in runs]
    true = [r.true for r in runs]
    sat = [r.saturated for r in runs]
    return (f"{sum(_passes(r) for r in runs)}/{len(runs)} | {sum(r.completed for r in runs)}/{len(runs)} | "
            f"{statistics.median(est) * 1e3:.4f} / {max(est) * 1e3:.3f} | "
            f"{statistics.median(true) * 1e3:.4f} / {max(true) * 1e3:.3f} | "
            f"{statistics.median(sat):.2%} / {max(sat):.2%} | {sum(s > SAT_TARGET for s in sat)}")


def render(res: PopulationResult) -> list[str]:
    masses = [r.mass for r in res.robots]
    volts = [r.supply_v for r in res.robots]
    lines = [
        f"{len(res.robots)} robots from a fixed-seed generator (`bench/population.py`, seed {SEED}): "
        f"{min(masses):.1f}-{max(masses):.1f} kg, {min(volts):.1f}-{max(volts):.1f} V motors, different wheels, "
        "tracks and inertias consistent with mass and size, a few percent between belief (`robot:`) and truth "
        "(`plant:`), 0.5-3 ms latency; each given as its `robot:` section with every other key at default "
        f"(so the speed profile derives its limits from the motors). The figure-eight and the rectangle at 50-90 % "
        f"of each robot's no-load speed; {len(res.runs)} runs on the simulated robot, {res.wall_s:.0f} s wall. "
        f"pass = completed with est RMS <= {EST_TARGET_M * 1e3:g} mm and true RMS <= {TRUE_TARGET_M * 1e3:g} mm.",
        "",
        "| controller | pass | completed | est RMS median / worst (mm) | true RMS median / worst (mm) | "
        f"saturated median / worst | runs saturated > {SAT_TARGET:.0%} |",
        "|---|---|---|---|---|---|---|",
    ]
    for v in res.variants:
        runs = _of(res, v)
        if runs:
            lines.append(f"| {v} | {_stats(runs)} |")
    for path in PATHS:
        lines += ["", f"{path}, per robot (dynamic): mass, supply, speed asked, est / true RMS (mm), saturated:", ""]
        cells = []
        for r in res.robots:
            run = res.runs.get((r.name, path, "dynamic"))
            if run is not None:
                cells.append(f"{r.name} {r.mass:.1f} kg {r.supply_v:.0f} V {r.speed:.2f} m/s: "
                             f"{run.est * 1e3:.3f} / {run.true * 1e3:.3f}, {run.saturated:.1%}"
                             f"{'' if run.completed else ' (' + (run.fault or 'time limit') + ')'}")
        lines.append("; ".join(cells) + ".")
    lines += ["", "Verdicts:", ""] + [f"- {v}" for v in res.verdict]
    return lines


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.population", description=__doc__.splitlines()[0])
    ap.add_argument("--robots", type=int, default=ROBOTS)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--variants", default=",".join(VARIANTS), help=f"comma-separated, of {', '.join(VARIANTS)}")
    ap.add_argument("--json", help="also write every run's numbers to this file")
    args = ap.parse_args(argv)
    variants = tuple(v for v in args.variants.split(",") if v)
    res = measure_population(args.robots, args.workers, variants)
    print("\n".join(render(res)))
    if args.json:
        import json

        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump([dict(vars(r)) for r in res.runs.values()], fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
