"""Reloading a following daemon with mangled config files: it keeps following, and a file
that does not load leaves the config in force untouched (the same object)."""

from __future__ import annotations

import random
import time
from pathlib import Path

import pytest
import yaml

from test_reload_live import REPO, Rig

_JUNK = [b"\xe9", b"\xff\xfe", b"1" * 400, b"1e308", b"-1e308", b".nan", b".inf", b"-1", b"0", b"null",
         b"[]", b"{}", b"[1, 2]", b"'abc'", b"{a: 1}", b"[" * 60 + b"]" * 60, b"x" * 5000, b"1.0e308",
         b"1e-300", b"true", b"-0.0", b"99999999999999999999", b"&a [*a]", b"!!python/object:os.system", b"\t"]


def mutations(data: bytes, rng: random.Random, n: int):
    """`n` mangled versions of a YAML file: a value swapped for junk, a line dropped or doubled
    (a duplicate key), a byte flipped or made Latin-1, the file cut short."""
    lines = data.splitlines(keepends=True)
    for _ in range(n):
        kind = rng.randrange(6)
        out = list(lines)
        j = rng.randrange(len(out))
        if kind == 0 and b":" in out[j]:
            head = out[j].split(b":", 1)[0]
            out[j] = head + b": " + rng.choice(_JUNK) + b"\n"
        elif kind == 1:
            del out[j]
        elif kind == 2:
            out.insert(j, out[j])
        elif kind == 3:
            blob = bytearray(b"".join(out))
            for _ in range(rng.randint(1, 4)):
                k = rng.randrange(len(blob))
                blob[k] = rng.randrange(256)
            yield bytes(blob)
            continue
        elif kind == 4:
            blob = b"".join(out)
            yield blob[: rng.randrange(len(blob))]
            continue
        else:
            out.append(rng.choice([b"limits: {v_max: 0.5}\n", b"robot: {m_p: " + rng.choice(_JUNK) + b"}\n",
                                   b"controller: {inner: {kp: " + rng.choice(_JUNK) + b"}}\n",
                                   b"daemon: {spin_us: " + rng.choice(_JUNK) + b"}\n"]))
        yield b"".join(out)

CASES = 1000


@pytest.fixture(scope="module")
def rig(tmp_path_factory: pytest.TempPathFactory) -> Rig:
    r = Rig(tmp_path_factory.mktemp("reload-fuzz"))
    yield r
    r.close()


def test_a_following_daemon_survives_any_reload(rig: Rig) -> None:
    d = rig.d
    # The whole config in one file (not a few lines over `extends:`), so every section is hit.
    full = yaml.safe_load((REPO / "configs" / "sim.yaml").read_text())
    full.pop("path", None)
    full["estimator"] = {"calibration_s": 0.05}
    full["daemon"] = yaml.safe_load(rig.file.read_text())["daemon"]
    baseline = yaml.safe_dump(full, sort_keys=False).encode()
    rig.file.write_bytes(baseline)
    first = d.reload()
    assert first["ok"] and first["applied"] == first["next_path"] == [], first
    rng = random.Random(20261201)
    rejected = applied = 0
    worst = 0.0
    for i, data in enumerate(mutations(baseline, rng, CASES)):
        before = d.cfg
        rig.file.write_bytes(data)
        t0 = time.perf_counter()
        reply = d.reload()
        worst = max(worst, time.perf_counter() - t0)
        assert isinstance(reply.get("ok"), bool), reply
        if reply["ok"]:
            applied += 1
            for key in ("applied", "next_path", "restart"):
                assert isinstance(reply[key], list)
        else:
            rejected += 1
            assert d.cfg is before, f"case {i}: a rejected reload changed the config in force"
            assert d.loop.cfg is before
            error = reply["error"]
            assert "Traceback" not in error and str(rig.file) in error, f"case {i}: {error}"
        rig.ticks(3)
        assert d.loop.state == "following", f"case {i}: {d.loop.fault} after {data[:200]!r}"
        rig.file.write_bytes(baseline)
        back = d.reload()
        assert back["ok"], back
    assert rejected > CASES // 4 and applied > 0
    assert worst < 5.0
