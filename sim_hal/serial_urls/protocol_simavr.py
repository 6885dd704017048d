"""pyserial URL handler `simavr://NAME`: the pseudo-terminal of a ddrt-simavr harness run in
lockstep, with the two waits that make a lockstep run deterministic.

The host driver (hal/bridge.py) opens it with `serial_for_url` and gets a real POSIX serial
port on the harness's pty. A pty hands bytes over through a kernel work queue, so a byte
written is not readable on the other side at once. In lockstep the harness only runs when
told to, so:

- host -> MCU: the port counts the bytes it wrote; the harness is told that count with the
  next `run` and waits until it has read them all before simulating (sim_hal/firmware_sim.py);
- MCU -> host: the harness reports how many bytes it has written; before a read (or a
  flush) the port waits until the kernel has delivered all of them.

Either wait is bounded; a byte stream that does not come through is an I/O error. Paced
runs (`ddrt run`, stepped by the daemon's tick) wait a little (`wait_s`) and go on without
what is late: a busy machine's scheduler must not stall the tick; the free-running harness
(`simavr://?free-running`) is opened on the pty's own path, with no counting at all.
"""

from __future__ import annotations

import select
import time

import serial
from serial.serialposix import Serial as PosixSerial
from serial.serialutil import SerialException

__all__ = ["PtyCounts", "register", "unregister"]

SYNC_TIMEOUT_S = 5.0
PACED_WRITE_TIMEOUT_S = 1.0


class PtyCounts:
    """Bytes each side put on one lockstep pty: `host_written` (by the port), `mcu_sent` (by
    the harness, from its replies) and `host_read` (by the port)."""

    def __init__(self, pty_path: str, wait_s: float = SYNC_TIMEOUT_S, strict: bool = True) -> None:
        self.pty_path = pty_path
        self.wait_s = wait_s  # how long a read waits for the MCU's bytes to come through
        self.strict = strict  # True: bytes that do not come in time are an I/O error
        self.host_written = 0
        self.mcu_sent = 0
        self.host_read = 0


_LINKS: dict[str, PtyCounts] = {}


def register(name: str, pty_path: str, wait_s: float = SYNC_TIMEOUT_S, strict: bool = True) -> PtyCounts:
    counts = PtyCounts(pty_path, wait_s, strict)
    _LINKS[name] = counts
    return counts


def unregister(name: str) -> None:
    _LINKS.pop(name, None)


class _SyncedPty(PosixSerial):
    """The pty's POSIX port, counting what crosses it (the class attribute `_counts`)."""

    _counts: PtyCounts

    def open(self) -> None:
        super().open()  # discards what the kernel already holds for the pty
        counts = self._counts
        # pyserial's write raises 'Write timeout' when its deadline passed by the time all bytes
        # were written, even if none had to wait: a host preempted for longer than the bridge's
        # 50 ms write timeout on a loaded machine fails a write the pty took at once. A pty
        # write only waits when 4 KiB are unread, so: no wall-clock bound in lockstep (simulated
        # time; a harness that died closes the pty, and the write fails on that), and a bound
        # well beyond any preemption when paced.
        self._write_timeout = None if counts.strict else max(self._write_timeout or 0.0, PACED_WRITE_TIMEOUT_S)
        if counts.mcu_sent != counts.host_read:
            # Opened after the MCU sent something (a reopen): what was in flight lands within
            # microseconds; let it land, drop it, and count it as read.
            time.sleep(0.02)
            super().reset_input_buffer()
            counts.host_read = counts.mcu_sent

    def _sync(self) -> None:
        counts = self._counts
        want = counts.mcu_sent - counts.host_read
        if want <= 0:
            return
        deadline = time.monotonic() + counts.wait_s
        while super().in_waiting < want:
            left = deadline - time.monotonic()
            if left <= 0:
                if not counts.strict:
                    return  # paced: what is late comes with a later read
                raise SerialException(f"{self.portstr}: {want} byte(s) from the simulated MCU did "
                                      f"not come through the pty")
            select.select([self.fd], [], [], min(left, 0.01))

    @property
    def in_waiting(self) -> int:
        self._sync()
        return super().in_waiting

    def read(self, size: int = 1) -> bytes:
        self._sync()
        data = super().read(size)
        self._counts.host_read += len(data)
        return data

    def write(self, data) -> int:
        n = super().write(data)
        self._counts.host_written += n if n is not None else len(data)
        return n

    def reset_input_buffer(self) -> None:
        self._sync()
        super().reset_input_buffer()
        self._counts.host_read = self._counts.mcu_sent


def serial_class_for_url(url: str):
    """pyserial's hook: `simavr://NAME` -> (the pty's path, a port class bound to its counts)."""
    name = url.split("://", 1)[-1].strip("/")
    try:
        counts = _LINKS[name]
    except KeyError:
        raise SerialException(f"simavr://{name}: no simulated microcontroller of that name") from None
    klass = type("SimavrPty", (_SyncedPty,), {"_counts": counts})
    return counts.pty_path, klass


if "sim_hal.serial_urls" not in serial.protocol_handler_packages:
    serial.protocol_handler_packages.append("sim_hal.serial_urls")
