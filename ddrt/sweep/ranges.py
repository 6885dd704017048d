"""An axis's values: a list as written, or a range.

`{start, stop, step}` counts from start by step up to stop (stop included when a step lands
on it; whole numbers stay whole); `{start, stop, num, scale: linear | log}` is num values
from start to stop inclusive, evenly spaced (in the logarithm for log). A range with no
values, or one with more than MAX_AXIS_VALUES, is refused naming the key.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Mapping

from ddrt.config.yamlio import shorten

RANGE_KEYS = ("start", "stop", "step", "num", "scale")
MAX_AXIS_VALUES = 100_000

Fail = Callable[[str, str], Exception]  # (key, problem) -> the error to raise


def axis_values(spec: Any, where: str, fail: Fail) -> tuple[Any, ...]:
    """An axis's values: a list as given, or a range {start, stop, step} (stop included when
    the steps land on it) or {start, stop, num, scale: linear | log}."""
    if isinstance(spec, list):
        if not spec:
            raise fail(where, "the list of values is empty")
        seen = []
        for i, v in enumerate(spec):
            if isinstance(v, Mapping):
                raise fail(f"{where}[{i}]", "a value cannot be a mapping (sweep its keys as axes of their own)")
            if v in seen:
                raise fail(where, f"the value {shorten(v)} is listed twice")
            seen.append(v)
        return tuple(spec)
    if not isinstance(spec, Mapping):
        raise fail(where, f"expected a list of values or a range {{start, stop, step | num}}, got {shorten(spec)}")
    for key in spec:
        if key not in RANGE_KEYS:
            raise fail(f"{where}.{key}", f"unknown range key (known: {', '.join(RANGE_KEYS)})")
    for key in ("start", "stop"):
        v = spec.get(key)
        if not finite(v):
            raise fail(f"{where}.{key}", f"expected a finite number, got {shorten(v)}")
    start, stop = spec["start"], spec["stop"]
    if ("step" in spec) == ("num" in spec):
        raise fail(where, "a range takes exactly one of step and num")
    scale = spec.get("scale", "linear")
    if scale not in ("linear", "log"):
        raise fail(f"{where}.scale", f"expected linear or log, got {shorten(scale)}")
    if "step" in spec:
        return _stepped(start, stop, spec["step"], scale, where, fail)
    num = spec["num"]
    if isinstance(num, bool) or not isinstance(num, int) or num < 0:
        raise fail(f"{where}.num", f"expected a whole number of values, got {shorten(num)}")
    if num == 0:
        raise fail(where, "the range has no values (num: 0)")
    if num > MAX_AXIS_VALUES:
        raise fail(f"{where}.num", f"{num} values, more than {MAX_AXIS_VALUES}")
    if scale == "log":
        if start <= 0 or stop <= 0:
            raise fail(where, "a log range needs start and stop > 0")
        lo, hi = math.log(start), math.log(stop)
        values = [math.exp(lo + (hi - lo) * i / (num - 1)) if num > 1 else float(start) for i in range(num)]
    else:
        values = [start + (stop - start) * i / (num - 1) if num > 1 else start for i in range(num)]
    return tuple(_tidy(v) for v in values)


def _stepped(start: float, stop: float, step: Any, scale: str, where: str, fail: Fail) -> tuple[Any, ...]:
    if not finite(step) or step == 0:
        raise fail(f"{where}.step", f"expected a finite nonzero number, got {shorten(step)}")
    if scale == "log":
        raise fail(where, "a log range takes num, not step")
    span = stop - start
    if span != 0 and (span > 0) != (step > 0):
        raise fail(where, f"the range has no values (from {start} the step {step} moves away from {stop})")
    try:
        steps = span / step
    except OverflowError:  # two whole numbers whose quotient is beyond a float
        steps = math.inf
    if not steps < MAX_AXIS_VALUES:  # also a span beyond the float range (inf)
        raise fail(where, f"more than {MAX_AXIS_VALUES} values "
                          f"(from {shorten(start)} to {shorten(stop)} by {shorten(step)})")
    count = int(math.floor(steps + 1e-9)) + 1
    whole = all(isinstance(v, int) for v in (start, stop, step))
    return tuple(start + i * step if whole else _tidy(start + i * step) for i in range(count))


def finite(v: Any) -> bool:
    """A finite int or float that a range can compute with: an integer beyond the float range
    is not one (math.isfinite would raise OverflowError on it)."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return False
    try:
        return math.isfinite(v)
    except OverflowError:
        return False


def _tidy(v: float) -> float:
    """A float of a range with the binary noise of its arithmetic removed (0.1 * 3 is 0.3)."""
    return float(f"{v:.12g}")
