"""CRC-16/CCITT-FALSE, the checksum of the serial protocol (docs/protocol.md).

Chosen because every microcontroller SDK ships it and a byte-wise table costs 512 bytes of
flash. Parameters: poly 0x1021, init 0xFFFF, not reflected, xorout 0; check value 0x29B1
for b"123456789".
"""

from __future__ import annotations

__all__ = ["CRC16_INIT", "crc16_ccitt_false"]

CRC16_INIT = 0xFFFF
_POLY = 0x1021


def _make_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ _POLY) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return tuple(table)


_TABLE = _make_table()


def crc16_ccitt_false(data: bytes | bytearray | memoryview, crc: int = CRC16_INIT) -> int:
    """Return the CRC of `data`; pass a previous result as `crc` to continue a running sum."""
    table = _TABLE
    for b in data:
        crc = ((crc << 8) & 0xFFFF) ^ table[(crc >> 8) ^ b]
    return crc
