"""Is the gyro's output alive? A MEMS gyro's noise never repeats one 16-bit word for long.

The argument that sets how long is long (docs/hardware.md, "A gyro that stops answering"):

- The noise of one reading is at least sigma = NOISE_FLOOR_DPS_RTHZ * sqrt(B) deg/s, B the
  low-pass's 3-dB bandwidth (the noise bandwidth of these filters is wider than that, so this
  understates it), times the range's LSB per deg/s. The floor is half the quietest family
  member's datasheet density (the MPU-6050's 0.005 deg/s/sqrt(Hz); the others are noisier), so
  a part quieter than its datasheet still counts as live.
- A reading lands on any one word with probability at most p = 1 / (sqrt(2 pi) sigma) (the
  density's peak times one LSB), capped at 1.
- Readings 1/B apart are independent (a first-order low-pass correlates them by exp(-2 pi)),
  and no closer than one sample: looks = min(B, sample rate) per second.
- A run of m more looks on the first one's word has probability p^m; runs start at every look,
  so false alarms come at most looks * p^m per second. m is the smallest count that makes that
  at most FALSE_ALARMS_PER_S, one in 10 000 hours of driving.

At the defaults (MPU-6050, 250 deg/s, DLPF_CFG 2: 98 Hz, 200 Hz output) sigma is 3.2 LSB,
p 0.12, m 11 looks: 0.11 s (45 mm at 0.4 m/s). A configuration whose noise is below one LSB
(a wide range with a narrow low-pass) gets a long bound, beyond MAX_STUCK_S: the watch then
still catches a FIFO that stops and a part that resets, and the estimator's
`estimator.stuck_gyro_ticks` the rest; `Mpu6050.stuck` says which it is.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["ALIVE", "FALSE_ALARMS_PER_S", "NOISE_FLOOR_DPS_RTHZ", "OutputWatch", "StuckBound", "Symptom", "stuck_bound"]

NOISE_FLOOR_DPS_RTHZ = 0.0025
FALSE_ALARMS_PER_S = 1.0 / (10_000 * 3600.0)
MAX_STUCK_S = 0.5  # a bound longer than this is reported as too long to stop within 0.3 m
FIFO_SILENT_PERIODS = 4  # FIFO reads with no new sample for this many sample periods ...
FIFO_SILENT_MIN_S = 0.02  # ... and at least this long: the FIFO has stopped filling


@dataclass(frozen=True)
class StuckBound:
    """How long one word may repeat before the output counts as frozen, and why."""

    sigma_lsb: float  # the noise floor of one reading, in LSB
    p_same: float  # the most probable word's probability
    looks_per_s: float  # independent readings per second
    looks: int  # m: repeats of one word, one look apart, that mean frozen
    after_s: float  # m / looks_per_s
    samples: int  # the same in the part's samples (the FIFO's count)

    @property
    def usable(self) -> bool:
        """False when the noise is too small for the bound to stop the robot in time."""
        return self.after_s <= MAX_STUCK_S


def stuck_bound(lsb_per_dps: float, bandwidth_hz: float, sample_rate_hz: float) -> StuckBound:
    """The bound for a reading of `lsb_per_dps` behind a low-pass of `bandwidth_hz`, produced at
    `sample_rate_hz` (module doc)."""
    sigma = NOISE_FLOOR_DPS_RTHZ * math.sqrt(bandwidth_hz) * lsb_per_dps
    p = min(1.0, 1.0 / (math.sqrt(2.0 * math.pi) * sigma))
    looks_per_s = min(bandwidth_hz, sample_rate_hz)
    if p >= 1.0:
        m = 10**9
    else:
        m = max(2, math.ceil(math.log(FALSE_ALARMS_PER_S / looks_per_s) / math.log(p)))
    after = m / looks_per_s
    samples = max(m, math.ceil(after * sample_rate_hz))
    return StuckBound(sigma, p, looks_per_s, m, after, samples)


@dataclass(frozen=True)
class Symptom:
    """What the watch saw: `kind` is "frozen", "zeros" or "fifo_stopped" ('' while the output
    looks alive), `text` says it in words (the caller names the part)."""

    kind: str = ""
    text: str = ""

    def __bool__(self) -> bool:
        return bool(self.kind)


ALIVE = Symptom()


class OutputWatch:
    """Watches the words one part delivers: `word(raw, t)` per register read (t: the read's
    clock time), `batch(...)` per FIFO read. Each returns ALIVE while the output looks alive,
    else the Symptom (the caller names the part and decides)."""

    def __init__(self, bound: StuckBound, sample_rate_hz: float) -> None:
        self.bound = bound
        self.silent_s = max(FIFO_SILENT_PERIODS / sample_rate_hz, FIFO_SILENT_MIN_S)
        self.reset()

    def reset(self) -> None:
        """Forget the history (after a re-initialisation)."""
        self._word: int | None = None
        self._since = 0.0  # clock time the current word first appeared (register path)
        self._looks = 0  # register reads of the current word after its first
        self._run = 0  # FIFO: samples of the current word in a row
        self._last_sample_t: float | None = None  # FIFO: clock time of the last read that had samples

    def word(self, raw: int, t: float) -> Symptom:
        """A register read. The run's looks are its span times looks_per_s, and never more than
        its reads: a loop faster than the part, or stalled between two reads, cannot make a run
        out of a few samples."""
        if raw != self._word:
            self._word, self._looks, self._since = raw, 0, t
            return ALIVE
        self._looks += 1  # here: the reads of the word after its first
        looks = min(self._looks, math.floor((t - self._since) * self.bound.looks_per_s + 1e-9))
        if looks >= self.bound.looks:
            return self._repeated(f"{looks} looks over {t - self._since:.3f} s")
        return ALIVE

    def batch(self, words: list[int], t: float) -> Symptom:
        """A FIFO read that returned `words` (oldest first; empty: no new sample)."""
        if not words:
            if self._last_sample_t is None:
                self._last_sample_t = t
            elif t - self._last_sample_t > self.silent_s:
                return Symptom("fifo_stopped", f"its FIFO stopped filling: no sample for "
                                               f"{t - self._last_sample_t:.3f} s")
            return ALIVE
        self._last_sample_t = t
        for w in words:
            if w == self._word:
                self._run += 1
            else:
                self._word, self._run = w, 1
        if self._run > self.bound.samples:
            return self._repeated(f"{self._run} samples in a row")
        return ALIVE

    def fifo_restarted(self, t: float) -> None:
        """The FIFO was emptied at `t`: its silence counts from now."""
        self._last_sample_t = t

    def silent_for(self, t: float) -> float:
        """FIFO: how long no read has brought a sample (0 when the last one did)."""
        return 0.0 if self._last_sample_t is None else max(0.0, t - self._last_sample_t)

    def _repeated(self, span: str) -> Symptom:
        w = self._word & 0xFFFF if self._word is not None else 0
        kind = "zeros" if w == 0 else "frozen"
        return Symptom(kind, f"its gyro z output repeated 0x{w:04x} for {span} ({'all zeros' if w == 0 else 'frozen'}: "
                             f"a live gyro's noise, >= {self.bound.sigma_lsb:.1f} LSB, repeats one word that long "
                             "less than once in 10 000 hours)")
