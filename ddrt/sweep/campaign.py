"""A campaign file: what to vary, how to run each case, what to keep and what passes.

Every key is declared beside its field (CampaignKeys and the sections it holds: type, unit,
bounds, one line of description), as config keys are: the config's walker converts each value
and holds it to its declaration, and docs/reference/campaign.md is written from the same
declarations (ddrt/sweep/reference.py). The file is read strictly: an unknown key, a wrong
type, a bound broken, a range with no values or an empty axis is a CampaignError naming the
file and the key, before any case is built. What a declaration cannot say (a file that must
exist, an axis's config key, a criterion's metric) is read by the small readers below.
"""

from __future__ import annotations

import dataclasses
import os
import re
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path as FsPath
from typing import Any, Mapping

from ddrt.config.filekind import CAMPAIGN, not_a
from ddrt.config.keys import key_of
from ddrt.config.schema import ConfigError, Section, convert, decl_of, field_types, setting
from ddrt.config.textfile import mode_kind
from ddrt.config.yamlio import read_yaml, shorten
from ddrt.errors import DdrtError
from ddrt.params.decl import Text
from ddrt.sweep.columns import KNOWN_METRICS, NUMERIC_METRICS, TEXT_METRICS
from ddrt.sweep.criteria import FORM, FORM_WORDS, Criterion, parse_criterion
from ddrt.sweep.ranges import axis_values

# Names the campaign gives its own axes; a config key cannot be one of them.
BUILTIN_AXES = ("base", "variant", "robot", "path", "seed")
MAX_CASES = 1_000_000
DEFAULT_TIMEOUT_S = 600.0
DEFAULT_SUMMARY_METRIC = "rms_cross_track_m"
# The figures a summary takes percentiles of: the numbers (completed is a yes/no).
PERCENTILE_METRICS = tuple(m for m in NUMERIC_METRICS if m != "completed")


def _one_of(names: tuple[str, ...], what: str) -> Text:
    return Text("|".join(map(re.escape, names)), f"{what}: {', '.join(names)}")


FILE_NAME = Text(r".+", "a file name")
METRIC = _one_of(KNOWN_METRICS, "a metric of metrics.json")
PERCENTILE_METRIC = _one_of(PERCENTILE_METRICS, "a number of metrics.json")
CRITERION = Text(FORM.pattern, FORM_WORDS)


class CampaignError(DdrtError, ValueError):
    """A campaign is malformed or one of its cases is invalid; the message names the file,
    the case where there is one, and the key."""


@dataclass(frozen=True)
class Axis:
    """One swept config key (dotted) and its values, in the file's order."""

    key: str
    values: tuple[Any, ...]


@dataclass(frozen=True)
class PopulationSpec(Section):
    """`robots` robots drawn from `seed` by ddrt/sweep/population.py."""

    robots: int = setting(ge=1, le=MAX_CASES, doc="How many robots are drawn (an axis `robot`).")
    seed: int = setting(20261201, doc="The seed they are drawn from: the same seed, the same robots.")
    path_speed: bool = setting(True, doc="Each robot follows its path at its own drawn speed.")


@dataclass(frozen=True)
class RunSpec(Section):
    """How long each case may run."""

    duration_s: float | None = setting(
        None, unit="s", gt=0, doc="Simulated time each case runs, as `ddrt sim --duration`; null: to the path's end.")
    timeout_s: float | None = setting(
        DEFAULT_TIMEOUT_S, unit="s", gt=0, doc="Wall time after which a case is stopped (status `timeout`); null: none.")


@dataclass(frozen=True)
class SummarySpec(Section):
    """What the summary gives percentiles of."""

    metrics: tuple[str, ...] | None = setting(
        None, text=PERCENTILE_METRIC, missing="the numbers `pass:` names, else `rms_cross_track_m`",
        doc="The figures the summary gives percentiles of; the first is the figures' metric.")


