"""telemetry.csv's rows formatted in C (row_format.c), for `ddrt sim` speed (simulator only).

Why compiled: formatting a tick's row with Python's "%.9g" cost about 8-11 us of the ~52 us
of CPU a `ddrt sim` tick takes. The C prints the same text for every double (its fast path
is exact and falls back to snprintf near rounding ties and outside 1e-14..1e31; see
row_format.c), so telemetry.csv is byte-identical to runner.format_rows' Python path, which
stays the reference and the fallback: without a C compiler, or with DDRT_ROWFMT=python, the
rows are formatted in Python. Built once per source version into the user's cache
(~/.cache/ddrt, or $XDG_CACHE_HOME/ddrt) by ddrt/runtime/cbuild.py, like sim_hal/plant_native.py's
plant.
"""

from __future__ import annotations

import ctypes
import threading
from pathlib import Path
from typing import Any

import numpy as np

from ddrt.runtime.cbuild import load_library

SOURCE = Path(__file__).with_name("row_format.c")
CFLAGS = ("-O2", "-shared", "-fPIC", "-ffp-contract=off", "-fno-fast-math")
MAX_LEN = 24  # row_format.c: bytes reserved per value
ENV = "DDRT_ROWFMT"  # DDRT_ROWFMT=python: the Python formatter

class _Buffer(threading.local):
    """Each thread's output buffer (the C runs without the GIL), grown and reused."""

    def __init__(self) -> None:
        self.out = bytearray()


_local = _Buffer()


def _declare(lib: ctypes.CDLL) -> None:
    lib.format_rows.restype = ctypes.c_int64
    lib.format_rows.argtypes = [ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64, ctypes.c_void_p]
    # One value; g9_fast: -1 where snprintf is needed (tests).
    lib.g9.restype = lib.g9_fast.restype = ctypes.c_int
    lib.g9.argtypes = lib.g9_fast.argtypes = [ctypes.c_double, ctypes.c_char_p]


def library() -> Any:
    """The loaded library (format_rows, g9, g9_fast), or None (Python formatting then)."""
    return load_library(SOURCE, CFLAGS, "row_format", ENV, _declare)


def format_rows(arr: np.ndarray) -> str | None:
    """runner.format_rows' text for a 2-D float64 array, or None when the C is not available."""
    lib = library()
    if lib is None or arr.dtype != np.float64 or arr.ndim != 2:
        return None
    n, ncols = arr.shape
    if n == 0 or ncols == 0:
        return "\r\n" * n if ncols == 0 else ""
    arr = np.ascontiguousarray(arr)
    need = n * (ncols * MAX_LEN + 2)
    out = _local.out
    if len(out) < need:
        out = _local.out = bytearray(need)
    buf = (ctypes.c_char * len(out)).from_buffer(out)
    size = lib.format_rows(arr.ctypes.data, n, ncols, ctypes.addressof(buf))
    del buf  # release the export so the buffer may be replaced later
    if size < 0:
        return None
    return str(memoryview(out)[:size], "ascii")
