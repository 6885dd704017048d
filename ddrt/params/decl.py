"""One declaration per setting: its unit, bounds, reload mode and one line of description,
stored in the dataclass field beside it (`setting(...)`).

The config's walker (ddrt/config/schema.py) checks a value against its field's declaration
and names the key in the error; the reload policy reads the mode from it; `python -m
ddrt.docgen` writes docs/reference/config.md from it; the Foxglove parameters carry it. A
rule between two fields stays in the section's `validate()`. This is a leaf (ddrt/params),
so the robot's and the motors' parameters declare their fields the same way.
"""

from __future__ import annotations

import dataclasses
import math
import re
from dataclasses import dataclass
from typing import Any, ClassVar, Iterator, Mapping

__all__ = ["Decl", "Text", "Section", "setting", "decl_of", "field_items", "LIVE", "NEXT_PATH", "RESTART",
           "APPLY_MODES", "NOT_EMPTY"]

# How a changed value takes effect in a running daemon:
#   live       handed to the running parts between two ticks
#   next_path  used from the next path the robot is given (the current one keeps its profile)
#   restart    read when the daemon starts; a change waits for a restart
LIVE, NEXT_PATH, RESTART = "live", "next_path", "restart"
APPLY_MODES = (LIVE, NEXT_PATH, RESTART)


@dataclass(frozen=True)
class Text:
    """What a text value must look like: a regular expression it matches whole, in words."""

    pattern: str
    what: str

    def fits(self, value: str) -> bool:
        return re.fullmatch(self.pattern, value, re.DOTALL) is not None


NOT_EMPTY = Text(r".+", "not empty")


def _g(x: float) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


@dataclass(frozen=True)
class Decl:
    """A setting's declaration. Bounds hold for a number (each number of a list); `ge`/`le`
    include the bound, `gt`/`lt` exclude it; `choices` lists the only values a number may take;
    `text` is the shape of a text value. None (where the type allows it) is always in bounds.
    `reload` None takes the enclosing section's mode; `name` is the YAML key when it is not
    the field's name (a dotted one for a section merged into another, robot.motor)."""

    doc: str
    unit: str = ""
    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    lt: float | None = None
    choices: tuple[Any, ...] = ()
    text: Text | None = None
    reload: str | None = None
    name: str | None = None
    missing: str = ""  # what a missing key takes, in words, where no dataclass default says it

    def __post_init__(self) -> None:
        if not self.doc.strip() or "\n" in self.doc:
            raise ValueError("setting: a one-line description is required")
        if self.reload is not None and self.reload not in APPLY_MODES:
            raise ValueError(f"setting: unknown reload mode {self.reload!r}")
        if self.ge is not None and self.gt is not None or self.le is not None and self.lt is not None:
            raise ValueError("setting: give one lower bound (ge or gt) and one upper (le or lt)")

    @property
    def lower(self) -> float | None:
        return self.gt if self.gt is not None else self.ge

    @property
    def upper(self) -> float | None:
        return self.lt if self.lt is not None else self.le

    def bounds(self) -> str:
        """The bounds in words: '> 0', '[0, 50]', '(0, 1]', '<= 5', 'one of 250, 500', a text's shape."""
        if self.choices:
            return "one of " + ", ".join(map(str, self.choices))
        if self.text is not None:
            return self.text.what
        lo, hi = self.lower, self.upper
        if lo is not None and hi is not None:
            return f"{'(' if self.gt is not None else '['}{_g(lo)}, {_g(hi)}{')' if self.lt is not None else ']'}"
        if lo is not None:
            return f"{'>' if self.gt is not None else '>='} {_g(lo)}"
        if hi is not None:
            return f"{'<' if self.lt is not None else '<='} {_g(hi)}"
        return ""

    def refusal(self, value: Any) -> str | None:
        """Why `value` (already of the field's type) breaks the bounds, or None when it keeps them."""
        if isinstance(value, str):
            if self.text is not None and not self.text.fits(value):
                return f"expected {self.text.what}, got {value[:60]!r}"
            return None
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return None
        if self.choices:
            return None if value in self.choices else f"must be one of {', '.join(map(str, self.choices))}, got {value!r}"
        sides = [(f">= {_g(self.ge)}", value >= self.ge) if self.ge is not None else
                 (f"> {_g(self.gt)}", value > self.gt) if self.gt is not None else None,
                 (f"<= {_g(self.le)}", value <= self.le) if self.le is not None else
                 (f"< {_g(self.lt)}", value < self.lt) if self.lt is not None else None]
        broken = [words for words, ok in filter(None, sides) if not ok]
        if not broken:
            return None
        kept = [words for words, ok in filter(None, sides) if ok]
        unit = f" {self.unit}" if self.unit else ""
        return f"must be {broken[0]}{unit}{f' (and {kept[0]})' if kept else ''}, got {value!r}"

    def check(self, value: Any, where: str) -> str | None:
        """The first refusal in `value` or in each item of a list of it, with the key it is at."""
        if isinstance(value, tuple):
            for i, item in enumerate(value):
                problem = self.check(item, f"{where}[{i}]")
                if problem is not None:
                    return problem
            return None
        reason = self.refusal(value)
        return None if reason is None else f"{where}: {reason}"


def setting(default: Any = dataclasses.MISSING, *, doc: str, unit: str = "", factory: Any = dataclasses.MISSING,
            ge: float | None = None, gt: float | None = None, le: float | None = None, lt: float | None = None,
            choices: tuple[Any, ...] = (), text: Text | None = None, reload: str | None = None,
            name: str | None = None, missing: str = "", **field_kwargs: Any) -> Any:
    """A dataclass field carrying its Decl (see Decl for the arguments)."""
    decl = Decl(doc=doc, unit=unit, ge=ge, gt=gt, le=le, lt=lt, choices=choices, text=text, reload=reload,
                name=name, missing=missing)
    return dataclasses.field(default=default, default_factory=factory, metadata={"decl": decl}, **field_kwargs)


def decl_of(f: dataclasses.Field) -> Decl | None:
    """The declaration of a field made by `setting`, else None."""
    decl = f.metadata.get("decl")
    return decl if isinstance(decl, Decl) else None


def field_items(obj: Any) -> Iterator[tuple[dataclasses.Field, Any]]:
    """Each dataclass field of `obj` with its value: the one place walkers read fields by name."""
    for f in dataclasses.fields(obj):
        yield f, getattr(obj, f.name)


class Section:
    """What a settings dataclass may declare beyond its fields, so that walkers read it
    instead of probing for it: its reload mode (`APPLY`; None: the enclosing section's),
    keys it no longer takes (`MOVED`: key -> what to write instead) and rules between its
    fields (`validate`, raising the config's error naming the key)."""

    APPLY: ClassVar[str | None] = None
    MOVED: ClassVar[Mapping[str, str]] = {}

    def validate(self, where: str) -> None:
        """Rules across fields; a single field's bounds are its declaration's."""


def check_declared(obj: Any, owner: str) -> None:
    """ValueError '<owner>.<field>: ...' for the first field of `obj` outside its declaration:
    for parameters built in code, not read by the walker (which checks as it reads)."""
    for f, value in field_items(obj):
        decl = decl_of(f)
        if decl is None:
            continue
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError(f"{owner}.{f.name}: must be finite, got {value!r}")
        problem = decl.check(value, f"{owner}.{f.name}")
        if problem is not None:
            raise ValueError(problem)
