"""What the estimator asks of a sensor's fusion step: one object per sensor, with one job.

Each step takes its channel of the Sample and updates the filter state through the estimator's
public calls (Estimator.fuse_travel, fuse_rate, fuse_bias, widen_bias, shift_bias, set_fault,
and the health's counters); it keeps its own state and writes no other object's fields. The
estimator composes its steps once, from what HalInfo says the configured sensors deliver, and a
sensor that is not there is a step that does nothing, so a tick runs the same calls whatever the
robot carries (docs/design.md, "Adding a sensor"):

- the distance: `FrontEncoder` (ddrt/core/front_encoder.py), or the drive wheels' when there is
  no front encoder (`WheelOdometry`, ddrt/core/wheel_odometry.py);
- the yaw rate: `GyroRegister` (ddrt/core/gyro_register.py) or `FifoRate` (ddrt/core/gyro_fifo.py);
- the gyro's bias against its die temperature: `TemperatureBias` or `StopsOnly` (ddrt/core/gyro_bias.py);
- the drive wheels' check of the turn, bias and slip: `WheelOdometry` or `NoWheels`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

from ddrt.config import EstimatorConfig
from ddrt.core.types import Sample

if TYPE_CHECKING:
    from ddrt.core.estimator import Estimator
    from ddrt.core.gyro_bias import GyroBias
    from ddrt.core.gyro_fifo import GyroFifo


class DistanceStep(Protocol):
    """A sensor that can give the travel filters their position measurement."""

    moved: bool  # a count came with the latest sample
    ds: float  # the distance (m) its latest sample counted

    @property
    def z(self) -> float:
        """The distance (m) counted since the reset (or the last re-base)."""

    @property
    def position_var(self) -> float:
        """The variance (m^2) of `z` as a measurement: its quantisation's."""

    def rebase(self) -> None:
        """Count from zero again (a reload's new metres per count)."""

    def catch_up(self, sample: Sample) -> None:
        """The first sample after a gap: take its counts without fusing them."""


class RateStep(Protocol):
    """The gyro's yaw rate, fused once per fresh sample, and the heading it turns."""

    fifo: "GyroFifo | None"  # the FIFO's learnt period and losses, for status; None at the register

    def reset(self, sample: Sample) -> None: ...

    def restart(self, t: float) -> None:
        """The samples count from loop time `t` on (a re-anchor)."""

    def fuse(self, est: "Estimator", sample: Sample, commanded_still: bool) -> None: ...

    def turn(self, w: float, dt: float, fresh: bool) -> float:
        """The heading's increment this tick (rad) at the yaw rate w."""


class BiasStep(Protocol):
    """The gyro's bias between stops: returns the heading's correction (rad) each tick."""

    line: "GyroBias | None"  # the (b0, k) line, for reports; None without a temperature

    def configure(self, cfg: EstimatorConfig) -> None: ...
    def reset(self, cfg: EstimatorConfig) -> None: ...
    def rescale(self, ratio: float) -> None: ...
    def fuse(self, est: "Estimator", sample: Sample, fresh: bool, dt: float) -> float: ...
