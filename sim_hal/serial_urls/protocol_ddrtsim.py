"""pyserial URL handler `ddrtsim://NAME`: a serial port wired, in process, to an emulated MCU.

`serial.serial_for_url("ddrtsim://robot")` returns a port whose writes go straight into the
McuEmulator registered under "robot" and whose reads return what the emulator transmitted
when its link was last pumped. Unlike a pseudo-terminal or a socket there is no kernel in
between, so a closed loop in simulated time is deterministic byte for byte; the bridge
driver still opens its port through serial_for_url and speaks the same bytes.
"""

from __future__ import annotations

import time
from typing import Any

import serial
from serial.serialutil import PortNotOpenError, SerialBase, SerialException

_LINKS: dict[str, "InProcessLink"] = {}


class InProcessLink:
    """The wire between the host's port and one McuEmulator."""

    def __init__(self, name: str, mcu: Any, now: float = 0.0) -> None:
        self.name = name
        self.mcu = mcu
        self.now = now
        self.to_host = bytearray()
        self.from_host_filter = None  # optional callable(bytes) -> bytes (fault injection)
        self.to_host_filter = None

    def pump(self, now: float) -> None:
        """Let the MCU run up to `now` and queue what it sends for the host."""
        self.now = now
        data = self.mcu.service(now)
        if data and self.to_host_filter is not None:
            data = self.to_host_filter(data)
        self.to_host += data

    def host_write(self, data: bytes) -> None:
        if self.from_host_filter is not None:
            data = self.from_host_filter(data)
        self.mcu.receive(bytes(data), self.now)


def register(name: str, mcu: Any, now: float = 0.0) -> InProcessLink:
    link = InProcessLink(name, mcu, now)
    _LINKS[name] = link
    return link


def unregister(name: str) -> None:
    _LINKS.pop(name, None)


class Serial(SerialBase):
    """The host end of an InProcessLink (only what the bridge driver uses)."""

    def open(self) -> None:
        if self._port is None:
            raise SerialException("Port must be configured before it can be used.")
        if self.is_open:
            raise SerialException("Port is already open.")
        name = self._port.split("://", 1)[-1].strip("/")
        try:
            self._link = _LINKS[name]
        except KeyError:
            raise SerialException(f"ddrtsim://{name}: no emulated microcontroller of that name") from None
        self.is_open = True

    def close(self) -> None:
        self.is_open = False

    def _reconfigure_port(self) -> None:
        pass

    @property
    def in_waiting(self) -> int:
        if not self.is_open:
            raise PortNotOpenError()
        return len(self._link.to_host)

    def read(self, size: int = 1) -> bytes:
        if not self.is_open:
            raise PortNotOpenError()
        buf = self._link.to_host
        if not buf and self._timeout:
            time.sleep(0)  # nothing arrives while we wait: time only moves when pumped
        out = bytes(buf[:size])
        del buf[:size]
        return out

    def write(self, data: bytes) -> int:
        if not self.is_open:
            raise PortNotOpenError()
        self._link.host_write(bytes(data))
        return len(data)

    def flush(self) -> None:
        pass

    def reset_input_buffer(self) -> None:
        if not self.is_open:
            raise PortNotOpenError()
        self._link.to_host.clear()

    def reset_output_buffer(self) -> None:
        pass

    @property
    def out_waiting(self) -> int:
        return 0

    def _update_break_state(self) -> None:
        pass

    def _update_rts_state(self) -> None:
        pass

    def _update_dtr_state(self) -> None:
        pass

    @property
    def cts(self) -> bool:
        return True

    @property
    def dsr(self) -> bool:
        return True

    @property
    def ri(self) -> bool:
        return False

    @property
    def cd(self) -> bool:
        return True


if "sim_hal.serial_urls" not in serial.protocol_handler_packages:
    serial.protocol_handler_packages.append("sim_hal.serial_urls")
