"""Pass criteria: `rms_cross_track_m < 0.005`, `completed == true`, `fault == ''`.

One comparison per criterion, a metric on the left and a constant on the right, so a
campaign says what "good" means in its own file and every row carries its verdict. A row
passes when its run ended (status ok) and every criterion holds; a metric with no value
(null) fails its criterion.
"""

from __future__ import annotations

import math
import operator
import re
from dataclasses import dataclass
from typing import Any, Callable, Mapping

from ddrt.sweep.columns import BOOL_METRICS, KNOWN_METRICS, TEXT_METRICS

_OPS: dict[str, Callable[[Any, Any], bool]] = {
    "<": operator.lt, "<=": operator.le, ">": operator.gt, ">=": operator.ge, "==": operator.eq, "!=": operator.ne,
}
# The form of a criterion; a campaign's `pass:` declares its text by it (ddrt/sweep/campaign.py).
FORM = re.compile(r"^\s*([A-Za-z_][\w.]*)\s*(<=|>=|==|!=|<|>)\s*(.+?)\s*$")
FORM_WORDS = "METRIC OP VALUE, e.g. 'rms_cross_track_m < 0.005' or 'completed == true'"
FORM_HELP = f"expected {FORM_WORDS}"


@dataclass(frozen=True)
class Criterion:
    """One comparison of a row's metric with a constant."""

    metric: str
    op: str
    value: float | bool | str
    text: str

    def holds(self, row: Mapping[str, Any]) -> bool:
        have = row.get(self.metric)
        if have is None:
            return False
        if isinstance(self.value, (bool, str)):
            return _OPS[self.op](have, self.value)
        if not isinstance(have, (int, float)) or math.isnan(have):
            return False
        return _OPS[self.op](float(have), self.value)


def _value(text: str) -> float | bool | str:
    if text in ("true", "false"):
        return text == "true"
    if len(text) >= 2 and text[0] == text[-1] and text[0] in "'\"":
        return text[1:-1]
    number = float(text)  # ValueError: not a number
    if math.isnan(number):
        raise ValueError(text)
    return number


def parse_criterion(text: Any, where: str) -> Criterion:
    """`text` as a Criterion; a ValueError names `where` and what is wrong."""
    if not isinstance(text, str):
        raise ValueError(f"{where}: {FORM_HELP}, got {text!r}")
    m = FORM.match(text)
    if m is None:
        raise ValueError(f"{where}: {FORM_HELP}, got {text!r}")
    metric, op, raw = m.groups()
    if metric not in KNOWN_METRICS:
        raise ValueError(f"{where}: unknown metric {metric!r} (known: {', '.join(KNOWN_METRICS)})")
    try:
        value = _value(raw)
    except ValueError:
        raise ValueError(f"{where}: {raw!r} is not a number, true, false or a quoted text") from None
    if metric in TEXT_METRICS and not isinstance(value, str):
        raise ValueError(f"{where}: {metric} is text: compare it with a quoted text, e.g. {metric} == ''")
    if metric in BOOL_METRICS and not isinstance(value, bool):
        raise ValueError(f"{where}: {metric} is true or false: compare it with true or false")
    if metric not in TEXT_METRICS + BOOL_METRICS and isinstance(value, (bool, str)):
        raise ValueError(f"{where}: {metric} is a number: compare it with a number")
    if op not in ("==", "!=") and isinstance(value, (bool, str)):
        raise ValueError(f"{where}: {op} needs a number on the right, got {raw!r}")
    return Criterion(metric, op, value, " ".join(text.split()))


def passes(row: Mapping[str, Any], criteria: tuple[Criterion, ...]) -> bool:
    return row.get("status") == "ok" and all(c.holds(row) for c in criteria)
