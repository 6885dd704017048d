"""`ddrt commission` measured: wiring faults found and fixed, and a harsh population
commissioned from ruler-and-datasheet configs.

`python -m bench.commissioning [--robots 20] [--workers 2] [--only wiring|population]
[--sensors front|wheels] [--mismatch 0.15] [--seed N] [--no-uncommissioned] [--json FILE]`
prints Markdown for docs/BENCHMARKS.md (and each robot's line on stderr as it finishes).

Wiring: configs/sim.yaml with each `sim.wiring` fault; the figure-eight (configs/sim.yaml's
path) driven with the uncommissioned config, then `ddrt commission --from-sim-truth --yes`, the
`hal.wiring` it wrote compared with the fix the fault needs, and the figure-eight driven again
with the commissioned config.

Population: the first `--robots` robots of ddrt/sweep/population.py (bench section 10's), made
harsh: section 10's `--harsh` cheap parts on the realistic plant (gyro scale 2-3 % off either
way, bias up to 5 deg/s, a 400-1024 count front encoder, 2-5 % deadband, 0.5-2 degrees of
backlash) and the encoder wheel's radius U(-2, +2) % off the nominal one. Each robot's config holds its `robot:`
belief as the generator gives it (nominal wheel radii and track, masses and inertias a few
percent off, the motor's datasheet values) and nothing calibrated (gyro_scale 1). Each is
driven on section 10's two paths at its speed, uncommissioned; then commissioned with
`--from-sim-truth` and the default measurement noise (2 mm, 0.5 deg) and driven again.
pass = completed, estimate RMS <= 1 mm, true RMS <= 5 mm (section 10's criterion).

`--mismatch X`: the truth's masses, inertias and motor constants each U(-X, +X) off the config's
belief and the platform's centre of mass X H off along x (`mismatched`): a model the ruler, the
scale and the datasheet got that wrong, which the dynamics step must identify; with it the
median target is 3 mm and the table counts the robots whose identified split was held physical
(ddrt/core/split.py). `--seed N` draws another population (robots, cheap parts, radii and
mismatch all from N), reproducibly; without it the robots are section 10's.

`--sensors wheels`: the same robots built the common way, without a front encoder: the drive
wheels counted at 1440 a turn and each wheel's radius U(-2, +2) % off the nominal one (which
the odometry step then scales, ddrt/calibrate.py's distance_radii).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import random
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from bench.common import REPO, SIM_CONFIG, pooled_by_key
from ddrt.config import config_from_mapping, load_config
from ddrt.config.load import merge_mappings

FAULTS = {  # sim.wiring key -> the hal.wiring that fixes it
    "left_motor_reversed": {"motor_left_inverted": True},
    "right_motor_reversed": {"motor_right_inverted": True},
    "motors_swapped": {"motors_swapped": True},
    "encoder_reversed": {"encoder_sign": -1},
    "gyro_upside_down": {"gyro_sign": -1},
}
IDENTITY = {"motor_left_inverted": False, "motor_right_inverted": False, "motors_swapped": False,
            "encoder_sign": 1, "gyro_sign": 1}
HARSH_SEED = 2020
ROBOTS = 20
EST_TARGET_M, TRUE_TARGET_M, MEDIAN_TARGET_M = 1e-3, 5e-3, 2e-3
MISMATCH_MEDIAN_TARGET_M = 3e-3  # with the model 15 % off, the true RMS median asked for


def _commission(config_file: Path, out: Path) -> tuple[Any, float]:
    """Commission `config_file` on the simulator from its truth; (outcome, wall seconds)."""
    from ddrt.commission import commission, session_for
    from ddrt.commission.session import Options

    t0 = time.perf_counter()
    opts = Options(out=out, from_sim_truth=True, figures=False)
    session = session_for(config_file, opts, yes=True, out=io.StringIO())
    outcome = commission(session)
    return outcome, time.perf_counter() - t0


def _drive(data: dict[str, Any], source: str) -> dict[str, Any]:
    """One simulated run of the config mapping's path; the metrics (a fault is a result)."""
    from ddrt.path.spec import resolve_path
    from ddrt.simrun.runner import run_sim

    cfg = config_from_mapping(data, source=source, base_dir=str(REPO / "configs"))
    try:
        return run_sim(cfg, resolve_path(cfg, None)).metrics
    except Exception as exc:  # a run that cannot even start is a failed run, named
        return {"completed": False, "fault": f"{type(exc).__name__}: {exc}", "rms_tracking_m": float("nan"),
                "rms_cross_track_m": float("nan")}


# --------------------------------------------------------------------------- wiring


