"""What each stage of one control tick costs, on the simulated backend.

`timed_tick` runs the real `ControlLoop.tick` with a stamp (`tick(stamp)`: called at the start
and after each stage; a no-op outside benchmarks) that records `time.perf_counter_ns`, for a
loop that is following a path.
The simulated plant's integration (`hal.sleep_until`) runs between ticks, outside the timed
region, and is reported on its own: on the robot that time is the motors' and the world's.
"""

from __future__ import annotations

import time
from array import array
from dataclasses import dataclass

import numpy as np

from bench.common import percentile
from ddrt.config import Config
from ddrt.loop import ControlLoop, LoopState
from ddrt.loop.states import MOVING
from ddrt.path.spec import resolve_path
from hal.registry import open_hal

STAGES = ("read", "estimate", "reference", "control", "write", "record")


class TickBenchError(RuntimeError):
    """The benchmarked loop left the following state (a fault), so its timings mean nothing."""


@dataclass(frozen=True)
class Percentiles:
    """p50, p99 and max of a set of durations, in microseconds."""

    p50_us: float
    p99_us: float
    max_us: float

    @classmethod
    def of_ns(cls, ns: array | np.ndarray) -> "Percentiles":
        a = np.asarray(ns, dtype=np.float64) / 1000.0
        if a.size == 0:
            raise ValueError("no samples")
        return cls(p50_us=percentile(a, 50.0), p99_us=percentile(a, 99.0), max_us=float(a.max()))


@dataclass(frozen=True)
class TickCost:
    """Per-stage and whole-tick durations over `ticks` ticks of period `period_s`."""

    ticks: int
    period_s: float
    stages: dict[str, Percentiles]
    tick: Percentiles
    compute: Percentiles  # the tick minus its read and write stages: what faster buses cannot remove
    plant: Percentiles  # the simulated robot's integration between ticks, not part of the tick
    timer_overhead_ns: float  # one stage stamp, paid once per stage
    restarts: int  # how often the path was restarted so every tick was "following"
    over_1ms: int  # ticks longer than 1 ms: on a shared machine, mostly the process being preempted

    def fraction_of_period(self, us: float) -> float:
        return us * 1e-6 / self.period_s


class StageStamps:
    """The tick's `stamp`: each call appends `time.perf_counter_ns()` to `ns`."""

    __slots__ = ("ns", "_append")

    def __init__(self) -> None:
        self.ns: list[int] = []
        self._append = self.ns.append

    def __call__(self) -> None:
        self._append(time.perf_counter_ns())

    def clear(self) -> None:
        self.ns.clear()


def timed_tick(loop: ControlLoop, out: list[array], i: int, stamps: StageStamps | None = None) -> None:
    """One real `ControlLoop.tick()` of a moving loop (following, stopping or driving); each stage's duration into out[k][i] (ns).

    The tick stamps itself (`tick(stamps)`): the done/finite checks between control and write
    count in "write", the adapter (if on) in "estimate". A tick that did not run every stage
    (a HAL error, a fault, the path's end) raises TickBenchError.
    """
    if stamps is None:
        stamps = StageStamps()
    else:
        stamps.clear()
    state = loop.state
    loop.tick(stamps)
    ns = stamps.ns
    if len(ns) != len(STAGES) + 1 or loop.state == LoopState.FAULT or state not in MOVING:
        raise TickBenchError(f"loop not following (state {loop.state}, fault {loop.fault!r})")
    for k in range(len(STAGES)):
        out[k][i] = ns[k + 1] - ns[k]


def timer_overhead_ns(n: int = 20000) -> float:
    """Median cost of one stage stamp (a call that reads perf_counter_ns), to read the
    smallest stage timings against."""
    stamps = StageStamps()
    for _ in range(n):
        stamps()
    return float(np.median(np.diff(np.asarray(stamps.ns))))


