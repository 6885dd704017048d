"""Size-bounded file rotation, the one policy telemetry files share (CSV and MCAP).

A leaf of the runtime layer so the service's CSV writer and viz/'s MCAP writer can both use it
without importing each other.
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["FileRotation", "positive_int"]


def positive_int(name: str, value: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name}: expected an int >= 1, got {value!r}")
    return value


class FileRotation:
    """The rotation policy telemetry files share (CSV and MCAP): `prefix.ext` is the one being
    written, `prefix.1.ext` ... `prefix.<max_files-1>.ext` the older ones (oldest last).

    A file is rotated once it has reached `max_bytes`. An existing `prefix.ext` from an earlier
    run is rotated away at open, so every run starts a fresh file. New bounds (a reload) may
    be set from any thread; the writing thread takes them before its next write."""

    def __init__(self, directory: str | os.PathLike[str], prefix: str, suffix: str, max_bytes: int,
                 max_files: int, owner: str = "FileRotation") -> None:
        if not prefix or "/" in prefix or prefix.startswith("."):
            raise ValueError(f"{owner}.prefix: expected a plain file name stem, got {prefix!r}")
        self.directory = Path(directory)
        if not self.directory.is_dir():
            raise FileNotFoundError(f"{owner}.directory: {self.directory} is not a directory")
        self.owner = owner
        self.prefix = prefix
        self.suffix = suffix
        self.max_bytes = positive_int(f"{owner}.max_bytes", max_bytes)
        self.max_files = positive_int(f"{owner}.max_files", max_files)
        self._pending_rotation: tuple[int, int] | None = None
        self.rotations = 0

    def path(self, index: int) -> Path:
        """File `index` (0 is the one being written)."""
        name = f"{self.prefix}{self.suffix}" if index == 0 else f"{self.prefix}.{index}{self.suffix}"
        return self.directory / name

    def rotate_stale(self) -> None:
        """At open: move an earlier run's non-empty current file out of the way."""
        current = self.path(0)
        if current.exists() and current.stat().st_size > 0:
            self._rotate()

    def _rotate(self) -> None:
        last = self.path(self.max_files - 1)
        last.unlink(missing_ok=True)
        for i in range(self.max_files - 2, -1, -1):
            src = self.path(i)
            if src.exists():
                os.replace(src, self.path(i + 1))
        self.rotations += 1

    def set_rotation(self, max_bytes: int, max_files: int) -> None:
        """New rotation bounds (a reload). Safe from another thread: the writing thread takes
        them before its next rows, and then removes files beyond the new count."""
        self._pending_rotation = (positive_int(f"{self.owner}.max_bytes", max_bytes),
                                  positive_int(f"{self.owner}.max_files", max_files))

    def _take_rotation(self) -> None:
        pending, self._pending_rotation = self._pending_rotation, None
        if pending is None:
            return
        old_files = self.max_files
        self.max_bytes, self.max_files = pending
        for i in range(self.max_files, old_files):
            self.path(i).unlink(missing_ok=True)
