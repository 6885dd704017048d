"""A microcontroller that speaks protocol v2 (or v1, `protocol_version=1`), so hal/bridge.py
can be tested byte for byte.

`McuEmulator` is the firmware model and does no I/O: `receive(data, now)` takes bytes from
the host, `service(now)` runs the watchdog and the STATE stream and returns the bytes to
send. Its physical side is a `MotorsAndEncoder` (later the simulated robot). A link moves the
bytes over a real pseudo-terminal (`PtyLink`, the Bridge opens `link.url`) or a TCP socket on
127.0.0.1 (`TcpLink`, `socket://127.0.0.1:PORT`), either from a background thread
(`start()`) or one step at a time (`pump(now)`, deterministic: the closed loop calls it from
the simulated clock).
"""

from __future__ import annotations

import errno
import math
import os
import select
import socket
import threading
import time
import tty
from typing import Callable, Protocol

from ddrt.core.wrap import wrap_i32
from hal.wire import (
    DUTY_FULL_SCALE, FEATURE_BATTERY, FEATURE_HW_ESTOP, FEATURE_WHEELS, FLAG_BAD_FRAME,
    FLAG_HW_ESTOP, FLAG_OUTPUTS_ON, FLAG_WATCHDOG, PROTOCOL_V1, PROTOCOL_VERSION, Drive,
    FrameDecoder, Hello, HelloReply, HelloReplyV1, Message, Packet, State, StateV1, Stop,
    encode_frame,
)

__all__ = [
    "DutyIntegratingEncoder", "McuEmulator", "MotorsAndEncoder", "PtyLink", "TcpLink",
]

ByteFilter = Callable[[bytes], bytes]


class MotorsAndEncoder(Protocol):
    """What the MCU drives and reads: two PWM outputs (duty in [-1, 1]) and one counter."""

    def set_duty(self, duty_l: float, duty_r: float) -> None: ...
    def encoder_count(self) -> int: ...


class DutyIntegratingEncoder:
    """In-memory plant for tests: the front wheel turns at the mean duty times a top speed.

    Keeps the history of every `set_duty` as (t, duty_l, duty_r) on its own time source, so a
    test can measure when the outputs changed.
    """

    def __init__(self, time_source: Callable[[], float] = time.monotonic,
                 counts_per_s_at_full: float = 8192.0 * 5.0) -> None:
        self._now = time_source
        self.counts_per_s_at_full = counts_per_s_at_full
        self.duty_l = 0.0
        self.duty_r = 0.0
        self._pos = 0.0
        self._t = time_source()
        self.history: list[tuple[float, float, float]] = []

    def _advance(self) -> float:
        t = self._now()
        self._pos += 0.5 * (self.duty_l + self.duty_r) * self.counts_per_s_at_full * (t - self._t)
        self._t = t
        return t

    def set_duty(self, duty_l: float, duty_r: float) -> None:
        t = self._advance()
        self.duty_l, self.duty_r = float(duty_l), float(duty_r)
        self.history.append((t, self.duty_l, self.duty_r))

    def encoder_count(self) -> int:
        self._advance()
        return int(self._pos)

    def add_counts(self, n: int) -> None:
        """Move the wheel by hand (tests)."""
        self._pos += n


