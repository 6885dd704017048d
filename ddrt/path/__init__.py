"""Paths: geometry -> speed profile -> a sampled Path; the spec loader; pure pursuit and the
reference stage that turn a Path and the estimated pose into the controller's setpoint."""

from ddrt.path.profile import SpeedLimits
from ddrt.path.sampled import Path, PathPoint
from ddrt.path.spec import PathError, load_path

__all__ = ["Path", "PathError", "PathPoint", "SpeedLimits", "load_path"]
