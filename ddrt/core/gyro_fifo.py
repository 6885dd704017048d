"""The heading from a gyro read through its FIFO (`sensors.gyro_fifo`): every sample once.

A FIFO read delivers the n samples the gyro produced since the last one (Sample.gyro_n, their
sum Sample.gyro_sum_raw). Integrated over n sample periods, not over the loop's tick, the
heading is the sum of all the samples times the period whatever the phase of the gyro's clock
against the loop's: no sample is counted twice or skipped, which a register read at the tick
does now and then as the two clocks beat, and the heading does not move by the hold's varying
age at every change of the yaw rate.

The period is the part's own (its oscillator may be 1 % off, which would scale every turn):
learnt as the slope of the loop time of each batch against the samples counted until it (a
least-squares line, so the unknown phase of the first and last sample averages out over the
reads instead of costing up to one period over the time learnt; nominal until LEARN_S). The heading
turned at the nominal period until then is rescaled once, when the period is first learnt:
the same samples, at the period they really had. A batch that
falls more than LOSS_PERIODS short of the time since the last one (the FIFO was reset after an
overflow or a bus error: samples were lost) covers that whole time at its mean rate instead,
and the line starts again (the period learnt so far is kept). A batch with more samples than the time since the last one
allows (a garbled FIFO_COUNT read past the FIFO's end: junk) is not fused (`bad`): its time is
dead-reckoned like a loss's.

Ticks whose sample is not fresh dead-reckon the heading from the last rate (`turn`); the batch that
follows brings their samples too (the HAL carries them over), so what they added is taken
back then (`blind`). A fresh tick with no new sample turns nothing: the next batch covers it.

`FifoRate` is the estimator's fusion step for a gyro read this way: each fresh sample's batch is
fused at its mean rate, its span the lead's interval, and the heading turns over the span.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from ddrt.core.gyro_register import RawWatch
from ddrt.core.types import Sample

if TYPE_CHECKING:
    from ddrt.core.estimator import Estimator

LEARN_S = 2.0  # loop time of batches before the learnt period replaces the nominal one
MAX_OFF = 0.05  # the learnt period is kept within this fraction of the nominal one
LOSS_PERIODS = 2.5  # a batch this many periods short of the time since the last one lost samples


def mean_rate(sample: Sample, rad_s_per_lsb: float) -> float:
    """The gyro's rate (rad/s, bias included) a sample says: its FIFO batch's mean, or the
    register's reading when it has no batch."""
    n = sample.gyro_n
    return (sample.gyro_sum_raw / n if n > 0 else sample.gyro_z_raw) * rad_s_per_lsb


