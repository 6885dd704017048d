"""Consistent Overhead Byte Stuffing: removes every 0x00 from a packet so 0x00 can end frames.

A receiver that loses sync (a dropped or garbled byte) recovers at the next 0x00, which is
why the serial protocol frames with it. Overhead is one byte per 254 bytes, plus one.
"""

from __future__ import annotations

from ddrt.errors import DdrtError

__all__ = ["CobsDecodeError", "decode", "encode", "max_encoded_len"]


class CobsDecodeError(DdrtError, ValueError):
    """The bytes are not a valid COBS encoding (a zero inside, or a code past the end)."""


def max_encoded_len(n: int) -> int:
    """Largest encoding of an `n`-byte input, without the delimiter."""
    return n + n // 254 + 1


def encode(data: bytes | bytearray) -> bytes:
    """Encode `data`; the result contains no 0x00 and no trailing delimiter."""
    out = bytearray()
    code_pos = 0
    out.append(0)  # placeholder for the first code byte
    code = 1
    for b in data:
        if b == 0:
            out[code_pos] = code
            code_pos = len(out)
            out.append(0)
            code = 1
            continue
        out.append(b)
        code += 1
        if code == 0xFF:  # a full run of 254 non-zero bytes: close it without an implied zero
            out[code_pos] = code
            code_pos = len(out)
            out.append(0)
            code = 1
    out[code_pos] = code
    return bytes(out)


def decode(data: bytes | bytearray) -> bytes:
    """Decode one frame (delimiter removed). Raises CobsDecodeError on a malformed frame."""
    out = bytearray()
    i = 0
    n = len(data)
    if n == 0:
        raise CobsDecodeError("empty frame")
    while i < n:
        code = data[i]
        if code == 0:
            raise CobsDecodeError(f"zero byte at offset {i}")
        end = i + code
        if end > n:
            raise CobsDecodeError(f"code {code} at offset {i} runs past the end ({n} bytes)")
        chunk = data[i + 1 : end]
        if 0 in chunk:
            raise CobsDecodeError(f"zero byte inside the run at offset {i}")
        out += chunk
        i = end
        if code != 0xFF and i < n:
            out.append(0)
    return bytes(out)