def wiring_case(fault: str) -> tuple[Any, ...]:
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / f"{fault}.yaml"
        src.write_text(yaml.safe_dump({"extends": str(SIM_CONFIG), "sim": {"wiring": {fault: True}}}))
        before = _drive(load_config(src).raw, "uncommissioned")
        outcome, wall = _commission(src, Path(tmp) / "out" / "robot.yaml")
        written = load_config(outcome.config_file)
        found = {k: getattr(written.hal.wiring, k) for k in IDENTITY}
        after = _drive(written.raw, "commissioned")
    return (fault, found == dict(IDENTITY, **FAULTS[fault]), found, before, after, wall)


def _short(fault: Any) -> str:
    """A fault's first clause (the path-error stop's message goes on to name the limit)."""
    return str(fault).split(", ")[0]


def render_wiring(rows: list[tuple[Any, ...]]) -> list[str]:
    lines = ["| fault (`sim.wiring`) | before: figure-eight | fix written (`hal.wiring`) | right fix | "
             "after: figure-eight | est / true RMS after (mm) | commission wall (s) |",
             "|---|---|---|---|---|---|---|"]
    for fault, ok, found, before, after, wall in rows:
        changed = ", ".join(f"{k}: {v}" for k, v in found.items() if IDENTITY[k] != v) or "none"
        b = "completed" if before["completed"] else f"failed ({_short(before.get('fault') or before.get('state'))})"
        a = "completed" if after["completed"] else f"failed ({_short(after.get('fault') or after.get('state'))})"
        lines.append(f"| {fault} | {b} | {changed} | {'yes' if ok else 'NO'} | {a} | "
                     f"{after['rms_tracking_m'] * 1e3:.3f} / {after['rms_cross_track_m'] * 1e3:.3f} | {wall:.1f} |")
    return lines


# --------------------------------------------------------------------------- population


WHEEL_CPR = 1440


MASS_KEYS = ("m_p", "m_L", "m_R", "m_3", "I_p", "I_L", "I_R", "I_3", "I_wL", "I_wR", "I_w3")
MOTOR_KEYS = ("resistance_ohm", "k_nm_per_a", "viscous_nms", "coulomb_nm")


def mismatched(sec: dict[str, Any], plant: dict[str, Any], mismatch: float, rng: random.Random) -> dict[str, Any]:
    """`plant` with every mass, inertia and motor constant U(-mismatch, +mismatch) off the belief
    (`robot:`) and the platform's centre of mass U(-mismatch, +mismatch) x H off it along x: a
    model the ruler, the scale and the datasheet got that far wrong."""
    robot = sec["robot"]
    out = dict(plant)
    for key in MASS_KEYS:
        out[key] = robot[key] * (1.0 + rng.uniform(-mismatch, mismatch))
    out["d_xc"] = robot["d_xc"] + rng.uniform(-mismatch, mismatch) * robot["H"]
    for side in ("motor_l", "motor_r"):
        out[side] = {key: robot["motor"][key] * (1.0 + rng.uniform(-mismatch, mismatch)) for key in MOTOR_KEYS}
    return out


def harsh_robots(n: int, sensors: str = "front", mismatch: float = 0.0,
                 seed: int | None = None) -> list[tuple[str, dict[str, Any], float]]:
    """(name, config mapping without a path, path speed) of the first `n` harsh robots: section
    10's `--harsh` cheap parts (bench/population.py's harsh_sections) and an encoder wheel whose
    radius is U(-2, +2) % off the nominal one the config believes; with `sensors` "wheels" no
    front encoder and each drive wheel's radius U(-2, +2) % off instead. `mismatch` > 0 puts
    the truth's masses, inertias and motors that far off the belief (`mismatched`). `seed`
    draws another population (the generator's and the radii's seeds), None the default one."""
    from bench.population import harsh_sections
    from ddrt.sweep.population import SEED, population

    rng = random.Random(HARSH_SEED if seed is None else f"{HARSH_SEED}/{seed}")
    out = []
    for robot in population(n, SEED if seed is None else seed):
        sec = robot.sections
        cheap = harsh_sections(robot.name if seed is None else f"{seed}/{robot.name}")
        plant = dict(sec["plant"])
        plant["r_3"] = sec["robot"]["r_3"] * (1.0 + rng.uniform(-0.02, 0.02))
        if mismatch > 0.0:
            plant = mismatched(sec, plant, mismatch, random.Random(f"mismatch/{seed}/{robot.name}"))
        sensed = dict(cheap["sensors"])
        if sensors == "wheels":
            plant["r_3"] = sec["plant"]["r_3"]
            plant["r_L"], plant["r_R"] = (sec["robot"][k] * (1.0 + rng.uniform(-0.02, 0.02)) for k in ("r_L", "r_R"))
            sensed.update(encoder_counts_per_rev=0, wheel_counts_per_rev=WHEEL_CPR)
        data = {"name": f"harsh {robot.name}", "robot": sec["robot"], "plant": plant,
                "sim": merge_mappings(sec["sim"], cheap["sim"]), "sensors": sensed,
                "daemon": {"socket": None}}
        out.append((robot.name, data, robot.path_speed))
    return out


