"""The heading from the gyro's FIFO (ddrt/core/gyro_fifo.py and the estimator's use of it):
every sample integrated once over the part's own period, learnt; losses, junk and stale
ticks accounted for (sensors.gyro_fifo)."""

from __future__ import annotations

import math
import random
from pathlib import Path

import pytest

from ddrt.config import load_config
from ddrt.core.gyro_fifo import LEARN_S, LOSS_PERIODS, GyroFifo, mean_rate
from ddrt.core.types import Sample
from ddrt.loop import ControlLoop
from hal.registry import open_hal

SIM_YAML = str(Path(__file__).resolve().parents[1] / "configs" / "sim.yaml")
DEG = math.pi / 180.0


def batches(true_period: float, tick: float, seconds: float, rng: random.Random, jitter: float = 0.0):
    """(read time, samples since the last read) for reads every `tick` (+- jitter) of a part
    whose samples come every `true_period` from a random phase."""
    phase = rng.uniform(0.0, true_period)
    t = 0.0
    produced = math.floor((t - phase) / true_period)
    while t < seconds:
        t += tick + rng.uniform(-jitter, jitter)
        now = math.floor((t - phase) / true_period)
        yield t, now - produced
        produced = now


@pytest.mark.parametrize("off", [-0.01, 0.005, 0.0])
def test_the_period_is_learnt_as_the_slope_of_time_against_samples(off):
    rng = random.Random(7)
    true = 0.005 * (1.0 + off)
    g = GyroFifo(0.005)
    g.restart(0.0)
    for t, n in batches(true, 0.005, 30.0, rng, jitter=0.001):
        if n:
            g.span(t, n)
    assert g.learnt
    # the line's slope: a tenth of one period over the time learnt, what t / n could be off by
    assert abs(g.period - true) <= 0.1 * true * true / 30.0
    assert g.losses == 0 and g.rejects == 0


def test_the_spans_add_up_to_the_time_whatever_the_beat():
    """Summed spans cover the time read (within a period), where counting a register read per
    tick would be off by the beat: 0.5 % of the time."""
    rng = random.Random(3)
    true = 0.005 / 1.005
    g = GyroFifo(0.005)
    g.restart(0.0)
    total = 0.0
    t_end = 0.0
    for t, n in batches(true, 0.005, 60.0, rng):
        if n:
            total += g.span(t, n)
            t_end = t
    assert abs(total - t_end) < 2.0 * LEARN_S * 0.005 / 1.005 + 2 * true  # nominal before LEARN_S


def test_a_batch_short_of_the_time_lost_samples_and_covers_the_time():
    g = GyroFifo(0.005)
    g.restart(0.0)
    assert g.span(0.005, 1) == pytest.approx(0.005)
    span = g.span(0.105, 2)  # 100 ms, 2 samples: the FIFO was reset meanwhile
    assert span == pytest.approx(0.1) and g.losses == 1 and not g.bad
    assert g.span(0.105 + LOSS_PERIODS * 0.005 * 0.9, 1) == pytest.approx(0.005)  # within the slack: a beat


def test_a_batch_with_more_samples_than_time_is_junk():
    g = GyroFifo(0.005)
    g.restart(0.0)
    span = g.span(0.005, 300)  # a garbled FIFO_COUNT: 300 samples in 5 ms
    assert g.bad and g.rejects == 1 and span == pytest.approx(0.005)
    g.span(0.010, 1)
    assert not g.bad


def test_stale_ticks_are_taken_back_when_their_samples_arrive():
    g = GyroFifo(0.005)
    g.restart(0.0)
    turns = [g.turn(1.0, 0.005, True, g.span(0.005, 1))]
    turns.append(g.turn(2.0, 0.005, False, 0.0))  # stale: dead-reckoned at 2 rad/s
    turns.append(g.turn(1.0, 0.005, True, 0.0))  # fresh, nothing new
    turns.append(g.turn(1.0, 0.005, True, g.span(0.020, 3)))  # the three samples since
    assert sum(turns) == pytest.approx(1.0 * 0.020)
    assert turns[2] == 0.0


def test_mean_rate_of_a_batch_and_of_a_register_reading():
    assert mean_rate(Sample(0.0, 0, 7, gyro_n=4, gyro_sum_raw=10), 0.5) == pytest.approx(1.25)
    assert mean_rate(Sample(0.0, 0, 7), 0.5) == pytest.approx(3.5)
    with pytest.raises(ValueError, match="nominal period"):
        GyroFifo(0.0)


# --- the estimator on the simulated robot ---------------------------------------------------

