"""Where the user's observations come from: an answers file (`--answers FILE`), else a prompt.

Every answer has a key (`odometry.distance_m`) so a script can give it in the file, and a
prompt that says exactly what to look at or measure. Closed stdin is "no answer": a clear
error that names the key to put in the file, never a traceback. `--yes` skips confirmations
(never measurements: a number nobody measured is not skipped, it is missing).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any, Callable, Mapping

from ddrt.config.filekind import ANSWERS, not_a
from ddrt.errors import DdrtError
from ddrt.config.yamlio import read_yaml


class NoAnswer(DdrtError, ValueError):
    """An answer was needed and none came (stdin closed, or no terminal)."""


class AnswersError(DdrtError, ValueError):
    """The answers file is malformed: wrong type, unknown key, a value out of range."""


# key -> (kind, what it is): "number" (finite float) or "choice" (one of the options)
WHEELS = ("left forward", "left backward", "right forward", "right backward")
KEYS: dict[str, tuple[str, Any]] = {
    "wiring.left_output_pulse": ("choice", WHEELS),
    "battery.multimeter_v": ("number", (0.5, 100.0)),
    "odometry.distance_m": ("number", (0.01, 100.0)),
    "odometry.turn_offset_deg": ("number", (-720.0, 720.0)),
    "odometry.umbmark_cw_mm": ("pair", (-5000.0, 5000.0)),
    "odometry.umbmark_ccw_mm": ("pair", (-5000.0, 5000.0)),
    "check.end_offset_mm": ("number", (0.0, 10000.0)),
}


def load_answers(path: str | Path) -> dict[str, Any]:
    """The answers file: YAML sections of keys (`odometry: {distance_m: 1.002}`), checked whole."""
    data = read_yaml(Path(path), AnswersError)
    if data is None:
        return {}
    if not isinstance(data, Mapping):
        raise AnswersError(f"{path}: expected a mapping of sections (wiring:, battery:, odometry:, check:), "
                           f"got {type(data).__name__}")
    other = not_a(data, ANSWERS, str(path), "an answers file")
    if other is not None:
        raise AnswersError(other)
    out: dict[str, Any] = {}
    sections = sorted({k.split(".")[0] for k in KEYS})
    for section, body in data.items():
        if section not in sections:
            raise AnswersError(f"{path}: {section}: unknown section (known: {', '.join(sections)})")
        if not isinstance(body, Mapping):
            raise AnswersError(f"{path}: {section}: expected a mapping of answers, got {body!r}")
        for key, value in body.items():
            full = f"{section}.{key}"
            if full not in KEYS:
                known = ", ".join(k.split(".", 1)[1] for k in KEYS if k.startswith(section + "."))
                raise AnswersError(f"{path}: {full}: unknown answer (known in {section}: {known})")
            out[full] = check_value(full, value, str(path))
    return out


def check_value(key: str, value: Any, where: str) -> Any:
    kind, spec = KEYS[key]
    if kind == "choice":
        text = " ".join(str(value).lower().split())
        if text not in spec:
            raise AnswersError(f"{where}: {key}: expected one of {', '.join(spec)}, got {value!r}")
        return text
    if kind == "pair":
        if not (isinstance(value, (list, tuple)) and len(value) == 2):
            raise AnswersError(f"{where}: {key}: expected [x, y] in mm, got {value!r}")
        return tuple(check_value_number(key, v, where, spec) for v in value)
    return check_value_number(key, value, where, spec)


def check_value_number(key: str, value: Any, where: str, bounds: tuple[float, float]) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise AnswersError(f"{where}: {key}: expected a number, got {value!r}")
    try:
        x = float(value)
    except ValueError:
        raise AnswersError(f"{where}: {key}: expected a number, got {value!r}") from None
    lo, hi = bounds
    if not (math.isfinite(x) and lo <= x <= hi):
        raise AnswersError(f"{where}: {key}: expected a number in [{lo:g}, {hi:g}], got {value!r}")
    return x


class Answers:
    """The answers of one run: the file's first, else asked on the terminal."""

    def __init__(self, given: Mapping[str, Any] | None = None, yes: bool = False,
                 ask: Callable[[str], str] | None = None, out: Any = None) -> None:
        self.given = dict(given or {})
        self.yes = yes
        self._ask = ask if ask is not None else input
        self.out = out if out is not None else sys.stderr
        self.used: dict[str, Any] = {}

    def say(self, text: str) -> None:
        print(text, file=self.out, flush=True)

    def confirm(self, what_to_do: str) -> None:
        """Tell the user what to do, and wait for Enter (--yes: go on at once)."""
        self.say(what_to_do)
        if self.yes:
            return
        try:
            self._ask("  press Enter when ready (Ctrl-C stops): ")
        except EOFError:
            raise NoAnswer("no answer on stdin (it is closed) to a confirmation; give --yes to skip "
                           "confirmations in a script") from None

    def value(self, key: str, prompt: str, tries: int = 5) -> Any:
        """The answer `key`: from the file, else asked up to `tries` times."""
        if key in self.given:
            self.used[key] = self.given[key]
            return self.given[key]
        for _ in range(tries):
            try:
                text = self._ask(prompt)
            except EOFError:
                raise NoAnswer(f"no answer on stdin (it is closed) for {key}; put it in --answers FILE "
                               f"as {key.split('.')[0]}: {{{key.split('.')[1]}: ...}}") from None
            try:
                kind = KEYS[key][0]
                parsed = check_value(key, text.split(",") if kind == "pair" else text, "answer")
            except AnswersError as exc:
                self.say(f"  {exc}; try again")
                continue
            self.used[key] = parsed
            return parsed
        raise NoAnswer(f"no usable answer for {key} after {tries} tries; put it in --answers FILE")
