"""The foxglove-sdk import, in one place, with the error a user can act on."""

from __future__ import annotations

import importlib
import importlib.util
from types import ModuleType

PIP = "pip install 'ddrt[foxglove]'"


def available() -> bool:
    """Is foxglove-sdk importable (without importing it)?"""
    return importlib.util.find_spec("foxglove") is not None


def foxglove(what: str) -> ModuleType:
    """The foxglove module, or ValueError naming `what` (a config key or an option) and the fix."""
    if not available():
        raise ValueError(f"{what} needs the foxglove-sdk package, which is not installed: {PIP}")
    return importlib.import_module("foxglove")
