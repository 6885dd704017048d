"""Fault injection for the emulated devices: the faults the real link and bus will have.

- `SerialFaults`: a byte filter for one direction of a link (PtyLink/TcpLink `to_host=` or
  `to_mcu=`): drops bytes, flips bits, injects garbage, or goes mute. Seeded, so a failing
  test replays exactly.
- `FaultyI2cBus`: wraps an smbus-like bus; fails the next n transfers with an errno (a burst
  of EIO), stops answering altogether (NAKs), or answers every read with zeros.
- `inject_gyro_fault`: one of GYRO_FAULTS on an emulated gyro and its bus: its output frozen,
  stalled (its FIFO stops filling), all zeros, NAKs, or a reset of the part (a brown-out).
- `reset_mcu`: reboots the emulated microcontroller (its seq restarts, its count jumps).
"""

from __future__ import annotations

import errno
import random
from typing import Any

from sim_hal.mcu_emulator import Link, McuEmulator
from sim_hal.mpu_emulator import MpuEmulator

__all__ = ["GYRO_FAULTS", "FaultyI2cBus", "SerialFaults", "inject_gyro_fault", "reset_mcu"]

# What a gyro that stops answering does: the part's own faults, then its bus's.
GYRO_FAULTS = ("frozen", "stalled", "zeros", "nak", "reset")


class SerialFaults:
    """Callable bytes -> bytes. Probabilities are per byte (drop, corrupt) or per chunk
    (garbage: a burst of 1..garbage_max random bytes, zeros included, at a random place)."""

    def __init__(self, seed: int = 0, drop_prob: float = 0.0, corrupt_prob: float = 0.0,
                 garbage_prob: float = 0.0, garbage_max: int = 8) -> None:
        for name, p in (("drop_prob", drop_prob), ("corrupt_prob", corrupt_prob),
                        ("garbage_prob", garbage_prob)):
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"{name}: expected a probability in [0, 1], got {p!r}")
        self.rng = random.Random(seed)
        self.drop_prob = drop_prob
        self.corrupt_prob = corrupt_prob
        self.garbage_prob = garbage_prob
        self.garbage_max = garbage_max
        self.mute = False  # the device stops answering: everything is swallowed
        self.dropped = 0
        self.corrupted = 0
        self.garbage_bytes = 0

    def __call__(self, data: bytes) -> bytes:
        if self.mute:
            self.dropped += len(data)
            return b""
        rng = self.rng
        out = bytearray()
        if self.drop_prob or self.corrupt_prob:
            for b in data:
                if rng.random() < self.drop_prob:
                    self.dropped += 1
                    continue
                if rng.random() < self.corrupt_prob:
                    b ^= 1 << rng.randrange(8)
                    self.corrupted += 1
                out.append(b)
        else:
            out += data
        if self.garbage_prob and rng.random() < self.garbage_prob:
            n = rng.randint(1, self.garbage_max)
            pos = rng.randint(0, len(out))
            out[pos:pos] = bytes(rng.randrange(256) for _ in range(n))
            self.garbage_bytes += n
        return bytes(out)


class FaultyI2cBus:
    """smbus-like wrapper: `fail_next(n, err)` makes the next n transfers raise OSError(err);
    `stop_answering(err)` makes every transfer fail, and `read_zeros()` every read return zeros
    (writes lost), until `resume()`."""

    def __init__(self, bus: Any) -> None:
        self.bus = bus
        self._fail_left = 0
        self._fail_errno = errno.EIO
        self._dead_errno: int | None = None
        self._zeros = False
        self.injected = 0

    def read_zeros(self) -> None:
        self._zeros = True

    def fail_next(self, n: int, err: int = errno.EIO) -> None:
        self._fail_left = n
        self._fail_errno = err

    def stop_answering(self, err: int = errno.EREMOTEIO) -> None:
        self._dead_errno = err

    def resume(self) -> None:
        self._dead_errno = None
        self._fail_left = 0
        self._zeros = False

    def _maybe_fail(self) -> None:
        if self._dead_errno is not None:
            self.injected += 1
            raise OSError(self._dead_errno, errno.errorcode.get(self._dead_errno, "I2C error"))
        if self._fail_left > 0:
            self._fail_left -= 1
            self.injected += 1
            raise OSError(self._fail_errno, errno.errorcode.get(self._fail_errno, "I2C error"))

    def read_byte_data(self, i2c_addr: int, register: int, force: bool | None = None) -> int:
        self._maybe_fail()
        if self._zeros:
            return 0
        return self.bus.read_byte_data(i2c_addr, register)

    def write_byte_data(self, i2c_addr: int, register: int, value: int,
                        force: bool | None = None) -> None:
        self._maybe_fail()
        if not self._zeros:
            self.bus.write_byte_data(i2c_addr, register, value)

    def read_i2c_block_data(self, i2c_addr: int, register: int, length: int,
                            force: bool | None = None) -> list[int]:
        self._maybe_fail()
        if self._zeros:
            return [0] * length
        return self.bus.read_i2c_block_data(i2c_addr, register, length)


def inject_gyro_fault(kind: str, part: MpuEmulator, bus: FaultyI2cBus) -> None:
    """Make the emulated gyro `part`, reached through `bus`, fail as `kind` (GYRO_FAULTS) from now."""
    if kind == "frozen":
        part.freeze()
    elif kind == "stalled":
        part.stall()
    elif kind == "reset":
        part.brown_out()
    elif kind == "zeros":
        bus.read_zeros()
    elif kind == "nak":
        bus.stop_answering(errno.EREMOTEIO)
    else:
        raise ValueError(f"gyro fault: expected one of {', '.join(GYRO_FAULTS)}, got {kind!r}")


def reset_mcu(target: McuEmulator | Link, now: float | None = None) -> None:
    """Reboot the emulated MCU at `now` (default: the link's clock). Given a link, this runs
    under its lock so it does not race the pump thread."""
    if isinstance(target, Link):
        with target.lock:
            target.mcu.reset(target.clock() if now is None else now)
    else:
        if now is None:
            raise ValueError("now: required when resetting a bare McuEmulator")
        target.reset(now)
