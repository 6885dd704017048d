"""Foxglove and MCAP (ddrt/viz) abused the way bad clients, broken installs and full disks
abuse them: a foxglove-sdk that is installed but does not import, parameter floods,
teleop floods, MCAP paths that cannot be written, rotation, shutdown with a client."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from ddrt.viz import optional
from tests.support.repo import REPO, SIM_YAML

needs_sdk = pytest.mark.skipif(not optional.available(), reason="foxglove-sdk not installed (pip install 'ddrt[foxglove]')")

# Run ddrt's CLI with the SDK's native extension failing to load (a wheel for another CPU or
# C library): found by find_spec, broken at import.
_BROKEN_SDK = textwrap.dedent("""
    import importlib.abc, sys
    class Broken(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path, target=None):
            if name.startswith("foxglove._foxglove_py"):
                raise ImportError("libc.so.6: version `GLIBC_2.38' not found (simulated)")
            return None
    sys.meta_path.insert(0, Broken())
    from ddrt.cli import main
    sys.exit(main(sys.argv[1:]))
""")


def _cli_with_broken_sdk(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", _BROKEN_SDK, *args], cwd=REPO, capture_output=True, text=True,
                          timeout=60)


@needs_sdk
def test_an_sdk_that_is_installed_but_does_not_import_is_a_clear_error_not_a_traceback(tmp_path: Path) -> None:
    out = _cli_with_broken_sdk("sim", str(SIM_YAML), "--duration", "0.1", "--out", str(tmp_path / "sim"),
                               "--mcap", str(tmp_path / "r.mcap"), "--quiet")
    assert out.returncode == 2, out.stderr
    assert "--mcap needs the foxglove-sdk package, which is installed but does not import" in out.stderr
    assert "GLIBC_2.38" in out.stderr and "pip install 'ddrt[foxglove]'" in out.stderr
    assert "Traceback" not in out.stderr
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(f"extends: {SIM_YAML}\ndaemon: {{telemetry_dir: {tmp_path / 'tel'}, foxglove: {{enabled: true, port: 0}}}}\n")
    out = _cli_with_broken_sdk("run", str(cfg), "--socket", str(tmp_path / "s.sock"), "--duration", "1")
    assert out.returncode == 2, out.stderr
    assert "daemon.foxglove.enabled: true needs the foxglove-sdk package, which is installed but does not import" \
        in out.stderr
    assert "Traceback" not in out.stderr


# ---------------------------------------------------------------- parameters


class _Param:
    """What the SDK hands the listener: a name and get_value()."""

    def __init__(self, name: str, value: object) -> None:
        self.name, self._value = name, value

    def get_value(self) -> object:
        return self._value


@pytest.fixture()
def viz_rig(tmp_path: Path):
    """A VizService (no server, no MCAP) on an in-process Daemon whose loop runs on the
    unpaced simulated robot: the parameter path from the SDK's thread to between_ticks."""
    from ddrt.viz.service import VizService
    from tests.support.drive_rigs import DaemonRig

    rig = DaemonRig(tmp_path)
    svc = VizService(rig.d, 40, truth=False, mcap_dir=None)
    rig.d.viz = svc
    try:
        yield rig, svc
    finally:
        svc.close()
        rig.d.hal.close()


