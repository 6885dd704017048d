"""How much a long-running process keeps per command cycle: a least-squares line through its
samples after a warm-up, and the verdict a soak holds it to. bench/soak.py samples the daemon
and its children; tests hold the arithmetic here to known lines."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

WARMUP_CYCLES = 30  # imports, caches and the allocator's arenas settle within these
RSS_LIMIT_KB_PER_100 = 100.0  # issue's bound: about 1.4 MB a week at one cycle a minute


@dataclass(frozen=True)
class Sample:
    """One process after `cycle` command cycles: resident set (KiB), open descriptors, threads."""

    cycle: int
    rss_kb: int
    fds: int
    threads: int


@dataclass(frozen=True)
class Trend:
    """A process's growth over a soak, after the warm-up: the least-squares slope of its RSS (KiB
    per 100 cycles); its descriptors and threads as (the most in the first quarter of the
    samples after it, the fewest in the last quarter), so a descriptor open for a moment at
    one sample is not a leak, while one kept per cycle (or per ten) is."""

    cycles: int  # the cycles the slope spans
    rss_kb_per_100: float
    rss_first_kb: int
    rss_last_kb: int
    fds: tuple[int, int]
    threads: tuple[int, int]

    def failures(self, limit_kb_per_100: float = RSS_LIMIT_KB_PER_100) -> list[str]:
        """What breaks the bound: RSS growing faster than the limit, or descriptors or threads
        at the end never as few as after the warm-up (fewer is not a leak)."""
        out = []
        if self.rss_kb_per_100 > limit_kb_per_100:
            out.append(f"RSS grows {self.rss_kb_per_100:.0f} KiB per 100 cycles (limit {limit_kb_per_100:g})")
        if self.fds[1] > self.fds[0]:
            out.append(f"open descriptors grew from {self.fds[0]} to {self.fds[1]}")
        if self.threads[1] > self.threads[0]:
            out.append(f"threads grew from {self.threads[0]} to {self.threads[1]}")
        return out


def slope_per_100(cycles: Sequence[float], values: Sequence[float]) -> float:
    """The least-squares slope of `values` against `cycles`, per 100 cycles; ValueError with
    fewer than two distinct cycles (no line through them)."""
    x = np.asarray(cycles, dtype=np.float64)
    y = np.asarray(values, dtype=np.float64)
    if x.shape != y.shape:
        raise ValueError(f"slope: {x.size} cycles against {y.size} values")
    if x.size < 2 or np.ptp(x) == 0.0:
        raise ValueError("slope: needs samples at two different cycle counts at least")
    dx = x - x.mean()
    return float(100.0 * np.dot(dx, y - y.mean()) / np.dot(dx, dx))


def trend(samples: Sequence[Sample], warmup: int = WARMUP_CYCLES) -> Trend:
    """The growth of one process over the samples taken at `warmup` cycles and after."""
    kept = sorted((s for s in samples if s.cycle >= warmup), key=lambda s: s.cycle)
    if len(kept) < 2:
        raise ValueError(f"trend: {len(kept)} sample(s) at or after cycle {warmup}: run more cycles")
    quarter = max(1, len(kept) // 4)
    head, tail = kept[:quarter], kept[-quarter:]
    return Trend(cycles=kept[-1].cycle - kept[0].cycle,
                 rss_kb_per_100=slope_per_100([s.cycle for s in kept], [s.rss_kb for s in kept]),
                 rss_first_kb=kept[0].rss_kb, rss_last_kb=kept[-1].rss_kb,
                 fds=(max(s.fds for s in head), min(s.fds for s in tail)),
                 threads=(max(s.threads for s in head), min(s.threads for s in tail)))
