"""Protocol v2 between the robot computer and the motor microcontroller (docs/protocol.md),
and the v1 layouts a v2 host still accepts (HelloReplyV1, StateV1).

Wire format: each packet `type u8 | seq u8 | payload | crc u16` (little-endian, at most
64 bytes) is COBS-encoded and followed by one 0x00. This module is pure: no I/O, so the host
driver (hal/bridge.py) and the firmware model (sim_hal/mcu_emulator.py) share one definition.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, fields
from typing import ClassVar, Union

from ddrt.errors import DdrtError
from hal import cobs
from hal.crc import crc16_ccitt_false

__all__ = [
    "DELIMITER", "DUTY_FULL_SCALE", "FEATURE_BATTERY", "FEATURE_HW_ESTOP", "FEATURE_WHEELS",
    "FLAG_BAD_FRAME", "FLAG_HW_ESTOP", "FLAG_OUTPUTS_ON", "FLAG_WATCHDOG",
    "MAX_FRAME_LEN", "MAX_PACKET_LEN", "PROTOCOL_V1", "PROTOCOL_VERSION", "TIMEOUT_MS_MAX",
    "TIMEOUT_MS_MIN", "Drive", "FrameDecoder", "Hello", "HelloReply", "HelloReplyV1", "Message",
    "Packet", "ProtocolError", "State", "StateV1", "Stop", "Unknown", "decode_packet",
    "encode_frame", "encode_packet", "seq_gap", "wire_bytes",
]

PROTOCOL_VERSION = 2  # what this side speaks
PROTOCOL_V1 = 1  # the older MCU a v2 host still accepts
MAX_PACKET_LEN = 64  # type + seq + payload + crc, before COBS
MAX_FRAME_LEN = cobs.max_encoded_len(MAX_PACKET_LEN)  # COBS bytes of one frame, no delimiter
DELIMITER = b"\x00"
DUTY_FULL_SCALE = 10000  # i16 duty units for 100 %
TIMEOUT_MS_MIN = 1
TIMEOUT_MS_MAX = 1000

FLAG_WATCHDOG = 0x01  # outputs zeroed by the watchdog since the previous STATE
FLAG_OUTPUTS_ON = 0x02  # at least one output is non-zero
FLAG_BAD_FRAME = 0x04  # a frame failed its CRC (or COBS) check since the previous STATE
FLAG_HW_ESTOP = 0x08  # v2: the hardware estop input is open (outputs held at zero)

FEATURE_BATTERY = 0x01  # HELLO_REPLY v2 features: STATE.battery_mv is measured
FEATURE_HW_ESTOP = 0x02  # a hardware estop input is wired (STATE flag bit3)
FEATURE_WHEELS = 0x04  # the two drive wheels' encoders are counted (count_left, count_right)

_HEADER = struct.Struct("<BB")
_CRC = struct.Struct("<H")


class ProtocolError(DdrtError, ValueError):
    """A packet that cannot be encoded or a frame that does not decode to a valid packet.

    `kind` names the failed check: "short", "oversize", "crc", "malformed" or "encode".
    """

    def __init__(self, text: str, kind: str = "encode") -> None:
        super().__init__(text)
        self.kind = kind


@dataclass(frozen=True, slots=True)
class Hello:
    """Host -> MCU 0x01: ask for HELLO_REPLY (protocol version and encoder facts)."""

    TYPE: ClassVar[int] = 0x01
    FMT: ClassVar[struct.Struct] = struct.Struct("<")


@dataclass(frozen=True, slots=True)
class Drive:
    """Host -> MCU 0x02: both duties in 1e-4 of full scale, and the watchdog for this command.

    Not validated on construction, so tests can build the out-of-range commands that a
    receiver must ignore; `in_range()` is the receiver's check.
    """

    duty_l: int
    duty_r: int
    timeout_ms: int
    TYPE: ClassVar[int] = 0x02
    FMT: ClassVar[struct.Struct] = struct.Struct("<hhH")

    def in_range(self) -> bool:
        return (
            -DUTY_FULL_SCALE <= self.duty_l <= DUTY_FULL_SCALE
            and -DUTY_FULL_SCALE <= self.duty_r <= DUTY_FULL_SCALE
            and TIMEOUT_MS_MIN <= self.timeout_ms <= TIMEOUT_MS_MAX
        )


@dataclass(frozen=True, slots=True)
class Stop:
    """Host -> MCU 0x03: zero both outputs now."""

    TYPE: ClassVar[int] = 0x03
    FMT: ClassVar[struct.Struct] = struct.Struct("<")


@dataclass(frozen=True, slots=True)
class HelloReply:
    """MCU -> host 0x81 (v2, 12 bytes): sent for every HELLO and once, unsolicited, after the
    MCU boots. `encoder_counts_per_rev` is 0 without a front encoder; `features` FEATURE_*."""

    protocol_version: int
    encoder_counts_per_rev: int
    state_rate_hz: int
    features: int = 0
    wheel_counts_per_rev: int = 0
    TYPE: ClassVar[int] = 0x81
    FMT: ClassVar[struct.Struct] = struct.Struct("<BIHBI")


@dataclass(frozen=True, slots=True)
class HelloReplyV1:
    """MCU -> host 0x81 as a v1 MCU sends it (7 bytes; protocol_version 1)."""

    protocol_version: int
    encoder_counts_per_rev: int
    state_rate_hz: int
    TYPE: ClassVar[int] = 0x81
    FMT: ClassVar[struct.Struct] = struct.Struct("<BIH")


@dataclass(frozen=True, slots=True)
class State:
    """MCU -> host 0x82 (v2, 20 bytes), streamed at state_rate_hz: clock, front encoder
    count, flags, last ack, battery (mV, 0 when not measured) and the drive-wheel counts
    (0 when not counted; each wraps as a signed 32-bit integer, like `count`)."""

    t_us: int  # MCU clock, u32, wraps
    count: int  # encoder counter, i32, wraps
    flags: int
    ack_seq: int  # seq of the last accepted DRIVE or STOP
    battery_mv: int = 0
    count_left: int = 0
    count_right: int = 0
    TYPE: ClassVar[int] = 0x82
    FMT: ClassVar[struct.Struct] = struct.Struct("<IiBBHii")


@dataclass(frozen=True, slots=True)
class StateV1:
    """MCU -> host 0x82 as a v1 MCU sends it (10 bytes)."""

    t_us: int
    count: int
    flags: int
    ack_seq: int
    TYPE: ClassVar[int] = 0x82
    FMT: ClassVar[struct.Struct] = struct.Struct("<IiBB")

    def as_v2(self) -> State:
        """The same STATE in the v2 shape: nothing measured, no wheel counts."""
        return State(self.t_us, self.count, self.flags, self.ack_seq)


@dataclass(frozen=True, slots=True)
class Unknown:
    """A packet with a valid CRC but a type this side does not know; receivers ignore it."""

    type: int
    payload: bytes


Message = Union[Hello, Drive, Stop, HelloReply, HelloReplyV1, State, StateV1, Unknown]
# (type, payload length) -> layout: a v2 receiver takes both versions' lengths of 0x81, 0x82
_KNOWN: dict[tuple[int, int], type] = {
    (c.TYPE, c.FMT.size): c for c in (Hello, Drive, Stop, HelloReply, HelloReplyV1, State, StateV1)}
_KNOWN_TYPES: dict[int, list[int]] = {}
for _t, _n in _KNOWN:
    _KNOWN_TYPES.setdefault(_t, []).append(_n)


@dataclass(frozen=True, slots=True)
class Packet:
    """One message and the sender's sequence number (0..255, wrapping)."""

    seq: int
    msg: Message

    @property
    def type(self) -> int:
        m = self.msg
        return m.type if isinstance(m, Unknown) else m.TYPE


