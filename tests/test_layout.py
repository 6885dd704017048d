"""The import rules of the layout (docs/design.md), checked on the source with ast.

- Computation (ddrt/core, ddrt/path) imports no driver, no service, no simulator and not the
  tick: it may import numpy, the standard library, ddrt.core, ddrt.path and ddrt.config.
- hal/ never imports sim_hal/: the simulator is reached only through the registry's names.
- hal/ never imports the service (the daemon's package), and viz/ never imports the service
  either: what both need from the operating system is the runtime layer, ddrt/runtime.
- ddrt/params and ddrt/runtime are leaves: they import nothing of ddrt but themselves (the
  runtime its Clock protocol from ddrt.core.types).
- No import cycle between packages: the package graph (every import, at any depth) is a DAG.
- The borders of the checkout: tests/ checks the product, bench/ measures it, and what both run
  (inputs and their targets) is lab/. No test module imports bench except bench's own tests,
  tests/test_bench_*.py (a benchmark's functions are what they test; other claims of a
  benchmark are rerun there too); bench/ and lab/ never import tests; lab/ never imports bench;
  the shipped packages (ddrt, hal, sim_hal) import none of tests, bench and lab.
"""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

import pytest

from hal.registry import BACKENDS
from tests.support.repo import REPO

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


def violations(folder: str, forbidden: tuple[str, ...], root: Path = REPO,
               exempt: str | None = None) -> list[str]:
    """"file:line imports module" for every import of a forbidden package under `folder`, but in
    files whose name matches the glob `exempt`."""
    files = sorted(f for f in (root / folder).rglob("*.py") if not (exempt and f.match(exempt)))
    assert files, f"no modules under {folder}"
    out = []
    for f in files:
        for line, mod in imported_modules(f, root):
            if any(mod == bad or mod.startswith(bad + ".") for bad in forbidden):
                out.append(f"{f.relative_to(root)}:{line} imports {mod}")
    return out


BENCH_OWN_TESTS = "test_bench_*.py"  # bench's own tests, the one place under tests/ that imports bench


def border_violations(root: Path = REPO) -> list[str]:
    """Every import across the checkout's borders (the module docstring's last rule)."""
    return (violations("tests", ("bench",), root, exempt=BENCH_OWN_TESTS)
            + violations("bench", ("tests",), root)
            + violations("lab", ("tests", "bench"), root)
            + [v for folder in ("ddrt", "hal", "sim_hal") for v in violations(folder, ("tests", "bench", "lab"), root)])


def test_hal_never_imports_sim_hal() -> None:
    assert violations("hal", ("sim_hal",)) == []


def test_hal_never_imports_the_service_viewer_simulator_or_loop() -> None:
    assert violations("hal", ("ddrt.service", "ddrt.viz", "ddrt.simrun", "ddrt.loop", "ddrt.cli")) == []


def test_viz_never_imports_the_service() -> None:
    assert violations("ddrt/viz", ("ddrt.service",)) == []


def test_params_and_runtime_are_leaves() -> None:
    ddrt_packages = sorted({package_of(".".join(f.relative_to(REPO).with_suffix("").parts))
                            for f in (REPO / "ddrt").rglob("*.py")} - {"ddrt"})
    others = tuple(p for p in ddrt_packages if p != "ddrt.params") + ("hal", "sim_hal", "bench")
    assert violations("ddrt/params", others) == []
    allowed_in_runtime = ("ddrt.runtime", "ddrt.core.types")
    out = [v for v in violations("ddrt/runtime", others) if not v.endswith(allowed_in_runtime)]
    assert out == []


def package_of(module: str) -> str | None:
    """The package a module belongs to, for the cycle rule: ddrt's sub-packages (and its
    top-level modules: ddrt.loop, ddrt.cli, ...) one each, hal, sim_hal, bench; None outside."""
    parts = module.split(".")
    if parts[0] == "ddrt":
        return ".".join(parts[:2]) if len(parts) > 1 else "ddrt"
    return parts[0] if parts[0] in ("hal", "sim_hal", "bench") else None


def package_graph(root: Path = REPO, folders: tuple[str, ...] = ("ddrt", "hal", "sim_hal")) -> dict[str, dict[str, str]]:
    """package -> {imported package: first "file:line imports module" that makes the edge}."""
    graph: dict[str, dict[str, str]] = {}
    for folder in folders:
        for f in sorted((root / folder).rglob("*.py")):
            rel = f.relative_to(root).with_suffix("").parts
            src = package_of(".".join(rel[:-1] if rel[-1] == "__init__" else rel))
            if src is None:
                continue
            edges = graph.setdefault(src, {})
            for line, mod in imported_modules(f, root):
                dst = package_of(mod)
                if dst is not None and dst not in (src, "ddrt"):
                    edges.setdefault(dst, f"{f.relative_to(root)}:{line} imports {mod}")
    return graph


