"""The plant's RK4 kernel compiled from plant_kernel.c, for `ddrt sim` speed (simulator only).

Why compiled: the plant integrates at 1 kHz, five RK4 steps per 200 Hz controller tick, and
in Python those steps alone cost about 35 us a tick: more than the whole 25 us budget of 200x
real time. The C kernel does the same arithmetic in the same order (no FMA contraction, no
fast-math, CPython's libm, MT19937 and gauss), so runs are bit-identical to SimRobot's Python
step, the reference and the fallback: without a C compiler, or with DDRT_PLANT=python,
SimRobot integrates in Python. The library is built once per source version into the user's
cache (~/.cache/ddrt, or $XDG_CACHE_HOME/ddrt; ddrt/runtime/cbuild.py).
"""

from __future__ import annotations

import ctypes
import random
from pathlib import Path
from typing import Any, Callable

from ddrt.runtime.cbuild import load_library

SOURCE = Path(__file__).with_name("plant_kernel.c")
CFLAGS = ("-O2", "-shared", "-fPIC", "-ffp-contract=off", "-fno-fast-math", "-fno-builtin")
NSTATE = 36  # plant_kernel.c: X .. GRR


class Rng(ctypes.Structure):
    """plant_kernel.c's rng_t: a random.Random's MT19937 state and its gauss pair cache."""

    _fields_ = [("mt", ctypes.c_uint32 * 624), ("index", ctypes.c_int32),
                ("has_next", ctypes.c_int32), ("next", ctypes.c_double)]

    @classmethod
    def from_random(cls, rng: random.Random) -> "Rng":
        _, words, gauss_next = rng.getstate()
        out = cls()
        out.mt[:] = words[:624]
        out.index = words[624]
        out.has_next = gauss_next is not None
        out.next = 0.0 if gauss_next is None else gauss_next
        return out


class Plant(ctypes.Structure):
    """plant_kernel.c's plant_t: the addresses of the buffers a SimRobot's kernel works on."""

    _fields_ = [("kp", ctypes.c_void_p), ("s", ctypes.c_void_p), ("c", ctypes.c_void_p),
                ("slip", ctypes.c_void_p), ("gyro", ctypes.c_void_p), ("ring_phi3", ctypes.c_void_p),
                ("ring_gyro", ctypes.c_void_p), ("n_ring", ctypes.c_int64), ("q", ctypes.c_void_p),
                ("q_step", ctypes.c_void_p), ("q_duty", ctypes.c_void_p), ("ring_phl", ctypes.c_void_p),
                ("ring_phr", ctypes.c_void_p), ("real", ctypes.c_void_p)]


def _declare(lib: ctypes.CDLL) -> None:
    lib.plant_run.restype = None
    lib.plant_run.argtypes = [ctypes.c_int64, ctypes.c_void_p]


def kernel() -> Callable[..., Any] | None:
    """plant_run(n_steps, address of a Plant), or None (pure Python then)."""
    lib = load_library(SOURCE, CFLAGS, "plant_kernel", "DDRT_PLANT", _declare)
    return lib.plant_run if lib is not None else None