@dataclass(frozen=True)
class CampaignKeys(Section):
    """A campaign file's top level, as written: the readers below turn it into a Campaign."""

    name: str = setting("", missing="the file's name", doc="Title of the summary.")
    description: str = setting("", doc="Not interpreted.")
    base: str | tuple[str, ...] | None = setting(
        None, text=FILE_NAME, missing="required unless `population:`",
        doc="The config file every case starts from (with its `extends:`); a list of files is an axis `base`.")
    overrides: dict[str, Any] = setting(
        factory=dict, doc="Config keys merged over every case's config, as a config file gives them; not `extends:`.")
    variants: dict[str, Any] | None = setting(
        None, doc="Name -> config keys merged over the config; an axis `variant` (`nominal: {}` is the base as it is).")
    population: PopulationSpec | None = setting(
        None, doc="Random robots drawn from a seed ([sweep.md](sweep.md#populations)); an axis `robot`.")
    paths: dict[str, Any] | tuple[str, ...] | None = setting(
        None, text=FILE_NAME, missing="the config's `path:`",
        doc="Name -> a path file or an inline spec (as a config's `path:`), or a list of files named by their "
            "stems; an axis `path`.")
    axes: dict[str, Any] | None = setting(
        None, doc="Dotted config key -> a list of values or a range (below); each is an axis of its own name.")
    seeds: int | tuple[int, ...] | None = setting(
        None, missing="each config's `sim.seed`",
        doc=f"The simulated robot's noise seeds: N (1 to {MAX_CASES}) is seeds 1..N, or a list of distinct "
            "seeds; an axis `seed`.")
    run: RunSpec = setting(factory=RunSpec, doc="How long each case may run.")
    metrics: tuple[str, ...] | None = setting(
        None, text=METRIC, missing="every number of metrics.json",
        doc="The metrics.json figures each row keeps; `state`, `fault` and what `pass:` and `summary:` read "
            "are always kept.")
    criteria: str | tuple[str, ...] | None = setting(
        None, name="pass", text=CRITERION, missing="`completed == true` (with `run.duration_s`: `fault == ''`)",
        doc="What a passing run holds: OP is one of `< <= > >= == !=`, VALUE a number, `true`/`false` or a "
            "quoted text; every criterion must hold.")
    summary: SummarySpec = setting(factory=SummarySpec, doc="What the summary gives percentiles of.")

    def validate(self, where: str) -> None:
        if not self.base and self.population is None:
            raise ConfigError("base: missing: a config file (or a population: of robots) is required")
        if self.seeds is not None and self.axes and "sim.seed" in self.axes:
            raise ConfigError("axes.sim.seed: seeds: sets every case's sim.seed: sweep the seed with one or the other")


# The YAML key of each field (`pass` is a word Python keeps for itself: its field is `criteria`).
FIELDS: dict[str, dataclasses.Field] = {key_of("", f): f for f in dataclasses.fields(CampaignKeys)}
KEYS = tuple(FIELDS)


@dataclass(frozen=True)
class RunSettings:
    """How every case runs and what its row keeps."""

    duration_s: float | None = None  # as `ddrt sim --duration`; None: the path's end
    timeout_s: float | None = DEFAULT_TIMEOUT_S  # wall seconds; None: no limit
    metrics: tuple[str, ...] = NUMERIC_METRICS  # TEXT_METRICS are always kept
    criteria: tuple[Criterion, ...] = ()


@dataclass(frozen=True)
class Campaign:
    """A campaign file, checked: everything needed to expand its cases."""

    source: str  # the file, as named, for messages
    folder: FsPath  # where its relative file names start
    name: str = ""
    bases: tuple[FsPath, ...] = ()  # absolute
    base_labels: tuple[str, ...] = ()  # as written
    base_axis: bool = False  # given as a list: the axis (and column) `base`
    overrides: dict[str, Any] = field(default_factory=dict)
    variants: dict[str, dict[str, Any]] = field(default_factory=dict)
    population: PopulationSpec | None = None
    paths: dict[str, str | dict[str, Any]] = field(default_factory=dict)  # name -> absolute file or spec
    axes: tuple[Axis, ...] = ()
    seeds: tuple[int, ...] | None = None  # None: each config's own sim.seed
    run: RunSettings = RunSettings()
    summary_metrics: tuple[str, ...] = (DEFAULT_SUMMARY_METRIC,)


def load_campaign(path: str | FsPath) -> Campaign:
    """Read and check a campaign file."""
    p = FsPath(path)
    kind = file_kind(p)
    if kind not in ("a file", "missing"):  # a missing file: read_yaml's "cannot read" says so
        raise CampaignError(f"{p}: {kind}, not a campaign file")
    data = read_yaml(p, CampaignError)
    return campaign_from_mapping(data, source=str(p), folder=p.resolve().parent)


def campaign_from_mapping(data: Any, source: str = "<campaign>", folder: str | FsPath = ".") -> Campaign:
    """Check a campaign given as a mapping (a parsed file, or built in code by a benchmark)."""
    return _Reader(source, FsPath(folder).resolve()).campaign(data)


def file_kind(p: FsPath) -> str:
    """"a file" for a regular file, else what `p` is ("missing", "a directory", "a FIFO", ...),
    found by stat alone: opening a FIFO that nobody writes would block for ever."""
    try:
        mode = os.stat(p).st_mode
    except FileNotFoundError:
        return "missing"
    except (OSError, ValueError) as exc:  # ValueError: a name with a NUL byte
        why = (exc.strerror if isinstance(exc, OSError) else None) or exc
        return f"unreadable ({' '.join(str(why).split())})"
    return mode_kind(mode)