@needs_sdk
def test_a_set_parameters_flood_is_refused_before_planning_and_the_loop_never_plans(viz_rig, monkeypatch) -> None:
    """2000 setParameters as fast as a client can send them: at most SET_BURST plus
    SET_RATE_HZ a second are planned (each plan is ~1.5 ms of CPU under the GIL), the rest
    refused as busy with a bounded number of log lines; the loop thread only puts plans in
    force, it never plans (before: every set planned on the SDK thread and again on the loop
    thread between two ticks, 306 missed ticks at 200 Hz and half the ticks at 1 kHz under
    a sustained flood, 17 000 log lines in 10 s)."""
    import logging
    import threading

    import ddrt.service.reloading as daemon_mod
    import ddrt.viz.params as params_mod
    import ddrt.viz.service as service_mod

    rig, svc = viz_rig
    d = rig.d
    planned_on: list[str] = []
    real_plan = params_mod.plan_reload
    real_daemon_plan = daemon_mod.plan_reload

    def spy(where: str, real):
        def plan(*a, **k):
            planned_on.append(where + ":" + threading.current_thread().name)
            return real(*a, **k)
        return plan

    monkeypatch.setattr(params_mod, "plan_reload", spy("sdk", real_plan))
    monkeypatch.setattr(daemon_mod, "plan_reload", spy("loop", real_daemon_plan))
    records: list[logging.LogRecord] = []
    handler = logging.Handler()
    handler.emit = records.append  # type: ignore[method-assign]
    logging.getLogger("ddrt").addHandler(handler)
    try:
        import time

        t0 = time.monotonic()
        for i in range(2000):
            svc.set_parameters([_Param("controller.inner.kp", 20.0 + i % 10)])
            if i % 50 == 0:
                svc.between_ticks()
                rig.ticks(1)
        elapsed = time.monotonic() - t0
        for _ in range(10):
            svc.between_ticks()
    finally:
        logging.getLogger("ddrt").removeHandler(handler)
    burst, rate = getattr(service_mod, "SET_BURST", 4), getattr(service_mod, "SET_RATE_HZ", 10.0)
    sdk_plans = [p for p in planned_on if p.startswith("sdk")]
    assert 1 <= len(sdk_plans) <= burst + rate * elapsed + 1, (len(sdk_plans), elapsed)
    assert not [p for p in planned_on if p.startswith("loop")], planned_on  # the loop only applied
    # a set to the value in force is counted as unchanged, not applied
    assert d.reloads["applied"] + d.reloads["unchanged"] == len(sdk_plans) and d.reloads["rejected"] == 0
    assert d.cfg.controller.inner.kp == d.loop.cfg.controller.inner.kp  # what was applied last is in force
    assert len(records) <= 2 * len(sdk_plans) + 10, len(records)  # a flood is not a flood of log lines
    assert any("more than 10 parameter sets a second" in r.getMessage() for r in records)


@needs_sdk
def test_queued_parameter_sets_each_apply_in_order_without_replanning_on_the_loop(viz_rig, monkeypatch) -> None:
    import ddrt.service.reloading as daemon_mod

    rig, svc = viz_rig
    d = rig.d
    loop_plans: list[int] = []
    real = daemon_mod.plan_reload
    monkeypatch.setattr(daemon_mod, "plan_reload", lambda *a, **k: (loop_plans.append(1), real(*a, **k))[1])
    for name, value in (("controller.inner.kp", 33.0), ("controller.inner.ki", 90.0), ("controller.outer.k_y", 300.0)):
        assert svc.set_parameters([_Param(name, value)])[0].get_value() == value
    for _ in range(3):
        svc.between_ticks()
    c = d.cfg.controller
    assert (c.inner.kp, c.inner.ki, c.outer.k_y) == (33.0, 90.0, 300.0) and loop_plans == []
    # A reload between the set and the loop taking it: planned again there, over the reload.
    assert svc.set_parameters([_Param("controller.inner.kp", 31.0)])[0].get_value() == 31.0
    d.apply_overrides({"controller": {"inner": {"kd": 0.5}}}, "test")
    loop_plans.clear()
    svc.between_ticks()
    assert loop_plans == [1] and (d.cfg.controller.inner.kp, d.cfg.controller.inner.kd) == (31.0, 0.5)


# ---------------------------------------------------------------- MCAP files that cannot be written