class McuEmulator:
    """Protocol v2 firmware (v1 with `protocol_version=1`), transport-free. All times in
    seconds on the caller's clock.

    At boot (construction, `reset`) it announces itself with an unsolicited HELLO_REPLY, its
    seq restarts at 0, its clock restarts at 0 and its counters restart at 0 (the wheels have
    not moved, so the host sees the counts jump). STATE streams from boot at `state_rate_hz`.

    v2 inputs, each present when given (and announced in HELLO_REPLY's features):
    `battery_v()` the supply at the driver (V, reported in whole mV), `wheel_counts()` the
    drive wheels' counters at `wheel_counts_per_rev`, and the hardware estop input
    (`estop_wired`, opened and closed with `set_estop`): while it is open the outputs are held
    at zero, a DRIVE is acknowledged but not applied, and STATE's flag bit3 is set (also in
    the first STATE after an opening shorter than a STATE period). When it closes nothing is
    applied until the next DRIVE. A v1 MCU has none of them.
    """

    def __init__(self, plant: MotorsAndEncoder, *, now: float = 0.0,
                 counts_per_rev: int = 8192, state_rate_hz: int = 200,
                 protocol_version: int = PROTOCOL_VERSION, t_us_offset: int = 0,
                 battery_v: Callable[[], float] | None = None,
                 wheel_counts: Callable[[], tuple[int, int]] | None = None,
                 wheel_counts_per_rev: int = 0, estop_wired: bool = False) -> None:
        if state_rate_hz <= 0:
            raise ValueError(f"state_rate_hz: must be positive, got {state_rate_hz!r}")
        if not 1 <= protocol_version <= 255:  # v1's layouts for 1, v2's for any other (tests)
            raise ValueError(f"protocol_version: must be 1..255, got {protocol_version!r}")
        if (wheel_counts is None) != (wheel_counts_per_rev <= 0):
            raise ValueError("wheel_counts and wheel_counts_per_rev > 0 go together")
        v1 = protocol_version == PROTOCOL_V1
        if v1 and (battery_v is not None or wheel_counts is not None or estop_wired):
            raise ValueError("a v1 MCU measures no battery, counts no wheels, has no estop input")
        self.plant = plant
        self.counts_per_rev = counts_per_rev
        self.state_rate_hz = state_rate_hz
        self.protocol_version = protocol_version
        self.t_us_offset = t_us_offset
        self.battery_v = battery_v
        self.wheel_counts = wheel_counts
        self.wheel_counts_per_rev = wheel_counts_per_rev if wheel_counts is not None else 0
        self.estop_wired = estop_wired
        self.estop_open = False
        self.drives_unapplied = 0  # acknowledged while the estop input was open
        self.boots = 0
        self.drives_accepted = 0
        self.drives_rejected = 0
        self.stops = 0
        self.hellos = 0
        self.watchdog_trips = 0
        self.states_sent = 0
        self.reset(now)

    # -- firmware state -------------------------------------------------------------------

    def reset(self, now: float) -> None:
        """Reboot: outputs off, seq, clock and counter restart, boot HELLO_REPLY queued."""
        self._decoder = FrameDecoder()
        self._bad_seen = 0
        self._out = bytearray()
        self._seq = 0
        self._boot_t = now
        self._count_base = self.plant.encoder_count()
        self._wheel_base = self.wheel_counts() if self.wheel_counts is not None else (0, 0)
        self.duty_l = 0
        self.duty_r = 0
        self.plant.set_duty(0.0, 0.0)
        self._deadline: float | None = None
        self._flags = 0
        self.ack_seq = 0
        self._state_k = 0  # index of the next STATE on the boot-relative schedule
        self.boots += 1
        self._send(self._hello_reply())

    @property
    def outputs(self) -> tuple[float, float]:
        """Duties currently applied to the plant, in [-1, 1]."""
        return self.duty_l / DUTY_FULL_SCALE, self.duty_r / DUTY_FULL_SCALE

    @property
    def bad_frames(self) -> int:
        d = self._decoder
        return d.crc_errors + d.undecodable + d.oversize + d.malformed

    @property
    def features(self) -> int:
        """HELLO_REPLY v2's features bits for what this MCU has."""
        return ((FEATURE_BATTERY if self.battery_v is not None else 0)
                | (FEATURE_HW_ESTOP if self.estop_wired else 0)
                | (FEATURE_WHEELS if self.wheel_counts is not None else 0))

    def set_estop(self, open_: bool, now: float) -> None:
        """The estop input opens (True) or closes (False) at `now`. Opening zeroes the
        outputs at once and disarms the DRIVE watchdog; closing applies nothing."""
        if not self.estop_wired:
            raise ValueError("this MCU has no hardware estop input (estop_wired=False)")
        self._check_watchdog(now)
        self.estop_open = bool(open_)
        if self.estop_open:
            self._flags |= FLAG_HW_ESTOP
            self._apply(0, 0)
            self._deadline = None

    def receive(self, data: bytes, now: float) -> None:
        """Bytes from the host (any chunking); commands take effect at once."""
        for pkt in self._decoder.feed(data):
            self._handle(pkt, now)
        bad = self.bad_frames
        if bad != self._bad_seen:
            self._bad_seen = bad
            self._flags |= FLAG_BAD_FRAME
        self._check_watchdog(now)

    def service(self, now: float) -> bytes:
        """Run the watchdog and the STATE stream up to `now`; return the bytes to transmit."""
        self._check_watchdog(now)
        period = 1.0 / self.state_rate_hz
        if now >= self._boot_t + self._state_k * period - 1e-9:
            self._send(self._state(now))
            # the schedule is k * period from boot (no drift); if behind, skip, do not burst
            self._state_k = max(self._state_k + 1,
                                math.floor((now - self._boot_t) / period + 1e-6) + 1)
        out = bytes(self._out)
        self._out.clear()
        return out

    # -- internals ------------------------------------------------------------------------

    def _handle(self, pkt: Packet, now: float) -> None:
        msg = pkt.msg
        if isinstance(msg, Hello):
            self.hellos += 1
            self._send(self._hello_reply())
        elif isinstance(msg, Drive):
            if not msg.in_range():
                self.drives_rejected += 1
                return
            self.drives_accepted += 1
            self.ack_seq = pkt.seq
            if self.estop_open:
                self.drives_unapplied += 1  # acknowledged, not applied: outputs stay zero
                return
            self._apply(msg.duty_l, msg.duty_r)
            self._deadline = now + msg.timeout_ms * 1e-3
        elif isinstance(msg, Stop):
            self.stops += 1
            self.ack_seq = pkt.seq
            self._apply(0, 0)
            self._deadline = None
        # every other type is ignored, as the protocol says

    def _apply(self, duty_l: int, duty_r: int) -> None:
        if (duty_l, duty_r) != (self.duty_l, self.duty_r):
            self.duty_l, self.duty_r = duty_l, duty_r
            self.plant.set_duty(duty_l / DUTY_FULL_SCALE, duty_r / DUTY_FULL_SCALE)

    def _check_watchdog(self, now: float) -> None:
        if self._deadline is not None and now >= self._deadline:
            self._deadline = None
            self._apply(0, 0)
            self._flags |= FLAG_WATCHDOG
            self.watchdog_trips += 1

    def _hello_reply(self) -> HelloReply | HelloReplyV1:
        if self.protocol_version == PROTOCOL_V1:
            return HelloReplyV1(self.protocol_version, self.counts_per_rev, self.state_rate_hz)
        return HelloReply(self.protocol_version, self.counts_per_rev, self.state_rate_hz,
                          self.features, self.wheel_counts_per_rev)

    def _state(self, now: float) -> State | StateV1:
        t_us = (round((now - self._boot_t) * 1e6) + self.t_us_offset) & 0xFFFFFFFF
        count = wrap_i32(self.plant.encoder_count() - self._count_base) if self.counts_per_rev else 0
        flags = self._flags | (FLAG_OUTPUTS_ON if (self.duty_l or self.duty_r) else 0)
        if self.estop_open:
            flags |= FLAG_HW_ESTOP
        self._flags = 0
        self.states_sent += 1
        if self.protocol_version == PROTOCOL_V1:
            return StateV1(t_us, count, flags, self.ack_seq)
        mv = 0
        if self.battery_v is not None:
            mv = min(0xFFFF, max(0, round(self.battery_v() * 1000.0)))
        left = right = 0
        if self.wheel_counts is not None:
            wl, wr = self.wheel_counts()
            left = wrap_i32(wl - self._wheel_base[0])
            right = wrap_i32(wr - self._wheel_base[1])
        return State(t_us, count, flags, self.ack_seq, mv, left, right)

    def _send(self, msg: Message) -> None:
        self._out += encode_frame(Packet(self._seq, msg))
        self._seq = (self._seq + 1) & 0xFF


