"""An axis's values: a list as written, or a range.

A range is a section declared as config keys are (RangeSpec): the config's walker checks its
keys, types and bounds and names the key. `{start, stop, step}` counts from start by step up
to stop (stop included when a step lands on it; whole numbers stay whole); `{start, stop, num,
scale: linear | log}` is num values from start to stop inclusive, evenly spaced (in the
logarithm for log). A range with no values, or one with more than MAX_AXIS_VALUES, is refused
naming the key.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Literal, Mapping

from ddrt.config.schema import ConfigError, Section, build, setting
from ddrt.config.yamlio import shorten

MAX_AXIS_VALUES = 100_000


@dataclass(frozen=True)
class RangeSpec(Section):
    """An axis given as a range: `{start, stop, step}` or `{start, stop, num, scale}`."""

    start: float = setting(doc="The first value.")
    stop: float = setting(doc="The last value (with `step`: included when a step lands on it).")
    step: float | None = setting(
        None, doc="The distance from one value to the next, not 0; whole numbers give whole numbers.")
    num: int | None = setting(None, ge=1, le=MAX_AXIS_VALUES,
                              doc="How many values, evenly spaced from start to stop inclusive.")
    scale: Literal["linear", "log"] = setting(
        "linear", doc="`log`: the values of `num` evenly spaced in the logarithm (start and stop > 0).")

    def validate(self, where: str) -> None:
        if (self.step is None) == (self.num is None):
            raise ConfigError(f"{where}: a range takes exactly one of step and num")
        if self.step == 0:
            raise ConfigError(f"{where}.step: must not be 0")
        if self.scale == "log" and self.step is not None:
            raise ConfigError(f"{where}: a log range takes num, not step")
        if self.scale == "log" and (self.start <= 0 or self.stop <= 0):
            raise ConfigError(f"{where}: a log range needs start and stop > 0")


def axis_values(spec: Any, where: str) -> tuple[Any, ...]:
    """An axis's values: a list as given, or a RangeSpec's; ConfigError naming `where` (the key)."""
    if isinstance(spec, list):
        if not spec:
            raise ConfigError(f"{where}: the list of values is empty")
        seen = []
        for i, v in enumerate(spec):
            if isinstance(v, Mapping):
                raise ConfigError(f"{where}[{i}]: a value cannot be a mapping (sweep its keys as axes of their own)")
            if v in seen:
                raise ConfigError(f"{where}: the value {shorten(v)} is listed twice")
            seen.append(v)
        return tuple(spec)
    if not isinstance(spec, Mapping):
        raise ConfigError(f"{where}: expected a list of values or a range {{start, stop, step | num}}, "
                          f"got {shorten(spec)}")
    r = build(RangeSpec, spec, where)
    if r.step is not None:
        whole = all(isinstance(spec[k], int) and not isinstance(spec[k], bool) for k in ("start", "stop", "step"))
        return _stepped(r.start, r.stop, r.step, whole, where)
    start, stop, num = r.start, r.stop, r.num or 1
    if r.scale == "log":
        lo, hi = math.log(start), math.log(stop)
        values = [math.exp(lo + (hi - lo) * i / (num - 1)) if num > 1 else float(start) for i in range(num)]
    else:
        values = [start + (stop - start) * i / (num - 1) if num > 1 else start for i in range(num)]
    return tuple(_tidy(v) for v in values)


def _stepped(start: float, stop: float, step: float, whole: bool, where: str) -> tuple[Any, ...]:
    """start, start + step, ... to stop; `whole`: all three were written as whole numbers, and
    so are the values (the walker read them as floats, exactly: they are at most 1e12)."""
    span = stop - start
    if span != 0 and (span > 0) != (step > 0):
        raise ConfigError(f"{where}: the range has no values (from {start:g} the step {step:g} moves away from {stop:g})")
    steps = span / step  # finite: the walker holds every number to 0 or [1e-12, 1e12] in magnitude
    if not steps < MAX_AXIS_VALUES:
        raise ConfigError(f"{where}: more than {MAX_AXIS_VALUES} values "
                          f"(from {start:g} to {stop:g} by {step:g})")
    count = int(math.floor(steps + 1e-9)) + 1
    if whole:
        return tuple(int(start) + i * int(step) for i in range(count))
    return tuple(_tidy(start + i * step) for i in range(count))


def _tidy(v: float) -> float:
    """A float of a range with the binary noise of its arithmetic removed (0.1 * 3 is 0.3)."""
    return float(f"{v:.12g}")
