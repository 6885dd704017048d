"""The loop's state as a stream of datagrams, for a process of its own (the ROS 2 bridge).

`{"cmd": "stream", "to": ADDRESS, "rate_hz": R}` over the control socket asks the daemon to
send the loop's latest state to the Unix datagram socket ADDRESS ("@name": Linux's abstract
namespace; otherwise a path) R times a second, for LEASE_S seconds; the client renews by
sending the request again. The reply names the fields in the order they are packed.

Why datagrams, and why the daemon cannot be stalled by a reader:
- The loop thread only packs its state into one preallocated buffer (`put`: one
  `struct.pack_into`, atomic under the GIL, about 1 us) when someone subscribes; nothing else.
- A sender thread (below the loop when it is real-time) copies the newest state and sends
  it with non-blocking `sendto`: the kernel's socket buffer of the reader is the bounded
  queue. A slow reader's full buffer makes the send fail at once (counted as dropped, the
  state is simply newer next time: drop-oldest by construction, nothing waits); a vanished
  reader (no socket at the address) is removed; a reader that stops renewing expires.
"""

from __future__ import annotations

import logging
import math
import socket
import struct
import threading
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable

if TYPE_CHECKING:
    from ddrt.loop import ControlLoop

log = logging.getLogger("ddrt.service.stream")

MAGIC = b"DDRS"
VERSION = 1
HEADER = struct.Struct("<4sHH")  # magic, version, field count (written once)
LEASE_S = 5.0
MAX_SUBSCRIBERS = 4

# The state, declared once: (name, unit, source over `loop`, `est` = loop.estimator, `sample`
# = loop.sample, `mono` = the tick's monotonic start; the supply from ddrt/loop/power.py). "nan" where ddrt does not know the value
# (the map pose before the first pose fix).
FIELDS: tuple[tuple[str, str, str], ...] = (
    ("seq", "count", "seq"),  # states packed so far: a reader sees whether it is new
    ("mono", "s", "mono"),
    ("t", "s", "sample.t if sample is not None else 0.0"),
    ("x", "m", "est.x"),
    ("y", "m", "est.y"),
    ("theta", "rad", "est.theta"),
    ("v", "m/s", "est.speed.v"),
    ("omega", "rad/s", "est.yaw.w"),
    ("var_v", "(m/s)^2", "est.speed.p11"),
    ("var_omega", "(rad/s)^2", "est.yaw.p00"),
    ("gyro", "rad/s", "sample.gyro_z_raw * est.rad_s_per_lsb if sample is not None else nan"),
    ("var_gyro", "(rad/s)^2", "est.yaw.meas_var"),
    ("gyro_bias", "rad/s", "est.yaw.b"),
    ("state", "code", "float(loop.state)"),
    ("fresh", "0/1", "1.0 if (sample is not None and sample.fresh) else 0.0"),
    ("battery_v", "V", "loop.power.v_slow if loop.power.good else nan"),  # measured, filtered over 1 s
    ("hw_estop", "0/1", "1.0 if loop.power.hw_estop else 0.0"),
    # The odometry's own pose covariance (/odom's; it never shrinks: docs/estimation.md).
    ("var_x", "m^2", "est.track.p_odom[0]"),
    ("var_y", "m^2", "est.track.p_odom[7]"),
    ("cov_xy", "m^2", "est.track.p_odom[1]"),
    ("var_theta", "rad^2", "est.track.p_odom[14]"),
    # The robot's pose in map (ddrt/core/pose_fix.py), once a fix has arrived (map -> odom).
    ("map_x", "m", "est.frame.x if est.frame.counters.fused else nan"),
    ("map_y", "m", "est.frame.y if est.frame.counters.fused else nan"),
    ("map_theta", "rad", "est.frame.th if est.frame.counters.fused else nan"),
)
NAMES = tuple(name for name, _, _ in FIELDS)
BODY = struct.Struct(f"<{len(FIELDS)}d")


def _compile() -> Callable[..., None]:
    lines = ["def pack(pack_into, buf, loop, mono, seq):", "    est = loop.estimator", "    sample = loop.sample",
             "    pack_into(buf, 0,"] + [f"        {src},  # {name}" for name, _, src in FIELDS] + ["    )"]
    ns: dict[str, Any] = {"nan": math.nan}
    exec(compile("\n".join(lines) + "\n", "<ddrt.service.stream: pack>", "exec"), ns)
    return ns["pack"]  # type: ignore[no-any-return]


_pack = _compile()


def decode(data: bytes) -> tuple[float, ...]:
    """The values of one datagram, in NAMES' order; ValueError if it is not one."""
    if len(data) < HEADER.size:
        raise ValueError(f"state datagram: {len(data)} bytes, shorter than its header")
    magic, version, n = HEADER.unpack_from(data)
    if magic != MAGIC or version != VERSION:
        raise ValueError(f"state datagram: magic {magic!r} version {version}, expected {MAGIC!r} {VERSION}")
    if len(data) != HEADER.size + 8 * n:
        raise ValueError(f"state datagram: {len(data)} bytes for {n} fields")
    return struct.unpack_from(f"<{n}d", data, HEADER.size)


