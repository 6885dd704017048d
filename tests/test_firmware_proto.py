"""The firmware's protocol code (firmware/src/proto.c), compiled for the host, held byte for
byte against hal/wire.py: CRC, frames it encodes, and the decoder's packets and error
counters on any byte stream (valid frames, corrupted ones, garbage, oversize, empty)."""

from __future__ import annotations

import ctypes
import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hal import cobs
from hal.crc import crc16_ccitt_false
from hal.wire import (
    Drive, FrameDecoder, Hello, HelloReply, HelloReplyV1, Packet, State, StateV1, Stop, Unknown,
    decode_packet,
    encode_frame, encode_packet,
)
from tests.support.firmware import require
from sim_hal import firmware_build


@pytest.fixture(scope="module")
def lib():
    require("host")
    so = ctypes.CDLL(str(firmware_build.artifact("host/libddrtproto.so")))
    so.proto_crc16.restype = ctypes.c_uint16
    so.proto_crc16.argtypes = [ctypes.c_uint16, ctypes.c_char_p, ctypes.c_uint8]
    so.proto_decoder_sizeof.restype = ctypes.c_size_t
    so.proto_decoder_feed.restype = ctypes.c_uint8
    so.proto_decoder_feed.argtypes = [ctypes.c_void_p, ctypes.c_uint8]
    so.proto_decoder_init.argtypes = [ctypes.c_void_p]
    so.proto_decoder_counters.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_uint16)]
    so.proto_decoder_packet.restype = ctypes.POINTER(ctypes.c_uint8)
    so.proto_decoder_packet.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_uint8)]
    so.proto_encode_frame.restype = ctypes.c_uint8
    so.proto_encode_frame.argtypes = [ctypes.c_uint8, ctypes.c_uint8, ctypes.c_char_p,
                                      ctypes.c_uint8, ctypes.c_char_p]
    so.proto_parse_drive.restype = ctypes.c_uint8
    so.proto_parse_drive.argtypes = [ctypes.c_char_p, ctypes.c_void_p]
    return so


class CDecoder:
    """The C decoder behind FrameDecoder's interface: feed bytes, get raw packets."""

    def __init__(self, lib) -> None:
        self.lib = lib
        self.mem = ctypes.create_string_buffer(lib.proto_decoder_sizeof())
        lib.proto_decoder_init(self.mem)

    def feed(self, data: bytes) -> list[bytes]:
        out = []
        n = ctypes.c_uint8()
        for b in data:
            if self.lib.proto_decoder_feed(self.mem, b):
                p = self.lib.proto_decoder_packet(self.mem, ctypes.byref(n))
                out.append(bytes(p[: n.value]))
        return out

    def counters(self) -> tuple[int, ...]:
        c = (ctypes.c_uint16 * 5)()
        self.lib.proto_decoder_counters(self.mem, c)
        return tuple(c)


def py_counters(d: FrameDecoder) -> tuple[int, ...]:
    return (d.frames_ok, d.crc_errors, d.undecodable, d.oversize, d.malformed)


