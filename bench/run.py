"""`python -m bench.run [--quick] [--out docs/BENCHMARKS.md] [--only N]`: regenerate the benchmark report.

One command measures everything and writes the Markdown; nobody edits BENCHMARKS.md by hand,
so every number in it can be traced to a run on the machine it names. The timing sections run
one after another on an otherwise idle process; only the accuracy grid uses a process pool.

Sections 14 to 26 (OWN_COMMAND) are measured by commands of their own; the full run keeps
their text from the file it replaces.

The report is grouped by capability (CAPABILITIES: a `# ` heading each); a section keeps its
number, which `--only N` and other documents use to name it, wherever its group puts it.
Each section opens with its headline (a line starting `**Headline`), written by whoever
measured it: a regenerated section keeps the headline of the file it replaces, so that a
reader gets the figure first; update it when the figures under it change.

`--only N` measures section N alone (those in ONLY: 1, 4, 9, 10, 11, 12, 13) and splices it into the --out file:
the section's text from its `## N.` heading to the next heading of level 1 or 2 is replaced
(or, when the file has no such section, inserted after the last section that precedes it in
DOC_ORDER); every other line of the file stays as it was. The spliced section says that it
was measured alone, with its command, date and load average, since the file's header names
the full run.
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import os
import platform
import shlex
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path as FsPath
from typing import Callable, Sequence

import numpy as np

from bench import commissioning
from bench import (accuracy, adaptation, battery, ctl_flood, foxglove_load, io_bound, loop_timing, paths_as_given,
                   population, sim_scaling, startup, tick_cost, velocity_mode)
from bench.common import REPO, SIM_CONFIG
from ddrt.config import load_config

SCENARIO_DIR = REPO / "configs" / "scenarios"

SECTIONS = (
    "Machine",
    "1. Accuracy",
    "2. Tick cost",
    "3. Loop timing",
    "4. Simulation speed",
    "5. Start-up and memory",
    "6. The physical bound",
    "7. Adaptive dynamics and calibration",
    "8. The control socket under abuse",
    "9. Paths as people hand them over",
    "10. A population of robots",
    "11. Foxglove live view, MCAP and the velocity mode",
    "12. The supply voltage measured",
    "13. Commissioning",
    "14. The ROS 2 bridge under flood",
    "15. The estimate's uncertainty and pose fixes",
    "16. Wheel encoders in the estimator",
    "17. Battery sag and gyro warm-up",
    "18. Sweep throughput",
    "19. Adaptation on by default?",
    "20. A reload beside the loop",
    "21. A gyro that stops answering",
    "22. Grid plans: time against length over speed",
    "23. A warming gyro with the shipped config",
    "24. Adaptation on by default, judged on the true pose",
    "25. Commissioning across a population of harsh robots",
    "26. The daemon's memory over many commands",
)

# What a reader wants to know, in the report's order: each group's sections by number.
CAPABILITIES: tuple[tuple[str, tuple[int, ...]], ...] = (
    ("Tracking accuracy", (1, 7, 19, 24)),
    ("Robots and paths", (9, 10, 13, 25, 22)),
    ("Sensing and estimation", (15, 16, 12, 17, 21, 23)),
    ("Timing and load", (2, 3, 6, 5, 11, 20, 26)),
    ("Simulation speed", (4, 18)),
    ("The daemon under abuse", (8, 14)),
)
DOC_ORDER: tuple[int, ...] = (0,) + tuple(n for _, group in CAPABILITIES for n in group)
HEADLINE = "**Headline"

# Sections measured by a command of their own (long, or needing extras and a quiet machine);
# a full run carries their text over from the file it replaces, and names the command where
# the file has none.
OWN_COMMAND: dict[int, str] = {
    14: "python -m bench.ros2_flood --duration 60",
    15: "python -m bench.uncertainty",
    16: "python -m bench.wheel_encoders --robots 5 --workers 1",
    17: "python -m bench.battery_sag and python -m bench.gyro_warmup",
    18: "python -m bench.sweep_throughput --runs 1000 --workers 2 --duration 5",
    19: "ddrt sweep configs/campaigns/adaptation_population.yaml, python -m bench.population "
        "--variants dynamic,dynamic+adapt [--harsh] and python -m bench.adaptation",
    20: "python -m bench.reload_stall --reloads 40 --repo OLDER_CHECKOUT --repo .",
    21: "python -m bench.gyro_faults and python -m bench.gyro_faults --before",
    22: "python -m bench.grid_plans --closed-loop 15 and python -m bench.run --only 9",
    23: "python -m bench.gyro_warmup --shipped",
    24: "python -m bench.population --workers 1 --variants dynamic,dynamic+adapt [--harsh]",
    25: "python -m bench.commissioning --only population --robots 100 --mismatch 0.15 --workers 1 --no-uncommissioned",
    26: "python -m bench.soak --cycles 1000 --every 10 [--ros2] [--foxglove]",
}


@dataclass(frozen=True)
class BenchOptions:
    """How much to measure. FULL is the documented run; QUICK a smoke run of every section."""

    seeds: tuple[int, ...] = (1, 2, 3)
    lookaheads: tuple[float, ...] = accuracy.LOOKAHEADS_M
    scenarios: tuple[str, ...] | None = None  # None: every file in configs/scenarios/
    workers: int = 2
    ticks: int = 100_000
    loop_rates: tuple[float, ...] = loop_timing.RATES_HZ
    loop_duration_s: float = 30.0
    speed_cases: tuple[tuple[str, str, int | None, float | None], ...] = sim_scaling.CASES  # section 4
    speed_repeats: int = 3  # runs of each `ddrt sim` case in section 4 (their median)
    import_modules: tuple[str, ...] = startup.MODULES
    import_repeats: int = 3
    sim_rss_duration_s: float | None = None
    ctl_counts: tuple[int, ...] = ctl_flood.COUNTS
    ctl_estops: int = ctl_flood.ESTOPS
    paths_cases: tuple[str, ...] | None = None  # None: every case of bench/paths_as_given.py
    paths_long: tuple[int, ...] = (10_000, 100_000)  # points of the long recordings timed
    robots: int = population.ROBOTS
    foxglove_duration_s: float = 60.0  # each daemon run, off and on: 60 s at 200 Hz
    mcap_duration_s: float | None = None  # `ddrt sim` on the scenario, None: to the path's end
    mcap_repeats: int = 2


FULL = BenchOptions()
QUICK = BenchOptions(seeds=(1,), speed_repeats=1, ticks=20_000, loop_duration_s=5.0, robots=4, foxglove_duration_s=4.0,
                     mcap_duration_s=3.0, mcap_repeats=1)


@dataclass
class Results:
    options: BenchOptions
    command: str
    machine: dict[str, str]
    accuracy: accuracy.AccuracyResult
    ticks: tick_cost.TickCost
    loop: loop_timing.LoopTiming
    speed: list[sim_scaling.CaseResult]  # `ddrt sim` on one core, per case (bench/sim_scaling.py)
    startup: startup.Startup
    bound: io_bound.IoBound
    adapt: adaptation.AdaptationResult
    ctl: list[ctl_flood.FloodRow] = field(default_factory=list)
    paths: paths_as_given.PathsResult | None = None
    robots: population.PopulationResult | None = None
    live: "LiveView | None" = None
    supply: battery.BatteryResult | None = None
    commissioning: commissioning.CommissioningResult | None = None
    wall_s: dict[str, float] = field(default_factory=dict)


@dataclass
class LiveView:
    """Section 11: foxglove_load's section (None with why, without foxglove-sdk) and the velocity mode."""

    foxglove: dict | None
    missing: str
    velocity: velocity_mode.VelocityMode


