"""Every campaign key's declaration is enforced, as a config key's is (tests/test_config_declared.py),
derived from the declarations so a key added tomorrow is covered: junk at any key of a campaign
file, its sections or an axis's range is a CampaignError naming the file and the key, never
another exception; and each declared bound refuses a value just outside it and takes one just
inside."""

from __future__ import annotations

import copy
import math
import types
import typing
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ddrt.config.keys import Key, declared_keys
from ddrt.sweep.campaign import MAX_CASES, CampaignError, CampaignKeys, campaign_from_mapping
from ddrt.sweep.ranges import RangeSpec
from tests.support.repo import SIM_YAML
from tests.test_config_declared import _edges, _junk, _parts

SOURCE = "c.yaml"
AXIS = "controller.outer.k_y"
RANGE = {"start": 1.0, "stop": 2.0, "num": 2}
BASE: dict[str, Any] = {"base": str(SIM_YAML)}
# A section's required keys, so that one other key of it can be spoiled.
SECTIONS: dict[str, dict[str, Any]] = {"population": {"robots": 2}, "run": {}, "summary": {}}
TOP: tuple[Key, ...] = tuple(k for k in declared_keys(CampaignKeys) if not k.parent)
INNER: tuple[Key, ...] = tuple(k for k in declared_keys(CampaignKeys) if k.parent and k.hint is not Any)
RANGE_KEYS: tuple[Key, ...] = tuple(declared_keys(RangeSpec, f"axes.{AXIS}"))

# What the small readers refuse beyond a key's type and declaration (files that do not exist,
# axes that are no config key, criteria of unknown metrics, a count of seeds beyond the bound
# the description states, a seed or a file listed twice).
READERS: dict[str, list[Any]] = {
    "base": ["missing.yaml", ["missing.yaml"], [str(SIM_YAML), str(SIM_YAML)], "/dev/null", "/tmp"],
    "overrides": [{"extends": "x.yaml"}],
    "variants": [{"v": 3}, {"v": {"extends": "x.yaml"}}, {"v": [1]}],
    "paths": [{"p": 3}, {"p": "missing.yaml"}, ["missing.yaml"], {"p": ""}],
    "axes": [{AXIS: 3}, {AXIS: []}, {AXIS: [1, 1]}, {AXIS: [{"a": 1}]}, {"": [1]}, {"seed": [1]}, {3: [1]},
             {"extends": [1]}, {AXIS: {"start": 1, "stop": 2}}, {AXIS: {"start": 2, "stop": 1, "step": 1}},
             {AXIS: {"start": -1, "stop": 1, "num": 2, "scale": "log"}}, {AXIS: {"start": 1, "stop": 2, "step": 0}}],
    "seeds": [0, -1, MAX_CASES + 1, 10 ** 30, [1, 1], [1, 2 ** 64], ["x"], 2.5],
    "metrics": [["nope"], ["ticks", 3]],
    "pass": ["rms < 1", ["completed == 1"], ["fault == 3"], ["rms_cross_track_m < true"], "x", [3]],
}


def _top_junk(k: Key) -> list[Any]:
    """Values a top-level key's type, declaration or reader refuses."""
    tp = _parts(k.hint)[1]
    options = typing.get_args(tp) if typing.get_origin(tp) in (typing.Union, types.UnionType) else (tp,)
    takes_map = any(o is dict or typing.get_origin(o) is dict or k.section is not None for o in options)
    takes_list = any(typing.get_origin(o) is tuple for o in options)
    pool: list[Any] = [math.nan, math.inf, True, 2.5]
    if not takes_map:
        pool.append({"junk": [1, {"x": None}]})
    if not takes_list:
        pool += [[1], ["a", "b"]]
    if takes_list:
        pool += [[], [math.nan], [{"a": 1}]]
    if takes_map:
        pool += ["text", 3]
        if k.section is None and k.default is None:  # a key that may be left out is not given empty
            pool.append({})
    if k.decl.text is not None:
        pool += [t for t in ("", "9 bad name!", "x" * 5000) if not k.decl.text.fits(t)]
    return pool + READERS.get(k.key, [])


def _put(k: Key, value: Any) -> tuple[dict[str, Any], str]:
    """A valid campaign with `value` at key `k`, and the key its error must name."""
    data = copy.deepcopy(BASE)
    if k.owner is RangeSpec:
        data["axes"] = {AXIS: dict(RANGE, **{k.name: value})}
    elif k.parent:
        data[k.parent] = dict(SECTIONS[k.parent], **{k.name: value})
    else:
        data[k.key] = value
        if k.key == "base":  # a campaign takes base: or population:; here base: is what is spoiled
            data["population"] = {"robots": 1}
    return data, k.key


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.data())
def test_junk_at_any_campaign_key_is_a_campaign_error_naming_the_file_and_the_key(data: st.DataObject) -> None:
    k = data.draw(st.sampled_from(TOP + INNER + RANGE_KEYS), label="key")
    value = data.draw(st.sampled_from(_top_junk(k)) if k in TOP else _junk(k), label="value")
    mapping, named = _put(k, value)
    with pytest.raises(CampaignError) as info:
        campaign_from_mapping(mapping, source=SOURCE, folder=Path(SIM_YAML).parent)
    message = str(info.value)
    assert message.startswith(f"{SOURCE}: {named}"), (k.key, value, message)
    assert "\n" not in message and len(message) < 2000


@pytest.mark.parametrize("k", TOP, ids=lambda k: k.key)
def test_every_campaign_key_refuses_every_kind_of_junk_by_name(k: Key) -> None:
    """Every top-level key, each junk value of its kind, not a random sample of them."""
    for value in _top_junk(k):
        mapping, named = _put(k, value)
        with pytest.raises(CampaignError) as info:
            campaign_from_mapping(mapping, source=SOURCE, folder=Path(SIM_YAML).parent)
        assert str(info.value).startswith(f"{SOURCE}: {named}"), (value, str(info.value))


BOUNDED = [k for k in INNER + RANGE_KEYS if k.section is None and _edges(k)]


def test_the_bounded_keys_are_those_declared() -> None:
    assert {k.key for k in BOUNDED} == {"population.robots", "run.duration_s", "run.timeout_s", f"axes.{AXIS}.num"}


@pytest.mark.parametrize("k", BOUNDED, ids=lambda k: k.key)
def test_every_declared_campaign_bound_refuses_just_outside_and_takes_just_inside(k: Key) -> None:
    for outside, inside, which in _edges(k):
        mapping, named = _put(k, outside)
        with pytest.raises(CampaignError, match=rf"^{SOURCE}: {named}: must be ") as info:
            campaign_from_mapping(mapping, source=SOURCE)
        assert repr(outside) in str(info.value) or str(outside) in str(info.value), (which, str(info.value))
        mapping, _ = _put(k, inside)
        campaign_from_mapping(mapping, source=SOURCE)  # taken: the bound is the declaration's, nothing else
