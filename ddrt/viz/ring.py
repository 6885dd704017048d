"""The loop thread's hand-off to the Foxglove publisher: one struct copy per tick, no lock.

`VizRing.put` packs the tick's telemetry row, its timing and (simulated robot) the true
pose into a preallocated bytearray slot with one `struct.pack_into` (about 0.5 us) and then
advances `head`. One producer, one consumer: the reader copies the slots it has not read
and re-reads `head` afterwards; any slot the producer may have overwritten meanwhile (the
reader fell more than `capacity` behind) is dropped and counted, never returned torn. The
GIL makes each pack and each slice copy indivisible, so no lock is needed and the reader can
never make the loop wait.
"""

from __future__ import annotations

import struct
from typing import Iterator, Sequence

# After the telemetry row (ddrt.loop.COLUMNS): what only the daemon's loop knows.
EXTRA = ("late_s", "tick_s", "mono_s", "true_x", "true_y", "true_theta", "true_v", "true_omega", "has_truth")


class VizRing:
    """`capacity` slots of `width` row values plus EXTRA, single producer, single consumer."""

    __slots__ = ("width", "capacity", "_struct", "_size", "_buf", "head", "_tail", "dropped")

    def __init__(self, width: int, capacity: int = 1024) -> None:
        if width < 1 or capacity < 2:
            raise ValueError(f"VizRing: width >= 1 and capacity >= 2, got {width}, {capacity}")
        self.width = width
        self.capacity = capacity
        self._struct = struct.Struct(f"<{width + len(EXTRA)}d")
        self._size = self._struct.size
        self._buf = bytearray(self._size * capacity)
        self.head = 0  # slots ever written (the producer's only shared store)
        self._tail = 0  # slots ever read
        self.dropped = 0

    def put(self, row: Sequence[float], late_s: float, tick_s: float, mono_s: float,
            truth: tuple[float, ...] | None = None) -> None:
        """Loop thread: copy one tick in, O(1). `truth` is (x, y, theta, v, omega) or None."""
        head = self.head
        off = (head % self.capacity) * self._size
        if truth is None:
            self._struct.pack_into(self._buf, off, *row, late_s, tick_s, mono_s, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        else:
            self._struct.pack_into(self._buf, off, *row, late_s, tick_s, mono_s, *truth, 1.0)
        self.head = head + 1

    def take(self) -> Iterator[tuple[float, ...]]:
        """Publisher thread: the slots written since the last take, oldest first."""
        head = self.head
        tail = self._tail
        cap = self.capacity
        if head - tail > cap:
            self.dropped += head - tail - cap
            tail = head - cap
        size = self._size
        # Copy out first (each slice copy is atomic under the GIL), then check for overwrites.
        chunks = []
        i = tail
        while i < head:
            j = i % cap
            n = min(head - i, cap - j)
            chunks.append((i, bytes(self._buf[j * size:(j + n) * size])))
            i += n
        now = self.head
        self._tail = head
        # A put may have packed slot `now` (overwriting `now - cap`) before advancing head.
        first_valid = now - cap + 1
        unpack = self._struct.unpack_from
        for start, data in chunks:
            for k in range(len(data) // size):
                if start + k < first_valid:
                    self.dropped += 1
                    continue
                yield unpack(data, k * size)