# --------------------------------------------------------------------------- machine


def cpu_model() -> str:
    try:
        for line in FsPath("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def load_average() -> str:
    load = os.getloadavg() if hasattr(os, "getloadavg") else (float("nan"),) * 3
    return " ".join(f"{x:.2f}" for x in load)


def machine_info() -> dict[str, str]:
    return {
        "CPU": cpu_model(),
        "cores": f"{os.cpu_count()} (usable by this process: {len(os.sched_getaffinity(0))})",
        "OS": f"{platform.system()} {platform.release()} ({platform.machine()})",
        "Python": f"{platform.python_implementation()} {platform.python_version()}",
        "numpy": np.__version__,
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "load average at start": load_average(),
    }


# --------------------------------------------------------------------------- measuring


def foxglove_missing() -> str:
    """Why section 11's Foxglove part cannot run here ('' when it can)."""
    import importlib.util

    gone = [m for m in ("foxglove", "websockets") if importlib.util.find_spec(m) is None]
    return f"not installed: {', '.join(gone)} (pip install 'ddrt[foxglove]' websockets)" if gone else ""


def measure_paths(opts: BenchOptions) -> object:
    return paths_as_given.measure(opts.paths_cases, opts.seeds[0], opts.paths_long)


def measure_live(opts: BenchOptions) -> LiveView:
    missing = foxglove_missing()
    fx = None if missing else foxglove_load.section(opts.foxglove_duration_s, opts.mcap_duration_s, opts.mcap_repeats)
    return LiveView(fx, missing, velocity_mode.measure(load_config(SIM_CONFIG), min(opts.ticks, 100_000)))


def render_live(live: LiveView) -> list[str]:
    lines = foxglove_load.render_section(live.foxglove) if live.foxglove else [f"Foxglove not measured: {live.missing}."]
    return lines + ["", "### The velocity mode", ""] + velocity_mode.render(live.velocity)


@dataclass
class AccuracySection:
    """Section 1: the accuracy grid and how many worker processes ran it."""

    accuracy: accuracy.AccuracyResult
    workers: int


def measure_accuracy_section(opts: BenchOptions) -> AccuracySection:
    acc = accuracy.measure_accuracy(SCENARIO_DIR, opts.seeds, opts.lookaheads, opts.workers, opts.scenarios,
                                    accuracy.stderr_progress)
    return AccuracySection(acc, opts.workers)


def render_accuracy(section: AccuracySection) -> list[str]:
    acc = section.accuracy
    lines = [
        f"Every scenario in configs/scenarios/ ({len(acc.scenarios)}) with three controllers on the same simulated "
        f"robot, sensors and noise seeds ({', '.join(map(str, acc.seeds))}): **dynamic** (the three-stage "
        f"controller), **kinematic** (pure pursuit + wheel-speed PID) at its best single lookahead, "
        f"{acc.best.lookahead_m:.2f} m, from the sweep below, and **seed** (the seed report's own method, "
        f"with limits.max_path_error_m widened to {accuracy.SEED_MAX_PATH_ERROR_M:g} m so its error is measured "
        "rather than stopped). "
        "true = cross-track error of the true pose, est = of the estimated pose (what the controller can "
        "correct, and what it is judged by). Cells are the median over seeds with the min–max spread in "
        "brackets when the seeds differ; time is the simulated time to complete (or to the fault or the time "
        f"limit of 1.5 x path duration + 10 s); {acc.runs} runs on {section.workers} worker processes, "
        f"{acc.wall_s:.0f} s wall.",
        "",
    ]
    lines += accuracy.render_table(acc)
    lines += [
        "",
        "### Kinematic lookahead sweep",
        "",
        "Median est-pose RMS cross-track (mm) over the seeds, per lookahead. The kept lookahead is the one "
        "whose worst scenario is best, among those with the fewest scenarios that failed to complete (a run "
        "that faults early has a small RMS over a short stretch, which must not win).",
        "",
    ]
    lines += accuracy.render_sweep(acc)
    lines += ["", f"Kept: **{acc.best.lookahead_m:.2f} m**.", "", "### Verdict", ""]
    lines += [f"- {v}" for v in acc.verdict]
    return lines


def measure_population_section(opts: BenchOptions) -> object:
    return population.measure_population(opts.robots, opts.workers)


def measure_commissioning(opts: BenchOptions) -> object:
    """Section 13: as many harsh robots as section 10 has (at most bench/commissioning.py's 20)."""
    return commissioning.measure(min(opts.robots, commissioning.ROBOTS), opts.workers)


def measure_speed_section(opts: BenchOptions) -> list[sim_scaling.CaseResult]:
    """`ddrt sim` on the figure-eight at 20 s and 300 s and on seed_square (`speed_cases`), each in
    a child process (bench/sim_scaling.py), `speed_repeats` times."""
    return sim_scaling.measure(REPO, opts.speed_repeats, opts.speed_cases)


def _say(text: str) -> None:
    sys.stderr.write(text + "\n")
    sys.stderr.flush()


def measure_all(opts: BenchOptions, command: str, say: Callable[[str], None] = _say,
                progress: Callable[[int, int], None] | None = accuracy.stderr_progress) -> Results:
    """Every section, timing-sensitive ones first while nothing else of ours runs."""
    walls: dict[str, float] = {}
    machine = machine_info()

    def timed(name: str, fn: Callable[[], object]) -> object:
        say(f"{name} ...")
        t0 = time.perf_counter()
        value = fn()
        walls[name] = time.perf_counter() - t0
        say(f"{name}: {walls[name]:.1f} s")
        return value

    ticks = timed("tick cost", lambda: tick_cost.measure_tick_cost(load_config(SIM_CONFIG), opts.ticks))
    loop = timed("loop timing", lambda: loop_timing.measure_loop_timing(opts.loop_rates, opts.loop_duration_s))
    ctl = timed("control socket", lambda: ctl_flood.measure_ctl_flood(opts.ctl_counts, opts.ctl_estops))
    speed = timed("simulation speed", lambda: measure_speed_section(opts))
    st = timed("start-up", lambda: startup.measure_startup(opts.import_modules, opts.import_repeats,
                                                           opts.sim_rss_duration_s))
    acc = timed("accuracy", lambda: accuracy.measure_accuracy(SCENARIO_DIR, opts.seeds, opts.lookaheads,
                                                              opts.workers, opts.scenarios, progress))
    adapt = timed("adaptation", lambda: adaptation.measure_adaptation(SCENARIO_DIR, opts.seeds, opts.workers,
                                                                      opts.scenarios))
    paths = timed("paths as given", lambda: measure_paths(opts))
    robots = timed("population", lambda: population.measure_population(opts.robots, opts.workers))
    live = timed("foxglove and velocity mode", lambda: measure_live(opts))
    supply = timed("supply voltage", lambda: battery.measure(opts.seeds))
    com = timed("commissioning", lambda: measure_commissioning(opts))
    machine["load average at the end"] = (load_average() + " (other work on this machine shows in the maxima "
                                          "and the loop timing)")
    return Results(options=opts, command=command, machine=machine, accuracy=acc,  # type: ignore[arg-type]
                   ticks=ticks, loop=loop, speed=speed, startup=st, bound=io_bound.io_bound(),  # type: ignore[arg-type]
                   adapt=adapt, ctl=ctl, paths=paths, robots=robots, live=live, supply=supply,  # type: ignore[arg-type]
                   commissioning=com, wall_s=walls)  # type: ignore[arg-type]


# --------------------------------------------------------------------------- the document


INTRO = (
    "Grouped by what a user wants to know: tracking accuracy, robots and paths, sensing and estimation, "
    "timing and load, simulation speed, the daemon under abuse. Each section opens with its headline, then "
    "the command that reproduces it, then the details; a section's number is its name for "
    "`python -m bench.run --only N` and for other documents. Every figure was measured on the machine "
    "below unless its section says otherwise; the machine is shared (2 cores, other work beside it), so "
    "ratios measured side by side are the figures to compare, not absolute times from different hours.",
    "",
    "Commands: `python -m bench.run` measures sections 1 to 13 (`--quick` a smoke run, `--only N` one of "
    "1, 4, 9, 10, 11, 12, 13, spliced into this file); sections 14 to 20 name their own commands. "
    "`python -m bench.gain_sweep` regenerates TUNING.md; `python -m bench.foxglove_gil` tells a late "
    "tick's cause (the machine, or the Foxglove publisher); bench/common.py is what every script shares.",
)


def _header(n: int) -> str:
    return f"## {SECTIONS[n]}"


def _section_end(lines: list[str], start: int) -> int:
    """Index of the next `## ` or `# ` heading after line `start` (len(lines): none)."""
    return next((i for i in range(start + 1, len(lines)) if lines[i].startswith(("## ", "# "))), len(lines))


def headline(doc: str, n: int) -> list[str]:
    """Section n's headline paragraph in `doc` and a blank line after it ([] when it has none)."""
    body = section_body(doc, n) or []
    if not body or not body[0].startswith(HEADLINE):
        return []
    end = body.index("") if "" in body else len(body)
    return body[:end] + [""]


def section_body(doc: str, n: int) -> list[str] | None:
    """Section n's lines of `doc` after its heading and blank line, up to the next `## `
    heading (trailing blank lines dropped); None when `doc` has no such section."""
    lines = doc.rstrip("\n").split("\n")
    try:
        start = lines.index(_header(n))
    except ValueError:
        return None
    body = lines[start + 1:_section_end(lines, start)]
    while body and not body[0].strip():
        body.pop(0)
    while body and not body[-1].strip():
        body.pop()
    return body


def render_document(r: Results, previous: str = "") -> str:
    """The whole report; the sections in OWN_COMMAND are carried over from `previous` (the
    file this one replaces) as they were."""
    o = r.options
    acc = r.accuracy
    lines: list[str] = [
        "# Benchmarks",
        "",
        f"Generated by `{r.command}` (from the repository root); do not edit by hand. "
        f"Total measuring time {sum(r.wall_s.values()) / 60:.1f} min "
        f"({', '.join(f'{k} {v:.0f} s' for k, v in r.wall_s.items())}).",
        "",
        *INTRO,
        "",
        _header(0),
        "",
    ]
    lines += [f"- {k}: {v}" for k, v in r.machine.items()]
    daemon_rss = None
    for run in r.loop.runs:
        if run.stats and run.rate_hz == 200 and isinstance(run.stats.get("maxrss_kb"), int):
            daemon_rss = run.stats["maxrss_kb"]
    absent = ["Not measured in this run."]
    bodies: dict[int, list[str]] = {
        1: render_accuracy(AccuracySection(acc, o.workers)),
        2: tick_cost.render(r.ticks),
        3: loop_timing.render(r.loop),
        4: sim_scaling.render_section(r.speed),
        5: startup.render(r.startup, loop_timing.ready_s(r.loop), daemon_rss),
        6: io_bound.render(r.bound, r.ticks.compute.p50_us, r.ticks.compute.p99_us, r.ticks.period_s),
        7: adaptation.render(r.adapt),
        8: ctl_flood.render(r.ctl),
        9: paths_as_given.render(r.paths) if r.paths is not None else absent,
        10: population.render(r.robots) if r.robots is not None else absent,
        11: render_live(r.live) if r.live is not None else absent,
        12: battery.render(r.supply) if r.supply is not None else absent,
        13: commissioning.render(r.commissioning) if r.commissioning is not None else absent,
    }
    bodies = {n: headline(previous, n) + body for n, body in bodies.items()}
    for n, command in OWN_COMMAND.items():
        kept = section_body(previous, n)
        bodies[n] = kept if kept else [f"Not measured: `{command}` measures this section (not part of the full run)."]
    for title, group in CAPABILITIES:
        lines += ["", f"# {title}"]
        for n in group:
            lines += ["", _header(n), ""] + bodies[n]
    return "\n".join(lines) + "\n"


# Sections that `--only` can measure alone: number -> (measure, render).
ONLY: dict[int, tuple[Callable[[BenchOptions], object], Callable[[object], list[str]]]] = {
    1: (measure_accuracy_section, render_accuracy),  # type: ignore[dict-item]
    4: (measure_speed_section, sim_scaling.render_section),  # type: ignore[dict-item]
    9: (measure_paths, paths_as_given.render),  # type: ignore[dict-item]
    10: (measure_population_section, population.render),  # type: ignore[dict-item]
    11: (measure_live, render_live),  # type: ignore[dict-item]
    12: (lambda opts: battery.measure(opts.seeds), battery.render),  # type: ignore[dict-item]
    13: (measure_commissioning, commissioning.render),  # type: ignore[dict-item]
}


def splice_section(doc: str, n: int, body: list[str]) -> str:
    """`doc` with section n's text (heading to the next `## ` or `# `) replaced by `body`, or
    inserted after the last earlier section of DOC_ORDER it has (before the next one) when it has none."""
    lines = doc.rstrip("\n").split("\n")
    heads = {line: i for i, line in enumerate(lines) if line.startswith("## ")}
    new = [_header(n), ""] + body
    if _header(n) in heads:
        start = heads[_header(n)]
        end = _section_end(lines, start)
        lines[start:end] = new + ([""] if end < len(lines) else [])
    else:
        later = [heads[_header(k)] for k in DOC_ORDER[DOC_ORDER.index(n) + 1:] if _header(k) in heads]
        at = min(later) if later else len(lines)
        lines[at:at] = ([""] if at == len(lines) else []) + new + ([""] if later else [])
    return "\n".join(lines) + "\n"


def measure_only(n: int, opts: BenchOptions, command: str) -> list[str]:
    measure, render = ONLY[n]
    load0 = load_average()
    t0 = time.perf_counter()
    value = measure(opts)
    when = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    return [f"Measured alone by `{command}` on {when} in {time.perf_counter() - t0:.0f} s (load average "
            f"{load0} at start, {load_average()} at the end; the machine is the one above).", ""] + render(value)


# --------------------------------------------------------------------------- command line


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bench.run", description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="1 seed, fewer ticks, 5 s loop runs (a smoke run)")
    ap.add_argument("--out", default="docs/BENCHMARKS.md", help="where to write (default: docs/BENCHMARKS.md)")
    ap.add_argument("--workers", type=int, default=2, help="processes for the accuracy grid (default: 2)")
    ap.add_argument("--only", type=int, metavar="N",
                    help=f"measure section N alone ({', '.join(map(str, ONLY))}) and splice it into --out")
    args = ap.parse_args(argv)
    if args.workers < 1:
        ap.error(f"--workers: must be at least 1, got {args.workers}")
    if args.only in OWN_COMMAND:
        ap.error(f"--only: section {args.only} is measured by its own command: {OWN_COMMAND[args.only]}")
    if args.only is not None and args.only not in ONLY:
        ap.error(f"--only: sections that can be measured alone: {', '.join(map(str, ONLY))}; got {args.only}")
    opts = QUICK if args.quick else FULL
    if args.workers != opts.workers:
        opts = dataclasses.replace(opts, workers=args.workers)
    command = shlex.join(["python", "-m", "bench.run"] + list(argv if argv is not None else sys.argv[1:]))
    out = FsPath(args.out)
    if not out.is_absolute():
        out = REPO / out
    out.parent.mkdir(parents=True, exist_ok=True)
    if args.only is not None:
        old = out.read_text(encoding="utf-8") if out.exists() else "# Benchmarks\n"
        body = headline(old, args.only) + measure_only(args.only, opts, command)
        out.write_text(splice_section(old, args.only, body), encoding="utf-8")
        _say(f"wrote section {args.only} into {out}")
        return 0
    results = measure_all(opts, command)
    previous = out.read_text(encoding="utf-8") if out.exists() else ""
    out.write_text(render_document(results, previous), encoding="utf-8")
    _say(f"wrote {out}")
    for v in results.accuracy.verdict:
        _say("  " + v)
    return 0


if __name__ == "__main__":
    sys.exit(main())
