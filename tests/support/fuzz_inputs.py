"""Seeded mutations of every input file in configs/ (YAML configs, path YAMLs, the CSV), and
an in-process harness that feeds them to `ddrt sim`. Reusable by any fuzz test:

    from tests.support.fuzz_inputs import Mutator, copy_configs, run_case

    root = copy_configs(tmp_path)                 # a private copy of configs/
    for case in Mutator(seed=1, kinds=("config",)).cases(1000):
        target = case.install(root)               # the mutated file, next to its original
        ...                                       # e.g. write case.data over a daemon's config

Case i of a seed is the same on every run and on every machine (`Mutator(seed).case(i)`
rebuilds it alone); `case.ops` says what was done to it. Run many more locally with

    python -m tests.support.fuzz_inputs --cases 20000 [--seed 1] [--kinds config,path,csv]

which prints every case whose outcome is not a clean one (exit 0, 1 or 2, no traceback, within
the time limit) with the command that reproduces it. The limit is on the case's CPU time, so
a machine busy with other work does not fail it; a hard wall-clock alarm (30 s) stops a hang.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import random
import re
import shutil
import sys
import time
import traceback
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator, Sequence

from tests.support.repo import REPO

CONFIGS = REPO / "configs"

# Numbers as they are written in a file: ordinary, huge, tiny, negative, not finite, beyond
# the float and C ranges, in every notation YAML and people use.
NUMBERS = (
    "0", "-0", "0.0", "1", "-1", "2", "0.5", "-0.5", "3", "10", "100", "1000", "1e3", "1e6", "1e9", "1e12",
    "1e15", "1e30", "1e100", "1e300", "1e308", "1.0e308", "1.7976931348623157e308", "1e309", "-1e308",
    "1e-3", "1e-6", "1e-9", "1e-12", "1e-100", "1e-300", "5e-324", "-1e-300", "2.5E+4", ".5", "1_000",
    ".nan", ".NaN", ".inf", "-.inf", ".Inf", "nan", "inf", "0x68", "0x7fffffff", "0o17", "0b101",
    "2147483648", "9223372036854775807", "9223372036854775808", "-9223372036854775809", "1:30",
    "9" * 400, "-" + "9" * 400, "1" + "0" * 40, "0.1" + "1" * 400,
)
SCALARS = ("~", "null", "''", "'text'", "true", "false", "yes", "[]", "{}", "[1, 2]", "[1, 2, 3]",
           "[0, 0, 0, 0]", "{a: 1}", "{x: [1, {y: 2}]}", "sim", "real", "cw", "circle", "2024-01-01",
           "!!binary aGVsbG8=", "&a [1, 2]", "'\\u00e9t\\u00e9'", "\"\\x00\"", "-", "? x", "*undefined")
LATIN1 = ("\xe9", "\xe0\xe7", "\xff\xfe", "\xa0", "\xb5m", "caf\xe9")
_KEY_LINE = re.compile(rb"^(\s*)(-\s+)?([A-Za-z_][\w]*)\s*:(\s*)(.*)$")
_NUMBER = re.compile(rb"(?<![\w.])-?(?:\d+\.?\d*(?:[eE][-+]?\d+)?|\.\d+)(?![\w.])")


@dataclass
class Case:
    """One mutated file: which file it came from, what was done, the bytes to write."""

    index: int
    origin: Path  # relative to configs/
    kind: str  # "config", "path" or "csv"
    data: bytes
    ops: list[str] = field(default_factory=list)

    @property
    def name(self) -> str:
        return f"case {self.index} ({self.origin}: {'; '.join(self.ops)})"

    def install(self, root: Path) -> Path:
        """Write the mutated file next to its original in `root` (a copy_configs tree), so its
        relative extends: and path: names resolve as the original's do."""
        target = root / self.origin.parent / f"_fuzz{self.origin.suffix}"
        target.write_bytes(self.data)
        return target

    def argv(self, root: Path, out: Path, duration: float = 0.2) -> list[str]:
        """`ddrt sim` arguments that load this file (a config, or a path with configs/sim.yaml)."""
        target = root / self.origin.parent / f"_fuzz{self.origin.suffix}"
        head = [str(target)] if self.kind == "config" else [str(root / "sim.yaml"), "--path", str(target)]
        return ["sim", *head, "--duration", str(duration), "--quiet", "--out", str(out)]


