"""Two DC motors on the Linux PWM class plus one direction GPIO line each (sign-magnitude
drive, as on most H-bridge boards: PWM on the enable pin, direction on a second pin).

Paths follow the kernel ABI under a configurable `root` (default "/sys"), so tests run
against a temp dir laid out like sysfs:
    {root}/class/pwm/pwmchipN/export, .../pwmchipN/pwmM/{period,duty_cycle,enable}
    {root}/class/gpio/export, .../gpio/gpioK/{direction,value}
The direction writer is pluggable (sysfs GPIO is deprecated on new kernels; a libgpiod
writer can replace it without touching the PWM side).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Protocol, Sequence

from hal.base import HalInitError, HalIOError, check_duty

__all__ = ["DirectionWriter", "PwmSysfsMotors", "SysfsGpioDirection"]


def _write(path: Path, value: str | int, init: bool = False) -> None:
    try:
        with open(path, "w") as f:
            f.write(str(value))
    except OSError as e:
        raise (HalInitError if init else HalIOError)(f"{path}: cannot write {value!r}: {e}") from e


def _wait_for(path: Path, timeout_s: float) -> None:
    """The kernel (and udev, for permissions) creates an exported node asynchronously."""
    deadline = time.monotonic() + timeout_s
    while not path.exists():
        if time.monotonic() >= deadline:
            raise HalInitError(f"{path}: did not appear within {timeout_s:g} s after export")
        time.sleep(0.001)


class DirectionWriter(Protocol):
    """Sets one motor's direction line; motor 0 is left, 1 is right."""

    def set_direction(self, motor: int, forward: bool) -> None: ...
    def close(self) -> None: ...


class SysfsGpioDirection:
    """Direction lines through /sys/class/gpio: value 1 = forward, 0 = reverse."""

    def __init__(self, gpios: Sequence[int], root: str | Path = "/sys",
                 export_timeout_s: float = 1.0) -> None:
        if len(gpios) != 2 or not all(isinstance(g, int) and g >= 0 for g in gpios):
            raise ValueError(f"direction_gpios: expected two GPIO numbers, got {gpios!r}")
        base = Path(root) / "class" / "gpio"
        self._values: list[Path] = []
        for g in gpios:
            node = base / f"gpio{g}"
            if not node.exists():
                _write(base / "export", g, init=True)
                _wait_for(node / "direction", export_timeout_s)
            _write(node / "direction", "low", init=True)  # output, driven low, glitch-free
            self._values.append(node / "value")

    def set_direction(self, motor: int, forward: bool) -> None:
        _write(self._values[motor], 1 if forward else 0)

    def close(self) -> None:
        """Lines stay exported and low; nothing to release."""


class PwmSysfsMotors:
    """Left/right motor duties in [-1, 1] -> duty_cycle (ns) and a direction line each."""

    drive_timeout_s: float | None = None  # no watchdog of its own: a duty holds until written again

    def __init__(self, chip: int, channels: Sequence[int], period_ns: int,
                 direction_gpios: Sequence[int] | None = None, root: str | Path = "/sys",
                 *, direction: DirectionWriter | None = None,
                 invert: Sequence[bool] = (False, False), export_timeout_s: float = 1.0) -> None:
        if isinstance(chip, bool) or not isinstance(chip, int) or chip < 0:
            raise ValueError(f"chip: expected a non-negative int, got {chip!r}")
        if len(channels) != 2 or not all(isinstance(c, int) and c >= 0 for c in channels):
            raise ValueError(f"channels: expected two PWM channel numbers, got {channels!r}")
        if isinstance(period_ns, bool) or not isinstance(period_ns, int) or period_ns <= 0:
            raise ValueError(f"period_ns: expected a positive int, got {period_ns!r}")
        if len(invert) != 2:
            raise ValueError(f"invert: expected two booleans, got {invert!r}")
        self.period_ns = period_ns
        self._invert = (bool(invert[0]), bool(invert[1]))
        self._closed = False
        self._duty_ns = [0, 0]
        self._forward = [True, True]
        self._dirs: list[Path] = []
        self._direction: DirectionWriter | None = None  # set once the outputs are at zero; close() releases it
        chip_dir = Path(root) / "class" / "pwm" / f"pwmchip{chip}"
        if not chip_dir.is_dir():
            raise HalInitError(f"{chip_dir}: no such PWM chip (is the overlay enabled?)")
        for ch in channels:
            node = chip_dir / f"pwm{ch}"
            if not node.exists():
                _write(chip_dir / "export", ch, init=True)
                _wait_for(node / "enable", export_timeout_s)
            self._dirs.append(node)
        try:
            for node in self._dirs:
                _write(node / "duty_cycle", 0, init=True)  # must never exceed the period
                _write(node / "period", period_ns, init=True)
                _write(node / "duty_cycle", 0, init=True)
            if direction is None:
                if direction_gpios is None:
                    raise ValueError("direction_gpios: required when no direction writer is given")
                direction = SysfsGpioDirection(direction_gpios, root, export_timeout_s)
            self._direction = direction
            for i in range(2):
                self._direction.set_direction(i, not self._invert[i])
            for node in self._dirs:
                _write(node / "enable", 1, init=True)
        except BaseException:
            self.close()
            raise

    def drive(self, duty_l: float, duty_r: float) -> None:
        """Apply both duties (raises HalValueError before moving anything if out of range)."""
        duties = (check_duty("duty_l", duty_l), check_duty("duty_r", duty_r))
        if self._closed:
            raise HalIOError("pwm_sysfs: motors are closed")
        for i, d in enumerate(duties):
            forward = d >= 0.0
            ns = min(self.period_ns, round(abs(d) * self.period_ns))
            if forward != self._forward[i]:
                if self._duty_ns[i]:
                    self._set_ns(i, 0)  # never drive the old duty the wrong way
                self._direction.set_direction(i, forward != self._invert[i])
                self._forward[i] = forward
            if ns != self._duty_ns[i]:
                self._set_ns(i, ns)

    def stop(self) -> None:
        """Both duties to zero now."""
        for i in range(2):
            self._set_ns(i, 0)

    def close(self) -> None:
        """Zero and disable both outputs (best effort). Safe twice."""
        if self._closed:
            return
        self._closed = True
        for i, node in enumerate(self._dirs):
            for name, value in (("duty_cycle", 0), ("enable", 0)):
                try:
                    _write(node / name, value)
                except HalIOError:
                    pass
            self._duty_ns[i] = 0
        if self._direction is not None:
            self._direction.close()

    def _set_ns(self, i: int, ns: int) -> None:
        _write(self._dirs[i] / "duty_cycle", ns)
        self._duty_ns[i] = ns

    def __enter__(self) -> "PwmSysfsMotors":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
