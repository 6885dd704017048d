"""A population of robots: does one config (its `robot:` section, every other key at default) serve them all?

`python -m bench.population [--robots 40] [--workers 2]` prints the table; bench/run.py renders it as a
section of BENCHMARKS.md.

The robots come from ddrt/sweep/population.py (the generator a campaign's `population:`
draws from; its module doc says how each is drawn), and the runs are a campaign,
bench/campaigns/population.yaml, run by the sweep runner (`ddrt sweep`'s: a Dask
LocalCluster of `--workers` processes, or this process for one).

Each robot drives the figure-eight (1.2 x 0.6 m) and the rectangle (1.2 x 0.8 m, pivots at
the corners) of configs/paths/ at a speed drawn from 50-90 % of its motors' full-voltage
no-load speed (a speed the motors reach; the profile keeps within its headroom and says so
when it clamps). Controllers: dynamic with adaptation off, with it on (the default), kinematic.

`--rerun ROBOT/PATH --sim-seeds 1,2,3`: that one run with adaptation off and on at each sim
seed, to tell a difference between the two from the plant's own spread.

`--harsh`: the same robots with cheap parts on the realistic plant (drawn per robot
from its name, so a robot is as harsh in every run): gyro sensitivity off by 2-3 % either
way, zero-rate bias up to 5 deg/s either way, a coarse front encoder (400, 600 or 1024
counts a turn), a driver deadband of 2-5 % of duty and 0.5-2 degrees of gearbox backlash.
"""

from __future__ import annotations

import argparse
import dataclasses
import random
import statistics
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path as FsPath
from typing import Any, Sequence

from ddrt.config import config_from_mapping
from ddrt.config.yamlio import read_yaml
from ddrt.sweep.campaign import Campaign, CampaignError, campaign_from_mapping
from ddrt.config.load import merge_mappings
from ddrt.config.sim_truth import ActuatorTruth
from ddrt.sweep.cases import Plan
from ddrt.sweep.cases import expand
from ddrt.sweep.driver import run_plan
from ddrt.sweep.population import SEED, Robot
from ddrt.sweep.population import population as draw
from ddrt.sweep.run import Row

CAMPAIGN = FsPath(__file__).resolve().parent / "campaigns" / "population.yaml"
ROBOTS = 40
_SPEC = read_yaml(CAMPAIGN, CampaignError)
PATHS: dict[str, dict[str, Any]] = _SPEC["paths"]
VARIANTS = tuple(_SPEC["variants"])
EST_TARGET_M = 1e-3
TRUE_TARGET_M = 5e-3
SAT_TARGET = 0.02
PASS_TARGET = 79  # of 80
# Adaptation on by default: the median true-pose RMS no worse with it, and no run's true RMS
# worse by more than the larger of 25 % and 0.1 mm (a scale a robot's position shows).
ADAPT_HARM = (0.25, 0.1e-3)


def population(n: int = ROBOTS, seed: int = SEED) -> list[Robot]:
    return draw(n, seed)


def config_of(robot: Robot, path: str, variant: str):
    """The config the campaign gives this robot on `path` with `variant`: its sections, the path
    at its speed, the campaign's overrides and the variant; every other key at its default."""
    data: dict[str, Any] = dict(robot.sections, path=dict(PATHS[path], speed=robot.path_speed))
    data = merge_mappings(merge_mappings(data, _SPEC["overrides"]), _SPEC["variants"][variant])
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


def _record(row: Row) -> Run:
    if row["status"] != "ok":
        raise RuntimeError(f"population: {row['robot']} {row['path']} {row['variant']}: {row['error']}")
    return Run(row["robot"], row["path"], row["variant"], float(row["rms_tracking_m"]),
               float(row["rms_cross_track_m"]), float(row["saturated_fraction"]), bool(row["completed"]),
               str(row["fault"] or ""), float(row["sim_duration_s"]), int(row["path_warnings"]))


def campaign(n: int = ROBOTS, variants: Sequence[str] = VARIANTS, seed: int = SEED) -> Campaign:
    """bench/campaigns/population.yaml with `n` robots from `seed` and the variants asked for."""
    unknown = sorted(set(variants) - set(VARIANTS))
    if unknown:
        raise ValueError(f"unknown variant {unknown[0]!r} (known: {', '.join(VARIANTS)})")
    data = dict(_SPEC, population=dict(_SPEC["population"], robots=n, seed=seed),
                variants={v: _SPEC["variants"][v] for v in variants})
    return campaign_from_mapping(data, source=str(CAMPAIGN), folder=CAMPAIGN.parent)