def seed_files(kinds: Sequence[str] = ("config", "path", "csv")) -> dict[str, list[Path]]:
    """The files under configs/ by kind, relative to configs/ (sorted: the same on every machine)."""
    out: dict[str, list[Path]] = {k: [] for k in kinds}
    for p in sorted(CONFIGS.rglob("*")):
        if not p.is_file() or p.name.startswith("_fuzz"):
            continue
        kind = "csv" if p.suffix == ".csv" else ("path" if p.parent.name == "paths" else "config")
        if p.suffix in (".yaml", ".yml", ".csv") and kind in out:
            out[kind].append(p.relative_to(CONFIGS))
    return {k: v for k, v in out.items() if v}


def copy_configs(dest: Path) -> Path:
    """A copy of configs/ under `dest`, for installing mutated files into."""
    root = dest / "configs"
    shutil.copytree(CONFIGS, root, ignore=shutil.ignore_patterns("_fuzz*"), dirs_exist_ok=True)
    return root


class Mutator:
    """Seeded mutations of the files of `kinds`; `weights` choose between the kinds."""

    def __init__(self, seed: int = 1, kinds: Sequence[str] = ("config", "path", "csv"),
                 weights: Sequence[float] | None = None, max_ops: int = 3) -> None:
        self.seed = seed
        self.files = seed_files(kinds)
        self.kinds = list(self.files)
        default = {"config": 0.45, "path": 0.4, "csv": 0.15}
        self.weights = list(weights) if weights is not None else [default.get(k, 1.0) for k in self.kinds]
        self.max_ops = max_ops
        self._text = {p: (CONFIGS / p).read_bytes() for files in self.files.values() for p in files}

    def cases(self, n: int, start: int = 0) -> Iterator[Case]:
        for i in range(start, start + n):
            yield self.case(i)

    def case(self, i: int) -> Case:
        rng = random.Random(self.seed * 1_000_003 + i)
        kind = rng.choices(self.kinds, self.weights)[0]
        origin = rng.choice(self.files[kind])
        data, ops = mutate(rng, self._text[origin], csv=kind == "csv", max_ops=self.max_ops)
        return Case(i, origin, kind, data, ops)


def mutate(rng: random.Random, data: bytes, csv: bool = False, max_ops: int = 3) -> tuple[bytes, list[str]]:
    """One to `max_ops` seeded mutations of a YAML (or CSV) file; returns it and what was done."""
    ops: list[str] = []
    table = _CSV_OPS if csv else _YAML_OPS
    for _ in range(min(max_ops, 1 + int(rng.expovariate(1.5)))):
        name, op, _w = rng.choices(table, [w for _, _, w in table])[0]
        data, what = op(rng, data)
        ops.append(f"{name}: {what}" if what else name)
    return data, ops


# --------------------------------------------------------------------------- operators
# Each takes (rng, data) and returns (new data, a short description).

Op = Callable[[random.Random, bytes], "tuple[bytes, str]"]


def _lines(data: bytes) -> list[bytes]:
    return data.split(b"\n")


def _key_lines(lines: list[bytes]) -> list[int]:
    return [i for i, line in enumerate(lines) if _KEY_LINE.match(line)]