def measure_tick_cost(cfg: Config, ticks: int = 100_000, seed: int | None = None) -> TickCost:
    """Follow the config's path (again whenever it has stopped at its end) for `ticks` timed ticks."""
    if ticks < 1:
        raise ValueError(f"ticks: must be at least 1, got {ticks}")
    path = resolve_path(cfg)
    pose = cfg.start or path.start_pose
    hal = open_hal(cfg, start=pose, seed=seed)
    try:
        loop = ControlLoop(cfg, hal)
        loop.calibrate(hal.sleep_until, hal.now)  # type: ignore[attr-defined]
        loop.follow(path, pose)
        out = [array("q", bytes(8 * ticks)) for _ in STAGES]
        plant = array("q", bytes(8 * ticks))
        period = loop.period
        t0 = hal.now()  # type: ignore[attr-defined]
        restarts = 0
        ns = time.perf_counter_ns
        for i in range(ticks):
            if loop.state == LoopState.STOPPED:  # at rest at the path's end: a path starts from rest
                loop.follow(path)
                restarts += 1
            a = ns()
            hal.sleep_until(t0 + (i + 1) * period)  # type: ignore[attr-defined]
            plant[i] = ns() - a
            timed_tick(loop, out, i)
    finally:
        hal.close()
    whole = np.sum([np.asarray(o, dtype=np.int64) for o in out], axis=0)
    return TickCost(
        ticks=ticks,
        period_s=period,
        stages={name: Percentiles.of_ns(o) for name, o in zip(STAGES, out)},
        tick=Percentiles.of_ns(whole),
        compute=Percentiles.of_ns(whole - np.asarray(out[0], dtype=np.int64) - np.asarray(out[4], dtype=np.int64)),
        plant=Percentiles.of_ns(plant),
        timer_overhead_ns=timer_overhead_ns(),
        restarts=restarts,
        over_1ms=int(np.count_nonzero(whole > 1_000_000)),
    )


def render(tc: TickCost) -> list[str]:
    period_us = tc.period_s * 1e6
    lines = [
        f"{tc.ticks} ticks of `ControlLoop` on the simulated backend (configs/sim.yaml, figure-eight at 0.3 m/s, "
        f"restarted {tc.restarts} times so every tick is following a path), period {period_us:.0f} us. "
        "The real `ControlLoop.tick` stamps `time.perf_counter_ns` after each stage "
        "(`hal.read`, `estimator.update`, `reference.update`, `controller.update`, `hal.write`, `fill_row`); "
        "write includes the done/finite checks before it. Ticks run back to back (the CPU's caches stay "
        "warm); section 3 shows the same tick in the paced daemon. The simulated robot's own integration "
        "(`hal.sleep_until`, between ticks) is excluded from the tick and shown on its own line. "
        f"One stage stamp costs about {tc.timer_overhead_ns:.0f} ns. The garbage collector is left on.",
        "",
        "| stage | p50 (us) | p99 (us) | max (us) | p50 / period | p99 / period |",
        "|---|---|---|---|---|---|",
    ]

    def row(name: str, p: Percentiles) -> str:
        return (f"| {name} | {p.p50_us:.1f} | {p.p99_us:.1f} | {p.max_us:.1f} | "
                f"{tc.fraction_of_period(p.p50_us):.2%} | {tc.fraction_of_period(p.p99_us):.2%} |")

    for name in STAGES:
        lines.append(row(name, tc.stages[name]))
    lines.append(row("**whole tick**", tc.tick))
    lines.append(row("compute (tick minus read, write)", tc.compute))
    lines.append(row("simulated plant, not in the tick", tc.plant))
    lines += ["", f"Whole tick: p50 {tc.tick.p50_us:.1f} us, p99 {tc.tick.p99_us:.1f} us, max {tc.tick.max_us:.1f} us "
                  f"= {tc.fraction_of_period(tc.tick.p99_us):.1%} of the {period_us:.0f} us period at p99, "
                  f"{tc.fraction_of_period(tc.tick.max_us):.1%} at worst. {tc.over_1ms} of {tc.ticks} ticks took "
                  "longer than 1 ms; the maxima of all stages move together, the mark of the process being "
                  "preempted (see the load average in Machine) rather than of slow code."]
    return lines
