"""Protocol v1 between the robot computer and the motor microcontroller (docs/protocol.md).

Wire format: each packet `type u8 | seq u8 | payload | crc u16` (little-endian, at most
64 bytes) is COBS-encoded and followed by one 0x00. This module is pure: no I/O, so the host
driver (hal/bridge.py) and the firmware model (sim_hal/mcu_emulator.py) share one definition.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, fields
from typing import ClassVar, Union

from hal import cobs
from hal.crc import crc16_ccitt_false

__all__ = [
    "DELIMITER", "DUTY_FULL_SCALE", "FLAG_BAD_FRAME", "FLAG_OUTPUTS_ON", "FLAG_WATCHDOG",
    "MAX_FRAME_LEN", "MAX_PACKET_LEN", "PROTOCOL_VERSION", "TIMEOUT_MS_MAX", "TIMEOUT_MS_MIN",
    "Drive", "FrameDecoder", "Hello", "HelloReply", "Message", "Packet", "ProtocolError",
    "State", "Stop", "Unknown", "decode_packet", "encode_frame", "encode_packet", "seq_gap",
]

PROTOCOL_VERSION = 1
MAX_PACKET_LEN = 64  # type + seq + payload + crc, before COBS
MAX_FRAME_LEN = cobs.max_encoded_len(MAX_PACKET_LEN)  # COBS bytes of one frame, no delimiter
DELIMITER = b"\x00"
DUTY_FULL_SCALE = 10000  # i16 duty units for 100 %
TIMEOUT_MS_MIN = 1
TIMEOUT_MS_MAX = 1000

FLAG_WATCHDOG = 0x01  # outputs zeroed by the watchdog since the previous STATE
FLAG_OUTPUTS_ON = 0x02  # at least one output is non-zero
FLAG_BAD_FRAME = 0x04  # a frame failed its CRC (or COBS) check since the previous STATE

_HEADER = struct.Struct("<BB")
_CRC = struct.Struct("<H")


class ProtocolError(ValueError):
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
    """MCU -> host 0x81: sent for every HELLO and once, unsolicited, after the MCU boots."""

    protocol_version: int
    encoder_counts_per_rev: int
    state_rate_hz: int
    TYPE: ClassVar[int] = 0x81
    FMT: ClassVar[struct.Struct] = struct.Struct("<BIH")


@dataclass(frozen=True, slots=True)
class State:
    """MCU -> host 0x82, streamed at state_rate_hz: clock, encoder count, flags, last ack."""

    t_us: int  # MCU clock, u32, wraps
    count: int  # encoder counter, i32, wraps
    flags: int
    ack_seq: int  # seq of the last accepted DRIVE or STOP
    TYPE: ClassVar[int] = 0x82
    FMT: ClassVar[struct.Struct] = struct.Struct("<IiBB")


@dataclass(frozen=True, slots=True)
class Unknown:
    """A packet with a valid CRC but a type this side does not know; receivers ignore it."""

    type: int
    payload: bytes


Message = Union[Hello, Drive, Stop, HelloReply, State, Unknown]
_KNOWN: dict[int, type] = {c.TYPE: c for c in (Hello, Drive, Stop, HelloReply, State)}


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
    cls = _KNOWN.get(ptype)
    if cls is None:
        return Packet(seq, Unknown(ptype, payload))
    if len(payload) != cls.FMT.size:
        raise _error("malformed", f"type 0x{ptype:02x} payload of {len(payload)} bytes, "
                                  f"expected {cls.FMT.size}")
    return Packet(seq, cls(*cls.FMT.unpack(payload)))


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