def _flip(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    if not data:
        return data, "empty"
    b = bytearray(data)
    i = rng.randrange(len(b))
    b[i] ^= 1 << rng.randrange(8)
    return bytes(b), f"byte {i} flipped"


def _latin1(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    i = rng.randrange(len(data) + 1)
    s = rng.choice(LATIN1).encode("latin-1")
    return data[:i] + s + data[i:], f"latin-1 {s!r} at {i}"


def _truncate(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    i = rng.randrange(len(data) + 1)
    return data[:i], f"cut at {i}"


def _duplicate_key(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    lines = _lines(data)
    keys = _key_lines(lines)
    if not keys:
        return data, "no key"
    i = rng.choice(keys)
    j = i + 1 + rng.randrange(3)
    lines.insert(min(j, len(lines)), lines[i])
    return b"\n".join(lines), f"line {i + 1} repeated"


def _delete_key(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    lines = _lines(data)
    keys = _key_lines(lines)
    if not keys:
        return data, "no key"
    i = rng.choice(keys)
    del lines[i]
    return b"\n".join(lines), f"line {i + 1} deleted"


def _set_value(rng: random.Random, data: bytes, value: bytes, what: str) -> tuple[bytes, str]:
    lines = _lines(data)
    keys = _key_lines(lines)
    if not keys:
        return data, "no key"
    i = rng.choice(keys)
    m = _KEY_LINE.match(lines[i])
    assert m is not None
    indent, dash, key, _, _ = m.groups()
    lines[i] = indent + (dash or b"") + key + b": " + value
    return b"\n".join(lines), f"{key.decode()} (line {i + 1}) = {what}"


def _type_swap(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    value = rng.choice(SCALARS + NUMBERS[:12])
    return _set_value(rng, data, value.encode(), value)


def _number(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    spans = [m.span() for m in _NUMBER.finditer(data)]
    if not spans:
        return _type_swap(rng, data)
    a, b = rng.choice(spans)
    value = rng.choice(NUMBERS)
    if rng.random() < 0.3:  # a nearby value: scaled or negated
        try:
            old = float(data[a:b])
            value = repr(rng.choice((-1.0, 0.0, 0.1, 0.5, 2.0, 10.0, 1000.0, 1e6)) * old)
        except ValueError:
            pass
    return data[:a] + value.encode() + data[b:], f"{data[a:b].decode(errors='replace')} -> {value[:30]}"


def _nest(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    depth = rng.choice((3, 20, 63, 64, 65, 200, 999, 1200))
    if rng.random() < 0.5:
        value = b"[" * depth + b"1" + b"]" * depth
    else:
        value = b"{a: " * depth + b"1" + b"}" * depth
    return _set_value(rng, data, value, f"nested {depth} deep")


def _long(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    n = rng.choice((1000, 70_000, 300_000))
    value = rng.choice((b"x", b"1", b"ab ", b"[1, ")) * n
    return _set_value(rng, data, value, f"{n} x {value[:4]!r}")


def _many_values(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    n = rng.choice((100, 20_000, 200_000))
    if rng.random() < 0.5:
        value = b"[" + b", ".join(b"[%d, %d]" % (i % 97, i % 89) for i in range(n)) + b"]"
    else:
        value = b"{" + b", ".join(b"k%d: %d" % (i, i) for i in range(n)) + b"}"
    return _set_value(rng, data, value, f"{n} values")


def _add_key(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    key = rng.choice((b"laps", b"speed", b"accel", b"omega_max", b"points", b"file", b"shape", b"start",
                      b"extends", b"path", b"paths", b"hal", b"robot", b"bogus", b"1", b"null", b"<<"))
    value = rng.choice(NUMBERS + SCALARS).encode()
    line = key + b": " + value
    return data.rstrip(b"\n") + b"\n" + line + b"\n", f"added {line[:40]!r}"


def _alias_bomb(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    levels = rng.choice((3, 6, 9))
    lines = [b"a0: &a0 [1, 1, 1, 1, 1, 1, 1, 1, 1, 1]"]
    for k in range(1, levels):
        lines.append(b"a%d: &a%d [" % (k, k) + b", ".join([b"*a%d" % (k - 1)] * 10) + b"]")
    return data.rstrip(b"\n") + b"\n" + b"\n".join(lines) + b"\n", f"alias bomb of {levels} levels"


# (name, operator, weight): values that stay loadable (numbers, type swaps) most often, so
# most cases get past the reader into the walker, the path builder and the loop.
_YAML_OPS: list[tuple[str, Op, float]] = [
    ("number", _number, 10), ("type swap", _type_swap, 4), ("add key", _add_key, 2),
    ("delete key", _delete_key, 2), ("duplicate key", _duplicate_key, 1), ("flip", _flip, 1),
    ("latin-1", _latin1, 0.5), ("truncate", _truncate, 1), ("nest", _nest, 0.7), ("long", _long, 0.5),
    ("many values", _many_values, 0.5), ("alias bomb", _alias_bomb, 0.3),
]


def _csv_cell(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    lines = _lines(data)
    rows = [i for i, line in enumerate(lines) if line and not line.startswith(b"#") and b"," in line]
    if not rows:
        return data, "no row"
    i = rng.choice(rows)
    cells = lines[i].split(b",")
    j = rng.randrange(len(cells))
    value = rng.choice(NUMBERS + ("", "x", " ", "1,2", "\"", "#"))
    cells[j] = value.encode()
    lines[i] = b",".join(cells)
    return b"\n".join(lines), f"line {i + 1} cell {j} = {value[:30]}"


def _csv_rows(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    lines = [line for line in _lines(data) if line]
    n = rng.choice((2, 50, 5000, 12_000, 100_000))
    mode = rng.choice(("repeat", "spread", "same"))
    if mode == "repeat":
        body = lines[1:] * (n // max(1, len(lines) - 1) + 1)
    elif mode == "spread":
        body = [b"%g,%g" % (0.05 * k, 0.01 * (k % 7)) for k in range(n)]
    else:
        body = [b"1,1"] * n
    return b"\n".join([lines[0]] + body[:n]) + b"\n", f"{n} rows ({mode})"


def _csv_header(rng: random.Random, data: bytes) -> tuple[bytes, str]:
    header = rng.choice((b"x,y", b"x,y,v", b"y,x", b"x", b"X,Y,V", b"x,y,v,w", b"", b"# x,y"))
    lines = _lines(data)
    lines[0] = header
    return b"\n".join(lines), f"header {header!r}"


_CSV_OPS: list[tuple[str, Op, float]] = [
    ("number", _number, 6), ("cell", _csv_cell, 4), ("rows", _csv_rows, 2), ("header", _csv_header, 0.5),
    ("delete line", _delete_key, 1), ("flip", _flip, 1), ("latin-1", _latin1, 0.5), ("truncate", _truncate, 1),
]


# --------------------------------------------------------------------------- the harness


class CaseTimeout(BaseException):
    """A case ran past the harness's hard limit (raised by SIGALRM inside it)."""


@dataclass
class Outcome:
    case: Case
    code: object
    seconds: float  # CPU time of this process: the case's own work, whatever else the machine runs
    stderr: str
    error: str = ""  # the traceback of an exception that escaped main()
    wall_s: float = 0.0

    def clean(self, time_limit_s: float) -> bool:
        return (not self.error and self.code in (0, 1, 2) and "Traceback" not in self.stderr
                and self.seconds <= time_limit_s)


def run_case(case: Case, root: Path, out: Path, duration: float = 0.2, hard_limit_s: float = 30.0) -> Outcome:
    """Install `case` under `root` and run `ddrt sim` on it in this process; a case still
    running after `hard_limit_s` is stopped (SIGALRM, main thread only) and reported."""
    import signal

    from ddrt.cli import main

    case.install(root)
    err = io.StringIO()
    error = ""
    code: object = None

    def expire(_signum: int, _frame: object) -> None:
        raise CaseTimeout(f"still running after {hard_limit_s} s")

    previous = signal.signal(signal.SIGALRM, expire)
    t0, cpu0 = time.perf_counter(), time.process_time()
    try:
        signal.setitimer(signal.ITIMER_REAL, hard_limit_s)
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            try:
                code = main(case.argv(root, out, duration))
            except SystemExit as exc:  # argparse (never expected: the arguments are ours)
                code = exc.code
            except BaseException:  # noqa: BLE001 - exactly what the fuzz looks for
                error = traceback.format_exc()
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0.0)
        signal.signal(signal.SIGALRM, previous)
    return Outcome(case, code, time.process_time() - cpu0, err.getvalue(), error, time.perf_counter() - t0)


def _main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="fuzz ddrt sim with mutated configs/ files")
    parser.add_argument("--cases", type=int, default=1000)
    parser.add_argument("--start", type=int, default=0)
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--kinds", default="config,path,csv")
    parser.add_argument("--time-limit", type=float, default=5.0)
    parser.add_argument("--keep", help="directory for the configs/ copy (default: a temp dir)")
    args = parser.parse_args(argv)
    import tempfile

    base = Path(args.keep or tempfile.mkdtemp(prefix="ddrt-fuzz-"))
    root = copy_configs(base)
    mutator = Mutator(args.seed, args.kinds.split(","))
    bad = 0
    slowest: list[tuple[float, str]] = []
    t0 = time.perf_counter()
    for case in mutator.cases(args.cases, args.start):
        outcome = run_case(case, root, base / "out")
        slowest = sorted(slowest + [(outcome.seconds, case.name)], reverse=True)[:5]
        if not outcome.clean(args.time_limit):
            bad += 1
            print(f"--- {case.name}: exit {outcome.code}, {outcome.seconds:.2f} s CPU ({outcome.wall_s:.2f} s wall)")
            print(outcome.error or outcome.stderr[-2000:])
            print(f"    reproduce: Mutator({args.seed}).case({case.index}), or --start {case.index} --cases 1")
        if (case.index + 1) % 500 == 0:
            print(f"{case.index + 1 - args.start} cases, {bad} bad, {time.perf_counter() - t0:.0f} s", file=sys.stderr)
    print(f"{args.cases} cases, {bad} bad, {time.perf_counter() - t0:.1f} s; most CPU:")
    for seconds, name in slowest:
        print(f"  {seconds:.2f} s  {name[:150]}")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(_main())
