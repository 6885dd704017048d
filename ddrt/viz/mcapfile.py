"""The daemon's telemetry as rotated MCAP files (daemon.telemetry_format: mcap | both).

An SDK MCAP writer is one more sink on the publisher's Context, so the files hold the live
channels. Rotation is the CSV files' policy (ddrt.runtime.rotation.FileRotation):
`telemetry.mcap`, `telemetry.1.mcap` ...; a file is closed (finished with its summary) and
rotated once it has reached max_bytes. Chunks are flushed every `flush_s` so a crash loses
at most that much (`mcap recover` reads a file without its summary).
"""

from __future__ import annotations

import logging
import os
import re
import time
from types import ModuleType
from typing import Any, Callable

from ddrt.runtime.rotation import FileRotation

log = logging.getLogger("ddrt.viz")
RETRY_S = 10.0  # after a failed write, a new MCAP file is tried this often


class SinkErrors(logging.Filter):
    """The SDK's word on a failed MCAP write (a full disk): it logs the failure, then a warning
    for every message after it ("attempted another write after a write method failed", ~1200
    lines a second at 200 Hz). This filter on its logger keeps the first reason, counts them
    all and lets through the first and one per `every` (none with 0)."""

    LOGGER = "foxglove.log_sink_set"

    def __init__(self, every: int = 10000) -> None:
        super().__init__()
        self.every = every
        self.count = 0
        self.first = ""

    def filter(self, record: logging.LogRecord) -> bool:
        msg = record.getMessage()
        if "error logging message" not in msg:
            return True
        self.count += 1
        if not self.first:
            m = re.search(r'message: "([^"]*)"', msg)
            self.first = m.group(1) if m else msg.removeprefix("error logging message: ")
        return self.every > 0 and (self.count == 1 or self.count % self.every == 0)

    def attach(self) -> "SinkErrors":
        logging.getLogger(self.LOGGER).addFilter(self)
        return self

    def detach(self) -> None:
        logging.getLogger(self.LOGGER).removeFilter(self)


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
        self.errors = SinkErrors().attach()
        self._errors_seen = 0
        self._failing = False  # since a write failed, until a file is written again
        self._moved_aside = False  # the file cut short by the failure has been rotated out of the way
        self._retry_at = 0.0
        try:
            self._open_new()
        except BaseException:
            self.errors.detach()
            raise

    def _open_new(self) -> None:
        from foxglove.mcap import MCAPWriteOptions

        chunk = max(4096, min(1 << 20, self.max_bytes // 4))
        self._writer = self._fg.open_mcap(os.fspath(self.path(0)), allow_overwrite=True, context=self._context,
                                          writer_options=MCAPWriteOptions(chunk_size=chunk))
        self._next_flush = time.monotonic() + self._flush_s
        if self._on_open is not None:
            self._on_open()

    def check(self) -> None:
        """Take new bounds, flush now and then, rotate a full file; a failed write (a full
        disk) closes the file as it is and tries a fresh one every RETRY_S."""
        if self._pending_rotation is not None:
            self._take_rotation()
        now = time.monotonic()
        if self._writer is None:
            if now >= self._retry_at:
                self._retry_at = now + RETRY_S
                self._errors_seen = self.errors.count
                try:
                    self._open_new()  # over the last failed retry's file, not a rotation: keeps the old files
                except OSError as exc:
                    self._writer = None
                    log.debug("MCAP telemetry: %s still cannot be opened: %s", self.path(0), exc)
            return
        if self.errors.count != self._errors_seen:
            self._fail(self.errors.first, now)
            return
        try:
            if now >= self._next_flush:
                self._writer.flush()
                self._next_flush = now + self._flush_s
                if self.errors.count != self._errors_seen:
                    self._fail(self.errors.first, now)
                    return
                if self._failing:  # a flush went through: the disk has room again
                    self._failing = self._moved_aside = False
                    log.warning("MCAP telemetry: writing %s again", self.path(0))
            try:
                size = self.path(0).stat().st_size
            except OSError:
                return
            if size >= self.max_bytes:
                self._writer.close()
                self._writer = None
                self._rotate()
                self._open_new()
        except (OSError, RuntimeError) as exc:
            self._fail(str(exc), now)

    def _fail(self, why: str, now: float) -> None:
        """Writing failed: log it once (until a file is written again), close the file as it
        is (`mcap recover` reads it) and move it aside, try a new one in RETRY_S."""
        if not self._failing:
            self._failing = True
            log.error("MCAP telemetry: writing %s failed (%s): recording stops, a new file is tried every "
                      "%g s; the daemon goes on", self.path(0), why, RETRY_S)
        writer, self._writer = self._writer, None
        if writer is not None:
            try:
                writer.close()
            except (OSError, RuntimeError):
                pass  # the failure logged above
            if not self._moved_aside:
                self._moved_aside = True
                try:
                    self._rotate()  # the file cut short keeps what it has; retries overwrite telemetry.mcap
                except OSError:
                    pass
        self._errors_seen = self.errors.count
        self._retry_at = now + RETRY_S

    def close(self) -> None:
        if self._writer is not None:
            try:
                self._writer.close()
            except (OSError, RuntimeError) as exc:
                log.error("MCAP telemetry: %s not finished: %s", self.path(0), exc)
            self._writer = None
        self.errors.detach()
