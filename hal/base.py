"""The hardware interface every backend implements, and the HAL's exception tree.

The controller only ever sees this module: a backend (the simulated robot, or the real
drivers on a bus and a serial port) is chosen by name in the config and handed to the loop
as a `Hal`. A backend must override `read`, `write`, `stop` and `close`; it may override
`__enter__`/`__exit__` (the default closes, which stops the motors first).
"""

from __future__ import annotations

from abc import ABC, abstractmethod

from ddrt.core.types import HalInfo, Sample

__all__ = ["Hal", "HalError", "HalInfo", "HalInitError", "HalIOError", "HalTimeoutError",
           "HalValueError", "Sample", "check_duty"]


class HalError(Exception):
    """Root of every error a HAL raises; catch this to catch them all."""


class HalInitError(HalError, OSError):
    """A device could not be opened or identified (wrong WHO_AM_I, protocol version, ...)."""


class HalIOError(HalError, OSError):
    """A transfer failed after its retries (I2C EIO, a serial write error, ...)."""


class HalTimeoutError(HalIOError, TimeoutError):
    """A device stopped answering within its bound (stale STATE stream, I2C timeout)."""


class HalValueError(HalError, ValueError):
    """A value handed to the HAL is out of range or not finite (a duty of 1.5, a NaN)."""


class Hal(ABC):
    """A robot as the controller sees it: sensors to read, two motors to drive."""

    info: HalInfo

    @abstractmethod
    def read(self) -> Sample:
        """Read every sensor once. Raises HalIOError/HalTimeoutError, never returns junk."""

    @abstractmethod
    def write(self, duty_l: float, duty_r: float) -> None:
        """Command both motors, duty in [-1, 1] (1 = full supply voltage forward).

        Raises HalValueError for a value out of range or not finite, without moving anything.
        """

    @abstractmethod
    def stop(self) -> None:
        """Set both motors to zero now. Must not raise for a device that is already gone."""

    @abstractmethod
    def close(self) -> None:
        """Stop the motors and release every device. Safe to call twice or half-built."""

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