def _paths() -> dict[str, dict[str, Any]]:
    from bench.population import PATHS

    return PATHS


def population_case(job: tuple[str, dict[str, Any], float, bool]) -> tuple[Any, ...]:
    """One robot: its paths uncommissioned (when the job's last item says so), commissioned,
    its paths with the config written; (name, refusal or "", runs, wall, odometry errors,
    the dynamics step's constrained parameters)."""
    name, data, speed, before = job
    runs: dict[str, dict[str, Any]] = {}
    if before:
        for p, spec in _paths().items():
            runs[f"before/{p}"] = _drive(dict(data, path=dict(spec, speed=speed)), f"{name} uncommissioned")
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp) / f"{name}.yaml"
        src.write_text(yaml.safe_dump(data, sort_keys=False))
        try:
            outcome, wall = _commission(src, Path(tmp) / "out" / f"{name}.yaml")
        except ValueError as exc:
            return (name, f"commissioning refused: {exc}", runs, 0.0, {}, [])
        except Exception as exc:  # a crash is a result too: named, and the other robots go on
            return (name, f"commissioning crashed: {type(exc).__name__}: {exc}", runs, 0.0, {}, [])
        written = yaml.safe_load(outcome.config_file.read_text())
        state = yaml.safe_load(Path(tmp, "out", f"{name}.state.json").read_text())
    for p, spec in _paths().items():
        runs[f"after/{p}"] = _drive(dict(written, path=dict(spec, speed=speed)), f"{name} commissioned")
    o = state["steps"]["odometry"]
    true_radius = sum(data["plant"][k] for k in o["radii"])  # r_3, or the drive wheels' sum
    scale = 1.0 + data["sim"]["gyro"]["scale_error"]
    errs = {"r_err": sum(o["radii"].values()) / true_radius - 1.0, "scale_err": o["gyro_scale"] / scale - 1.0,
            "r_before": sum(o["radii_before"].values()) / true_radius - 1.0,
            "scale_before": o["gyro_scale_before"] / scale - 1.0, "radii": "/".join(o["radii"])}
    constrained = [c["name"] for c in state["steps"]["dynamics"].get("constrained", [])]
    return (name, "", runs, wall, errs, constrained)


def _passes(m: dict[str, Any]) -> bool:
    return bool(m["completed"]) and m["rms_tracking_m"] <= EST_TARGET_M and m["rms_cross_track_m"] <= TRUE_TARGET_M


def _cell(runs: list[dict[str, Any]]) -> str:
    est = [r["rms_tracking_m"] * 1e3 for r in runs]
    true = [r["rms_cross_track_m"] * 1e3 for r in runs]
    return (f"{sum(_passes(r) for r in runs)}/{len(runs)} | {sum(bool(r['completed']) for r in runs)}/{len(runs)} | "
            f"{statistics.median(est):.3f} / {max(est):.3f} | {statistics.median(true):.3f} / {max(true):.3f}")


