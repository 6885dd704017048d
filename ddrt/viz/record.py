"""`ddrt sim --mcap FILE`: the run recorded on the live channels (ddrt/viz/channels.py).

The SDK's MCAP writer is a sink of a private Context, so the file holds exactly what a
Foxglove client would have seen live, stamped with simulated time (ns since the path
started). Rows arrive a chunk at a time from the runner's TelemetryStream, off its hot loop.
"""

from __future__ import annotations

import os
from typing import Any, Callable

import numpy as np

from ddrt.viz.mcapfile import SinkErrors
from ddrt.viz.optional import foxglove


class SimRecording:
    """One MCAP file for one `ddrt sim` run; `chunk` takes rows in the runner's SIM_COLUMNS."""

    def __init__(self, file: str | os.PathLike[str], columns: tuple[str, ...],
                 fault: Callable[[], str] | None = None) -> None:
        fg = foxglove("--mcap")
        from ddrt.loop import COLUMNS
        from ddrt.viz.channels import Channels, TRUTH

        self.context = fg.Context()
        self.channels = Channels(fg, self.context, truth=True, timing=False)
        # The row as the loop recorded it (COLUMNS) and the truth, by position in `columns`.
        index = {name: i for i, name in enumerate(columns)}
        self._row_idx = [index["t"]] + [index[c] for c in COLUMNS[1:]]
        self._truth_idx = [index[c.removeprefix("true_")] for c in TRUTH]
        self._fault = fault
        self.file = os.fspath(file)
        if os.path.isdir(self.file):
            raise IsADirectoryError(f"--mcap {self.file}: is a directory; give a file name, "
                                    f"e.g. {os.path.join(self.file, 'run.mcap')}")
        try:
            os.makedirs(os.path.dirname(os.path.abspath(self.file)), exist_ok=True)
            self.writer: Any = fg.open_mcap(self.file, allow_overwrite=True, context=self.context)
        except OSError as exc:
            raise OSError(f"--mcap {self.file}: cannot write it: {exc.strerror or exc}") from None
        self.errors = SinkErrors(every=0).attach()  # the first failure ends the run (chunk), in its own words

    def path(self, xs: Any, ys: Any) -> None:
        self.channels.publish_path(xs, ys, 0)

    def chunk(self, arr: np.ndarray) -> None:
        """TelemetryStream's sink: every row of a chunk becomes its tick's messages."""
        rows = arr[:, self._row_idx].tolist()
        truths = arr[:, self._truth_idx].tolist()
        publish = self.channels.publish_tick
        for row, truth in zip(rows, truths):
            publish(row, max(0, int(round(row[0] * 1e9))), truth, None, self._fault)
        if self.errors.count:
            raise OSError(f"--mcap {self.file}: the recording could not be written: {self.errors.first}")

    def close(self) -> None:
        """Finish the file (its summary). The SDK's writer keeps a failed write (a full disk)
        to itself until here: OSError naming the flag and the file."""
        errors = self.errors
        errors.detach()
        try:
            self.writer.close()
        except (OSError, RuntimeError) as exc:
            raise OSError(f"--mcap {self.file}: the recording could not be written: {errors.first or exc}") from None
