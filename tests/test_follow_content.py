"""`ddrt ctl follow FILE` sends the file's content, so a sandboxed daemon
(ProtectHome, PrivateTmp, its own user) can follow a user's file; the socket's `follow`
takes `content` + `format` + `name`, checked as strictly as a file."""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.support.daemon import DaemonProc, ctl, ready_daemon, wait_for

LIMIT = 3000


@pytest.fixture(scope="module")
def daemon() -> Iterator[DaemonProc]:
    with ready_daemon(paths={"max_file_bytes": LIMIT}) as d:
        yield d


@pytest.fixture()
def idle(daemon: DaemonProc) -> DaemonProc:
    daemon.request({"cmd": "stop"})
    wait_for(lambda: daemon.status()["state"] in ("idle", "stopped"), 8.0, "idle")
    return daemon


def line_from_robot(d: DaemonProc, length: float = 0.2) -> list[list[float]]:
    p = d.status()["pose"]
    x, y, th = p["x"], p["y"], p["theta"]
    return [[round(x + s * length * math.cos(th), 4), round(y + s * length * math.sin(th), 4)] for s in (0.0, 0.5, 1.0)]


def csv_text(pts: list[list[float]]) -> str:
    return "x,y\n" + "".join(f"{a},{b}\n" for a, b in pts)


def test_ctl_follow_sends_the_content_not_the_name(idle: DaemonProc, tmp_path: Path) -> None:
    f = tmp_path / "mine.csv"
    f.write_text(csv_text(line_from_robot(idle)))
    res = ctl(idle.socket, "follow", str(f))
    assert res.returncode == 0, res.stdout + res.stderr
    assert json.loads(res.stdout)["state"] == "following"
    assert "following mine.csv (sent as content)" in idle.stderr()
    idle.request({"cmd": "stop"})


def test_content_form_over_the_socket_yaml(idle: DaemonProc) -> None:
    pts = line_from_robot(idle)
    text = "points:\n" + "".join(f"  - [{a}, {b}]\n" for a, b in pts) + "speed: 0.2\n"
    r = idle.request({"cmd": "follow", "content": text, "format": "yaml", "name": "p.yaml"})
    assert r["ok"] is True, r
    idle.request({"cmd": "stop"})


@pytest.mark.parametrize("extra, needle", [
    ({"content": 5}, "content: expected"),
    ({"content": "x,y\n0,0\n", "format": "json"}, "format: expected 'csv' or 'yaml'"),
    ({"content": "x,y\n0,0\n", "name": "../etc/x.csv"}, "name: expected a file name"),
    ({"content": "x,y\n0,0\n", "format": "csv", "speed": 1}, "speed: not a key of the content form"),
    ({"content": "x,y\n" + "0.1,0.2\n" * 500, "format": "csv"}, f"more than paths.max_file_bytes = {LIMIT}"),
    ({"content": "x,y\n\ud800,0\n", "format": "csv"}, "not valid UTF-8"),
    ({"content": "x,y\n0,0\n", "format": "csv", "name": "a.csv"}, "a.csv (sent as content)"),
    ({"content": "file: pts.csv\nspeed: 0.2\n", "format": "yaml", "name": "r.yaml"}, "key 'file': 'pts.csv' is relative"),
    ({"content": "file: /nonexistent/ddrt/pts.csv\n", "format": "yaml"}, "the daemon reads that file itself, as uid"),
])
def test_bad_content_is_refused_naming_the_field(idle: DaemonProc, extra: dict[str, Any], needle: str) -> None:
    before = idle.status()["state"]
    r = idle.request({"cmd": "follow", **extra})
    assert r["ok"] is False and needle in r["error"], r
    assert "Traceback" not in r["error"]
    assert idle.status()["state"] == before


def test_ctl_follow_refuses_a_large_or_binary_file_before_sending(idle: DaemonProc, tmp_path: Path) -> None:
    cfg = idle.config
    big = tmp_path / "big.csv"
    big.write_text("x,y\n" + "0.1,0.2\n" * 1000)
    res = ctl(idle.socket, "--config", str(cfg), "follow", str(big))
    assert res.returncode == 1 and f"more than paths.max_file_bytes = {LIMIT}" in json.loads(res.stdout)["error"]
    binary = tmp_path / "b.csv"
    binary.write_bytes(b"x,y\n\xff\xfe\n")
    res = ctl(idle.socket, "follow", str(binary))
    assert res.returncode == 1 and "not UTF-8" in json.loads(res.stdout)["error"]
    res = ctl(idle.socket, "follow", str(tmp_path / "missing.csv"))
    assert res.returncode == 1 and "cannot read" in json.loads(res.stdout)["error"]
    assert os.path.exists(idle.socket)