@dataclass
class Subscriber:
    address: str
    interval_s: float
    expires: float
    next_send: float = 0.0
    sent: int = 0
    dropped: int = 0  # sends refused because the reader's buffer was full
    last_seq: int = 0  # the state last sent: a state is sent once (a stalled loop sends nothing)


def _sockaddr(address: str) -> str | bytes:
    return b"\0" + address[1:].encode() if address.startswith("@") else address


class StateStream:
    """The loop's packed state and the thread that sends it to its subscribers."""

    def __init__(self, loop: "ControlLoop", loop_priority: int = 0, clock: Callable[[], float] = time.monotonic) -> None:
        self.loop = loop
        self.clock = clock
        self._buf = bytearray(HEADER.size + BODY.size)
        HEADER.pack_into(self._buf, 0, MAGIC, VERSION, len(FIELDS))
        self._body = memoryview(self._buf)[HEADER.size:]
        self._seq = 0
        self._subs: dict[str, Subscriber] = {}
        self.active = False  # read by the loop thread: pack only while someone listens
        self._lock = threading.Lock()  # subscribers: the loop thread (requests) and the sender
        self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self._sock.setblocking(False)
        self._wake = threading.Event()
        self._stop = False
        self._priority = loop_priority
        self._thread = threading.Thread(target=self._run, name="ddrt-stream", daemon=True)
        self._thread.start()

    # -------------------------------------------------------------- loop thread

    def put(self, mono: float) -> None:
        """After a tick: the state into the buffer (nothing when nobody listens)."""
        if self.active:
            self._seq += 1
            _pack(BODY.pack_into, self._body, self.loop, mono, float(self._seq))

    def subscribe(self, to: str, rate: float) -> dict[str, Any]:
        """The `stream` request (between two ticks; its fields checked by their declaration in
        ddrt/service/commands.py): add or renew a subscriber."""
        now = self.clock()
        with self._lock:
            sub = self._subs.get(to)
            if sub is None:
                if len(self._subs) >= MAX_SUBSCRIBERS:
                    return {"ok": False, "error": f"stream: busy: {MAX_SUBSCRIBERS} subscribers already "
                                                  f"(each expires {LEASE_S:g} s after its last request)"}
                sub = self._subs[to] = Subscriber(to, 1.0 / rate, now + LEASE_S)
                log.info("stream: sending the loop's state to %s at %g Hz", to, rate)
            sub.interval_s = 1.0 / rate
            sub.expires = now + LEASE_S
            self.active = True
        self._wake.set()
        return {"ok": True, "fields": list(NAMES), "lease_s": LEASE_S, "rate_hz": rate}

    def counts(self) -> dict[str, dict[str, int]]:
        with self._lock:
            return {a: {"sent": s.sent, "dropped": s.dropped} for a, s in self._subs.items()}

    # -------------------------------------------------------------- sender thread

    def _run(self) -> None:
        if self._priority:
            from ddrt.runtime import rt

            warning = rt.raise_gil_helper(self._priority)
            if warning:
                log.warning("stream: %s", warning)
        while not self._stop:
            with self._lock:
                subs = list(self._subs.values())
            if not subs:
                self._wake.wait(1.0)
                self._wake.clear()
                continue
            now = self.clock()
            wait = 1.0
            for sub in subs:
                if now >= sub.expires:
                    self._remove(sub, "its lease ran out")
                    continue
                if now >= sub.next_send:
                    self._send(sub)
                    sub.next_send = max(sub.next_send + sub.interval_s, now)
                wait = min(wait, sub.next_send - now)
            time.sleep(max(wait, 0.0005))

    def _send(self, sub: Subscriber) -> None:
        seq = self._seq
        if seq == sub.last_seq:
            return
        data = bytes(self._buf)  # one copy, atomic under the GIL: never torn by a put
        sub.last_seq = seq
        try:
            self._sock.sendto(data, _sockaddr(sub.address))
            sub.sent += 1
        except BlockingIOError:
            sub.dropped += 1  # the reader is slow: its buffer is full; newer state next time
        except OSError as exc:  # nobody at the address (ECONNREFUSED, ENOENT): it is gone
            self._remove(sub, f"{exc.strerror or exc}")

    def _remove(self, sub: Subscriber, why: str) -> None:
        with self._lock:
            if self._subs.get(sub.address) is sub:
                del self._subs[sub.address]
            self.active = bool(self._subs)
        log.info("stream: stopped sending to %s (%s; %d sent, %d dropped)", sub.address, why, sub.sent, sub.dropped)

    def close(self) -> None:
        self._stop = True
        self._wake.set()
        self._thread.join(timeout=2.0)
        self._sock.close()
