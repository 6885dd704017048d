"""The front omni wheel's encoder as a fusion step: the distance travelled along body x.

Its count is a position (metres since the reset), fused as one, so its quantisation stays
white: the travel filters' measurement noise is the quantisation's, metres_per_count^2 / 12.
A robot without one (encoder_counts_per_rev 0) has `NoFront`, and its drive wheels give the
distance (ddrt/core/wheel_odometry.py).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from ddrt.core.types import Sample
from ddrt.core.wrap import wrap_i32

if TYPE_CHECKING:
    from ddrt.core.estimator import Estimator


class FrontEncoder:
    """Counts since the reset (unwrapped), and what the latest sample added (`ds`, `moved`)."""

    __slots__ = ("metres_per_count", "last", "counts", "ds", "moved")

    def __init__(self) -> None:
        self.metres_per_count = 0.0
        self.last = 0  # the raw counter at the latest sample (wraps as a signed 32-bit integer)
        self.counts = 0  # unwrapped counts since the reset (or the last re-base)
        self.ds = 0.0
        self.moved = False

    def configure(self, metres_per_count: float) -> None:
        self.metres_per_count = metres_per_count

    @property
    def z(self) -> float:
        return self.counts * self.metres_per_count

    @property
    def position_var(self) -> float:
        return self.metres_per_count * self.metres_per_count / 12.0

    def reset(self, sample: Sample) -> None:
        self.last = sample.encoder_count
        self.counts = 0

    def rebase(self) -> None:
        self.counts = 0

    def catch_up(self, sample: Sample) -> None:
        delta = wrap_i32(sample.encoder_count - self.last)
        self.last = sample.encoder_count
        self.counts += delta
        self.moved = delta != 0
        self.ds = delta * self.metres_per_count

    def fuse(self, est: "Estimator", sample: Sample, dt: float) -> None:
        """Take the sample's count and fuse the distance since the reset."""
        self.catch_up(sample)
        est.fuse_travel(self.moved, self.counts * self.metres_per_count, dt)


class NoFront:
    """No front encoder: nothing counted, nothing fused."""

    __slots__ = ()
    moved = False
    ds = 0.0
    z = 0.0
    position_var = 0.0

    def configure(self, metres_per_count: float) -> None:
        pass

    def reset(self, sample: Sample) -> None:
        pass

    def rebase(self) -> None:
        pass

    def catch_up(self, sample: Sample) -> None:
        pass

    def fuse(self, est: "Estimator", sample: Sample, dt: float) -> None:
        pass
