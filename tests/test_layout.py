"""The import rules of the layout (docs/design.md), checked on the source with ast.

- Computation (ddrt/core, ddrt/path) imports no driver, no service, no simulator and not the
  tick: it may import numpy, the standard library, ddrt.core, ddrt.path and ddrt.config.
- hal/ never imports sim_hal/: the simulator is reached only through the registry's names.
"""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

from hal.registry import BACKENDS

REPO = Path(__file__).resolve().parents[1]
FORBIDDEN_IN_COMPUTATION = ("ddrt.service", "ddrt.simrun", "ddrt.loop", "ddrt.calibrate", "ddrt.cli",
                            "hal", "sim_hal", "bench")


def imported_modules(path: Path, root: Path = REPO) -> list[tuple[int, str]]:
    """(line, module) of every import in a file, at any depth (function-level imports too)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    found: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.extend((node.lineno, alias.name) for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative: resolve against the file's package
                package = path.relative_to(root).parent.parts
                base = ".".join(package[: len(package) - node.level + 1])
                if node.module:
                    found.append((node.lineno, f"{base}.{node.module}" if base else node.module))
                else:  # `from .. import name`: the names are modules
                    found.extend((node.lineno, f"{base}.{a.name}" if base else a.name) for a in node.names)
            else:
                found.append((node.lineno, node.module or ""))
    return found


def violations(folder: str, forbidden: tuple[str, ...]) -> list[str]:
    files = sorted((REPO / folder).rglob("*.py"))
    assert files, f"no modules under {folder}"
    out = []
    for f in files:
        for line, mod in imported_modules(f):
            if any(mod == bad or mod.startswith(bad + ".") for bad in forbidden):
                out.append(f"{f.relative_to(REPO)}:{line} imports {mod}")
    return out


def test_hal_never_imports_sim_hal() -> None:
    assert violations("hal", ("sim_hal",)) == []


@pytest.mark.parametrize("folder", ["ddrt/core", "ddrt/path"])
def test_computation_imports_no_driver_service_simulator_or_loop(folder: str) -> None:
    assert violations(folder, FORBIDDEN_IN_COMPUTATION) == []


def test_the_scan_sees_imports_at_any_depth_and_relative_ones(tmp_path: Path) -> None:
    # The checker itself: if it missed these, the rules above would prove nothing.
    (tmp_path / "hal").mkdir()
    probe = tmp_path / "hal" / "probe.py"
    probe.write_text("import os\n\ndef f():\n    from sim_hal.plant import SimRobot\n"
                     "    from .base import Hal\n    from .. import sim_hal\n")
    assert [m for _, m in imported_modules(probe, tmp_path)] == ["os", "sim_hal.plant", "hal.base", "sim_hal"]


@pytest.mark.parametrize("name", sorted(BACKENDS))
def test_every_registered_backend_resolves(name: str) -> None:
    module_name, func_name = BACKENDS[name].split(":")
    assert callable(getattr(importlib.import_module(module_name), func_name))


def test_the_package_map_names_every_module() -> None:
    """docs/design.md's map is how a reader finds a module: every module of a package is
    named in that package's row (a new module without a line there fails here)."""
    doc = (REPO / "docs" / "design.md").read_text(encoding="utf-8")
    rows = {line.split("|")[1].strip().strip("`"): line for line in doc.splitlines()
            if line.startswith("| `") and line.count("|") >= 4}
    missing = []
    for pkg in ("ddrt/core/", "ddrt/path/", "ddrt/config/", "ddrt/service/", "ddrt/simrun/", "ddrt/viz/",
                "hal/", "sim_hal/"):
        row = rows.get(pkg)
        assert row is not None, f"docs/design.md has no row for {pkg}"
        for f in sorted((REPO / pkg).glob("*.py")):
            if f.name != "__init__.py" and f"`{f.name}`" not in row:
                missing.append(f"{pkg}{f.name}")
    assert not missing, f"not in docs/design.md's package map: {missing}"