def _union_option(hint: Any, value: Any) -> Any:
    """The option of a union type that has `value`'s shape (a list, a mapping, else a scalar),
    so a bad value's error is that option's ("seeds[1]: expected a whole number"), not the
    first option's; `hint` itself when it is no union or no option has the shape."""
    options = typing.get_args(hint) if typing.get_origin(hint) in (typing.Union, types.UnionType) else ()

    def shape(tp: Any) -> str:
        if typing.get_origin(tp) is tuple:
            return "list"
        return "mapping" if tp is dict or typing.get_origin(tp) is dict or dataclasses.is_dataclass(tp) else "scalar"

    wanted = "list" if isinstance(value, list) else "mapping" if isinstance(value, Mapping) else "scalar"
    fits = [tp for tp in options if tp is not type(None) and shape(tp) == wanted]
    return fits[0] if len(fits) == 1 else hint


class _Reader:
    """Reads one campaign mapping: the declared keys through the walker, then what needs a
    reader of its own; every error names the source and the key."""

    def __init__(self, source: str, folder: FsPath) -> None:
        self.source = source
        self.folder = folder

    def fail(self, key: str, problem: str) -> CampaignError:
        return CampaignError(f"{self.source}: {key}: {problem}")

    def campaign(self, data: Any) -> Campaign:
        if data is None:
            raise CampaignError(f"{self.source}: the campaign is empty")
        if not isinstance(data, Mapping):
            raise CampaignError(f"{self.source}: the top level must be a mapping of campaign keys")
        other = not_a(data, CAMPAIGN, self.source, "a campaign")
        if other is not None:
            raise CampaignError(other)
        try:
            keys = self.declared(data)
            axes = tuple(Axis(key, axis_values(spec, self.axis_key(key))) for key, spec in (keys.axes or {}).items())
        except ConfigError as exc:
            raise CampaignError(f"{self.source}: {exc}") from None
        bases = self.bases(keys.base)
        criteria = self.criteria(keys.criteria)
        metrics = NUMERIC_METRICS if keys.metrics is None else \
            tuple(m for m in dict.fromkeys(keys.metrics) if m not in TEXT_METRICS)
        summary_metrics = self.summary(keys.summary, criteria)
        # What the criteria and the summary read is kept even when metrics: leaves it out.
        wanted = [c.metric for c in criteria] + list(summary_metrics)
        kept = metrics + tuple(dict.fromkeys(m for m in wanted if m not in metrics + TEXT_METRICS))
        duration, timeout = keys.run.duration_s, keys.run.timeout_s
        if not criteria:  # as `ddrt sim`'s exit status: the path completed, or ran its duration without a fault
            criteria = (parse_criterion("fault == ''" if duration else "completed == true", "pass"),)
        camp = Campaign(
            source=self.source, folder=self.folder, name=keys.name,
            bases=bases, base_labels=keys.base if isinstance(keys.base, tuple) else (keys.base,) if keys.base else (),
            base_axis=isinstance(keys.base, tuple),
            overrides=self.config_keys(keys.overrides, "overrides"),
            variants={str(name): self.config_keys(over, f"variants.{name}") for name, over in (keys.variants or {}).items()},
            population=keys.population,
            paths=self.paths(keys.paths),
            axes=axes,
            seeds=self.seeds(keys.seeds),
            run=RunSettings(duration, timeout, kept, criteria),
            summary_metrics=summary_metrics,
        )
        self.count(camp)
        return camp

    def declared(self, data: Mapping[Any, Any]) -> CampaignKeys:
        """The top level through the walker: each key converted to its field's type and held to
        its declaration. A key that may be left out is not given empty: leaving it out says so."""
        for key in data:
            if key not in FIELDS:
                shown = key if isinstance(key, str) and len(key) <= 60 else shorten(key)
                raise ConfigError(f"{shown}: unknown key (known: {', '.join(KEYS)})")
        hints = field_types(CampaignKeys)
        values: dict[str, Any] = {}
        for key, f in FIELDS.items():
            value = data.get(key)
            if value is None:  # null is the key left out, as in a config
                continue
            value = convert(_union_option(hints[f.name], value), value, key)
            if f.default is None and isinstance(value, (tuple, dict)) and not value:
                raise ConfigError(f"{key}: empty: give at least one, or leave the key out")
            decl = decl_of(f)
            problem = None if decl is None or value is None else decl.check(value, key)
            if problem is not None:
                raise ConfigError(problem)
            values[f.name] = value
        keys = CampaignKeys(**values)
        keys.validate("")
        return keys

    def axis_key(self, key: Any) -> str:
        """`axes.KEY` for a dotted config key an axis may sweep."""
        where = f"axes.{key if isinstance(key, str) and len(key) <= 60 else shorten(key)}"
        if not isinstance(key, str) or not key or any(not part for part in key.split(".")):
            raise ConfigError(f"{where}: expected a dotted config key, e.g. controller.outer.k_y")
        if key in BUILTIN_AXES or key.split(".")[0] == "extends":
            own = " (paths:)" if key == "path" else " (base:)" if key == "extends" else ""
            raise ConfigError(f"{where}: not a config key to sweep: {key} has its own campaign key{own}")
        return where

    # ----------------------------------------------------------------- keys with readers of their own

    def config_keys(self, value: Any, key: str) -> dict[str, Any]:
        """A mapping laid over a case's config. `extends:` names the file a config is read over,
        which is resolved before any of this is laid on: here it would do nothing, silently."""
        if not isinstance(value, Mapping):
            raise self.fail(key, f"expected a mapping of config keys, got {shorten(value)}")
        if "extends" in value:
            raise self.fail(f"{key}.extends", "a case's config is read from base: (a list of files makes "
                                              "them an axis); extends: here would be ignored")
        return dict(value)

    def file(self, value: str, key: str) -> FsPath:
        p = self.folder / value
        kind = file_kind(p)
        if kind == "missing":
            raise self.fail(key, f"no such file {shorten(value)} (looked for {os.path.normpath(p)})")
        if kind != "a file":
            raise self.fail(key, f"{shorten(value)} is {kind}, not a file")
        return p.resolve()

    def bases(self, value: tuple[str, ...] | str | None) -> tuple[FsPath, ...]:
        if value is None:
            return ()
        if isinstance(value, str):
            return (self.file(value, "base"),)
        if len(set(value)) != len(value):
            raise self.fail("base", "a config file is listed twice")
        return tuple(self.file(v, f"base[{i}]") for i, v in enumerate(value))

    def paths(self, value: tuple[str, ...] | dict[str, Any] | None) -> dict[str, str | dict[str, Any]]:
        out: dict[str, str | dict[str, Any]] = {}
        if isinstance(value, tuple):
            for i, item in enumerate(value):
                f = self.file(item, f"paths[{i}]")
                if f.stem in out:
                    raise self.fail(f"paths[{i}]", f"two paths named {f.stem!r}: give them names (a mapping)")
                out[f.stem] = str(f)
            return out
        for name, spec in (value or {}).items():
            if isinstance(spec, Mapping):
                spec = dict(spec)
                if isinstance(spec.get("file"), str):  # a CSV named by an inline spec: from this file's folder
                    spec["file"] = str(self.folder / spec["file"])
                out[str(name)] = spec
            elif isinstance(spec, str) and spec:
                out[str(name)] = str(self.file(spec, f"paths.{name}"))
            else:
                raise self.fail(f"paths.{name}", f"expected a file name or a path spec, got {shorten(spec)}")
        return out

    def seeds(self, value: tuple[int, ...] | int | None) -> tuple[int, ...] | None:
        if value is None or isinstance(value, tuple):
            if value is not None and len(set(value)) != len(value):
                raise self.fail("seeds", "a seed is listed twice")
            return value
        if not 1 <= value <= MAX_CASES:  # before the tuple is built: seeds: 10000000000 would exhaust the memory
            raise self.fail("seeds", f"a count of seeds is 1 to {MAX_CASES} (more cases: split the campaign), "
                                     f"got {shorten(value)}")
        return tuple(range(1, value + 1))

    def criteria(self, value: tuple[str, ...] | str | None) -> tuple[Criterion, ...]:
        items = (value,) if isinstance(value, str) else value or ()
        try:
            return tuple(parse_criterion(c, "pass" if isinstance(value, str) else f"pass[{i}]")
                         for i, c in enumerate(items))
        except ValueError as exc:
            raise CampaignError(f"{self.source}: {exc}") from None

    def summary(self, value: SummarySpec, criteria: tuple[Criterion, ...]) -> tuple[str, ...]:
        if value.metrics is not None:
            if not value.metrics:
                raise self.fail("summary.metrics", "empty: give at least one, or leave the key out")
            return tuple(dict.fromkeys(value.metrics))
        numbers = [c.metric for c in criteria if c.metric in PERCENTILE_METRICS]
        return tuple(dict.fromkeys(numbers)) or (DEFAULT_SUMMARY_METRIC,)

    def count(self, camp: Campaign) -> None:
        n = max(1, len(camp.bases)) * max(1, len(camp.variants)) * (camp.population.robots if camp.population else 1)
        n *= max(1, len(camp.paths)) * len(camp.seeds or (0,))
        for axis in camp.axes:
            n *= len(axis.values)
        if n > MAX_CASES:
            raise self.fail("axes", f"{n} cases, more than {MAX_CASES}: split the campaign")
