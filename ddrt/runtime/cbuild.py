"""A C source built once with the system's compiler into ~/.cache/ddrt (or $XDG_CACHE_HOME/ddrt),
for the simulator's compiled parts (sim_hal/plant_native.py, ddrt/simrun/row_native.py).

The library's name carries a hash of the source and the flags, so an edit builds a new one;
the build goes to a temporary file replaced atomically, so concurrent builders (sweep workers)
never load half a file. No compiler, or a failed build: None, and the caller runs its Python.
`load_library` adds what every such part does with the file: an environment variable that
asks for the Python instead, one attempt per process, and its functions' signatures declared.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Callable

_loaded: dict[str, ctypes.CDLL | None] = {}  # stem -> the library, or None: built and loaded once a process


def cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "ddrt"


def built_library(source: Path, cflags: tuple[str, ...], stem: str) -> Path | None:
    """`source` compiled with `cflags` (and -lm) as cache_dir()/STEM-HASH.so, built now if
    needed; None when it cannot be built ($CC, else cc or gcc)."""
    src = source.read_bytes()
    tag = hashlib.sha256(src + " ".join(cflags).encode()).hexdigest()[:16]
    lib = cache_dir() / f"{stem}-{tag}.so"
    if lib.exists():
        return lib
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        return None
    try:
        lib.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(suffix=".so", dir=lib.parent)
        os.close(fd)
        proc = subprocess.run([cc, *cflags, "-o", tmp, str(source), "-lm"], capture_output=True, timeout=120)
        if proc.returncode != 0:
            os.unlink(tmp)
            return None
        os.replace(tmp, lib)
    except (OSError, subprocess.SubprocessError):
        return None
    return lib


def load_library(source: Path, cflags: tuple[str, ...], stem: str, python_env: str,
                 declare: Callable[[ctypes.CDLL], None]) -> ctypes.CDLL | None:
    """built_library loaded, `declare(lib)` having set its functions' signatures; None (the
    caller's Python then) when $`python_env` is "python", or it cannot be built, loaded or
    declared (a missing symbol). Tried once a process; the variable is read on every call."""
    if os.environ.get(python_env, "").lower() == "python":
        return None
    if stem not in _loaded:
        lib: ctypes.CDLL | None = None
        path = built_library(source, cflags, stem)
        if path is not None:
            try:
                lib = ctypes.CDLL(str(path))
                declare(lib)
            except (OSError, AttributeError):
                lib = None
        _loaded[stem] = lib
    return _loaded[stem]