def render_population(rows: list[tuple[Any, ...]], wall_s: float,
                      median_target_m: float = MEDIAN_TARGET_M) -> list[str]:
    refused = [(r[0], r[1]) for r in rows if r[1]]
    ok = [r for r in rows if not r[1]]
    before = [m for r in rows for k, m in r[2].items() if k.startswith("before/")]
    after = [m for r in ok for k, m in r[2].items() if k.startswith("after/")]
    lines = [f"{len(rows)} harsh robots x {len(_paths())} paths, {wall_s:.0f} s wall. pass = completed, est RMS <= "
             f"{EST_TARGET_M * 1e3:g} mm, true RMS <= {TRUE_TARGET_M * 1e3:g} mm.", "",
             "| config | pass | completed | est RMS median / worst (mm) | true RMS median / worst (mm) |",
             "|---|---|---|---|---|"]
    if before:
        lines.append(f"| as drawn (ruler, scale, datasheet) | {_cell(before)} |")
    if after:
        lines.append(f"| commissioned (`--from-sim-truth`, 2 mm / 0.5 deg noise) | {_cell(after)} |")
        med = statistics.median(m["rms_cross_track_m"] for m in after)
        n_pass = sum(_passes(m) for m in after)
        total = len(rows) * len(_paths())
        lines += ["", f"Targets: true RMS median {med * 1e3:.3f} mm (target <= {median_target_m * 1e3:g} mm): "
                  f"**{'MET' if med <= median_target_m else 'NOT MET'}**; {n_pass} of {total} pass (target all): "
                  f"**{'MET' if n_pass == total else 'NOT MET'}**; {len(ok)} of {len(rows)} robots commissioned "
                  f"(target all): **{'MET' if not refused else 'NOT MET'}**."]
        constrained = [(r[0], r[5]) for r in ok if r[5]]
        lines += ["", f"Dynamics fits constrained to a physical split: {len(constrained)} of {len(ok)} robots"
                  + (" (" + "; ".join(f"{n}: {', '.join(c)}" for n, c in constrained) + ")" if constrained else "")
                  + "."]
        r3 = [abs(r[4]["r_err"]) * 100 for r in ok]
        sc = [abs(r[4]["scale_err"]) * 100 for r in ok]
        r3b = [abs(r[4]["r_before"]) * 100 for r in ok]
        scb = [abs(r[4]["scale_before"]) * 100 for r in ok]
        radii = " and ".join(sorted({r[4]["radii"] for r in ok}))
        lines += ["", f"Odometry against the truth, |error| median / worst: {radii} {statistics.median(r3b):.2f} / "
                  f"{max(r3b):.2f} % before, {statistics.median(r3):.3f} / {max(r3):.3f} % after; gyro scale "
                  f"{statistics.median(scb):.2f} / {max(scb):.2f} % before, {statistics.median(sc):.3f} / "
                  f"{max(sc):.3f} % after. Commissioning one robot took {statistics.median(r[3] for r in ok):.1f} s "
                  "wall (median)."]
        failed = [(r[0], k, m) for r in ok for k, m in r[2].items() if k.startswith("after/") and not _passes(m)]
        if failed:
            lines += ["", "Commissioned runs that missed: " + "; ".join(
                f"{n} {k[6:]} est {m['rms_tracking_m'] * 1e3:.3f} true {m['rms_cross_track_m'] * 1e3:.3f} mm"
                + ("" if m["completed"] else f" ({m.get('fault') or 'not completed'})") for n, k, m in failed) + "."]
    if refused:
        lines += ["", "Commissioning refused: " + "; ".join(f"{n}: {e}" for n, e in refused) + "."]
    return lines


@dataclass
class CommissioningResult:
    wiring: list[tuple[Any, ...]] | None
    wiring_wall_s: float
    population: list[tuple[Any, ...]] | None
    population_wall_s: float
    sensors: str = "front"
    mismatch: float = 0.0
    seed: int | None = None


def _progress(row: tuple[Any, ...]) -> None:
    """One robot's line on stderr as it finishes (a long population run shows where it is)."""
    after = [m for k, m in row[2].items() if k.startswith("after/")]
    print(f"{row[0]}: {row[1] or 'commissioned'}; " + ", ".join(
        f"{k} {'pass' if _passes(m) else 'MISS'} true {m['rms_cross_track_m'] * 1e3:.2f} mm"
        for k, m in row[2].items() if k.startswith("after/")) + (f"; constrained {row[5]}" if row[5] else ""),
        file=sys.stderr, flush=True) if after or row[1] else None


def _population_case_logged(job: tuple[str, dict[str, Any], float, bool]) -> tuple[Any, ...]:
    row = population_case(job)
    _progress(row)
    return row


def measure(robots: int = ROBOTS, workers: int = 2, only: str | None = None,
            sensors: str = "front", mismatch: float = 0.0, seed: int | None = None,
            before: bool = True) -> CommissioningResult:
    res = CommissioningResult(None, 0.0, None, 0.0, sensors, mismatch, seed)
    if only in (None, "wiring"):
        t0 = time.perf_counter()
        acc = pooled_by_key(wiring_case, list(FAULTS), workers)
        res.wiring = [(k, *acc[k][0]) for k in FAULTS]
        res.wiring_wall_s = time.perf_counter() - t0
    if only in (None, "population"):
        t0 = time.perf_counter()
        jobs = [(*job, before) for job in harsh_robots(robots, sensors, mismatch, seed)]
        acc = pooled_by_key(_population_case_logged, jobs, workers)
        res.population = [(job[0], *acc[job[0]][0]) for job in jobs]
        res.population_wall_s = time.perf_counter() - t0
    return res


