"""The hardware interface every backend implements, and the HAL's exception tree.

The controller only ever sees this module: a backend (the simulated robot, or the real
drivers on a bus and a serial port) is chosen by name in the config and handed to the loop
as a `Hal`. What a backend must and may override is in `Hal`'s docstring.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Protocol

from ddrt.core.types import HalInfo, Sample
from ddrt.errors import DdrtError

__all__ = ["GyroCaps", "Hal", "HalError", "HalInfo", "HalInitError", "HalIOError", "HalTimeoutError",
           "HalSensorFault", "HalValueError", "Sample", "TrueMotion", "check_duty"]


class HalError(DdrtError):
    """Root of every error a HAL raises; catch this to catch them all (a `DdrtError` too)."""


class HalInitError(HalError, OSError):
    """A device could not be opened or identified (wrong WHO_AM_I, protocol version, ...)."""


class HalIOError(HalError, OSError):
    """A transfer failed after its retries (I2C EIO, a serial write error, ...)."""


class HalTimeoutError(HalIOError, TimeoutError):
    """A device stopped answering within its bound (stale STATE stream, I2C timeout)."""


class HalSensorFault(HalError):
    """A sensor answers, but not with a live measurement: its output repeats one word longer
    than its noise allows, reads all zeros, its FIFO stopped filling, or it reset itself and
    could not safely be restarted. Not retried and not held: the loop latches a fault."""


class HalValueError(HalError, ValueError):
    """A value handed to the HAL is out of range or not finite (a duty of 1.5, a NaN)."""


@dataclass(frozen=True, slots=True)
class GyroCaps:
    """What a gyro driver delivers, as the driver declares it (its `caps`): the HAL builds its
    HalInfo and chooses its reads from this, and asks the driver nothing else.

    `age_s`: the mean age of a reading against the encoder's (the low-pass's group delay, plus
    half the output register's hold when the register is read at the tick). `fifo_period_s` > 0:
    every sample is read through the part's FIFO (`read_gyro_fifo()`) at this nominal period;
    0: the output register at the tick (`read_gyro_z_raw()`). `die_temp`: `read_temp_c()` gives
    the die's temperature (degC)."""

    age_s: float = 0.0
    fifo_period_s: float = 0.0
    die_temp: bool = False


class TrueMotion(Protocol):
    """What a simulated robot knows and a real one cannot tell: where it really is and how
    fast it really moves (sim_hal.plant.SimRobot)."""

    @property
    def pose(self) -> tuple[float, float, float]:
        """(x, y, theta): the true pose (m, m, rad; theta continuous)."""

    @property
    def velocity(self) -> tuple[float, float]:
        """(v, omega): the true forward speed (m/s) and yaw rate (rad/s)."""

    def truth(self) -> list[float]:
        """[x, y, theta, v, omega]: `pose` and `velocity` in one call (`ddrt sim`'s telemetry)."""


class Hal(ABC):
    """A robot as the controller sees it: sensors to read, two motors to drive.

    The public calls are template methods: `write` checks both duties and then calls the
    backend's `_write`; `close` runs the backend's `_close` once, however often it is called.
    A backend MUST override `read`, `_write`, `stop` and `_close` (and set `info`). It MAY
    override `__enter__`/`__exit__` (the default closes); when its robot lives in simulated
    time, `owns_time` and `advance_to_wall_clock`; and the optional capabilities, each None
    here for a backend that has none: `robot` (the simulated robot's true motion) and
    `fault_counters` (what it counted of the faults it absorbed). See each.
    """

    info: HalInfo

    #: The simulated robot behind a simulated backend, whose true pose and speeds the daemon's
    #: viewer, `ddrt sim`'s telemetry and calibration's report show beside the estimate. None:
    #: a real robot (nothing knows its true motion).
    robot: TrueMotion | None = None

    #: True for a backend whose robot runs in simulated time (the simulator, the real drivers
    #: on emulated devices). Such a backend is also a clock (`now()`, `sleep_until()`, see
    #: ddrt.core.types.Clock) in that time, and a caller that schedules on the wall clock must
    #: open it paced and call `advance_to_wall_clock()` before each tick. Hardware: False.
    owns_time: bool = False

    _closed: bool = False  # class default, so close() is safe on a half-built object

    @abstractmethod
    def read(self) -> Sample:
        """Read every sensor once. Raises HalIOError/HalTimeoutError, never returns junk."""

    def write(self, duty_l: float, duty_r: float) -> None:
        """Command both motors, duty in [-1, 1] (1 = full supply voltage forward).

        Raises HalValueError for a value out of range or not finite, without moving anything.
        """
        dl = check_duty("duty_l", duty_l)
        dr = check_duty("duty_r", duty_r)
        self._write(dl, dr)

    @abstractmethod
    def _write(self, duty_l: float, duty_r: float) -> None:
        """Command both motors; both duties are already checked floats in [-1, 1]."""

    @abstractmethod
    def stop(self) -> None:
        """Set both motors to zero now. Must not raise for a device that is already gone."""

    def close(self) -> None:
        """Stop the motors and release every device (the backend's `_close`, run once).

        Safe to call twice, and on an object whose constructor failed part-way."""
        if self._closed:
            return
        self._closed = True
        self._close()

    @abstractmethod
    def _close(self) -> None:
        """Stop the motors and release every device; called at most once, by `close`. It must
        cope with a half-built object (attributes the constructor never set)."""

    @property
    def fault_counters(self) -> dict[str, int] | None:
        """Counts of the faults the backend absorbed (retries, errors, watchdog trips) by name,
        for status; None when it keeps none."""
        return None

    def advance_to_wall_clock(self) -> None:
        """Bring a paced simulated robot up to the wall clock (backends that own time); the
        caller does it before a tick so the tick's own cost excludes the physics. No-op here."""

    def __enter__(self) -> "Hal":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def check_duty(name: str, duty: float) -> float:
    """Return `duty` as float if finite and within [-1, 1], else raise HalValueError."""
    d = float(duty)
    if not (-1.0 <= d <= 1.0):  # also false for NaN
        raise HalValueError(f"{name}={duty!r} is outside [-1, 1] or not finite")
    return d
