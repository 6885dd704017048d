"""One rule for the file names in a config: a relative name is taken from the folder of the
file that gives it (through extends: too), never from the working directory, so a config
copied elsewhere with the files beside it runs from anywhere."""

from __future__ import annotations

import dataclasses
import os
import shutil
import subprocess
import sys
import typing
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
import yaml

from ddrt.config import load_config
from ddrt.config.load import FILE_KEYS, daemon_socket_of, files_relative_to
from ddrt.config.sections import Config
from ddrt.service.ctlclient import control_socket
from tests.support.repo import REPO, SIM_YAML

# Text keys of a config that name no file: hosts, ROS names, a serial URL, the I2C bus, a part.
NOT_FILES = {"hal.imu.bus", "hal.bridge.url", "daemon.foxglove.host", "daemon.ros2.namespace", "sim.gyro.part",
             "daemon.ros2.node_name", "daemon.ros2.odom_frame", "daemon.ros2.base_frame", "daemon.ros2.map_frame",
             "daemon.ros2.imu_frame", "daemon.ros2.path_topic", "daemon.ros2.pose_topic"}
NOT_KEYS = {"source", "base_dir", "raw", "path"}  # Config's own fields; path: is checked below


def _text_keys(cls: type, prefix: tuple[str, ...] = ()) -> set[str]:
    """The dotted keys of every field of the config that may hold text."""
    out: set[str] = set()
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        kinds = typing.get_args(hints[f.name]) or (hints[f.name],)
        for k in kinds:
            if dataclasses.is_dataclass(k):
                out |= _text_keys(k, prefix + (f.name,))
        if str in kinds:
            out.add(".".join(prefix + (f.name,)))
    return out


def test_every_text_key_of_a_config_is_a_file_name_or_listed_as_none() -> None:
    """A new key that names a file must join FILE_KEYS (and the rule) or this fails."""
    files = {".".join(k) for k in FILE_KEYS}
    text = _text_keys(Config) - NOT_KEYS
    assert text - NOT_FILES == files - {"path", "path.file"}


def _write(folder: Path, name: str, data: dict) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    f = folder / name
    f.write_text(yaml.safe_dump(data))
    return f


def test_every_file_key_resolves_against_the_folder_of_the_file_that_gives_it(tmp_path, monkeypatch) -> None:
    _write(tmp_path / "base", "base.yaml", {
        "extends": str(SIM_YAML),
        "daemon": {"socket": "run/b.sock", "telemetry_dir": "tel"},
        "hal": {"pwm_sysfs": {"root": "fake-sys"}},
    })
    top = _write(tmp_path / "robots" / "one", "r.yaml", {
        "extends": "../../base/base.yaml", "daemon": {"telemetry_dir": "my-tel"},
        "path": {"file": "w.csv"},
    })
    monkeypatch.chdir(tmp_path / "robots")  # somewhere else than either file
    cfg = load_config(os.path.relpath(top, tmp_path / "robots"))
    assert Path(cfg.daemon.socket) == tmp_path / "base" / "run" / "b.sock"  # from the base
    assert Path(cfg.daemon.telemetry_dir) == tmp_path / "robots" / "one" / "my-tel"  # the top file's own
    assert Path(cfg.hal.pwm_sysfs.root) == tmp_path / "base" / "fake-sys"
    assert Path(cfg.path["file"]) == tmp_path / "robots" / "one" / "w.csv"
    assert Path(load_config(SIM_YAML).daemon.socket) == REPO / "configs" / "out" / "ddrt.sock"
    # ddrt ctl --config finds the same socket, also when the config does not validate.
    assert Path(control_socket(None, str(top))[0]) == tmp_path / "base" / "run" / "b.sock"
    assert Path(daemon_socket_of(top, ValueError("x"))) == tmp_path / "base" / "run" / "b.sock"


@pytest.mark.parametrize("value", ["/run/ddrt/x.sock", "", None])
def test_absolute_empty_and_null_names_are_kept(tmp_path, value) -> None:
    f = _write(tmp_path, "c.yaml", {"extends": str(SIM_YAML), "daemon": {"socket": value}})
    assert load_config(f).daemon.socket == value


def test_a_commissioned_config_names_the_same_files_from_its_own_folder(tmp_path) -> None:
    given_in = tmp_path / "configs"
    data = {"path": str(given_in / "paths" / "p.yaml"), "daemon": {"socket": str(given_in / "out" / "s.sock"),
                                                                  "telemetry_dir": "/var/lib/ddrt/telemetry"}}
    out = files_relative_to(data, tmp_path / "robots" / "mine", given_in)
    assert out["path"] == "../../configs/paths/p.yaml" and out["daemon"]["socket"] == "../../configs/out/s.sock"
    assert out["daemon"]["telemetry_dir"] == "/var/lib/ddrt/telemetry"  # given absolute: kept
    assert data["path"].startswith("/")  # the loaded mapping is not changed


