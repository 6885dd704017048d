"""The import rules of the layout (docs/design.md), checked on the source with ast.

- Computation (ddrt/core, ddrt/path) imports no driver, no service, no simulator and not the
  tick: it may import numpy, the standard library, ddrt.core, ddrt.path and ddrt.config.
- hal/ never imports sim_hal/: the simulator is reached only through the registry's names.
- hal/ never imports the service (the daemon's package), and viz/ never imports the service
  either: what both need from the operating system is the runtime layer, ddrt/runtime.
- ddrt/params and ddrt/runtime are leaves: they import nothing of ddrt but themselves (the
  runtime its Clock protocol from ddrt.core.types).
- No import cycle between packages: the package graph (every import, at any depth) is a DAG.
- Every exception class of ddrt/, hal/ and sim_hal/ descends from ddrt.errors.DdrtError.
- No module reaches into another object's private state (a write, a read, a private import),
  but for the known list that is being taken out; modules are sized by cohesion, not lines.
- No function writes the fields of an object it is handed (but a plain record it fills), and
  getattr/hasattr ask only what is really foreign (at most 15), but for the known lists.
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


def private_reaches(root: Path = REPO, folders: tuple[str, ...] = ("ddrt", "hal", "sim_hal")) -> set[str]:
    """Each "file: name._attr" where a module reaches into another object's private attribute
    (one its own module neither defines nor assigns on self), and each "file: import m._name"
    of a private name from another module. An object keeps its own state: what is shared is
    passed, returned or asked of a method."""
    out: set[str] = set()
    for folder in folders:
        for f in sorted((root / folder).rglob("*.py")):
            tree = ast.parse(f.read_text(encoding="utf-8"))
            own: set[str] = set()
            for node in ast.walk(tree):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                    own.add(node.name)
                elif (isinstance(node, ast.Attribute) and isinstance(node.ctx, ast.Store)
                      and isinstance(node.value, ast.Name) and node.value.id in ("self", "cls")):
                    own.add(node.attr)
                elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name):
                    own.add(node.target.id)
                elif isinstance(node, ast.Assign):
                    own.update(t.id for t in node.targets if isinstance(t, ast.Name))
            rel = f.relative_to(root)
            for node in ast.walk(tree):
                if isinstance(node, ast.ImportFrom) and node.module:
                    out.update(f"{rel}: import {node.module}.{a.name}" for a in node.names
                               if a.name.startswith("_") and not a.name.startswith("__"))
                elif (isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__")
                      and isinstance(node.value, ast.Name) and node.value.id not in ("self", "cls")
                      and node.attr not in own):
                    out.add(f"{rel}: {node.value.id}.{node.attr}")
    return out


# Reaches that are still there, each to be taken out by giving the owner a method or passing
# the value; the list only shrinks (an entry that is gone must be struck from it too).
KNOWN_PRIVATE_REACHES = frozenset({
})


def test_no_module_reaches_into_another_objects_private_state() -> None:
    found = private_reaches()
    assert sorted(found - KNOWN_PRIVATE_REACHES) == [], "a module reaches into another object's private state"
    assert sorted(KNOWN_PRIVATE_REACHES - found) == [], "gone now: strike these from KNOWN_PRIVATE_REACHES"


def test_the_reach_check_sees_a_private_write_and_a_private_import(tmp_path: Path) -> None:
    # The checker itself: a write to another object's private field, a read of one, and a
    # private import are found; the module's own privates (on self, or of a class it defines) are not.
    (tmp_path / "ddrt").mkdir()
    (tmp_path / "ddrt" / "m.py").write_text(
        "from ddrt.other import _helper\n\nclass A:\n    def __init__(self):\n        self._mine = 1\n\n"
        "    def clone(self, other):\n        other._mine = self._mine\n\n"
        "def poke(loop, est):\n    loop._state = 3\n    return est._fuse()\n")
    assert private_reaches(tmp_path, ("ddrt",)) == {
        "ddrt/m.py: import ddrt.other._helper", "ddrt/m.py: loop._state", "ddrt/m.py: est._fuse"}


def probes(root: Path = REPO, folders: tuple[str, ...] = ("ddrt", "hal", "sim_hal")) -> dict[str, int]:
    """file -> how many getattr/hasattr calls it makes: a capability probed, not declared."""
    out: dict[str, int] = {}
    for folder in folders:
        for f in sorted((root / folder).rglob("*.py")):
            n = sum(1 for node in ast.walk(ast.parse(f.read_text(encoding="utf-8")))
                    if isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
                    and node.func.id in ("getattr", "hasattr"))
            if n:
                out[f.relative_to(root).as_posix()] = n
    return out


# Where the object really is foreign, so a name is all there is to ask it by (at most 15).
FOREIGN_PROBES: dict[str, tuple[int, str]] = {
    "hal/registry.py": (1, "a backend's factory, named by a string in BACKENDS, in the module imported by name"),
    "hal/wiring.py": (1, "WiredHal.__getattr__ forwards the inner backend's own members (its clock, fault "
                         "injection): a proxy of whatever backend it wraps"),
    "ddrt/config/yamlio.py": (1, "PyYAML's C loader, there only when PyYAML was built with libyaml"),
    "ddrt/params/decl.py": (1, "field_items: the one walker that reads a declared dataclass's fields by name"),
}
MAX_FOREIGN_PROBES = 15

# Probes still being replaced by a declaration; the list only shrinks (lower a count that fell).
KNOWN_PROBES: dict[str, int] = {
    "hal/wire.py": 1,  # a message's dataclass fields for struct.pack, on the serial path
}


def test_capabilities_are_declared_not_probed() -> None:
    found = probes()
    allowed = {f: n for f, (n, _) in FOREIGN_PROBES.items()}
    for f, n in KNOWN_PROBES.items():
        allowed[f] = allowed.get(f, 0) + n
    more = {f: f"{n} > {allowed.get(f, 0)}" for f, n in found.items() if n > allowed.get(f, 0)}
    assert more == {}, "getattr/hasattr probes a capability: declare it (a Protocol, an attribute always set)"
    fewer = {f: f"{found.get(f, 0)} < {n}" for f, n in allowed.items() if found.get(f, 0) < n}
    assert fewer == {}, "fewer probes now: lower or strike these in KNOWN_PROBES"
    assert sum(n for n, _ in FOREIGN_PROBES.values()) <= MAX_FOREIGN_PROBES


def test_the_probe_count_sees_getattr_and_hasattr_at_any_depth(tmp_path: Path) -> None:
    (tmp_path / "hal").mkdir()
    (tmp_path / "hal" / "p.py").write_text(
        "def f(o):\n    if hasattr(o, 'x'):\n        return [getattr(o, k, None) for k in 'ab']\n"
        "    return o.getattr('y')\n")
    (tmp_path / "hal" / "q.py").write_text("x = 1\n")
    assert probes(tmp_path, ("hal",)) == {"hal/p.py": 2}


# Plain records a function is handed to fill in place, with no rule of their own to keep: a
# tick's setpoint, a HAL read being assembled, a path's pieces while they are built.
FILLED_RECORDS = frozenset({"Setpoint", "Sample", "Piece", "Geometry", "Conditioning"})
FOREIGN_MODULES = frozenset({"ctypes"})  # a library's objects (a loaded C library's prototypes)


def _annotation_names(ann: ast.expr | None) -> set[str]:
    """The names an annotation mentions (in a string annotation too); the module of `m.Type`."""
    if ann is None:
        return set()
    if isinstance(ann, ast.Constant) and isinstance(ann.value, str):
        try:
            ann = ast.parse(ann.value, mode="eval").body
        except SyntaxError:
            return set()
    return {n.id for n in ast.walk(ann) if isinstance(n, ast.Name)}


def param_writes(root: Path = REPO, folders: tuple[str, ...] = ("ddrt", "hal", "sim_hal")) -> set[str]:
    """Each "file: function(param).field" where a function assigns a field of an object it was
    handed (a parameter other than self and cls), unless the parameter's annotation names a
    class of the same module, a FILLED_RECORDS record or a FOREIGN_MODULES object. An object
    keeps its own state: what the owner should change is returned or asked of its method."""
    out: set[str] = set()
    for folder in folders:
        for f in sorted((root / folder).rglob("*.py")):
            tree = ast.parse(f.read_text(encoding="utf-8"))
            own = {n.name for n in ast.walk(tree) if isinstance(n, ast.ClassDef)}
            exempt = own | FILLED_RECORDS | FOREIGN_MODULES
            rel = f.relative_to(root).as_posix()
            for fn in ast.walk(tree):
                if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    continue
                a = fn.args
                params = {p.arg for p in [*a.posonlyargs, *a.args, *a.kwonlyargs, a.vararg, a.kwarg]
                          if p is not None and p.arg not in ("self", "cls")
                          and not _annotation_names(p.annotation) & exempt}
                for node in ast.walk(fn):
                    if not isinstance(node, (ast.Assign, ast.AugAssign, ast.AnnAssign)):
                        continue
                    targets = node.targets if isinstance(node, ast.Assign) else [node.target]
                    for t in (e for t in targets for e in (t.elts if isinstance(t, ast.Tuple) else [t])):
                        chain: list[str] = []
                        base = t
                        while isinstance(base, ast.Attribute):
                            chain.append(base.attr)
                            base = base.value
                        if chain and isinstance(base, ast.Name) and base.id in params:
                            out.add(f"{rel}: {fn.name}({base.id}).{'.'.join(reversed(chain))}")
    return out


# Writes still being taken out (the owner given a method, or the value returned); only shrinks.
KNOWN_PARAM_WRITES = frozenset({
})


def test_no_function_writes_the_fields_of_an_object_it_is_handed() -> None:
    found = param_writes()
    assert sorted(found - KNOWN_PARAM_WRITES) == [], "a function writes another object's fields"
    assert sorted(KNOWN_PARAM_WRITES - found) == [], "gone now: strike these from KNOWN_PARAM_WRITES"


def test_the_write_check_sees_a_field_written_through_a_parameter(tmp_path: Path) -> None:
    # The checker itself: writes through a parameter (a field, a nested one, a tuple target,
    # an augmented one) are found; self's, a local's, a record's and the module's own class's are not.
    (tmp_path / "ddrt").mkdir()
    (tmp_path / "ddrt" / "m.py").write_text(
        "class Own:\n    pass\n\n"
        "def apply(loop, d: 'Daemon', own: Own, sp: Setpoint, n: int) -> None:\n"
        "    loop.cfg = 1\n    loop.holds.bounds = 2\n    d.error, d.code = 'x', 2\n    d.ticks += 1\n"
        "    own.x = 1\n    sp.v_d = 0.0\n    here = object()\n    here.y = 3\n\n"
        "class A:\n    def f(self, other: 'A', est) -> None:\n        self.z = 1\n        other.z = 2\n"
        "        est.dyn = 3\n")
    assert param_writes(tmp_path, ("ddrt",)) == {
        "ddrt/m.py: apply(loop).cfg", "ddrt/m.py: apply(loop).holds.bounds", "ddrt/m.py: apply(d).error",
        "ddrt/m.py: apply(d).code", "ddrt/m.py: apply(d).ticks", "ddrt/m.py: f(est).dyn"}


STATE_OWNER = "ddrt/loop/modes.py"  # the loop's mode machine: the one place a loop state is assigned
_MEMBERS = frozenset({"LoopState", "IDLE", "FOLLOWING", "STOPPING", "STOPPED", "ESTOP", "FAULT", "HOLDING",
                      "DRIVING", "MOVING"})


def state_writes(root: Path = REPO, folders: tuple[str, ...] = ("ddrt", "hal", "sim_hal")) -> list[str]:
    """Each "file:line" outside the mode machine that assigns a `state` attribute a loop state
    (a LoopState member, an alias of one, LoopState(...)), writes `state` on an object other
    than self, or sets it with setattr: the loop's state changes only by the machine's table."""
    out: list[str] = []
    for folder in folders:
        for f in sorted((root / folder).rglob("*.py")):
            rel = f.relative_to(root).as_posix()
            if rel == STATE_OWNER:
                continue
            for node in ast.walk(ast.parse(f.read_text(encoding="utf-8"))):
                if isinstance(node, (ast.Assign, ast.AugAssign, ast.AnnAssign)):
                    targets = node.targets if isinstance(node, ast.Assign) else [node.target]
                    flat = [e for t in targets for e in (t.elts if isinstance(t, ast.Tuple) else [t])]
                    for t in flat:
                        if not (isinstance(t, ast.Attribute) and t.attr == "state"):
                            continue
                        on_self = isinstance(t.value, ast.Name) and t.value.id == "self"
                        loopish = node.value is not None and any(
                            isinstance(n, ast.Name) and n.id in _MEMBERS for n in ast.walk(node.value))
                        if not on_self or loopish:
                            out.append(f"{rel}:{node.lineno}")
                elif (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "setattr"
                      and len(node.args) >= 2 and isinstance(node.args[1], ast.Constant)
                      and node.args[1].value == "state"):
                    out.append(f"{rel}:{node.lineno}")
    return out


def test_only_the_mode_machine_assigns_the_loops_state() -> None:
    assert state_writes() == [], f"a loop state is assigned outside {STATE_OWNER}: fire an Event instead"


def test_the_state_write_check_sees_each_way_of_assigning_a_state(tmp_path: Path) -> None:
    (tmp_path / "ddrt" / "loop").mkdir(parents=True)
    (tmp_path / "ddrt" / "m.py").write_text(
        "from ddrt.loop.states import LoopState\nFOLLOWING = LoopState.FOLLOWING\n\n"
        "class A:\n    def go(self, loop, other):\n        self.state = 'ok'\n"
        "        self.state = LoopState.IDLE\n        loop.state = FOLLOWING\n"
        "        other.state = 3\n        setattr(loop, 'state', 0)\n        self.state = LoopState(2)\n")
    (tmp_path / "ddrt" / "loop" / "modes.py").write_text("class M:\n    def enter(self, t):\n        self.state = t.to\n")
    # line 6 (a state of self that is no loop state) and the machine's own write are not found
    assert sorted(state_writes(tmp_path, ("ddrt",))) == [f"ddrt/m.py:{n}" for n in (10, 11, 7, 8, 9)]


def project_exceptions(root: Path = REPO, folders: tuple[str, ...] = ("ddrt", "hal", "sim_hal"),
                       ) -> tuple[list[type[BaseException]], list[str]]:
    """Every exception class defined in the folders' modules (each imported), and the modules
    that could not be imported here (an optional dependency missing)."""
    found: list[type[BaseException]] = []
    unimported: list[str] = []
    for folder in folders:
        for f in sorted((root / folder).rglob("*.py")):
            parts = f.relative_to(root).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            if parts[-1] == "__main__":
                continue
            try:
                module = importlib.import_module(name)
            except ImportError:
                unimported.append(name)
                continue
            found.extend(obj for obj in vars(module).values()
                         if isinstance(obj, type) and issubclass(obj, BaseException) and obj.__module__ == name)
    return found, unimported


def test_every_error_of_the_project_descends_from_one_root() -> None:
    """A caller catches ddrt's errors by kind: each one is a DdrtError (the HAL's tree under
    it), beside the builtin it is a kind of."""
    from ddrt.errors import DdrtError

    found, unimported = project_exceptions()
    assert len(found) > 20 and not unimported, unimported
    outside = sorted(f"{e.__module__}.{e.__qualname__}" for e in found
                     if e is not DdrtError and not issubclass(e, DdrtError))
    assert outside == [], f"exceptions outside DdrtError: {outside}"


def test_the_root_check_sees_a_stray_exception(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # The checker itself: an exception defined at any depth of a package is found by the walk,
    # and one imported from elsewhere is not counted twice.
    pkg = tmp_path / "strayroot"
    (pkg / "inner").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "inner" / "__init__.py").write_text("")
    (pkg / "inner" / "mod.py").write_text("from ddrt.errors import DdrtError\n\n"
                                          "class Stray(ValueError):\n    pass\n\n"
                                          "class Kept(DdrtError, ValueError):\n    pass\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    found, unimported = project_exceptions(tmp_path, ("strayroot",))
    assert sorted(e.__name__ for e in found) == ["Kept", "Stray"] and unimported == []
    names = {e.__name__ for e in project_exceptions()[0]}
    assert {"ConfigError", "PathError", "HalError", "HalTimeoutError", "ProtocolError"} <= names
