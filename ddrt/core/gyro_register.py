"""The gyro's output register read at the tick, as a fusion step: one rate per fresh sample.

The reading (raw times the scale, bias included) is fused into both yaw filters through
Estimator.fuse_rate, with the time since the previous reading for the lead that undoes the
gyro's low-pass lag. `RawWatch` is the raw word's own checks, which the FIFO's step shares: a
word repeated `estimator.stuck_gyro_ticks` samples in a row is a stuck gyro, a word at full
scale a saturated one (a live MEMS gyro's noise never repeats a 16-bit word for long).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from ddrt.core.types import Sample

if TYPE_CHECKING:
    from ddrt.core.estimator import Estimator
    from ddrt.core.gyro_fifo import GyroFifo


class RawWatch:
    """The newest raw word and how many samples in a row repeated it."""

    __slots__ = ("last", "same")

    def __init__(self) -> None:
        self.last: int | None = None
        self.same = 0

    def reset(self, raw: int) -> None:
        self.last = raw

    def check(self, est: "Estimator", raw: int) -> None:
        """Latch a fault on the estimator for a stuck or saturated word."""
        if raw == self.last:
            self.same += 1
            if self.same >= est.cfg.stuck_gyro_ticks:
                est.set_fault(f"gyro stuck at raw {raw} for {self.same} samples")
        else:
            self.same = 0
        self.last = raw
        if abs(raw * est.rad_s_per_lsb) >= est.gyro_full_scale * 0.999:
            est.set_fault("gyro saturated")


class GyroRegister:
    """The register's reading at each fresh sample; the heading turns w dt a tick."""

    __slots__ = ("watch", "last_t")
    fifo: "GyroFifo | None" = None

    def __init__(self) -> None:
        self.watch = RawWatch()
        self.last_t = 0.0  # the previous reading's time (the lead's interval)

    def reset(self, sample: Sample) -> None:
        self.watch.reset(sample.gyro_z_raw)

    def restart(self, t: float) -> None:
        pass  # the lead is restarted by the estimator; the register keeps no count

    def fuse(self, est: "Estimator", sample: Sample, commanded_still: bool) -> None:
        raw = sample.gyro_z_raw
        self.watch.check(est, raw)
        t = sample.t
        dt = t - self.last_t
        self.last_t = t
        est.fuse_rate(raw * est.rad_s_per_lsb, dt, commanded_still)

    def turn(self, w: float, dt: float, fresh: bool) -> float:
        return w * dt
