"""The gains as Foxglove parameters: named by their config keys, read off the keys' declarations.

A parameter is every number under `controller.` whose declaration (or its section's) applies
live (ddrt.config.keys.declared_keys: the same walk the reference and the reload policy read),
so a gain added to the config is a parameter without a list to keep. Foxglove's parameter
carries a name, a type and a value only; a gain's unit, bounds and meaning are its
declaration's (`gain_declarations`, and the key's row in docs/reference/config.md). Setting
parameters is a reload of those keys: `plan_for` builds the config with them and plans it
exactly as a reload would (ddrt.config.policy.plan_reload), so an invalid value (outside its
declared bounds too), a wrong type or an unknown name refuses the whole set.
"""

from __future__ import annotations

from typing import Any, Mapping

from ddrt.config import Config, ConfigError, with_overrides
from ddrt.config.keys import Key, declared_keys
from ddrt.config.policy import ReloadPlan, plan_reload, value_at
from ddrt.config.schema import LIVE

PREFIX = "controller."


def gain_declarations() -> tuple[Key, ...]:
    """Every live number under `controller.`, with its declaration (unit, bounds, description)."""
    return tuple(k for k in declared_keys(Config)
                 if k.mode == LIVE and k.key.startswith(PREFIX) and k.hint in (float, int))


def gain_keys() -> tuple[str, ...]:
    """The parameters' names: the gains' dotted config keys."""
    return tuple(k.key for k in gain_declarations())


def values(cfg: Config, keys: tuple[str, ...]) -> dict[str, float]:
    return {k: float(value_at(cfg, k)) for k in keys}


def overrides_for(changes: Mapping[str, Any], keys: tuple[str, ...]) -> dict[str, Any]:
    """{dotted key: value} as the nested mapping a config file would have; unknown names refused."""
    nested: dict[str, Any] = {}
    for name, value in changes.items():
        if name not in keys:
            raise ConfigError(f"{name}: not a gain parameter (known: {', '.join(keys)})")
        node = nested
        parts = name.split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = value
    return nested


def plan_for(cfg: Config, changes: Mapping[str, Any], keys: tuple[str, ...]) -> ReloadPlan:
    """The reload plan that puts `changes` in force over `cfg`, or ConfigError naming the key."""
    if not changes:
        raise ConfigError("no parameters given")
    return plan_reload(cfg, with_overrides(cfg, overrides_for(changes, keys)))
