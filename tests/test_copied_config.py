"""A config copied to another directory (its `path:` relative, now pointing
nowhere) still starts the daemon without --follow, with a warning naming the config file and
the `path:` key; with --follow, and in `ddrt sim`, it is an error naming both."""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.support.repo import REPO, SIM_YAML


@pytest.fixture()
def copied() -> Iterator[Path]:
    d = Path(tempfile.mkdtemp(prefix="ddrtcfg-", dir="/tmp"))
    cfg = d / "my.yaml"
    text = SIM_YAML.read_text().replace("out/daemon-telemetry", str(d / "tel"))
    cfg.write_text(text + "\nestimator: {calibration_s: 0.5}\n" if "estimator:" not in text else text)
    yield cfg
    shutil.rmtree(d, ignore_errors=True)


def ddrt(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "ddrt.cli", *args], cwd=REPO, capture_output=True, text=True,
                          timeout=120)


def test_run_without_follow_warns_and_goes_on(copied: Path) -> None:
    r = ddrt("run", str(copied), "--socket", str(copied.parent / "s.sock"), "--duration", "0.5")
    assert r.returncode == 0, r.stderr
    warn = [ln for ln in r.stderr.splitlines() if "WARNING" in ln and "cannot read" in ln]
    assert len(warn) == 1, r.stderr
    assert f"{copied}: path: " in warn[0] and "not followed" in warn[0] and str(copied.parent) in warn[0]


def test_run_with_follow_is_an_error_naming_config_and_key(copied: Path) -> None:
    r = ddrt("run", str(copied), "--socket", str(copied.parent / "s.sock"), "--duration", "0.5", "--follow")
    assert r.returncode == 2, r.stderr
    assert f"{copied}: path: {copied.parent}/paths/figure8_slow.yaml: cannot read" in r.stderr


def test_sim_error_names_config_and_key(copied: Path) -> None:
    r = ddrt("sim", str(copied), "--duration", "1", "--out", str(copied.parent / "out"), "--quiet")
    assert r.returncode == 2, r.stderr
    assert f"{copied}: path: {copied.parent}/paths/figure8_slow.yaml: cannot read" in r.stderr
    assert "config's directory" in r.stderr