def spin(fifo: bool, seed: int, seconds: float = 24.0, backend: str = "sim", freeze: tuple[float, float] | None = None,
         **gyro: float) -> tuple[float, object]:
    """The seed robot weaving (yaw-rate reversals of about 2 rad/s every second)
    with its register held at the part's own 0.5 %-fast clock, then at rest: the heading error
    (deg) at the end, and the estimator."""
    over = {"sim": {"seed": seed, "gyro": {"register_hold": True, "clock_ppm": 5000.0, **gyro}},
            "sensors": {"gyro_fifo": fifo}}
    if backend == "real":
        over["hal"] = {"backend": "real", "imu": {"bus": "sim"}, "bridge": {"url": "ddrtsim://robot"}}
    cfg = load_config(SIM_YAML, over)
    hal = open_hal(cfg, start=(0.0, 0.0, 0.0), seed=seed)
    try:
        loop = ControlLoop(cfg, hal)
        loop.calibrate(hal.sleep_until, hal.now)
        if freeze is not None:  # the sensors stop updating (SimHal's fault injection)
            hal.freeze(hal.now() + freeze[0], freeze[1])
        est = loop.estimator
        period = loop.period
        bias = cfg.sim.gyro.bias_dps * DEG
        drift = 0.0  # the heading the bias estimate's error turns: (true - estimate) dt
        t = hal.now()
        k = 0
        while k * period < seconds + 1.0:
            moving = k * period < seconds
            d = 0.25 * math.sin(2.0 * math.pi * 0.5 * k * period) if moving else 0.0
            c = 0.3 if moving else 0.0  # forward too, so the encoder tells moving from at rest
            hal.write(c + d, c - d)
            t += period
            hal.sleep_until(t)
            est.update(hal.read(), c + d, c - d, not moving)
            drift += (bias - est.heading.b) * est.dt
            k += 1
        dth = est.theta - hal.robot.pose[2] - drift
        return math.degrees(math.atan2(math.sin(dth), math.cos(dth))), est
    finally:
        hal.close()


@pytest.mark.parametrize("backend", ["sim", "real"])
def test_through_the_fifo_the_heading_is_the_samples_integrated(backend):
    """A noise-free gyro with no bias, its clock 0.5 % fast, the register held: what is left of
    the heading error once the bias estimate's own error (the heading filter re-learns it on the
    move) is taken out is how the samples were integrated. Through the FIFO every sample counts
    once at the learnt period: hundredths of a degree after 16 s of reversals. Read at the tick,
    the held register's age varies with the beat and each reversal moves the heading: more."""
    errs_fifo, errs_reg = [], []
    for seed in (1, 2):
        err, est = spin(True, seed, 16.0, backend=backend, noise_dps_rthz=0.0, bias_dps=0.0)
        assert est.fifo is not None and est.fifo.losses == 0 and est.fifo.rejects == 0
        assert est.fifo.period == pytest.approx(0.005 / 1.005, rel=5e-5)
        errs_fifo.append(abs(err))
        errs_reg.append(abs(spin(False, seed, 16.0, backend=backend, noise_dps_rthz=0.0, bias_dps=0.0)[0]))
    assert max(errs_fifo) < 0.03
    assert min(errs_reg) > 3.0 * max(errs_fifo)


def test_status_reports_the_learnt_period_and_the_lost_batches():
    from ddrt.service.status import estimate_report

    _, est = spin(True, 1, 4.0, noise_dps_rthz=0.0, bias_dps=0.0)
    fifo = estimate_report(est)["gyro_fifo"]
    assert fifo["gyro_period_ms"] == pytest.approx(5.0 / 1.005, rel=5e-4)
    assert fifo["gyro_fifo_losses"] == 0 and fifo["gyro_fifo_rejects"] == 0
    assert estimate_report(spin(False, 1, 1.0)[1])["gyro_fifo"] is None


def test_a_short_freeze_is_covered_by_the_samples_that_waited_in_the_fifo():
    """30 ms without a fresh sample mid-run (below the estimator's max gap): the ticks are
    dead-reckoned, then the batch after them brings every sample of the freeze and takes back
    what dead reckoning added: the heading is as good as without the freeze."""
    err, est = spin(True, 1, 12.0, freeze=(5.0, 0.03), noise_dps_rthz=0.0, bias_dps=0.0)
    assert est.health.counters()["stale_ticks"] == 0 and est.fifo.losses == 0
    assert abs(err) < 0.03


@pytest.mark.parametrize("dur", [0.2, 3.0])
def test_a_long_freeze_re_anchors_or_loses_samples_without_a_traceback(dur):
    """A freeze beyond the max gap (0.2 s) or beyond the FIFO (3 s: it overflowed, that read
    flagged and repeated like a frozen one) while the robot weaves on blind: the estimate is
    re-anchored as it is without the FIFO (the gap's heading is dead reckoning either way), and
    the period learnt before is kept."""
    err, est = spin(True, 2, 8.0, freeze=(4.0, dur), noise_dps_rthz=0.0, bias_dps=0.0)
    assert est.fifo.rejects == 0 and est.health.gaps == 1
    assert est.fifo.period == pytest.approx(0.005 / 1.005, rel=5e-4)
    assert abs(err) < abs(spin(False, 2, 8.0, freeze=(4.0, dur), noise_dps_rthz=0.0, bias_dps=0.0)[0]) + 1.0
