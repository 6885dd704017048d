"""lab/soak.py: the slope a soak reports is the least-squares line through the samples after
the warm-up, and the verdict catches RSS, descriptor and thread growth but not noise."""

from __future__ import annotations

import random

import pytest

from lab.soak import RSS_LIMIT_KB_PER_100, WARMUP_CYCLES, Sample, slope_per_100, trend


def _samples(kb_per_cycle: float, start_kb: float = 44_000.0, warmup_jump_kb: float = 0.0, noise_kb: float = 0.0,
             fds: list[int] | None = None, cycles: int = 1000, every: int = 10, seed: int = 1) -> list[Sample]:
    rng = random.Random(seed)
    out = []
    for k, c in enumerate(range(0, cycles + 1, every)):
        jump = warmup_jump_kb * min(1.0, c / WARMUP_CYCLES)  # caches filling in the first cycles
        rss = start_kb + jump + kb_per_cycle * c + rng.uniform(-noise_kb, noise_kb)
        out.append(Sample(c, round(rss), fds[k] if fds else 13, 5))
    return out


@pytest.mark.parametrize("kb_per_cycle", [0.0, 0.4, 5.5, -0.2])
def test_a_straight_line_gives_its_slope_whatever_the_warm_up(kb_per_cycle: float) -> None:
    # A 3 MB jump during the warm-up must not count: the slope is after it.
    t = trend(_samples(kb_per_cycle, warmup_jump_kb=3000.0))
    assert t.rss_kb_per_100 == pytest.approx(100 * kb_per_cycle, abs=0.05)
    assert t.cycles == 1000 - WARMUP_CYCLES


def test_the_issue_s_growth_fails_and_a_flat_noisy_daemon_passes() -> None:
    leaking = trend(_samples(5.5, noise_kb=40.0))  # 550 KiB per 100 cycles, as measured on 243 cycles
    assert leaking.failures() == [f"RSS grows {leaking.rss_kb_per_100:.0f} KiB per 100 cycles "
                                  f"(limit {RSS_LIMIT_KB_PER_100:g})"]
    for seed in range(20):  # +-40 KiB of page noise on a flat process, 1000 cycles: within the bound
        flat = trend(_samples(0.0, noise_kb=40.0, seed=seed))
        assert abs(flat.rss_kb_per_100) < 10.0 and flat.failures() == []


def test_the_slope_is_least_squares_not_the_end_points() -> None:
    # One high last sample moves the end-to-end difference, not much the fitted line.
    cycles = list(range(30, 131, 10))
    values = [1000.0] * (len(cycles) - 1) + [1100.0]
    # Sxy = 50 * 100 (only the last point is off the mean line), Sxx = 2 * (10² + ... + 50²) = 11000
    assert slope_per_100(cycles, values) == pytest.approx(100 * 5000 / 11000, rel=1e-9)
    assert slope_per_100([0, 50, 100], [10.0, 20.0, 30.0]) == pytest.approx(20.0)
    with pytest.raises(ValueError, match="two different cycle counts"):
        slope_per_100([40, 40], [1.0, 2.0])
    with pytest.raises(ValueError, match="2 cycles against 3 values"):
        slope_per_100([1, 2], [1.0, 2.0, 3.0])


def test_descriptors_kept_per_cycle_fail_and_one_open_for_a_moment_does_not() -> None:
    n = len(range(0, 1001, 10))
    blip = [13] * n
    blip[50] = 14  # a connection open at one sample
    assert trend(_samples(0.0, fds=blip)).failures() == []
    creeping = [13 + k // 20 for k in range(n)]  # one more every 200 cycles
    t = trend(_samples(0.0, fds=creeping))
    assert t.fds[1] > t.fds[0]
    assert [f for f in t.failures() if "descriptors" in f] == [f"open descriptors grew from {t.fds[0]} to {t.fds[1]}"]


def test_too_few_samples_after_the_warm_up_is_said() -> None:
    with pytest.raises(ValueError, match="run more cycles"):
        trend(_samples(1.0, cycles=30))
