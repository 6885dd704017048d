"""The systemd unit, sysusers/tmpfiles snippets and udev rule, checked with systemd's own tools.

Needs systemd-analyze (and, for the snippets, systemd-sysusers/systemd-tmpfiles); each test
skips with the reason when its tool is missing (e.g. on macOS or in a minimal container).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest
from tests.support.repo import REPO

SYSTEMD = REPO / "systemd"
UNIT = SYSTEMD / "ddrt.service"
MAX_EXPOSURE = 1.5
REAL_EXEC = "/opt/ddrt/venv/bin/ddrt"


def tool(name: str) -> str:
    path = shutil.which(name) or next((p for p in (f"/usr/bin/{name}", f"/bin/{name}") if os.path.exists(p)), None)
    if path is None:
        pytest.skip(f"{name} not installed (systemd tools are needed to check the unit)")
    return path


def unit_settings(text: str) -> dict[str, list[str]]:
    """Key -> every value it is given (systemd keys may repeat), sections ignored."""
    out: dict[str, list[str]] = {}
    for line in text.splitlines():
        line = line.strip()
        if not line or line[0] in "#;[":
            continue
        key, _, value = line.partition("=")
        out.setdefault(key.strip(), []).append(value.strip())
    return out


def runnable_copy(tmp_path: Path) -> Path:
    """The unit with ExecStart pointing at a binary that exists here (the venv does not)."""
    text = UNIT.read_text()
    assert REAL_EXEC in text
    copy = tmp_path / "ddrt.service"
    copy.write_text(text.replace(REAL_EXEC, "/bin/true"))
    return copy


def test_security_exposure_within_target() -> None:
    analyze = tool("systemd-analyze")
    out = subprocess.run([analyze, "security", "--offline=true", "--no-pager", str(UNIT)],
                         capture_output=True, text=True, timeout=60)
    text = out.stdout + out.stderr
    m = re.search(r"Overall exposure level for ddrt\.service:\s*([0-9.]+)", text)
    if m is None and "offline" in text and "unrecognized" in text:
        pytest.skip("this systemd-analyze has no --offline (needs systemd >= 250)")
    assert m, text
    assert float(m.group(1)) <= MAX_EXPOSURE, text


def test_verify_clean(tmp_path: Path) -> None:
    analyze = tool("systemd-analyze")
    out = subprocess.run([analyze, "verify", "--no-pager", str(runnable_copy(tmp_path))],
                         capture_output=True, text=True, timeout=60)
    ours = [line for line in (out.stdout + out.stderr).splitlines() if "ddrt" in line]
    assert ours == [], "\n".join(ours)
    assert out.returncode == 0, out.stdout + out.stderr


def test_verify_original_only_misses_the_venv() -> None:
    analyze = tool("systemd-analyze")
    if os.path.exists(REAL_EXEC):
        pytest.skip(f"{REAL_EXEC} exists here: test_verify_clean covers it")
    out = subprocess.run([analyze, "verify", "--no-pager", str(UNIT)], capture_output=True, text=True, timeout=60)
    lines = [line for line in (out.stdout + out.stderr).splitlines() if "ddrt" in line]
    assert lines, "verify should complain that the venv binary is missing"
    assert all(REAL_EXEC in line for line in lines), "\n".join(lines)


def test_unit_has_the_required_settings() -> None:
    s = unit_settings(UNIT.read_text())
    expected = {
        "Type": "notify", "NotifyAccess": "main", "WatchdogSec": "2", "Restart": "on-failure",
        "User": "ddrt", "Group": "ddrt", "RuntimeDirectory": "ddrt", "RuntimeDirectoryMode": "0750",
        "StateDirectory": "ddrt", "ConfigurationDirectory": "ddrt", "LimitMEMLOCK": "infinity",
        "DevicePolicy": "closed", "RestrictRealtime": "no", "PrivateNetwork": "yes",
        "RestrictAddressFamilies": "AF_UNIX", "IPAddressDeny": "any", "NoNewPrivileges": "yes",
        "ProtectSystem": "strict", "MemoryDenyWriteExecute": "yes",
    }
    for key, value in expected.items():
        assert s.get(key, [None])[-1] == value, f"{key}= is {s.get(key)}, expected {value}"
    assert s["ExecStart"] == [f"{REAL_EXEC} run /etc/ddrt/ddrt.yaml --socket /run/ddrt/ddrt.sock"]
    assert s["ExecReload"] == ["/bin/kill -HUP $MAINPID"]
    assert set(s["SupplementaryGroups"][-1].split()) == {"i2c", "dialout"}
    assert {"/dev/i2c-1 rw", "/dev/ttyACM0 rw", "char-ttyACM rw"} <= set(s["DeviceAllow"])
    assert int(s["LimitRTPRIO"][-1]) >= 1  # SCHED_FIFO without CAP_SYS_NICE needs it
    assert s["SystemCallFilter"][0] == "@system-service"
    # What the loop calls must survive the later "~@resources" exclusion.
    allowed_back = " ".join(s["SystemCallFilter"][2:]).split()
    assert {"sched_setscheduler", "sched_setaffinity"} <= set(allowed_back)


def test_sysusers_creates_user_and_memberships(tmp_path: Path) -> None:
    sysusers = tool("systemd-sysusers")
    (tmp_path / "etc").mkdir()  # it locks etc/.pwd.lock in the root before writing
    conf = (SYSTEMD / "ddrt.sysusers.conf").read_text()
    out = subprocess.run([sysusers, f"--root={tmp_path}", "-"], input=conf, capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    passwd = {line.split(":")[0]: line.split(":") for line in (tmp_path / "etc/passwd").read_text().splitlines()}
    groups = {line.split(":")[0]: line.split(":") for line in (tmp_path / "etc/group").read_text().splitlines()}
    assert passwd["ddrt"][5] == "/var/lib/ddrt" and passwd["ddrt"][4] == "ddrt robot controller"
    assert int(passwd["ddrt"][2]) < 1000  # a system user
    assert "nologin" in passwd["ddrt"][6]
    for g in ("i2c", "dialout"):
        assert "ddrt" in groups[g][3].split(","), f"ddrt not in group {g}"


def test_tmpfiles_creates_owned_directories(tmp_path: Path) -> None:
    sysusers, tmpfiles = tool("systemd-sysusers"), tool("systemd-tmpfiles")
    if os.geteuid() != 0:
        pytest.skip("systemd-tmpfiles --root needs root to chown to the ddrt user")
    (tmp_path / "etc/ddrt").mkdir(parents=True)
    subprocess.run([sysusers, f"--root={tmp_path}", "-"], input=(SYSTEMD / "ddrt.sysusers.conf").read_text(),
                   capture_output=True, text=True, timeout=60, check=True)
    (tmp_path / "etc/ddrt/ddrt.yaml").write_text("rate_hz: 200\n")
    out = subprocess.run([tmpfiles, f"--root={tmp_path}", "--create", "-"],
                         input=(SYSTEMD / "ddrt.tmpfiles.conf").read_text(), capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0, out.stderr
    uid = int(next(line for line in (tmp_path / "etc/passwd").read_text().splitlines()
                   if line.startswith("ddrt:")).split(":")[2])
    for d in ("var/lib/ddrt", "var/log/ddrt"):
        st = (tmp_path / d).stat()
        assert (st.st_uid, st.st_mode & 0o777) == (uid, 0o750), d
    cfg = (tmp_path / "etc/ddrt/ddrt.yaml").stat()
    assert (cfg.st_uid, cfg.st_mode & 0o777) == (0, 0o640)


def test_udev_rules_are_well_formed() -> None:
    """udevadm has no offline checker before systemd 254; check the grammar and the intent."""
    rules = [line for line in (SYSTEMD / "99-ddrt.rules").read_text().splitlines()
             if line.strip() and not line.lstrip().startswith("#")]
    token = re.compile(r'^\s*([A-Za-z_]+(?:\{[^}]+\})?)\s*(==|!=|\+=|-=|:=|=)\s*"([^"]*)"\s*$')
    parsed = []
    for line in rules:
        tokens = [token.match(t) for t in line.split(",")]
        assert all(tokens), f"bad token in: {line}"
        parsed.append({(m.group(1), m.group(2)): m.group(3) for m in tokens if m})
    i2c = next(r for r in parsed if r.get(("SUBSYSTEM", "==")) == "i2c-dev")
    assert i2c[("GROUP", "=")] == "i2c" and i2c[("MODE", "=")] == "0660"
    bridge = next(r for r in parsed if r.get(("SUBSYSTEM", "==")) == "tty")
    assert ("ATTRS{idVendor}", "==") in bridge and bridge[("SYMLINK", "+=")] == "ddrt-bridge"
    assert all(re.fullmatch(r"[0-9a-f]{4}", bridge[(k, "==")]) for k in ("ATTRS{idVendor}", "ATTRS{idProduct}"))