def _payload(msg: Message) -> tuple[int, bytes]:
    if isinstance(msg, Unknown):
        return msg.type, bytes(msg.payload)
    try:
        values = [getattr(msg, f.name) for f in fields(msg)]
        return msg.TYPE, msg.FMT.pack(*values)
    except struct.error as e:
        raise ProtocolError(f"{type(msg).__name__}: field out of its wire range: {e}") from None


def encode_packet(pkt: Packet) -> bytes:
    """Packet -> raw bytes (header, payload, CRC), before COBS."""
    if not 0 <= pkt.seq <= 0xFF:
        raise ProtocolError(f"seq={pkt.seq!r} outside 0..255")
    ptype, payload = _payload(pkt.msg)
    if not 0 <= ptype <= 0xFF:
        raise ProtocolError(f"type={ptype!r} outside 0..255")
    body = _HEADER.pack(ptype, pkt.seq) + payload
    if len(body) + _CRC.size > MAX_PACKET_LEN:
        raise ProtocolError(f"packet of {len(body) + _CRC.size} bytes exceeds {MAX_PACKET_LEN}")
    return body + _CRC.pack(crc16_ccitt_false(body))


def encode_frame(pkt: Packet) -> bytes:
    """Packet -> bytes on the wire: COBS of the raw packet, then the 0x00 delimiter."""
    return cobs.encode(encode_packet(pkt)) + DELIMITER


