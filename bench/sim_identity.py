"""`python -m bench.sim_identity save|check [FILE]`: do speed-ups change what `ddrt sim` computes?

Runs configs/sim.yaml and every configs/scenarios/*.yaml in-process (run_sim, rows kept)
and records each run's metrics (all but wall_s and realtime_factor), a SHA-256 of its
telemetry rows' bytes and one of their text as telemetry.csv holds it (format_rows: the C
formatter when built, so a change to it shows). `save` writes them (run it on the commit
before a change); `check` reruns and compares: metrics to 1e-9 (relative or absolute), and
reports whether the telemetry is bit-identical and its text the same. Exit status 1 on a
metric mismatch.
"""

from __future__ import annotations

import hashlib
import json
import math
import sys
from pathlib import Path as FsPath
from typing import Any

from ddrt.config import load_config
from ddrt.path.spec import resolve_path
from ddrt.simrun.runner import format_rows, json_ready, run_sim

REPO = FsPath(__file__).resolve().parent.parent
DEFAULT = FsPath("/tmp/ddrt_sim_identity.json")
VOLATILE = ("wall_s", "realtime_factor")


def configs() -> list[FsPath]:
    return [REPO / "configs/sim.yaml"] + sorted((REPO / "configs/scenarios").glob("*.yaml"))


def run_one(config: FsPath) -> dict[str, Any]:
    """One run's comparable outcome: metrics without the timings, and the rows' digest."""
    cfg = load_config(str(config))
    result = run_sim(cfg, resolve_path(cfg), keep_rows=True)
    metrics = {k: v for k, v in json_ready(result.metrics).items() if k not in VOLATILE}
    rows = result.rows_array()
    return {"metrics": metrics, "rows_sha256": hashlib.sha256(rows.tobytes()).hexdigest(),
            "csv_sha256": hashlib.sha256(format_rows(rows).encode()).hexdigest()}


def collect() -> dict[str, Any]:
    return {str(c.relative_to(REPO)): run_one(c) for c in configs()}


def diff(a: Any, b: Any, where: str, tol: float = 1e-9) -> list[str]:
    """Where `a` and `b` differ beyond `tol` (floats), or at all (anything else)."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = [f"{where}.{k}: only on one side" for k in set(a) ^ set(b)]
        for k in sorted(set(a) & set(b)):
            out += diff(a[k], b[k], f"{where}.{k}", tol)
        return out
    if isinstance(a, float) and isinstance(b, float):
        ok = math.isclose(a, b, rel_tol=tol, abs_tol=tol) or (math.isnan(a) and math.isnan(b))
        return [] if ok else [f"{where}: {a!r} != {b!r}"]
    return [] if a == b else [f"{where}: {a!r} != {b!r}"]


def main(argv: list[str]) -> int:
    mode = argv[0] if argv else "check"
    if mode not in ("save", "check") or len(argv) > 2:
        print(__doc__.splitlines()[0].split(":")[0].strip("`"), file=sys.stderr)
        return 0 if mode in ("-h", "--help") else 2
    file = FsPath(argv[1]) if len(argv) > 1 else DEFAULT
    if mode == "check" and not file.exists():
        print(f"{file}: no saved runs to check against; run `python -m bench.sim_identity save` first", file=sys.stderr)
        return 2
    now = collect()
    if mode == "save":
        file.write_text(json.dumps(now, indent=1, sort_keys=True))
        print(f"saved {len(now)} runs to {file}")
        return 0
    ref = json.loads(file.read_text())
    problems, bitwise, text, texts = [], 0, 0, 0
    for name in sorted(set(ref) | set(now)):
        if name not in ref or name not in now:
            problems.append(f"{name}: only on one side")
            continue
        problems += diff(ref[name]["metrics"], now[name]["metrics"], name)
        bitwise += ref[name]["rows_sha256"] == now[name]["rows_sha256"]
        if "csv_sha256" in ref[name]:  # files saved before the text was recorded lack it
            texts += 1
            text += ref[name]["csv_sha256"] == now[name]["csv_sha256"]
    print(f"{len(now)} runs: metrics {'identical to 1e-9' if not problems else 'DIFFER'}; "
          f"telemetry bit-identical in {bitwise}/{len(now)}; its CSV text the same in "
          + (f"{text}/{texts}" if texts else "- (not in the saved file)"))
    for p in problems:
        print("  " + p)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