def harsh_sections(name: str) -> dict[str, Any]:
    """The cheap parts robot `name` gets with --harsh (module doc), as config keys."""
    rng = random.Random(f"harsh/{name}")
    return {
        "sim": {"gyro": {"scale_error": rng.choice((-1, 1)) * rng.uniform(0.02, 0.03),
                         "bias_dps": rng.uniform(-5.0, 5.0)},
                "actuators": {"deadband": rng.uniform(0.02, 0.05), "backlash_deg": rng.uniform(0.5, 2.0)}},
        "sensors": {"encoder_counts_per_rev": rng.choice((400, 600, 1024))},
    }


def harsh_plan(plan: Plan) -> Plan:
    """`plan` with every robot's cheap parts (harsh_sections) in its config."""
    cases = []
    for case in plan.cases:
        keys = harsh_sections(case.params["robot"])
        cfg = case.config
        gyro = dataclasses.replace(cfg.sim.gyro, **keys["sim"]["gyro"])
        actuators = ActuatorTruth(**keys["sim"]["actuators"])
        actuators.validate("harsh.sim.actuators")
        cfg = dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, gyro=gyro, actuators=actuators),
                                  sensors=dataclasses.replace(cfg.sensors, **keys["sensors"]))
        cases.append(dataclasses.replace(case, config=cfg, case_id=case.case_id + "-harsh"))
    return dataclasses.replace(plan, cases=tuple(cases), fingerprint=plan.fingerprint + "-harsh")


@dataclass
class PopulationResult:
    robots: list[Robot]
    runs: dict[tuple[str, str, str], Run]
    variants: tuple[str, ...]
    wall_s: float
    verdict: list[str] = field(default_factory=list)
    harsh: bool = False


def measure_population(n: int = ROBOTS, workers: int = 2, variants: Sequence[str] = VARIANTS,
                       seed: int = SEED, harsh: bool = False) -> PopulationResult:
    robots = population(n, seed)
    t0 = time.perf_counter()
    plan = expand(campaign(n, variants, seed))
    rows = run_plan(harsh_plan(plan) if harsh else plan, workers)
    runs = {(r["robot"], r["path"], r["variant"]): _record(r) for r in rows}
    res = PopulationResult(robots, runs, tuple(variants), time.perf_counter() - t0, harsh=harsh)
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
        out.append(adaptation_verdict(pairs))
    kin = {(r.robot, r.path): r for r in _of(res, "kinematic")}
    if dyn and kin:
        pairs = [(r, kin[(r.robot, r.path)]) for r in dyn if (r.robot, r.path) in kin]
        ok = sum(_passes(b) for _, b in pairs)
        out.append(f"kinematic baseline: {ok} of {len(pairs)} pass; median est RMS "
                   f"{statistics.median(b.est for _, b in pairs) * 1e3:.4f} mm against dynamic "
                   f"{statistics.median(a.est for a, _ in pairs) * 1e3:.4f} mm; dynamic better on "
                   f"{sum(a.est < b.est for a, b in pairs)} of {len(pairs)} runs.")
    return out


def adaptation_worse(off: Run, on: Run) -> bool:
    """On is worse than off on the true pose by more than ADAPT_HARM allows."""
    rel, absm = ADAPT_HARM
    return on.true - off.true > max(rel * off.true, absm)


def adaptation_verdict(pairs: list[tuple[Run, Run]]) -> str:
    """The rule for adaptation on by default (ADAPT_HARM) over (off, on) pairs of runs."""
    rel, absm = ADAPT_HARM
    med_off = statistics.median(a.true for a, _ in pairs)
    med_on = statistics.median(b.true for _, b in pairs)
    worse = [(a, b) for a, b in pairs if adaptation_worse(a, b)]
    most = max(pairs, key=lambda p: p[1].true - p[0].true)
    qualifies = med_on <= med_off and not worse
    return (f"adaptation: median true RMS {med_off * 1e3:.4f} -> {med_on * 1e3:.4f} mm (est "
            f"{statistics.median(a.est for a, _ in pairs) * 1e3:.4f} -> {statistics.median(b.est for _, b in pairs) * 1e3:.4f}"
            f" mm); better on {sum(b.true < a.true for a, b in pairs)} of {len(pairs)}; runs worse on the true pose by "
            f"more than {rel:.0%} or {absm * 1e3:g} mm, whichever is larger: {len(worse)}; the most worse: "
            f"{most[0].robot} {most[0].path} {most[0].true * 1e3:.3f} -> {most[1].true * 1e3:.3f} mm "
            f"(the rule for on by default: median no worse and none worse): "
            f"**{'qualifies' if qualifies else 'does not qualify'}**"
            + (" (" + "; ".join(f"{a.robot} {a.path} {a.true * 1e3:.3f} -> {b.true * 1e3:.3f} mm"
                                for a, b in worse[:8]) + ")" if worse else "") + ".")


