"""The daemon's telemetry as rotated MCAP files (daemon.telemetry_format: mcap | both).

An SDK MCAP writer is one more sink on the publisher's Context, so the files hold the live
channels. Rotation is the CSV files' policy (ddrt.service.telemetry.FileRotation):
`telemetry.mcap`, `telemetry.1.mcap` ...; a file is closed (finished with its summary) and
rotated once it has reached max_bytes. Chunks are flushed every `flush_s` so a crash loses
at most that much (`mcap recover` reads a file without its summary).
"""

from __future__ import annotations

import os
import time
from types import ModuleType
from typing import Any, Callable

from ddrt.service.telemetry import FileRotation


class RotatingMcap(FileRotation):
    """MCAP files on `context`, rotated by size; `check()` from the publisher thread only."""

    def __init__(self, fg: ModuleType, context: Any, directory: str, prefix: str, max_bytes: int, max_files: int,
                 on_open: Callable[[], None] | None = None, flush_s: float = 1.0) -> None:
        super().__init__(directory, prefix, ".mcap", max_bytes, max_files, owner="RotatingMcap")
        self._fg = fg
        self._context = context
        self._on_open = on_open
        self._flush_s = flush_s
        self._next_flush = 0.0
        self.rotate_stale()
        self._writer: Any = None
        self._open_new()

    def _open_new(self) -> None:
        from foxglove.mcap import MCAPWriteOptions

        chunk = max(4096, min(1 << 20, self.max_bytes // 4))
        self._writer = self._fg.open_mcap(os.fspath(self.path(0)), allow_overwrite=True, context=self._context,
                                          writer_options=MCAPWriteOptions(chunk_size=chunk))
        self._next_flush = time.monotonic() + self._flush_s
        if self._on_open is not None:
            self._on_open()

    def check(self) -> None:
        """Take new bounds, flush now and then, rotate a full file."""
        if self._pending_rotation is not None:
            self._take_rotation()
        now = time.monotonic()
        if now >= self._next_flush:
            self._writer.flush()
            self._next_flush = now + self._flush_s
        try:
            size = self.path(0).stat().st_size
        except OSError:
            return
        if size >= self.max_bytes:
            self._writer.close()
            self._rotate()
            self._open_new()

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
            self._writer = None
