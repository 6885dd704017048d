"""Every config key's declaration is enforced, derived from the declarations themselves so a key
added tomorrow is covered: junk at any key (wrong types, out-of-range numbers, nan and inf,
huge text, nested junk) is a ConfigError naming the file and the key, never another
exception; and each declared bound refuses a value just outside it and takes one just inside."""

from __future__ import annotations

import copy
import dataclasses
import math
import re
import types
import typing
from typing import Any, Literal

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ddrt.config import ConfigError, config_from_mapping
from ddrt.config.keys import ITEM, Key, declared_keys
from ddrt.config.schema import FLOAT_MAX, INT_LIMIT, build
from ddrt.config.sections import Config
from ddrt.config.sim_truth import FloorPatch, PayloadEvent
from ddrt.params.robot import RobotParams
from tests.support.repo import SIM_YAML

KEYS: tuple[Key, ...] = tuple(k for k in declared_keys(Config) if k.hint is not Any)
SOURCE = "fuzz.yaml"


def _sim() -> dict[str, Any]:
    data = yaml.safe_load(SIM_YAML.read_text(encoding="utf-8"))
    data.pop("path", None)
    return data


BASE = _sim()
# A valid item of each list of sections, so one key of it can be spoiled.
ITEMS: dict[type, dict[str, Any]] = {
    PayloadEvent: {"at_s": 1.0, "mass_kg": 1.0},
    FloorPatch: {"x_min": 0.0, "y_min": 0.0, "x_max": 1.0, "y_max": 1.0},
}