def rerun(robot: str, path: str, sim_seeds: Sequence[int], harsh: bool = False) -> dict[str, list[Run]]:
    """One robot's run on `path` with adaptation off and on, at each of `sim_seeds`: how much of
    a difference between the two is the plant's noise (the campaign runs each once)."""
    drawn = {r.name: r for r in population(ROBOTS)}
    if robot not in drawn or path not in PATHS:
        raise ValueError(f"--rerun: expected ROBOT/PATH with ROBOT r00..r{ROBOTS - 1:02d} and PATH of "
                         f"{', '.join(PATHS)}, got {robot}/{path}")
    from ddrt.path.spec import resolve_path
    from ddrt.simrun.runner import run_sim

    out: dict[str, list[Run]] = {}
    for variant in ("dynamic", "dynamic+adapt"):
        runs = []
        for seed in sim_seeds:
            cfg = config_of(drawn[robot], path, variant)
            cfg = dataclasses.replace(cfg, sim=dataclasses.replace(cfg.sim, seed=seed))
            if harsh:
                keys = harsh_sections(robot)
                sim = dataclasses.replace(cfg.sim, gyro=dataclasses.replace(cfg.sim.gyro, **keys["sim"]["gyro"]),
                                          actuators=ActuatorTruth(**keys["sim"]["actuators"]))
                cfg = dataclasses.replace(cfg, sim=sim, sensors=dataclasses.replace(cfg.sensors, **keys["sensors"]))
            m = run_sim(cfg, resolve_path(cfg)).metrics
            runs.append(Run(robot, path, variant, float(m["rms_tracking_m"]), float(m["rms_cross_track_m"]),
                            float(m["saturated_fraction"]), bool(m["completed"]), str(m.get("fault") or ""),
                            float(m["sim_duration_s"]), 0))
        out[variant] = runs
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
        f"{len(res.robots)} robots from a fixed-seed generator (`ddrt/sweep/population.py`, seed {SEED}; "
        "`bench/population.py` runs them as the campaign bench/campaigns/population.yaml): "
        f"{min(masses):.1f}-{max(masses):.1f} kg, {min(volts):.1f}-{max(volts):.1f} V motors, different wheels, "
        "tracks and inertias consistent with mass and size, a few percent between belief (`robot:`) and truth "
        "(`plant:`), 0.5-3 ms latency; each given as its `robot:` section with every other key at default "
        f"(so the speed profile derives its limits from the motors). The figure-eight and the rectangle at 50-90 % "
        f"of each robot's no-load speed; {len(res.runs)} runs on the simulated robot, {res.wall_s:.0f} s wall. "
        f"pass = completed with est RMS <= {EST_TARGET_M * 1e3:g} mm and true RMS <= {TRUE_TARGET_M * 1e3:g} mm."
        + (" **Harsh**: each robot with cheap parts on the realistic plant (`--harsh`: gyro scale 2-3 % off, "
           "bias up to 5 deg/s, 400-1024 count encoder, 2-5 % deadband, 0.5-2 degrees backlash)." if res.harsh else ""),
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
    ap.add_argument("--harsh", action="store_true", help="cheap parts on the realistic plant (module doc)")
    ap.add_argument("--rerun", metavar="ROBOT/PATH", help="only this run, adaptation off and on, at --sim-seeds")
    ap.add_argument("--sim-seeds", default="1,2,3", help="with --rerun: comma-separated sim.seed values")
    args = ap.parse_args(argv)
    if args.rerun:
        robot, _, path = args.rerun.partition("/")
        seeds = [int(v) for v in args.sim_seeds.split(",") if v]
        for variant, runs in rerun(robot, path, seeds, args.harsh).items():
            print(f"{args.rerun}{' (harsh)' if args.harsh else ''} {variant}: true / est RMS (mm) at sim seeds "
                  f"{', '.join(map(str, seeds))}: " + "; ".join(f"{r.true * 1e3:.3f} / {r.est * 1e3:.4f}" for r in runs))
        return 0
    variants = tuple(v for v in args.variants.split(",") if v)
    res = measure_population(args.robots, args.workers, variants, harsh=args.harsh)
    print("\n".join(render(res)))
    if args.json:
        import json

        with open(args.json, "w", encoding="utf-8") as fh:
            json.dump([dict(vars(r)) for r in res.runs.values()], fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
