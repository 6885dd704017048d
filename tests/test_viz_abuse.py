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

REPO = Path(__file__).resolve().parents[1]
SIM = REPO / "configs" / "sim.yaml"
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
    out = _cli_with_broken_sdk("sim", str(SIM), "--duration", "0.1", "--out", str(tmp_path / "sim"),
                               "--mcap", str(tmp_path / "r.mcap"), "--quiet")
    assert out.returncode == 2, out.stderr
    assert "--mcap needs the foxglove-sdk package, which is installed but does not import" in out.stderr
    assert "GLIBC_2.38" in out.stderr and "pip install 'ddrt[foxglove]'" in out.stderr
    assert "Traceback" not in out.stderr
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(f"extends: {SIM}\ndaemon: {{telemetry_dir: {tmp_path / 'tel'}, foxglove: {{enabled: true, port: 0}}}}\n")
    out = _cli_with_broken_sdk("run", str(cfg), "--socket", str(tmp_path / "s.sock"), "--duration", "1")
    assert out.returncode == 2, out.stderr
    assert "daemon.foxglove.enabled: true needs the foxglove-sdk package, which is installed but does not import" \
        in out.stderr
    assert "Traceback" not in out.stderr
