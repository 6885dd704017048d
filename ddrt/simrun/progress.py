"""`ddrt sim`'s progress on stderr, readable on a terminal and in a log alike.

On a terminal it is one line rewritten in place (a carriage return before each update) and
ended with a newline when the run ends. Elsewhere (a pipe, a log file, systemd's journal)
a carriage return would run the updates together with the next line, so each update is a
line of its own, one at each tenth of the run. The run's length is the path's duration (or
--duration): what is expected, not the time limit past which a run is stopped.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field
from typing import TextIO

STEPS = 10  # lines written off a terminal, one at each tenth of the expected time


@dataclass
class StderrProgress:
    """A run_sim progress callback: `self(t, expected)` with simulated and expected seconds."""

    stream: TextIO = field(default_factory=lambda: sys.stderr)
    tty: bool | None = None  # None: whether the stream is a terminal
    _shown: int = -1  # the last tenth written (off a terminal)
    _open: bool = False  # a terminal line is waiting for its newline

    def __post_init__(self) -> None:
        if self.tty is None:
            self.tty = self.stream.isatty()

    def __call__(self, t: float, expected: float) -> None:
        text = f"  simulated {t:7.1f} s of {expected:.1f} s"
        if self.tty:
            self.stream.write("\r" + text)
            self._open = True
        else:
            step = math.floor(STEPS * t / expected) if expected > 0 else 0
            if step <= self._shown:
                return
            self._shown = step
            self.stream.write(" ".join(text.split()) + "\n")
        self.stream.flush()

    def end(self) -> None:
        """Close the terminal line, so that what follows starts on a line of its own."""
        if self._open:
            self.stream.write("\n")
            self.stream.flush()
            self._open = False
