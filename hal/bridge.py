"""Host side of protocol v2 (and of v1, which it still accepts): the serial link to the
microcontroller that counts the encoders, measures the battery, reads the hardware estop
input and drives both PWMs (docs/protocol.md).

The port is opened only through `serial.serial_for_url`, so the same driver runs on
/dev/ttyACM0, on a pseudo-terminal of the emulator, over `socket://host:port` and on
`loop://`. Each control tick sends exactly one DRIVE (`drive`) and reads, without blocking,
whatever STATE frames arrived (`state`, which keeps the newest). The MCU's own watchdog
zeroes the motors when DRIVEs stop, so a dead host cannot leave the robot running.
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass
from typing import Any

from ddrt.core.types import Clock
from ddrt.core.wrap import wrap_i32
from ddrt.runtime.clock import MonotonicClock
from hal.base import HalError, HalInitError, HalIOError, HalTimeoutError, check_duty
from hal.wire import (
    DELIMITER, DUTY_FULL_SCALE, FEATURE_BATTERY, FEATURE_HW_ESTOP, FEATURE_WHEELS,
    FLAG_BAD_FRAME, FLAG_HW_ESTOP, FLAG_WATCHDOG, PROTOCOL_V1, PROTOCOL_VERSION, TIMEOUT_MS_MAX,
    TIMEOUT_MS_MIN, Drive, FrameDecoder, Hello, HelloReply, HelloReplyV1, Message, Packet,
    State, StateV1, Stop, encode_frame, seq_gap, wire_bytes,
)

__all__ = ["Bridge", "BridgeState"]

log = logging.getLogger(__name__)

_READ_CHUNK = 4096
_MAX_READS_PER_POLL = 16  # bounds the time one poll can take when the MCU floods the line
# The MCU's clock against the host's: the offset is the lower envelope of (arrival - t_us),
# allowed to creep up this fast (a resonator-clocked AVR may run 0.5 % slow).
_CLOCK_CREEP = 0.01
_RATE_WINDOW_S = 0.02  # the count rate is taken over the STATEs of this long


@dataclass(frozen=True, slots=True)
class BridgeState:
    """The newest STATE as the host sees it.

    `count` continues across MCU resets (the jump at a reset is removed, assuming the wheel
    did not move during the reboot); `raw_count` is what the MCU sent. `new` is True when at
    least one STATE arrived since the previous `state()` call; `resets` is the running
    number of MCU resets seen, so a caller notices one by its change.

    `sampled_at` is when the MCU took the count, on the host's clock: its `t_us` mapped
    through the earliest arrival seen (so it excludes the varying part of the delay: where
    in its STATE period the MCU was when the host asked, and the host's own polling), and
    `counts_per_s` the count's rate over the last STATEs; `count_at(t)` uses both.
    """

    count: int
    raw_count: int
    t_us: int
    flags: int
    ack_seq: int
    age_s: float
    new: bool
    resets: int
    sampled_at: float = math.nan
    counts_per_s: float = 0.0
    # protocol v2 (zero from a v1 MCU): the supply in mV (0 when not measured), the drive
    # wheels' counts (continuous across resets, like `count`) and their rates
    battery_mv: int = 0
    count_left: int = 0
    count_right: int = 0
    left_per_s: float = 0.0
    right_per_s: float = 0.0

    @property
    def hw_estop(self) -> bool:
        """The MCU's hardware estop input is open (or opened since the previous STATE)."""
        return bool(self.flags & FLAG_HW_ESTOP)

    def count_at(self, t: float) -> int:
        """The count carried forward to host time `t` at its rate (the STATE stream runs on
        the MCU's clock, not the host's ticks, so the newest count's age varies from tick
        to tick; at most one STATE period plus the delay's jitter is bridged)."""
        return _carry(self.count, self.counts_per_s, t - self.sampled_at)

    def wheel_counts_at(self, t: float) -> tuple[int, int]:
        """The drive wheels' counts carried forward to host time `t`, as `count_at`."""
        age = t - self.sampled_at
        return _carry(self.count_left, self.left_per_s, age), _carry(self.count_right, self.right_per_s, age)


def _carry(count: int, rate: float, age: float) -> int:
    if not 0.0 < age < 0.05 or not math.isfinite(rate):
        return count
    return count + round(rate * age)


class Bridge:
    """Protocol v2 host driver; a v1 MCU is accepted too (`protocol_version` says which
    answered). Use as a context manager, or call `close()` (safe twice)."""

    def __init__(
        self,
        url: str,
        baudrate: int = 115200,
        drive_timeout_ms: int = 100,
        state_stale_s: float = 0.05,
        *,
        hello_timeout_s: float = 0.5,
        hello_resend_s: float = 0.1,
        write_timeout_s: float = 0.05,
        max_wheel_rev_s: float = 20.0,
        clock: Clock | None = None,
        connect: bool = True,
    ) -> None:
        if not isinstance(url, str) or not url:
            raise ValueError(f"url: expected a non-empty port or URL string, got {url!r}")
        if isinstance(baudrate, bool) or not isinstance(baudrate, int) or baudrate <= 0:
            raise ValueError(f"baudrate: expected a positive int, got {baudrate!r}")
        if (isinstance(drive_timeout_ms, bool) or not isinstance(drive_timeout_ms, int)
                or not TIMEOUT_MS_MIN <= drive_timeout_ms <= TIMEOUT_MS_MAX):
            raise ValueError(f"drive_timeout_ms: expected an int in {TIMEOUT_MS_MIN}.."
                             f"{TIMEOUT_MS_MAX}, got {drive_timeout_ms!r}")
        for name, v in (("state_stale_s", state_stale_s), ("hello_timeout_s", hello_timeout_s),
                        ("hello_resend_s", hello_resend_s), ("write_timeout_s", write_timeout_s),
                        ("max_wheel_rev_s", max_wheel_rev_s)):
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name}: expected a positive finite number, got {v!r}")
        self.url = url
        self.drive_timeout_ms = drive_timeout_ms
        self.state_stale_s = float(state_stale_s)
        self.hello_timeout_s = float(hello_timeout_s)
        self.hello_resend_s = float(hello_resend_s)
        self.max_wheel_rev_s = float(max_wheel_rev_s)
        self.clock: Clock = clock if clock is not None else MonotonicClock()
        # One byte's time on the line (8N1: 10 bits): a STATE's snapshot is older than its
        # arrival by at least its frame's bytes. A link without a line (the in-process
        # emulated MCU) sets 0; a simulated one its own figure.
        self.byte_time_s = 10.0 / baudrate
        self.protocol_version: int | None = None
        self.counts_per_rev = 0
        self.state_rate_hz = 0
        self.features = 0  # HELLO_REPLY v2's FEATURE_* bits (0 from a v1 MCU)
        self.wheel_counts_per_rev = 0
        self._warned_battery = False
        self._decoder = FrameDecoder()
        self._tx_seq = 0
        self._rx_seq: int | None = None
        self._connected = False
        self._connected_at = 0.0
        self._closed = False
        self._fatal: HalError | None = None
        self._last: State | None = None
        self._last_at = 0.0
        self._new = False
        self._offset = 0
        self._count = 0
        self._wheel_offset = (0, 0)
        self._wheels = (0, 0)  # stitched drive-wheel counts
        self._mcu_s = 0.0  # MCU clock, unwrapped, since its boot
        self._clock_offset: float | None = None  # host time - MCU time, lower envelope
        self._offset_at = 0.0
        # (MCU s, stitched count, left, right)
        self._history: deque[tuple[float, int, int, int]] = deque(maxlen=64)
        self.last_drive_seq: int | None = None
        self._hellos_outstanding = 0
        self._stats = {
            "lost_packets": 0, "mcu_resets": 0, "watchdog_trips": 0, "mcu_bad_frames": 0,
            "unknown_packets": 0, "hello_replies": 0, "states": 0, "drives_sent": 0, "stale": 0,
            "io_errors": 0, "hw_estop_states": 0,
        }
        import serial  # lazy: only the real backend needs pyserial

        self._serial_mod = serial
        self._port: Any = None  # until it opens
        try:
            self._port = serial.serial_for_url(
                url, baudrate=baudrate, timeout=0, write_timeout=write_timeout_s)
        except (serial.SerialException, OSError, ValueError) as e:
            raise HalInitError(f"{url}: cannot open serial port: {e}") from e
        if connect:
            try:
                self.connect()
            except BaseException:
                self.close()
                raise

    # -- public API ---------------------------------------------------------------------

    @property
    def port(self) -> Any:
        """The pyserial port (tests on loop:// read the bytes the bridge wrote from it)."""
        return self._port

    @property
    def drive_timeout_s(self) -> float:
        """The MCU's own watchdog (s): it zeroes the motors when no DRIVE arrived for this long."""
        return self.drive_timeout_ms / 1000.0

    @property
    def stats(self) -> dict[str, int]:
        """Fault and traffic counters for telemetry (copy)."""
        d = self._decoder
        out = dict(self._stats)
        out.update(crc_errors=d.crc_errors, undecodable=d.undecodable, oversize=d.oversize,
                   malformed=d.malformed, frames_ok=d.frames_ok)
        return out

    def connect(self, flush_input: bool = True) -> None:
        """HELLO handshake: checks the protocol version within `hello_timeout_s`.

        Input queued before the handshake is discarded (`flush_input`), so an old boot
        announcement is not taken for the reply. A lone 0x00 goes before the HELLO so the
        MCU drops whatever partial frame it holds.
        """
        self._connected = False
        self._rx_seq = None
        self._last = None
        self._hellos_outstanding = 0
        if flush_input:
            try:
                self._port.reset_input_buffer()
            except (self._serial_mod.SerialException, OSError) as e:
                raise HalInitError(f"{self.url}: cannot flush input: {e}") from e
        start = self.clock.now()
        deadline = start + self.hello_timeout_s
        self._send_hello(DELIMITER)
        resend_at = start + self.hello_resend_s
        while True:
            self._poll(init=True)
            if self._connected:
                break
            now = self.clock.now()
            if now >= deadline:
                raise HalInitError(
                    f"{self.url}: no HELLO_REPLY within {self.hello_timeout_s:g} s "
                    "(is the microcontroller powered and running protocol v2 or v1 firmware?)")
            if now >= resend_at:
                self._send_hello(b"")
                resend_at = now + self.hello_resend_s
            self.clock.sleep_until(min(now + 0.002, deadline))
        if self._fatal is not None:
            raise self._fatal
        if self.state_rate_hz <= 0 or 1.0 / self.state_rate_hz >= self.state_stale_s:
            raise HalInitError(
                f"{self.url}: MCU streams STATE at {self.state_rate_hz} Hz, too slow for "
                f"state_stale_s={self.state_stale_s:g}")
        self._note_battery()
        # The link is up when the stream is: wait (within the stale bound) for the first
        # STATE, so a read right after connecting finds one (a v2 STATE at 250 Hz comes up
        # to 6.4 ms after the reply); none by then is left for state() to report.
        deadline = self.clock.now() + self.state_stale_s
        while self._last is None and self._fatal is None:
            now = self.clock.now()
            if now >= deadline:
                break
            self.clock.sleep_until(min(now + 0.001, deadline))
            self._poll(init=True)

    @property
    def battery_measured(self) -> bool:
        return bool(self.features & FEATURE_BATTERY)

    @property
    def hw_estop_wired(self) -> bool:
        return bool(self.features & FEATURE_HW_ESTOP)

    def _note_battery(self) -> None:
        """Say once per bridge that the supply is not measured, and why."""
        if self._warned_battery or self.battery_measured:
            return
        self._warned_battery = True
        why = (f"the MCU speaks protocol v{self.protocol_version}, which does not measure it"
               if self.protocol_version == PROTOCOL_V1 else "the MCU's firmware does not measure it")
        log.warning("%s: battery voltage not measured (%s); the config's supply_v "
                    "(robot.motor.supply_v) is used instead", self.url, why)

    def drive(self, duty_l: float, duty_r: float) -> None:
        """Send one DRIVE (duty in [-1, 1]); the MCU zeroes both outputs if the next one
        does not arrive within drive_timeout_ms."""
        dl = check_duty("duty_l", duty_l)
        dr = check_duty("duty_r", duty_r)
        self._check_fatal()
        msg = Drive(round(dl * DUTY_FULL_SCALE), round(dr * DUTY_FULL_SCALE),
                    self.drive_timeout_ms)
        self.last_drive_seq = self._tx_seq
        self._write(self._frame(msg))
        self._stats["drives_sent"] += 1

    def stop(self) -> None:
        """Send STOP (zero both outputs now). Raises HalIOError if the write fails."""
        self._write(self._frame(Stop()))

    def poll(self) -> None:
        """Read whatever arrived, without blocking. Raises HalIOError if the port failed."""
        self._poll(init=False)

    def state(self) -> BridgeState:
        """Poll, then return the newest STATE. Raises HalTimeoutError when it is older than
        state_stale_s (or none arrived that long after the handshake)."""
        self._check_fatal()
        self._poll(init=False)
        self._check_fatal()
        now = self.clock.now()
        last = self._last
        age = now - (self._last_at if last is not None else self._connected_at)
        if age > self.state_stale_s:
            self._stats["stale"] += 1
            what = "no STATE" if last is None else "newest STATE is"
            raise HalTimeoutError(f"{self.url}: {what} {age * 1e3:.1f} ms old "
                                  f"(limit {self.state_stale_s * 1e3:.1f} ms)")
        if last is None:
            raise HalTimeoutError(f"{self.url}: no STATE received yet")
        new, self._new = self._new, False
        sampled_at = self._mcu_s + self._clock_offset if self._clock_offset is not None else math.nan
        rates = self._rates()
        return BridgeState(count=self._count, raw_count=last.count, t_us=last.t_us,
                           flags=last.flags, ack_seq=last.ack_seq, age_s=age, new=new,
                           resets=self._stats["mcu_resets"], sampled_at=sampled_at,
                           counts_per_s=rates[0], battery_mv=last.battery_mv,
                           count_left=self._wheels[0], count_right=self._wheels[1],
                           left_per_s=rates[1], right_per_s=rates[2])

    def close(self) -> None:
        """Send STOP (best effort) and close the port. Safe to call twice or half-built."""
        if self._closed:
            return
        self._closed = True
        port = self._port
        if port is None:
            return
        try:
            if port.is_open:
                port.write(self._frame(Stop()))
        except Exception:  # noqa: BLE001 - the device may already be gone; closing anyway
            self._stats["io_errors"] += 1
        try:
            port.close()
        except Exception:  # noqa: BLE001
            self._stats["io_errors"] += 1

    def __enter__(self) -> "Bridge":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- internals ------------------------------------------------------------------------

    def _frame(self, msg: Message) -> bytes:
        frame = encode_frame(Packet(self._tx_seq, msg))
        self._tx_seq = (self._tx_seq + 1) & 0xFF
        return frame

    def _send_hello(self, prefix: bytes) -> None:
        self._write(prefix + self._frame(Hello()), init=True)
        self._hellos_outstanding += 1

    def _write(self, data: bytes, init: bool = False) -> None:
        if self._closed:
            raise HalIOError(f"{self.url}: bridge is closed")
        try:
            n = self._port.write(data)
        except (self._serial_mod.SerialException, OSError) as e:
            self._stats["io_errors"] += 1
            cls = HalInitError if init else HalIOError
            raise cls(f"{self.url}: write failed: {e}") from e
        if n is not None and n != len(data):
            self._stats["io_errors"] += 1
            raise (HalInitError if init else HalIOError)(
                f"{self.url}: short write ({n} of {len(data)} bytes)")

    def _poll(self, init: bool) -> None:
        if self._closed:
            raise HalIOError(f"{self.url}: bridge is closed")
        for _ in range(_MAX_READS_PER_POLL):
            try:
                data = self._port.read(_READ_CHUNK)
            except (self._serial_mod.SerialException, OSError) as e:
                self._stats["io_errors"] += 1
                cls = HalInitError if init else HalIOError
                raise cls(f"{self.url}: read failed: {e}") from e
            if not data:
                return
            for pkt in self._decoder.feed(data):
                self._on_packet(pkt)
            if len(data) < _READ_CHUNK:
                return

    def _check_fatal(self) -> None:
        if self._fatal is not None:
            raise self._fatal

    def _on_packet(self, pkt: Packet) -> None:
        msg = pkt.msg
        if isinstance(msg, (HelloReply, HelloReplyV1)):
            self._on_hello_reply(pkt.seq, msg)
            return
        wire_s = wire_bytes(msg.FMT.size) * self.byte_time_s if isinstance(msg, (State, StateV1)) else 0.0
        if isinstance(msg, StateV1):
            msg = msg.as_v2()
        if not isinstance(msg, State):
            self._stats["unknown_packets"] += 1  # host-bound unknown types (or our echo)
            return
        if not self._connected:
            return  # a STATE queued before our HELLO was answered
        prev_seq = self._rx_seq
        self._rx_seq = pkt.seq
        prev = self._last
        reset = False
        if prev is not None:
            dt_us = (msg.t_us - prev.t_us) & 0xFFFFFFFF
            jump = abs(wrap_i32(msg.count - prev.count))
            limit = self.max_wheel_rev_s * self.counts_per_rev * dt_us * 1e-6 + 256
            wheel_limit = self.max_wheel_rev_s * self.wheel_counts_per_rev * dt_us * 1e-6 + 256
            wheel_jump = max(abs(wrap_i32(msg.count_left - prev.count_left)),
                             abs(wrap_i32(msg.count_right - prev.count_right)))
            if dt_us >= 0x80000000 or jump > limit or wheel_jump > wheel_limit:
                # The MCU clock went backwards or the count jumped: it rebooted (its boot
                # HELLO_REPLY, if it got through, only announced it; this is the evidence).
                reset = True
                self._stats["mcu_resets"] += 1
        if reset:
            # Hold the count over the reset: the reboot takes milliseconds, the wheel barely moves.
            self._offset = wrap_i32(self._count - msg.count)
            self._wheel_offset = (wrap_i32(self._wheels[0] - msg.count_left),
                                  wrap_i32(self._wheels[1] - msg.count_right))
        elif prev_seq is not None:
            self._stats["lost_packets"] += seq_gap(prev_seq, pkt.seq)
        self._count = wrap_i32(msg.count + self._offset)
        self._wheels = (wrap_i32(msg.count_left + self._wheel_offset[0]),
                        wrap_i32(msg.count_right + self._wheel_offset[1]))
        self._track_clock(msg.t_us, prev.t_us if prev is not None and not reset else None, wire_s)
        if msg.flags & FLAG_WATCHDOG:
            self._stats["watchdog_trips"] += 1
        if msg.flags & FLAG_BAD_FRAME:
            self._stats["mcu_bad_frames"] += 1
        if msg.flags & FLAG_HW_ESTOP:
            self._stats["hw_estop_states"] += 1
        self._last = msg
        self._last_at = self.clock.now()
        self._new = True
        self._stats["states"] += 1

    def _track_clock(self, t_us: int, prev_t_us: int | None, wire_s: float) -> None:
        """Map the MCU's clock onto the host's (see BridgeState.sampled_at); `wire_s` is how
        long the STATE's frame took on the line after its snapshot."""
        now = self.clock.now() - wire_s
        if prev_t_us is None:  # the first STATE, or the MCU rebooted: its clock restarted
            self._mcu_s = t_us * 1e-6
            self._clock_offset = None
            self._history.clear()
        else:
            self._mcu_s += ((t_us - prev_t_us) & 0xFFFFFFFF) * 1e-6
        seen = now - self._mcu_s
        off = self._clock_offset
        if off is None or seen < off + _CLOCK_CREEP * (now - self._offset_at):
            self._clock_offset = seen
        else:
            self._clock_offset = off + _CLOCK_CREEP * (now - self._offset_at)
        self._offset_at = now
        self._history.append((self._mcu_s, self._count, self._wheels[0], self._wheels[1]))

    def _rates(self) -> tuple[float, float, float]:
        """Counts per second (front, left, right) over the STATEs of the last _RATE_WINDOW_S
        (0 with fewer than two)."""
        h = self._history
        if len(h) < 2:
            return 0.0, 0.0, 0.0
        s1, c1, l1, r1 = h[-1]
        for s0, c0, l0, r0 in h:
            if s1 - s0 <= _RATE_WINDOW_S:
                break
        if s1 <= s0:
            return 0.0, 0.0, 0.0
        dt = s1 - s0
        return wrap_i32(c1 - c0) / dt, wrap_i32(l1 - l0) / dt, wrap_i32(r1 - r0) / dt

    def _on_hello_reply(self, seq: int, msg: HelloReply | HelloReplyV1) -> None:
        v1 = isinstance(msg, HelloReplyV1)
        expected = PROTOCOL_V1 if v1 else PROTOCOL_VERSION
        if msg.protocol_version != expected:
            self._fatal = HalInitError(
                f"{self.url}: MCU speaks protocol version {msg.protocol_version} (in a "
                f"{msg.FMT.size}-byte HELLO_REPLY), this host speaks {PROTOCOL_VERSION} "
                f"and accepts {PROTOCOL_V1}")
        features = 0 if v1 else msg.features
        wheel_cpr = 0 if v1 or not features & FEATURE_WHEELS else msg.wheel_counts_per_rev
        solicited = self._hellos_outstanding > 0
        self._hellos_outstanding = max(0, self._hellos_outstanding - 1)
        if self._connected and solicited:
            pass  # the answer to a HELLO we resent during the handshake
        elif self._connected:
            # Unsolicited: the MCU announces a reboot this way, but a stale boot announcement
            # can also arrive just after the handshake; the next STATE decides (_on_packet).
            self._stats["hello_replies"] += 1
            same = (msg.protocol_version, msg.encoder_counts_per_rev, features, wheel_cpr) == (
                self.protocol_version, self.counts_per_rev, self.features, self.wheel_counts_per_rev)
            if not same and self._fatal is None:
                self._fatal = HalIOError(
                    f"{self.url}: MCU came back as protocol v{msg.protocol_version} with "
                    f"{msg.encoder_counts_per_rev} counts/rev, features 0x{features:02x}, "
                    f"{wheel_cpr} wheel counts/rev; was v{self.protocol_version}, "
                    f"{self.counts_per_rev}, 0x{self.features:02x}, {self.wheel_counts_per_rev}")
        else:
            self._connected = True
            self._connected_at = self.clock.now()
            self.protocol_version = msg.protocol_version
            self.counts_per_rev = msg.encoder_counts_per_rev
            self.state_rate_hz = msg.state_rate_hz
            self.features = features
            self.wheel_counts_per_rev = wheel_cpr
        self._rx_seq = seq