def check_same(lib, stream: bytes, chunks: int = 1) -> None:
    c = CDecoder(lib)
    py = FrameDecoder()
    got_c: list[bytes] = []
    got_py: list[Packet] = []
    step = max(1, len(stream) // chunks)
    for i in range(0, len(stream), step):
        got_c += c.feed(stream[i:i + step])
        got_py += py.feed(stream[i:i + step])
    assert [decode_packet(raw) for raw in got_c] == got_py
    assert got_c == [encode_packet(p) for p in got_py]
    assert c.counters() == py_counters(py)


def test_crc_check_value_and_random(lib) -> None:
    assert lib.proto_crc16(0xFFFF, b"123456789", 9) == 0x29B1
    rng = random.Random(1)
    for _ in range(200):
        data = bytes(rng.randrange(256) for _ in range(rng.randrange(0, 64)))
        assert lib.proto_crc16(0xFFFF, data, len(data)) == crc16_ccitt_false(data)


PACKETS = [
    Packet(0, Hello()), Packet(1, Drive(5000, -2500, 100)), Packet(255, Stop()),
    Packet(0, HelloReply(2, 8192, 250, 7, 1320)), Packet(7, State(0xFFFFFFFF, -(2 ** 31), 15, 255, 12000, -5, 2 ** 31 - 1)),
    Packet(0, HelloReplyV1(1, 8192, 500)), Packet(7, StateV1(0xFFFFFFFF, -(2 ** 31), 7, 255)),
    Packet(3, Drive(0, 0, 1)), Packet(9, Unknown(0x33, b"\x00" * 10)),
    Packet(10, Unknown(0x44, bytes(range(60)))), Packet(0, State(0, 0, 0, 0)),
]


@pytest.mark.parametrize("pkt", PACKETS, ids=lambda p: type(p.msg).__name__)
def test_encoded_frames_are_the_python_bytes(lib, pkt: Packet) -> None:
    raw = encode_packet(pkt)
    out = ctypes.create_string_buffer(66)
    n = lib.proto_encode_frame(raw[0], raw[1], raw[2:-2], len(raw) - 4, out)
    assert out.raw[:n] == encode_frame(pkt)


def test_the_protocol_docs_example_bytes(lib) -> None:
    out = ctypes.create_string_buffer(66)
    n = lib.proto_encode_frame(0x02, 1, bytes.fromhex("88133cf66400"), 6, out)
    assert out.raw[:n] == bytes.fromhex("08 02 01 88 13 3c f6 64 03 d4 c0 00")


@given(st.integers(0, 255), st.integers(0, 255), st.binary(max_size=60))
@settings(max_examples=300, deadline=None)
def test_any_packet_encodes_identically(lib, ptype: int, seq: int, payload: bytes) -> None:
    body = bytes([ptype, seq]) + payload
    raw = body + crc16_ccitt_false(body).to_bytes(2, "little")
    out = ctypes.create_string_buffer(66)
    n = lib.proto_encode_frame(ptype, seq, payload, len(payload), out)
    assert out.raw[:n] == cobs.encode(raw) + b"\x00"


def test_decoder_edge_cases(lib) -> None:
    good = encode_frame(Packet(1, Drive(1, 2, 3)))
    cases = [
        b"\x00\x00\x00",  # empty frames: ignored, no error
        good,
        b"\x00" + good,  # the host's leading lone 0x00
        good[:5] + b"\x00" + good,  # a truncated frame, then a good one
        bytes(good[:3]) + bytes([good[3] ^ 0x10]) + good[4:],  # bit flip: CRC
        b"\x05\x01\x02\x00",  # code runs past the end
        b"\x02\x01\x00",  # shorter than header + CRC
        b"\x01" * 65 + b"\x00",  # 65 COBS bytes: the longest allowed (64 zero bytes: CRC)
        b"\x01" * 66 + b"\x00" + good,  # oversize, then resync
        bytes([0x42] * 200) + b"\x00" + good,  # far oversize
        encode_frame(Packet(2, Unknown(0x02, b"\x01\x02"))),  # DRIVE of the wrong length
        encode_frame(Packet(2, Unknown(0x82, b"\x01"))),  # STATE of the wrong length
        encode_frame(Packet(2, Unknown(0x82, bytes(10)))),  # a v1 STATE: both lengths are known
        encode_frame(Packet(2, Unknown(0x82, bytes(20)))),  # a v2 STATE
        encode_frame(Packet(2, Unknown(0x82, bytes(15)))),  # neither
        encode_frame(Packet(2, Unknown(0x81, bytes(7)))),  # HELLO_REPLY, v1 and v2, and neither
        encode_frame(Packet(2, Unknown(0x81, bytes(12)))),
        encode_frame(Packet(2, Unknown(0x81, bytes(10)))),
        encode_frame(Packet(2, Unknown(0x7E, b""))),  # unknown type, valid CRC
        encode_frame(Packet(4, Unknown(0x10, bytes(60)))),  # 64-byte packet
        cobs.encode(bytes(range(1, 255)) + b"\x01\x02") + b"\x00",  # a 0xFF code run
    ]
    for stream in cases:
        check_same(lib, stream)
    check_same(lib, b"".join(cases), chunks=7)


def frame_stream(rng: random.Random, n: int) -> bytes:
    """Valid frames of every type mixed with bit flips, cuts, garbage and long runs."""
    out = bytearray()
    for _ in range(n):
        kind = rng.random()
        msg = rng.choice([Hello(), Stop(), Drive(rng.randint(-32768, 32767), rng.randint(-32768, 32767),
                                                 rng.randint(0, 65535)),
                          HelloReply(2, 8192, 250, 3, 0), State(rng.getrandbits(32), 0, 3, 4, 11000, -3, 3),
                          HelloReplyV1(1, 8192, 500), StateV1(rng.getrandbits(32), 0, 3, 4),
                          Unknown(rng.randrange(256), bytes(rng.randrange(256) for _ in range(rng.randrange(61))))])
        frame = bytearray(encode_frame(Packet(rng.randrange(256), msg)))
        if kind < 0.15:
            frame[rng.randrange(len(frame))] ^= 1 << rng.randrange(8)
        elif kind < 0.25:
            del frame[rng.randrange(len(frame)):]
        elif kind < 0.35:
            frame[rng.randrange(len(frame) + 1):0] = bytes(rng.randrange(256) for _ in range(rng.randrange(1, 90)))
        out += frame
    return bytes(out)


@pytest.mark.parametrize("seed", range(8))
def test_decoder_matches_on_mixed_streams(lib, seed: int) -> None:
    rng = random.Random(seed)
    check_same(lib, frame_stream(rng, 150), chunks=rng.randint(1, 40))


@given(st.binary(max_size=400))
@settings(max_examples=300, deadline=None)
def test_decoder_matches_on_arbitrary_bytes(lib, data: bytes) -> None:
    check_same(lib, data)


@pytest.mark.parametrize("drive", [Drive(10000, -10000, 1), Drive(0, 0, 1000), Drive(10001, 0, 100),
                                   Drive(0, -10001, 100), Drive(5, 5, 0), Drive(5, 5, 1001),
                                   Drive(-32768, 32767, 65535)])
def test_drive_range_rules_match(lib, drive: Drive) -> None:
    out = ctypes.create_string_buffer(6)
    assert bool(lib.proto_parse_drive(Drive.FMT.pack(drive.duty_l, drive.duty_r, drive.timeout_ms), out)) \
        == drive.in_range()