@pytest.fixture()
def copied(tmp_path) -> Path:
    """configs/sim.yaml and its paths/ folder copied to a folder of their own."""
    home = tmp_path / "home" / "robot"
    shutil.copytree(REPO / "configs" / "paths", home / "paths")
    text = SIM_YAML.read_text()
    (home / "sim.yaml").write_text(text + "\nestimator: {calibration_s: 0.5}\n" if "estimator:" not in text else text)
    return home / "sim.yaml"


def _ddrt(cwd: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    return subprocess.run([sys.executable, "-m", "ddrt.cli", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=180, env=env)


def test_a_copied_config_runs_from_another_folder_and_writes_beside_itself(copied, tmp_path) -> None:
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    r = _ddrt(elsewhere, "sim", str(copied), "--duration", "1", "--out", "simout", "--quiet")
    assert r.returncode == 0, r.stderr
    assert (elsewhere / "simout" / "telemetry.csv").exists()  # --out: the command line's, from the cwd
    # The daemon, started in one folder, is reached by `ddrt ctl --config` from another.
    env = dict(os.environ, PYTHONPATH=str(REPO))
    daemon = subprocess.Popen([sys.executable, "-m", "ddrt.cli", "run", str(copied), "--duration", "20"],
                              cwd=elsewhere, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=env)
    try:
        for _ in range(60):
            status = _ddrt(tmp_path, "ctl", "--config", str(copied), "status")
            if status.returncode == 0 or daemon.poll() is not None:
                break
        assert status.returncode == 0, status.stderr
        assert (copied.parent / "out" / "ddrt.sock").is_socket()
        assert _ddrt(tmp_path, "ctl", "--config", str(copied), "estop").returncode == 0
    finally:
        daemon.terminate()
        daemon.wait(timeout=30)
    assert (copied.parent / "out" / "daemon-telemetry" / "telemetry.csv").exists()
    assert not (elsewhere / "out").exists() and not (tmp_path / "out").exists()


SEGMENT = st.sampled_from(["a", "b", "c d", "..", "x.y"])


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(folders=st.lists(st.lists(SEGMENT.filter(lambda s: s != ".."), min_size=0, max_size=3), min_size=1, max_size=3),
       names=st.lists(st.fixed_dictionaries({}, optional={k: st.lists(SEGMENT, min_size=1, max_size=3)
                                                          for k in ("socket", "telemetry_dir", "root", "path")}),
                      min_size=3, max_size=3),
       cwd=st.lists(SEGMENT.filter(lambda s: s != ".."), max_size=2))
def test_any_chain_of_extends_resolves_each_name_against_the_file_that_gives_it(tmp_path, folders, names, cwd) -> None:
    """A chain of 1 to 3 files in any folders, each giving some of the file keys (relative
    names with `..` and spaces): each key is the last file's to give it, from that file's folder."""
    import uuid

    root = tmp_path / uuid.uuid4().hex
    files = [root.joinpath(*f, f"c{i}.yaml") for i, f in enumerate(folders)]
    expected: dict[str, Path] = {}
    for i, f in enumerate(files):
        given = names[i]
        doc: dict = {"extends": os.path.relpath(files[i - 1], f.parent) if i else str(SIM_YAML)}
        sections = {"socket": ("daemon", "socket"), "telemetry_dir": ("daemon", "telemetry_dir"),
                    "root": ("hal", "pwm_sysfs", "root")}
        for key, parts in given.items():
            value = "/".join(parts)
            if key == "path":
                doc["path"] = {"file": value + ".csv"}
                expected["path"] = Path(os.path.normpath(f.parent / (value + ".csv")))
                continue
            *outer, leaf = sections[key]
            node = doc
            for part in outer:
                node = node.setdefault(part, {})
            node[leaf] = value
            expected[key] = Path(os.path.normpath(f.parent / value))
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_text(yaml.safe_dump(doc))
    where = root.joinpath(*cwd)
    where.mkdir(parents=True, exist_ok=True)
    old = os.getcwd()
    os.chdir(where)
    try:
        cfg = load_config(os.path.relpath(files[-1], where))
    finally:
        os.chdir(old)
    got = {"socket": cfg.daemon.socket, "telemetry_dir": cfg.daemon.telemetry_dir, "root": cfg.hal.pwm_sysfs.root,
           "path": cfg.path["file"] if isinstance(cfg.path, dict) else None}
    for key, want in expected.items():
        assert Path(os.path.normpath(got[key])) == want, (key, got[key], want)