def render(res: CommissioningResult) -> list[str]:
    out = ["`ddrt commission` on the simulator (bench/commissioning.py; `python -m bench.commissioning` prints this "
           "section). Every commissioning takes its measurements with `--from-sim-truth` at the default noise (a tape "
           "read to 2 mm, a protractor to 0.5 deg, one sigma) and `--yes`.", ""]
    if res.wiring is not None:
        out += ["### Wiring faults", "",
                "configs/sim.yaml with one `sim.wiring` fault each: its figure-eight (the config's path) driven as is, "
                "then commissioned, then driven with the config written.", ""]
        out += render_wiring(res.wiring) + ["", f"({res.wiring_wall_s:.0f} s wall.)", ""]
    if res.population is not None and res.sensors == "wheels":
        out += ["### Harsh population without a front encoder, commissioned", "",
                "The robots below built the common way: no front encoder, the drive wheels counted at "
                f"{WHEEL_CPR} a turn, each drive wheel's radius U(-2, +2) % off nominal (seed {HARSH_SEED}); "
                "otherwise the harsh population's cheap parts (gyro scale 2-3 % off either way, bias up to 5 deg/s, "
                "2-5 % deadband, 0.5-2 degrees of backlash) and beliefs. The odometry step scales r_L and r_R "
                "together by the tape and writes the difference between them the estimator learnt on the "
                "straight.", ""]
        out += render_population(res.population, res.population_wall_s)
    elif res.population is not None and (res.mismatch > 0.0 or res.seed is not None):
        out += ["### Harsh population with a mismatched model, commissioned", "",
                f"{len(res.population)} robots of section 10's generator (seed "
                f"{'the default' if res.seed is None else res.seed}), with the harsh population's cheap parts (gyro "
                "scale 2-3 % off either way, bias up to 5 deg/s, a 400-1024 count front encoder, 2-5 % deadband, "
                "0.5-2 degrees of backlash), the encoder wheel's radius U(-2, +2) % off nominal, and the truth's "
                f"masses, inertias and motor constants each U(-{res.mismatch:.0%}, +{res.mismatch:.0%}) off the "
                f"config's belief (the platform's centre of mass {res.mismatch:.0%} of H along x). Commissioned with "
                "`--from-sim-truth`, then section 10's two paths at each robot's speed.", ""]
        out += render_population(res.population, res.population_wall_s, MISMATCH_MEDIAN_TARGET_M)
    elif res.population is not None:
        out += ["### Harsh population, commissioned", "",
                "The first robots of section 10's generator, made harsh: section 10's `--harsh` cheap parts on the "
                "realistic plant (gyro scale 2-3 % off either way, bias up to 5 deg/s, a 400-1024 count front "
                "encoder, 2-5 % deadband, 0.5-2 degrees of backlash) and the encoder wheel's radius U(-2, +2) % off "
                f"nominal (seed {HARSH_SEED}). Each config "
                "is the generator's `robot:` belief (nominal radii and track, masses and inertias a few percent "
                "off, the motor's datasheet values) with nothing calibrated. Section 10's two paths at each robot's "
                "speed.", ""]
        out += render_population(res.population, res.population_wall_s)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=(__doc__ or "").split("\n")[0])
    ap.add_argument("--robots", type=int, default=ROBOTS)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--only", choices=("wiring", "population"))
    ap.add_argument("--sensors", choices=("front", "wheels"), default="front",
                    help="the population's distance sensor: the front encoder, or the drive wheels' only")
    ap.add_argument("--mismatch", type=float, default=0.0,
                    help="the truth's masses, inertias and motor constants U(-x, +x) off the belief (0.15: 15 %%)")
    ap.add_argument("--seed", type=int, default=None,
                    help="draw another population of robots (default: section 10's generator seed)")
    ap.add_argument("--no-uncommissioned", action="store_true",
                    help="skip driving each robot before it is commissioned (halves a population's time)")
    ap.add_argument("--json", help="also write each robot's results to this file")
    args = ap.parse_args(argv)
    if args.robots < 1:
        ap.error(f"--robots: expected at least 1, got {args.robots}")
    if not 0.0 <= args.mismatch < 0.5:
        ap.error(f"--mismatch: expected a fraction in [0, 0.5), got {args.mismatch}")
    res = measure(args.robots, args.workers, args.only, args.sensors, args.mismatch, args.seed,
                  not args.no_uncommissioned)
    text = "\n".join(render(res))
    if args.json and res.population is not None:
        import json

        Path(args.json).write_text(json.dumps(
            [{"robot": r[0], "refused": r[1], "runs": r[2], "wall_s": r[3], "odometry": r[4], "constrained": r[5]}
             for r in res.population], indent=1, default=str), encoding="utf-8")
    with contextlib.suppress(BrokenPipeError):
        print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
