"""The foxglove-sdk import, in one place, with the error a user can act on."""

from __future__ import annotations

import importlib
import importlib.util
from types import ModuleType

PIP = "pip install 'ddrt[foxglove]'"


def available() -> bool:
    """Is foxglove-sdk installed (found, without importing it)?"""
    try:
        return importlib.util.find_spec("foxglove") is not None
    except (ImportError, ValueError):  # sys.modules["foxglove"] is None: imports of it blocked
        return False


def foxglove(what: str) -> ModuleType:
    """The foxglove module, or ValueError naming `what` (a config key or an option) and the fix.

    An install that is found but does not import (its native extension built for another
    CPU or C library, a partial upgrade) is the same error with the import's reason: the
    SDK is a compiled wheel, and a Raspberry Pi is where a wrong one turns up."""
    if not available():
        raise ValueError(f"{what} needs the foxglove-sdk package, which is not installed: {PIP}")
    try:
        return importlib.import_module("foxglove")
    except ImportError as exc:
        raise ValueError(f"{what} needs the foxglove-sdk package, which is installed but does not import "
                         f"({type(exc).__name__}: {exc}): reinstall it for this machine: {PIP}") from None
