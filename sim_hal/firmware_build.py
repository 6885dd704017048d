"""Builds the reference firmware (firmware/) and its simavr harness with make, for the
firmware-sim backend and the tests.

`make -C firmware test-builds` is cheap when nothing changed, so callers just ask for the
artifacts they need; `missing_tools` says, before trying, which Debian packages are absent.
"""

from __future__ import annotations

import fcntl
import os
import shutil
import subprocess
from pathlib import Path

from ddrt.errors import DdrtError

__all__ = ["FIRMWARE_DIR", "BUILD_DIR", "BuildError", "artifact", "build", "missing_tools"]

FIRMWARE_DIR = Path(__file__).resolve().parents[1] / "firmware"
BUILD_DIR = FIRMWARE_DIR / "build"

# what each make target needs: (program or header, the Debian package that brings it)
_NEEDS = {
    "all": [("make", "make"), ("avr-gcc", "gcc-avr"), ("/usr/lib/avr/include/avr/io.h", "avr-libc")],
    "hang": [("make", "make"), ("avr-gcc", "gcc-avr"), ("/usr/lib/avr/include/avr/io.h", "avr-libc")],
    "host": [("make", "make"), ("gcc", "gcc")],
    "sim": [("make", "make"), ("gcc", "gcc"), ("/usr/include/simavr/sim_avr.h", "libsimavr-dev")],
}
INSTALL_HINT = ("apt-get install -y --no-install-recommends gcc-avr avr-libc libsimavr-dev "
                "make gcc")


class BuildError(DdrtError, RuntimeError):
    """make failed (the message carries its output) or the toolchain is missing."""


def missing_tools(*targets: str) -> list[str]:
    """Debian packages missing for these make targets (empty: all there)."""
    missing: list[str] = []
    for target in targets or ("all",):
        for thing, package in _NEEDS.get(target, []):
            present = os.path.exists(thing) if thing.startswith("/") else shutil.which(thing)
            if not present and package not in missing:
                missing.append(package)
    return missing


def build(*targets: str, extra: tuple[str, ...] = ()) -> None:
    """Run `make -C firmware TARGETS` (serialised by a lock file); raise BuildError on failure."""
    targets = targets or ("all",)
    missing = missing_tools(*targets)
    if missing:
        raise BuildError(f"cannot build firmware ({' '.join(targets)}): missing Debian "
                         f"package(s) {', '.join(missing)}; install with: {INSTALL_HINT}")
    if not (FIRMWARE_DIR / "Makefile").exists():
        raise BuildError(f"{FIRMWARE_DIR}: no firmware sources here (run from a source tree)")
    BUILD_DIR.mkdir(parents=True, exist_ok=True)
    with open(BUILD_DIR / ".lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        proc = subprocess.run(["make", "-C", str(FIRMWARE_DIR), "--no-print-directory", *extra,
                               *targets], capture_output=True, text=True, timeout=300)
    if proc.returncode != 0:
        raise BuildError(f"make -C firmware {' '.join(targets)} failed:\n{proc.stdout}{proc.stderr}")


def artifact(name: str) -> Path:
    """Path of a build product (e.g. 'ddrt_bridge.elf', 'ddrt-simavr')."""
    return BUILD_DIR / name