@needs_sdk
@pytest.mark.parametrize("target", ["directory", "missing", "full"])
def test_sim_mcap_to_a_path_that_cannot_be_written_names_the_flag_without_a_traceback(tmp_path: Path,
                                                                                      target: str) -> None:
    """A directory, a parent that cannot be made, a full disk (/dev/full): `ddrt sim --mcap`
    says which flag and file and why, exit 1. Before: 'Is a directory (os error 21)' without
    the flag or the file, and on a full disk a traceback after the whole run (the SDK logs a
    warning for every message after the failure and raises only at close)."""
    path = {"directory": str(tmp_path), "missing": "/proc/ddrt-nope/run.mcap", "full": "/dev/full"}[target]
    if target == "full" and not Path("/dev/full").exists():
        pytest.skip("no /dev/full")
    out = subprocess.run([sys.executable, "-m", "ddrt.cli", "sim", str(SIM_YAML), "--duration", "5", "--out",
                          str(tmp_path / "sim"), "--mcap", path, "--quiet"], cwd=REPO, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 1, out.stderr
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"ddrt: error: --mcap {path}: "), out.stderr
    why = {"directory": "is a directory", "missing": "cannot write it", "full": "No space left on device"}[target]
    assert why in lines[0]


class _FakeWriter:
    def __init__(self, path: str, fail: list[bool]) -> None:
        Path(path).write_bytes(b"\x89MCAP0\r\n")
        self.fail = fail
        self.closed = False

    def flush(self) -> None:
        if self.fail[0]:
            raise RuntimeError("FoxgloveError: MCAP error: I/O error from writing (simulated: no space left)")

    def close(self) -> None:
        self.closed = True
        if self.fail[0]:
            raise RuntimeError("FoxgloveError: MCAP error: attempted another write after a write method failed")


@needs_sdk
def test_daemon_mcap_on_a_full_disk_logs_once_keeps_going_and_records_again_when_there_is_room(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture) -> None:
    """Measured before the fix on a 300 kB tmpfs: the publisher logged 'foxglove publisher:
    RuntimeError ...' 30 times a second for as long as the disk stayed full (the flush was
    retried on every publish), the SDK a warning per message. Now: one error, the file cut
    short moved aside, a new file tried every RETRY_S, one line when it writes again."""
    import logging

    import ddrt.viz.mcapfile as mcapfile

    fail = [False]
    writers: list[_FakeWriter] = []

    class Fg:
        @staticmethod
        def open_mcap(path: str, **_: object) -> _FakeWriter:
            writers.append(_FakeWriter(path, fail))
            return writers[-1]

    now = [1000.0]
    monkeypatch.setattr(mcapfile.time, "monotonic", lambda: now[0])
    rot = mcapfile.RotatingMcap(Fg, None, str(tmp_path), "telemetry", 10_000_000, 5, flush_s=1.0)
    try:
        caplog.set_level(logging.INFO, logger="ddrt.viz")
        for _ in range(20):
            now[0] += 0.02
            rot.check()
        fail[0] = True
        for _ in range(3000):  # 60 s of a full disk at the publisher's 50 Hz
            now[0] += 0.02
            rot.check()
        errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
        assert len(errors) == 1 and "writing" in errors[0].getMessage() and "no space left" in errors[0].getMessage()
        assert (tmp_path / "telemetry.1.mcap").exists()  # the file cut short, kept
        assert 5 <= len(writers) <= 1 + 60 / mcapfile.RETRY_S + 1  # a retry every RETRY_S, not every publish
        fail[0] = False
        for _ in range(int(mcapfile.RETRY_S / 0.02) + 100):
            now[0] += 0.02
            rot.check()
        assert rot._writer is not None and any("again" in r.getMessage() for r in caplog.records)
        # The SDK's own warnings after a failure: the first passes, the flood does not.
        sdk = logging.getLogger(mcapfile.SinkErrors.LOGGER)
        before = len(caplog.records)
        caplog.set_level(logging.WARNING, logger=mcapfile.SinkErrors.LOGGER)
        for _ in range(5000):
            sdk.warning("error logging message: McapError(AttemptedWriteAfterFailure)")
        assert len(caplog.records) - before <= 3
    finally:
        rot.close()
