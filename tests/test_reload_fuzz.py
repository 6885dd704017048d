"""Reloading a following daemon with mangled config files: it keeps following, and a file
that does not load leaves the config in force untouched (the same object)."""

from __future__ import annotations

import random
import time

import pytest
import yaml

from ddrt.loop import LoopState
from tests.support.fuzz_inputs import mutate
from tests.support.reload_rig import Rig
from tests.support.repo import SIM_YAML

CASES = 1000


SAFETY_STOPS = ("the path's reference point is", "non-finite value")


def _full_config(rig: Rig) -> bytes:
    """The whole config in one file (not a few lines over `extends:`), so every section is hit."""
    full = yaml.safe_load(SIM_YAML.read_text())
    full.pop("path", None)
    full["estimator"] = {"calibration_s": 0.05}
    full["daemon"] = yaml.safe_load(rig.file.read_text())["daemon"]
    return yaml.safe_dump(full, sort_keys=False).encode()


def test_a_following_daemon_survives_any_reload(tmp_path_factory: pytest.TempPathFactory) -> None:
    """A file that does not load leaves the daemon following with the config in force (the same
    object). A file that loads is the operator's new config: it is put in force, and whatever it
    says (a motor ten times stronger than believed, say), the robot stays within its limits and
    at worst the path-error or non-finite check stops it with the motors at zero."""
    rig = Rig(tmp_path_factory.mktemp("reload-fuzz"))
    baseline = _full_config(rig)
    rig.file.write_bytes(baseline)
    first = rig.d.reload()
    assert first["ok"] and first["applied"] == first["next_path"] == [], first
    rng = random.Random(20261201)
    rejected = applied = stops = 0
    worst = 0.0
    for i in range(CASES):
        d = rig.d
        data, ops = mutate(rng, baseline)
        before = d.cfg
        rig.file.write_bytes(data)
        t0 = time.thread_time()  # the work the reload does, not the CPU a loaded host gave it
        reply = d.reload()
        worst = max(worst, time.thread_time() - t0)
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
        duty_max = d.cfg.limits.duty_max
        for _ in range(20):
            rig.ticks(1)
            assert max(abs(d.loop.duty_l), abs(d.loop.duty_r)) <= duty_max + 1e-12, f"case {i} ({ops})"
            if d.loop.state != LoopState.FOLLOWING:
                break
        if d.loop.state != LoopState.FOLLOWING:
            if d.loop.state != LoopState.STOPPED:  # stopped: the path's end, after many cases
                assert reply["ok"], f"case {i} ({ops}): rejected, yet {d.loop.state}: {d.loop.fault}"
                assert d.loop.state == LoopState.FAULT and d.loop.fault.startswith(SAFETY_STOPS), (i, ops, d.loop.fault)
                stops += 1
            assert d.loop.duty_l == d.loop.duty_r == 0.0
            rig.close()
            rig = Rig(tmp_path_factory.mktemp("reload-fuzz"))
            rig.file.write_bytes(baseline)
            assert rig.d.reload()["ok"]
            continue
        rig.file.write_bytes(baseline)
        back = d.reload()
        assert back["ok"], back
    rig.close()
    assert rejected > CASES // 4 and applied > 0
    print(f"reload fuzz: {rejected} rejected, {applied} applied, {stops} safety stops")
    assert stops <= applied // 4, (stops, applied)
    assert worst < 5.0  # CPU seconds for the worst file (300 000 digits, 200 000 aliased values)