def decode_packet(raw: bytes) -> Packet:
    """Raw bytes (after COBS) -> Packet. Raises ProtocolError; `.kind` says which check failed."""
    if len(raw) < _HEADER.size + _CRC.size:
        raise _error("short", f"packet of {len(raw)} bytes is shorter than header + CRC")
    if len(raw) > MAX_PACKET_LEN:
        raise _error("oversize", f"packet of {len(raw)} bytes exceeds {MAX_PACKET_LEN}")
    body = raw[:-2]
    (crc,) = _CRC.unpack_from(raw, len(raw) - 2)
    if crc16_ccitt_false(body) != crc:
        raise _error("crc", "CRC mismatch")
    ptype, seq = _HEADER.unpack_from(body, 0)
    payload = bytes(body[2:])
    sizes = _KNOWN_TYPES.get(ptype)
    if sizes is None:
        return Packet(seq, Unknown(ptype, payload))
    cls = _KNOWN.get((ptype, len(payload)))
    if cls is None:
        want = " or ".join(str(n) for n in sorted(sizes))
        raise _error("malformed", f"type 0x{ptype:02x} payload of {len(payload)} bytes, "
                                  f"expected {want}")
    return Packet(seq, cls(*cls.FMT.unpack(payload)))


def wire_bytes(payload_len: int) -> int:
    """Bytes one packet of this payload takes on the wire (COBS, delimiter; no 0xFF runs)."""
    raw = _HEADER.size + payload_len + _CRC.size
    return cobs.max_encoded_len(raw) + len(DELIMITER)


def _error(kind: str, text: str) -> ProtocolError:
    return ProtocolError(text, kind)


def seq_gap(prev: int, seq: int) -> int:
    """Packets lost between `prev` and `seq` (mod 256): 0 when seq == prev + 1."""
    return (seq - prev - 1) & 0xFF


class FrameDecoder:
    """Splits a byte stream at 0x00 and yields only packets whose COBS and CRC check out.

    Never raises on input bytes. A frame that grows past MAX_FRAME_LEN is dropped up to the
    next 0x00 (counted once). Empty frames (two delimiters in a row) are ignored silently:
    a sender may emit a lone 0x00 to end whatever partial frame the receiver holds.
    """

    def __init__(self) -> None:
        self._buf = bytearray()
        self._overflow = False
        self.frames_ok = 0
        self.crc_errors = 0
        self.undecodable = 0  # COBS invalid, or shorter than header + CRC
        self.oversize = 0
        self.malformed = 0  # valid CRC, known type, wrong payload length

    @property
    def errors(self) -> int:
        return self.crc_errors + self.undecodable + self.oversize + self.malformed

    def feed(self, data: bytes | bytearray) -> list[Packet]:
        if not isinstance(data, (bytes, bytearray)):
            data = bytes(data)
        out: list[Packet] = []
        start = 0
        n = len(data)
        while start < n:
            end = data.find(0, start)
            if end < 0:
                self._append(data[start:])
                break
            self._append(data[start:end])
            self._end_frame(out)
            start = end + 1
        return out

    def _append(self, chunk: bytes | bytearray) -> None:
        if self._overflow:
            return
        self._buf += chunk
        if len(self._buf) > MAX_FRAME_LEN:
            self._overflow = True
            self._buf.clear()

    def _end_frame(self, out: list[Packet]) -> None:
        if self._overflow:
            self._overflow = False
            self.oversize += 1
            return
        if not self._buf:
            return
        frame = bytes(self._buf)
        self._buf.clear()
        try:
            raw = cobs.decode(frame)
            pkt = decode_packet(raw)
        except cobs.CobsDecodeError:
            self.undecodable += 1
            return
        except ProtocolError as e:
            kind = e.kind
            if kind == "crc":
                self.crc_errors += 1
            elif kind == "malformed":
                self.malformed += 1
            elif kind == "oversize":
                self.oversize += 1
            else:
                self.undecodable += 1
            return
        self.frames_ok += 1
        out.append(pkt)