def _parts(hint: Any) -> tuple[bool, Any]:
    """(None allowed, the type without None)."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType):
        args = typing.get_args(hint)
        rest = tuple(a for a in args if a is not type(None))
        return len(rest) < len(args), rest[0] if len(rest) == 1 else typing.Union[rest]
    return False, hint


def _scalars(hint: Any) -> tuple[Any, ...]:
    """The scalar types a value of `hint` may be (a tuple's items count as its own)."""
    _, tp = _parts(hint)
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return tuple(s for a in typing.get_args(tp) for s in _scalars(a))
    return (tp,)


def _out_of_bounds(k: Key) -> list[Any]:
    """Numbers the declaration (or, without bounds, the walker's number range) refuses."""
    kinds = _scalars(k.hint)
    is_int = int in kinds and float not in kinds
    d = k.decl
    if d.choices:
        return [max(d.choices) + 1, min(d.choices) - 1]
    out: list[Any] = []
    if d.lower is not None:
        out.append(d.lower if d.gt is not None else d.lower - (1 if is_int else 1e-3 * max(1.0, abs(d.lower))))
    if d.upper is not None:
        out.append(d.upper if d.lt is not None else d.upper + (1 if is_int else 1e-3 * max(1.0, abs(d.upper))))
    if not out:
        out = [INT_LIMIT + 1] if is_int else [FLOAT_MAX * 10, -FLOAT_MAX * 10]
    return out


def _takes(k: Key, kind: type) -> bool:
    return any(s is kind or typing.get_origin(s) is kind for s in _scalars(k.hint))


def _junk(k: Key) -> st.SearchStrategy[Any]:
    """Values the key's type and declaration refuse, whatever the rest of the file says."""
    nested = st.recursive(st.dictionaries(st.text(max_size=5), st.integers(), max_size=3),
                          lambda inner: st.dictionaries(st.text(max_size=5), inner, max_size=3)
                          | st.lists(inner, min_size=1, max_size=3), max_leaves=8)
    pool = [st.sampled_from([math.nan, math.inf, -math.inf])]
    if k.section is None or typing.get_origin(_parts(k.hint)[1]) is tuple:
        pool.append(nested.filter(lambda v: isinstance(v, dict)))  # a mapping where a value belongs
    if k.section is not None:
        pool.append(st.sampled_from(["text", 3, 2.5, True]))  # a value where a mapping belongs
        return st.one_of(pool)
    tp = _parts(k.hint)[1]
    if typing.get_origin(tp) is tuple:
        pool.append(st.sampled_from(["text", 3, True]))
        items = typing.get_args(tp)
        if items and items[0] in (int, float):
            length = 1 if items[-1] is Ellipsis else len(items)
            pool.append(st.sampled_from([[v] * length for v in _out_of_bounds(k)]))
        return st.one_of(pool)
    if typing.get_origin(tp) is Literal or k.decl.choices:
        choices = typing.get_args(tp) if typing.get_origin(tp) is Literal else k.decl.choices
        pool.append(st.sampled_from(["not-a-choice", 12345, [1]]).filter(lambda v: v not in choices))
    if _takes(k, bool):
        pool.append(st.sampled_from([1, 0.0, "yes", [True]]))
    elif _takes(k, int) or _takes(k, float):
        pool.append(st.sampled_from(_out_of_bounds(k)))
        pool.append(st.sampled_from([True, [1.0], 2 ** 80]))
        if not _takes(k, str) and not any(typing.get_origin(s) is Literal for s in _scalars(k.hint)):
            pool.append(st.text(min_size=1, max_size=40))
        if _takes(k, int) and not _takes(k, float):
            pool.append(st.sampled_from([1.5, 0.25]))
    if _takes(k, str) and k.decl.text is not None:
        text = k.decl.text
        refused = [t for t in ("", "x" * 100_000 + " \x00 !", "9 bad name!") if not text.fits(t)]
        if refused:
            pool.append(st.sampled_from(refused))
    if _takes(k, str):
        pool.append(st.sampled_from([[1]] + [v for v, kind in ((3, int), (2.5, float), (True, bool))
                                              if not _takes(k, kind)]))
    return st.one_of(pool)


def _put(data: dict[str, Any], k: Key, value: Any) -> str:
    """`data` with `value` at key `k` (a list's key spoils a valid item); the key the error names."""
    parts = k.key.split(".")
    node = data
    shown = []
    for i, part in enumerate(parts[:-1]):
        name, listed = (part[:-len(ITEM)], True) if part.endswith(ITEM) else (part, False)
        shown.append(name + ("[0]" if listed else ""))
        if listed:
            item_cls = next(c for c in ITEMS if ".".join(parts[:i + 1]).endswith(name + ITEM)
                            and any(f.name == parts[i + 1] for f in dataclasses.fields(c)))
            node[name] = [copy.deepcopy(ITEMS[item_cls])]
            node = node[name][0]
        else:
            child = node.get(name)
            node[name] = dict(child) if isinstance(child, dict) else {}
            node = node[name]
    node[parts[-1]] = value
    return ".".join(shown + [parts[-1]])


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_junk_at_any_key_is_a_config_error_naming_the_file_and_the_key(data: st.DataObject) -> None:
    k = data.draw(st.sampled_from(KEYS), label="key")
    value = data.draw(_junk(k), label="value")
    mapping = copy.deepcopy(BASE)
    named = _put(mapping, k, value)
    with pytest.raises(ConfigError) as info:
        config_from_mapping(mapping, source=SOURCE)
    message = str(info.value)
    assert message.startswith(f"{SOURCE}: {named}"), (k.key, value, message)
    assert "\n" not in message and len(message) < 2000


def _fixed_junk(k: Key) -> list[Any]:
    """A few junk values every key refuses, drawn the same way each run: NaN, a mapping of
    junk, and (for a value) a number outside its declaration."""
    out: list[Any] = [math.nan, {"junk": [1, {"x": None}]}]
    tp = _parts(k.hint)[1]
    if k.section is None and typing.get_origin(tp) is not tuple and (_takes(k, int) or _takes(k, float)) \
            and not _takes(k, bool):
        out.append(_out_of_bounds(k)[0])
    if k.section is not None and typing.get_origin(tp) is tuple:
        out.remove(out[1])  # a mapping of junk is a list's item here, read as a section
    return out


@pytest.mark.parametrize("k", KEYS, ids=lambda k: k.key)
def test_every_key_refuses_junk_naming_the_file_and_the_key(k: Key) -> None:
    """Every key, not a random sample of them: NaN, a mapping of junk and a number outside the
    declaration are each a ConfigError whose message starts with the file and the key."""
    for value in _fixed_junk(k):
        mapping = copy.deepcopy(BASE)
        named = _put(mapping, k, value)
        with pytest.raises(ConfigError) as info:
            config_from_mapping(mapping, source=SOURCE)
        assert str(info.value).startswith(f"{SOURCE}: {named}"), (value, str(info.value))


def _steps(k: Key) -> tuple[float, bool]:
    kinds = _scalars(k.hint)
    is_int = int in kinds and float not in kinds
    return (1.0 if is_int else 0.0), is_int


def _edges(k: Key) -> list[tuple[Any, Any, str]]:
    """(just outside, just inside, which bound) for each declared numeric bound."""
    d = k.decl
    _, is_int = _steps(k)
    out = []
    for bound, strict, sign in ((d.ge, False, -1), (d.gt, True, -1), (d.le, False, 1), (d.lt, True, 1)):
        if bound is None:
            continue
        eps = 1 if is_int else max(abs(bound) * 1e-6, 1e-6)
        outside, inside = (bound, bound - sign * eps) if strict else (bound + sign * eps, bound)
        if is_int:
            outside, inside = int(outside), int(inside)
        out.append((outside, inside, ("gt" if sign < 0 else "lt") if strict else ("ge" if sign < 0 else "le")))
    for choice in d.choices:
        out.append((max(d.choices) + 1, choice, "choices"))
    return out


BOUNDED = [k for k in KEYS if k.section is None and _edges(k)]


def _section_input(k: Key, value: Any) -> dict[str, Any]:
    base: dict[str, Any] = {}
    if k.owner is RobotParams:
        base = copy.deepcopy(BASE["robot"])
        base.pop("motor", None)
    base.update(ITEMS.get(k.owner, {}))
    tp = _parts(k.hint)[1]
    if typing.get_origin(tp) is tuple:  # each number of a list is held to the bounds
        items = typing.get_args(tp)
        value = [value] * (1 if items[-1] is Ellipsis else len(items))
    base[k.name] = value
    return base


@pytest.mark.parametrize("k", BOUNDED, ids=lambda k: k.key)
def test_every_declared_bound_refuses_just_outside_and_takes_just_inside(k: Key) -> None:
    where = k.parent.replace(ITEM, "[0]")
    for outside, inside, which in _edges(k):
        with pytest.raises(ConfigError) as info:
            build(k.owner, _section_input(k, outside), where)
        assert str(info.value).startswith(f"{where + '.' if where else ''}{k.name}"), (which, str(info.value))
        assert repr(outside) in str(info.value) or str(outside) in str(info.value), (which, str(info.value))
        try:
            build(k.owner, _section_input(k, inside), where)
        except ConfigError as exc:
            # Only a rule between fields may refuse it (fault_latch_s > max_gap_s), never the bound.
            assert not re.search(r": must be [<>]", str(exc)) and k.decl.check(inside, k.key) is None, (which, str(exc))


def test_bounded_keys_are_most_numeric_keys() -> None:
    """The bounds test covers every key that declares a bound; most numbers declare one."""
    numeric = [k for k in KEYS if k.section is None and (_takes(k, float) or _takes(k, int)) and not _takes(k, bool)]
    assert len(BOUNDED) > 0.8 * len(numeric), sorted(k.key for k in numeric if k not in BOUNDED)


# A valid spec of each path kind, so one key of it can be pushed to its bounds.
PATH_BASES: dict[str, dict[str, Any]] = {
    "line": {"length": 1.0}, "circle": {"radius": 1.0}, "rectangle": {"width": 1.0, "height": 1.0},
    "ellipse": {"a": 1.0, "b": 0.5}, "figure_eight": {"size": 1.0}, "s_curve": {"length": 1.0, "offset": 0.2},
    "points": {"points": [[0.0, 0.0], [1.0, 0.0]]}, "file": {"file": "p.csv"},
}


def _path_keys() -> list[tuple[str, Key]]:
    from ddrt.path.shapes import KINDS, SHAPES
    return [(kind, k) for kind, cls in {**SHAPES, **KINDS}.items() for k in declared_keys(cls)
            if k.section is None and _edges(k) and k.key not in ("width", "height")]  # figure_eight: size given


@pytest.mark.parametrize(("kind", "k"), _path_keys(), ids=lambda v: v if isinstance(v, str) else v.key)
def test_every_path_key_bound_refuses_just_outside_and_takes_just_inside(kind: str, k: Key) -> None:
    """Path specs declare their keys as config keys do: the same walker holds them to their bounds."""
    from ddrt.path.shapes import KINDS, SHAPES
    cls = {**SHAPES, **KINDS}[kind]
    for outside, inside, which in _edges(k):
        with pytest.raises(ConfigError, match=rf"^{k.key}: must be "):
            build(cls, {**PATH_BASES[kind], k.key: outside})
        try:
            build(cls, {**PATH_BASES[kind], k.key: inside})
        except ConfigError as exc:  # only a rule between keys may refuse it, never the bound
            assert not re.search(r": must be [<>]", str(exc)), (which, str(exc))

