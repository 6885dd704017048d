"""The root of every error ddrt raises on purpose.

Each error also inherits the builtin it is a kind of (ValueError for bad input, OSError for a
device or a socket, RuntimeError for a run that could not finish), so a caller catches either
`DdrtError` for "anything ddrt said no to" or the builtin it already handles. The HAL's tree
(`hal.base.HalError`) hangs under this root too.
"""

from __future__ import annotations

__all__ = ["DdrtError"]


class DdrtError(Exception):
    """An error of ddrt's own: a refused input, a device that failed, a run that could not finish."""