class GyroFifo:
    """The learnt sample period and the time each batch covers (module doc)."""

    __slots__ = ("nominal", "period", "last_t", "blind", "losses", "bad", "rejects", "learnt", "turned", "rescale",
                 "fit_k", "fit_t0", "fit_n", "fit_mt", "fit_mn", "fit_ctn", "fit_cnn")

    def __init__(self, nominal_period_s: float) -> None:
        if not nominal_period_s > 0.0:
            raise ValueError(f"GyroFifo: nominal period must be > 0 s, got {nominal_period_s!r}")
        self.nominal = self.period = nominal_period_s
        self._refit()
        self.losses = 0  # batches that lost samples
        self.rejects = 0  # batches with more samples than time (junk)
        self.bad = False  # the last batch is junk: not to be fused
        self.learnt = False  # the period is learnt (until then: nominal)
        self.turned = 0.0  # the heading turned at the nominal period (rad)
        self.rescale = 0.0  # when first learnt: the factor less one to apply to `turned`
        self.restart(None)

    def _refit(self) -> None:
        """A new line of loop time against samples counted (Welford's running covariance)."""
        self.fit_k = 0  # points (batches) on the line
        self.fit_t0 = 0.0  # loop time of its first point
        self.fit_n = 0  # samples counted since then
        self.fit_mt = self.fit_mn = self.fit_ctn = self.fit_cnn = 0.0

    def _fit(self, t: float, n: int) -> None:
        """A batch of n at loop time t on the line; the period is its slope once LEARN_S long."""
        if self.fit_k == 0:
            self.fit_t0 = t
        else:
            self.fit_n += n
        self.fit_k += 1
        x, y = float(self.fit_n), t - self.fit_t0
        dx = x - self.fit_mn
        self.fit_mn += dx / self.fit_k
        self.fit_mt += (y - self.fit_mt) / self.fit_k
        self.fit_cnn += dx * (x - self.fit_mn)
        self.fit_ctn += dx * (y - self.fit_mt)
        if y >= LEARN_S and self.fit_cnn > 0.0:
            p = self.fit_ctn / self.fit_cnn
            lo, hi = self.nominal * (1.0 - MAX_OFF), self.nominal * (1.0 + MAX_OFF)
            self.period = lo if p < lo else hi if p > hi else p
            if not self.learnt:
                self.learnt = True
                self.rescale = self.period / self.nominal - 1.0

    def restart(self, t: float | None) -> None:
        """The samples count from loop time `t` on (a reset, a re-anchor: the batch of the gap
        was used otherwise, so the line starts again, the period learnt so far kept); None:
        from the next batch, whose span is then its own count's."""
        self.last_t = t
        self.blind = 0.0
        self._refit()

    def span(self, t: float, n: int) -> float:
        """The time (s) the batch of n > 0 samples read at loop time t covers."""
        last, self.last_t = self.last_t, t
        span = n * self.period
        self.bad = False
        if last is None:
            return span
        elapsed = t - last
        if span - elapsed > LOSS_PERIODS * self.period:
            self.rejects += 1
            self.bad = True
            self._refit()
            self._fit(t, 0)
            return elapsed
        if elapsed - span > LOSS_PERIODS * self.period:
            self.losses += 1
            self._refit()
            self._fit(t, 0)
            return elapsed
        if self.fit_k == 0:
            self._fit(last, 0)
        self._fit(t, n)
        return span

    def turn(self, w: float, dt: float, fresh: bool, span: float) -> float:
        """The heading's increment this tick (rad) at the yaw rate w: over the batch's span less
        what stale ticks added since the last batch; nothing on a fresh tick without samples;
        w dt on a stale tick (remembered)."""
        if not fresh:
            d = w * dt
            self.blind += d
            return d
        if span == 0.0:
            return 0.0
        d = w * span - self.blind
        self.blind = 0.0
        if not self.learnt:
            self.turned += d
        elif self.rescale:
            d += self.turned * self.rescale
            self.rescale = 0.0
        return d

    def counters(self) -> dict[str, float | int]:
        """For status: the learnt sample period (ms) and the batches that lost samples."""
        return {"gyro_period_ms": self.period * 1e3, "gyro_fifo_losses": self.losses, "gyro_fifo_rejects": self.rejects}


class FifoRate:
    """The fusion step of a gyro read through its FIFO (module doc): `span` is the time the
    latest fresh sample's batch covers (0: it brought no sample)."""

    __slots__ = ("fifo", "watch", "span")

    def __init__(self, nominal_period_s: float) -> None:
        self.fifo = GyroFifo(nominal_period_s)
        self.watch = RawWatch()
        self.span = 0.0

    def reset(self, sample: Sample) -> None:
        self.watch.reset(sample.gyro_z_raw)
        self.fifo.restart(sample.t)

    def restart(self, t: float) -> None:
        self.fifo.restart(t)

    def fuse(self, est: "Estimator", sample: Sample, commanded_still: bool) -> None:
        """Fuse the batch's mean rate; a batch with no sample (or junk) fuses nothing."""
        n = sample.gyro_n
        fifo = self.fifo
        self.span = fifo.span(sample.t, n) if n > 0 else 0.0
        if n <= 0 or fifo.bad:
            est.fuse_no_rate()
            return
        self.watch.check(est, sample.gyro_z_raw)
        est.fuse_rate(sample.gyro_sum_raw / n * est.rad_s_per_lsb, self.span, commanded_still)

    def turn(self, w: float, dt: float, fresh: bool) -> float:
        return self.fifo.turn(w, dt, fresh, self.span if fresh else 0.0)

