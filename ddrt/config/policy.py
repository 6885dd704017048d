"""The reload policy, derived from the declarations beside each field (`APPLY` on a section,
`setting(..., reload=...)` on a field; ddrt/params/decl.py), never listed by hand.

`plan_reload(running, new)` compares two validated configs leaf by leaf and returns the
config to put in force (the new values of live and next-path fields, the running values of
restart fields) with the dotted keys of each kind of change, so what a reload reports is
exactly what it hands to the running parts.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any, Iterator

from ddrt.config.keys import ROOT_MODE, is_section, key_of, mode_of, section_mode
from ddrt.config.schema import APPLY_MODES, LIVE, NEXT_PATH, RESTART, ConfigError, field_items, validate_tree
from ddrt.config.sections import Config


@dataclass(frozen=True)
class ReloadPlan:
    """What a reload changes: the config to run with, and the changed keys by how they apply."""

    in_force: Config
    live: tuple[str, ...] = ()
    next_path: tuple[str, ...] = ()
    restart: tuple[str, ...] = ()

    @property
    def applied(self) -> tuple[str, ...]:
        """Every change now in force (live at once, or for the next path)."""
        return self.live + self.next_path

    def summary(self) -> str:
        if not (self.live or self.next_path or self.restart):
            return "applied: nothing changed"
        parts = [f"applied: {', '.join(self.live) or 'nothing'}"]
        if self.next_path:
            parts.append(f"from the next path: {', '.join(self.next_path)}")
        if self.restart:
            parts.append(f"need a restart: {', '.join(self.restart)}")
        return "; ".join(parts)

    def report(self) -> dict[str, Any]:
        return {"applied": list(self.live), "next_path": list(self.next_path), "restart": list(self.restart)}


@dataclass
class _Walk:
    changes: dict[str, list[str]] = field(default_factory=lambda: {m: [] for m in APPLY_MODES})


def value_at(cfg: Any, key: str) -> Any:
    """The value of the setting at dotted `key` (as leaf_modes and the reload report name it)."""
    node, parts = cfg, key.split(".")
    while parts:
        by_key = {key_of("", f): value for f, value in field_items(node)}
        for n in range(len(parts), 0, -1):
            head = ".".join(parts[:n])
            if head in by_key:
                node, parts = by_key[head], parts[n:]
                break
        else:
            raise KeyError(key)
    return node


def leaf_modes(cfg: Config) -> Iterator[tuple[str, str]]:
    """(dotted key, mode) of every leaf setting in `cfg`: the policy as data (docs, tests)."""
    yield from _leaves(cfg, "", ROOT_MODE)


def _leaves(obj: Any, prefix: str, inherited: str) -> Iterator[tuple[str, str]]:
    here = section_mode(type(obj), inherited)
    for f, value in field_items(obj):
        if not f.compare:
            continue
        key = key_of(prefix, f)
        mode = mode_of(f, here)
        if is_section(value):
            yield from _leaves(value, key, mode)
        else:
            yield key, mode


def _merge(old: Any, new: Any, prefix: str, inherited: str, walk: _Walk) -> Any:
    """`new` with every restart-mode leaf that changed put back to `old`'s value."""
    here = section_mode(type(new), inherited)
    kept: dict[str, Any] = {}
    running = dict(field_items(old))
    for f, b in field_items(new):
        if not f.compare:
            continue
        key = key_of(prefix, f)
        mode = mode_of(f, here)
        a = running[f]
        if a == b:
            continue
        if is_section(a) and is_section(b) and type(a) is type(b):
            merged = _merge(a, b, key, mode, walk)
            if merged is not b:
                kept[f.name] = merged
            continue
        walk.changes[mode].append(key)
        if mode == RESTART:
            kept[f.name] = a
    return dataclasses.replace(new, **kept) if kept else new


def plan_reload(running: Config, new: Config) -> ReloadPlan:
    """Which changes of `new` over `running` apply now, from the next path, or at restart.

    The mix of new and kept values is checked again with every rule (a section's own and
    those across sections), so a reload cannot put in force a combination that no file
    could load: raises ConfigError naming the rule, and nothing is applied.
    """
    walk = _Walk()
    merged = _merge(running, new, "", ROOT_MODE, walk)
    if merged is not new:
        merged = dataclasses.replace(merged, source=new.source, base_dir=new.base_dir, raw=new.raw)
        try:
            validate_tree(merged)
        except ConfigError as exc:
            waiting = ", ".join(walk.changes[RESTART])
            raise ConfigError(f"{new.source}: {exc}, with the running values of {waiting} that only a "
                              "restart changes; restart to apply the whole file") from None
    c = walk.changes
    return ReloadPlan(merged, tuple(c[LIVE]), tuple(c[NEXT_PATH]), tuple(c[RESTART]))