class Link:
    """Moves bytes between a McuEmulator and one byte stream; optional fault filters sit on
    each direction (sim_hal/faults.py). `lock` serialises pump() with a test's interventions."""

    def __init__(self, mcu: McuEmulator, *, to_host: ByteFilter | None = None,
                 to_mcu: ByteFilter | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.mcu = mcu
        self.to_host = to_host
        self.to_mcu = to_mcu
        self.clock = clock
        self.lock = threading.Lock()
        self.tx_dropped = 0  # bytes the host side did not take (nobody listening, full buffer)
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._closed = False

    @property
    def url(self) -> str:
        raise NotImplementedError

    def pump(self, now: float | None = None) -> None:
        """One firmware step: take the host's bytes, service, transmit."""
        if now is None:
            now = self.clock()
        with self.lock:
            data = self._recv()
            if data:
                if self.to_mcu is not None:
                    data = self.to_mcu(data)
                self.mcu.receive(data, now)
            out = self.mcu.service(now)
            if out and self.to_host is not None:
                out = self.to_host(out)
            if out:
                self._send(out)

    def start(self, period_s: float = 0.0005) -> "Link":
        """Pump from a daemon thread every `period_s` (and whenever host bytes arrive)."""
        if self._thread is not None:
            return self
        self._stop.clear()

        def run() -> None:
            while not self._stop.is_set():
                self._wait(period_s)
                if self._stop.is_set():
                    break
                try:
                    self.pump()
                except OSError:
                    if self._stop.is_set():
                        break
                    raise

        self._thread = threading.Thread(target=run, name=type(self).__name__, daemon=True)
        self._thread.start()
        return self

    def stop_thread(self, timeout_s: float = 2.0) -> None:
        t = self._thread
        if t is not None:
            self._stop.set()
            t.join(timeout_s)
            self._thread = None

    def close(self) -> None:
        """Stop the thread and release the descriptors. Safe twice."""
        self.stop_thread()
        if not self._closed:
            self._closed = True
            self._close_fds()

    def __enter__(self) -> "Link":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _wait(self, timeout_s: float) -> None:
        fds = self._fds()
        if fds:
            try:
                select.select(fds, [], [], timeout_s)
            except (OSError, ValueError):
                time.sleep(timeout_s)
        else:
            time.sleep(timeout_s)

    # transport hooks
    def _fds(self) -> list: raise NotImplementedError
    def _recv(self) -> bytes: raise NotImplementedError
    def _send(self, data: bytes) -> None: raise NotImplementedError
    def _close_fds(self) -> None: raise NotImplementedError


class PtyLink(Link):
    """The MCU behind a pseudo-terminal: open `url` (the slave's /dev/pts path) with pyserial.

    The slave is put in raw mode at once (no echo, no line editing) and kept open here, so the
    host may close and reopen it.
    """

    def __init__(self, mcu: McuEmulator, **kw) -> None:
        super().__init__(mcu, **kw)
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self._path = os.ttyname(self._slave)

    @property
    def url(self) -> str:
        return self._path

    def _fds(self) -> list:
        return [self._master]

    def _recv(self) -> bytes:
        chunks = []
        while True:
            try:
                data = os.read(self._master, 4096)
            except (BlockingIOError, InterruptedError):
                break
            except OSError as e:
                if e.errno == errno.EIO:  # no slave open: nothing to read
                    break
                raise
            if not data:
                break
            chunks.append(data)
        return b"".join(chunks)

    def _send(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            try:
                n = os.write(self._master, view)
            except (BlockingIOError, InterruptedError):
                self.tx_dropped += len(view)  # a UART with nobody reading: bytes are lost
                return
            view = view[n:]

    def _close_fds(self) -> None:
        for fd in (self._master, self._slave):
            try:
                os.close(fd)
            except OSError:
                pass


class TcpLink(Link):
    """The MCU behind a TCP socket on 127.0.0.1 (ephemeral port): `socket://127.0.0.1:PORT`.

    One host at a time; bytes sent while no host is connected are lost, like a UART's.
    """

    def __init__(self, mcu: McuEmulator, **kw) -> None:
        super().__init__(mcu, **kw)
        self._listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self._listener.bind(("127.0.0.1", 0))
        self._listener.listen(1)
        self._listener.setblocking(False)
        self.port = self._listener.getsockname()[1]
        self._client: socket.socket | None = None

    @property
    def url(self) -> str:
        return f"socket://127.0.0.1:{self.port}"

    def _fds(self) -> list:
        return [self._client if self._client is not None else self._listener]

    def _accept(self) -> None:
        try:
            conn, _ = self._listener.accept()
        except (BlockingIOError, InterruptedError):
            return
        conn.setblocking(False)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self._client = conn

    def _drop_client(self) -> None:
        if self._client is not None:
            try:
                self._client.close()
            except OSError:
                pass
            self._client = None

    def _recv(self) -> bytes:
        if self._client is None:
            self._accept()
            if self._client is None:
                return b""
        chunks = []
        while True:
            try:
                data = self._client.recv(4096)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                self._drop_client()
                break
            if not data:  # host closed the connection
                self._drop_client()
                break
            chunks.append(data)
        return b"".join(chunks)

    def _send(self, data: bytes) -> None:
        if self._client is None:
            self.tx_dropped += len(data)
            return
        view = memoryview(data)
        while view:
            try:
                n = self._client.send(view)
            except (BlockingIOError, InterruptedError):
                self.tx_dropped += len(view)
                return
            except OSError:
                self.tx_dropped += len(view)
                self._drop_client()
                return
            view = view[n:]

    def _close_fds(self) -> None:
        self._drop_client()
        try:
            self._listener.close()
        except OSError:
            pass
