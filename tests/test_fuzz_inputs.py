"""Fuzz: seeded mutations of every file in configs/ (configs, path YAMLs, the CSV) through
`ddrt sim` in this process (tests/support/fuzz_inputs.py). Every case must end on the clean path:
exit 0, 1 or 2, no traceback on stderr, no exception out of main(), within 15 s of CPU time
(the case's own work: another job on the machine does not count against it). The bound is for
inputs nothing bounds (they would take minutes or never end), not a speed test: the costliest
legit case here, a figure-eight 1000 m wide (case 785), took 5.3 s of CPU (3.3 s building the
dense path) on a day this virtual machine ran the same code at half the speed it had hours
before, and failed the old 5 s bound.

Deterministic (fixed seed): a failure names its case, which `Mutator(1).case(i)` rebuilds.
Many more cases locally: `python -m tests.support.fuzz_inputs --cases 20000`.
"""

from __future__ import annotations

import collections
from pathlib import Path

import pytest

from tests.support.fuzz_inputs import Mutator, copy_configs, run_case, seed_files

SEED = 1
N_CASES = 1200
TIME_LIMIT_S = 15.0


@pytest.mark.slow
def test_mutated_inputs_never_escape_the_clean_error_path(tmp_path: Path) -> None:
    root = copy_configs(tmp_path)
    bad: list[str] = []
    codes: collections.Counter[object] = collections.Counter()
    kinds: collections.Counter[str] = collections.Counter()
    ops: set[str] = set()
    for case in Mutator(SEED).cases(N_CASES):
        outcome = run_case(case, root, tmp_path / "out")
        codes[outcome.code] += 1
        kinds[case.kind] += 1
        ops.update(op.split(":")[0] for op in case.ops)
        if not outcome.clean(TIME_LIMIT_S):
            bad.append(f"{case.name}: exit {outcome.code}, {outcome.seconds:.2f} s CPU, {outcome.wall_s:.2f} s wall\n"
                       f"{outcome.error or outcome.stderr[-1500:]}")
    assert not bad, f"{len(bad)} of {N_CASES} cases left the clean error path:\n" + "\n".join(bad[:5])
    # The fuzz means something only if it reaches every stage: errors at load time (2) and
    # runs of the loop (0 or 1: a 0.01 s run ends unfinished), on every kind of file.
    assert codes[2] >= N_CASES // 5 and codes[0] + codes[1] >= N_CASES // 5, codes
    assert set(kinds) == {"config", "path", "csv"} and min(kinds.values()) >= 50, kinds
    assert {"number", "type swap", "duplicate key", "delete key", "flip", "latin-1", "truncate", "nest",
            "long", "many values", "alias bomb", "cell", "rows"} <= ops, ops


def test_mutator_is_deterministic_and_covers_every_input_file(repo_root: Path) -> None:
    a, b = Mutator(SEED), Mutator(SEED)
    for i in (0, 7, 999):
        ca, cb = a.case(i), b.case(i)
        assert (ca.origin, ca.data, ca.ops) == (cb.origin, cb.data, cb.ops)
    assert Mutator(SEED + 1).case(7).data != a.case(7).data or Mutator(SEED + 1).case(7).origin != a.case(7).origin
    files = seed_files()
    every = {p for ps in files.values() for p in ps}
    assert Path("sim.yaml") in every and Path("paths/waypoints_sparse.csv") in every
    on_disk = [*(repo_root / "configs").rglob("*.yaml"), *(repo_root / "configs").rglob("*.csv")]
    assert len(every) == len(on_disk)
    seen = {case.origin for case in a.cases(N_CASES)}
    assert seen == every  # every file of configs/ is mutated at least once
    only = Mutator(SEED, kinds=("config",))
    assert {c.kind for c in only.cases(50)} == {"config"}
