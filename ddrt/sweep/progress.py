"""A progress bar with an ETA on stderr: how far a campaign is, and how long the rest takes.

On a terminal the bar is redrawn in place (at most five times a second); into a file or a
pipe it is a line every tenth of the campaign, so a CI log stays short. The rate is this
session's (rows resumed from an earlier one are not counted as work done now).
"""

from __future__ import annotations

import sys
import time
from typing import Callable, TextIO

WIDTH = 24


def _clock(seconds: float) -> str:
    s = int(round(seconds))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"


class Progress:
    """Counts finished runs of `total` and draws the bar."""

    def __init__(self, total: int, stream: TextIO | None = None, enabled: bool = True,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.total = total
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = enabled and total > 0
        self.clock = clock
        self.t0 = clock()
        self.done = 0
        self.failed = 0
        self._drawn_at = -1.0
        self._tenth = -1
        self._tty = self.stream.isatty()

    def start(self) -> None:
        """Count the rate from now (after the cluster is up, so its start-up is not in the ETA)."""
        self.t0 = self.clock()

    def line(self) -> str:
        """The bar as text: count, percentage, rate, ETA, failures."""
        frac = self.done / self.total if self.total else 1.0
        filled = int(WIDTH * frac)
        elapsed = self.clock() - self.t0
        rate = self.done / elapsed if elapsed > 0 else 0.0
        if self.done == self.total:
            eta = f"took {_clock(elapsed)}"
        elif rate > 0:
            eta = f"ETA {_clock((self.total - self.done) / rate)}"
        else:
            eta = "ETA --:--:--"
        failed = f", {self.failed} failed" if self.failed else ""
        return (f"sweep {self.done:>{len(str(self.total))}}/{self.total} [{'#' * filled}{'.' * (WIDTH - filled)}] "
                f"{frac:4.0%} {rate:.2f} runs/s {eta}{failed}")

    def update(self, ok: bool) -> None:
        """One more run finished (`ok`: its status was ok)."""
        self.done += 1
        self.failed += 0 if ok else 1
        if not self.enabled:
            return
        now = self.clock()
        last = self.done == self.total
        if self._tty:
            if last or now - self._drawn_at >= 0.2:
                self.stream.write("\r" + self.line())
                self.stream.flush()
                self._drawn_at = now
        else:
            tenth = self.done * 10 // self.total
            if tenth != self._tenth:
                self.stream.write(self.line() + "\n")
                self.stream.flush()
                self._tenth = tenth

    def close(self) -> None:
        if self.enabled and self._tty and self._drawn_at >= 0:
            self.stream.write("\n")
            self.stream.flush()