def cycles(graph: dict[str, dict[str, str]]) -> list[list[str]]:
    """Strongly connected components with more than one package (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, {}):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_import_cycle_between_packages() -> None:
    graph = package_graph()
    found = cycles(graph)
    detail = [f"{a} -> {b}: {graph[a][b]}" for c in found for a in c for b in c if b in graph.get(a, {})]
    assert found == [], f"import cycles between packages: {found}\n" + "\n".join(detail)


def test_the_cycle_check_finds_a_cycle_through_three_packages(tmp_path: Path) -> None:
    # The checker itself: a -> b -> c -> a through function-level imports is one cycle.
    for pkg, target in (("core", "ddrt.path.x"), ("path", "ddrt.loop"), ("", None)):
        (tmp_path / "ddrt" / pkg).mkdir(parents=True, exist_ok=True)
        if target:
            (tmp_path / "ddrt" / pkg / "x.py").write_text(f"def f():\n    import {target}\n")
    (tmp_path / "ddrt" / "loop.py").write_text("from ddrt.core import x\n")
    graph = package_graph(tmp_path, ("ddrt",))
    assert cycles(graph) == [["ddrt.core", "ddrt.loop", "ddrt.path"]]
    (tmp_path / "ddrt" / "loop.py").write_text("import math\n")
    assert cycles(package_graph(tmp_path, ("ddrt",))) == []


def test_tests_bench_and_lab_keep_their_borders() -> None:
    assert border_violations() == []


def test_the_border_check_finds_a_crossing_in_each_direction(tmp_path: Path) -> None:
    # The checker itself: one clean tree, then each forbidden import added in turn is found.
    files = {"tests/test_x.py": "import math\n", "tests/test_bench_x.py": "from bench import run\n",
             "bench/b.py": "from lab import path_inputs\n", "lab/l.py": "import numpy\n",
             "ddrt/d.py": "import os\n", "hal/h.py": "import os\n", "sim_hal/s.py": "import os\n"}
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    assert border_violations(tmp_path) == []
    crossings = {"tests/test_x.py": "def f():\n    from bench.soak import slope\n",
                 "bench/b.py": "from tests.support.daemon import ready_daemon\n",
                 "lab/l.py": "import bench.common\n", "ddrt/d.py": "from lab import repo\n",
                 "sim_hal/s.py": "import tests\n"}
    for name, text in crossings.items():
        clean = (tmp_path / name).read_text()
        (tmp_path / name).write_text(text)
        found = border_violations(tmp_path)
        assert len(found) == 1 and found[0].startswith(name + ":"), (name, found)
        (tmp_path / name).write_text(clean)


def test_only_the_runtime_packages_ship() -> None:
    """pyproject.toml installs ddrt, hal and sim_hal; tests, bench and lab are used from a checkout."""
    import tomllib

    spec = tomllib.loads((REPO / "pyproject.toml").read_text(encoding="utf-8"))
    include = spec["tool"]["setuptools"]["packages"]["find"]["include"]
    assert {name.split(".")[0] for name in include} == {"ddrt", "hal", "sim_hal"}


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
    packages = sorted(f"{p.parent.relative_to(REPO)}/" for folder in ("ddrt", "hal", "sim_hal")
                      for p in (REPO / folder).rglob("__init__.py") if p.parent != REPO / "ddrt")
    for pkg in packages:
        row = rows.get(pkg)
        assert row is not None, f"docs/design.md has no row for {pkg}"
        for f in sorted((REPO / pkg).glob("*.py")):
            if f.name != "__init__.py" and f"`{f.name}`" not in row:
                missing.append(f"{pkg}{f.name}")
    assert not missing, f"not in docs/design.md's package map: {missing}"


MAX_MODULE_LINES = 600  # a module longer than this holds more than one job (issue 19)
MAX_CLASS_LINES = {("ddrt/loop/tick.py", "ControlLoop"): 400, ("ddrt/service/daemon.py", "Daemon"): 400}


def test_no_module_outgrows_one_job() -> None:
    long = [f"{f.relative_to(REPO)}: {n} lines" for folder in ("ddrt", "hal", "sim_hal")
            for f in sorted((REPO / folder).rglob("*.py"))
            if (n := len(f.read_text(encoding="utf-8").splitlines())) > MAX_MODULE_LINES]
    assert long == [], f"over {MAX_MODULE_LINES} lines: split by job: {long}"


@pytest.mark.parametrize("where", sorted(MAX_CLASS_LINES))
def test_the_tick_and_the_daemon_stay_small(where: tuple[str, str]) -> None:
    path, name = where
    tree = ast.parse((REPO / path).read_text(encoding="utf-8"))
    cls = next(n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == name)
    assert cls.end_lineno - cls.lineno + 1 <= MAX_CLASS_LINES[where]
