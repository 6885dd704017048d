"""The bridge as the daemon's child (ddrt/service/ros2proc.py) and as a command: restarted
when it dies, not when it cannot run (exit 2), stopped on close; `ddrt ros2` refuses bad
input with exit 2 and one line; the `stream` command is for processes, not `ddrt ctl`."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from ddrt.cli import build_parser
from ddrt.service import ros2proc
from ddrt.service.ros2proc import BridgeProcess
from tests.support.daemon import wait_for
from tests.support.repo import REPO


def test_a_bridge_that_dies_is_started_again_and_close_stops_it(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(ros2proc, "RESTART_S", 0.1)
    marker = tmp_path / "starts"
    script = f"open({str(marker)!r}, 'a').write('x'); import time; time.sleep(0.3); raise SystemExit(1)"
    b = BridgeProcess("unused", "unused", argv=[sys.executable, "-c", script])
    try:
        wait_for(lambda: marker.exists() and len(marker.read_text()) >= 3, 30.0, "three starts")
    finally:
        b.close()
    n = len(marker.read_text())
    time.sleep(0.6)
    assert len(marker.read_text()) == n  # closed: no more starts
    assert b.proc is not None and b.proc.poll() is not None


def test_a_bridge_that_cannot_run_is_not_restarted(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(ros2proc, "RESTART_S", 0.05)
    marker = tmp_path / "starts"
    b = BridgeProcess("unused", "unused", argv=[sys.executable, "-c", f"open({str(marker)!r}, 'a').write('x'); "
                                                                     "raise SystemExit(2)"])
    try:
        wait_for(lambda: b.proc is not None and b.proc.poll() is not None, 30.0, "the first exit")
        time.sleep(0.5)
        assert marker.read_text() == "x"
    finally:
        b.close()


def test_close_stops_a_running_bridge_with_sigterm() -> None:
    b = BridgeProcess("unused", "unused", argv=[sys.executable, "-c", "import time; time.sleep(60)"])
    wait_for(lambda: b.proc is not None, 30.0, "the start")
    t0 = time.monotonic()
    b.close()
    assert b.proc is not None and b.proc.returncode == -15 and time.monotonic() - t0 < ros2proc.STOP_S


@pytest.mark.parametrize("args, text", [
    (["--domain-id", "300"], "domain_id: must be <= 232"),
    (["--namespace", "bad ns!"], "namespace: expected a ROS namespace"),
    (["--config", "/nonexistent/ddrt.yaml"], "/nonexistent/ddrt.yaml"),
])
def test_ddrt_ros2_refuses_bad_input_in_one_line(args: list[str], text: str) -> None:
    out = subprocess.run([sys.executable, "-m", "ddrt.cli", "ros2", "--socket", "/tmp/none.sock", *args],
                         cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.returncode == 2, out.stderr
    assert text in out.stderr and "Traceback" not in out.stderr


def test_ctl_does_not_offer_the_stream_command() -> None:
    with pytest.raises(SystemExit):
        build_parser().parse_args(["ctl", "stream"])


def test_a_daemon_streams_its_state_to_whoever_asks_over_its_socket() -> None:
    import socket as so

    from ddrt.service.stream import decode
    from tests.support.daemon import ready_daemon

    with ready_daemon(path=None) as d, so.socket(so.AF_UNIX, so.SOCK_DGRAM) as r:
        r.bind(b"\0ddrt-test-daemon-stream")
        r.settimeout(10.0)
        bad = d.request({"cmd": "stream", "to": "@ddrt-test-daemon-stream", "rate_hz": 0})
        assert bad["ok"] is False and "rate_hz" in bad["error"]
        reply = d.request({"cmd": "stream", "to": "@ddrt-test-daemon-stream", "rate_hz": 50})
        assert reply["ok"] is True
        states = [dict(zip(reply["fields"], decode(r.recv(4096)))) for _ in range(20)]
        pose = d.status()["pose"]
        assert all(b["seq"] > a["seq"] for a, b in zip(states, states[1:]))
        assert states[-1]["mono"] - states[0]["mono"] == pytest.approx(19 / 50, rel=0.5)
        assert states[-1]["x"] == pytest.approx(pose["x"], abs=1e-4)
        assert states[-1]["theta"] == pytest.approx(pose["theta"], abs=1e-3)


def _bridges_of(pid: int) -> list[int]:
    out = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
                cmd = (entry / "cmdline").read_bytes()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid and b"ddrt.ros2" in cmd:
                out.append(int(entry.name))
    return out


def test_telemetry_format_rosbag2_records_the_topics_and_a_killed_daemon_leaves_no_bridge() -> None:
    """rosbag2 without ROS 2: the bridge records only (--no-dds); SIGTERM closes the bag
    readable. A daemon killed outright: its bridge notices and exits."""
    pytest.importorskip("cyclonedds", reason="the ros2 extra")
    pytest.importorskip("rosbags", reason="the ros2 extra")
    import os
    import signal

    from rosbags.highlevel import AnyReader

    from tests.support.daemon import start_daemon

    d = start_daemon(path=None, daemon={"telemetry_format": "rosbag2", "ros2": {"odom_rate_hz": 20.0}})
    try:
        d.wait_ready()
        bridge = wait_for(lambda: _bridges_of(d.proc.pid), 60.0, "the recording bridge")[0]
        wait_for(lambda: "sending the loop's state to @ddrt-ros2" in d.stderr(), 60.0, "the bridge's stream")
        for _ in range(20):  # 2 s at 10 Hz, inside the 0.5 s command timeout
            assert d.request({"cmd": "drive", "v": 0.1, "omega": 0.0})["ok"]
            time.sleep(0.1)
        time.sleep(1.0)
        d.proc.send_signal(signal.SIGTERM)
        assert d.proc.wait(60) == 0
        wait_for(lambda: not Path(f"/proc/{bridge}").exists(), 30.0, "the bridge's exit")
        bags = sorted(d.telemetry_dir.glob("rosbag2-*"))
        assert len(bags) == 1 and (bags[0] / "metadata.yaml").exists(), list(d.telemetry_dir.iterdir())
        assert (d.telemetry_dir / "telemetry.csv").exists()  # the CSV as well
        with AnyReader([bags[0]]) as reader:
            topics = {c.topic: c for c in reader.connections}
            odom = [reader.deserialize(raw, c.msgtype) for c, _t, raw in reader.messages([topics["/odom"]])]
            static = list(reader.messages([topics["/tf_static"]]))
        assert len(odom) >= 20 and len(static) == 1
        assert max(m.twist.twist.linear.x for m in odom) == pytest.approx(0.1, rel=0.2)
    finally:
        d.close()
    # Killed outright (SIGKILL): the bridge it started goes too.
    d = start_daemon(path=None, daemon={"telemetry_format": "rosbag2"})
    try:
        d.wait_ready()
        bridge = wait_for(lambda: _bridges_of(d.proc.pid), 60.0, "the recording bridge")[0]
        os.kill(d.proc.pid, signal.SIGKILL)
        wait_for(lambda: not Path(f"/proc/{bridge}").exists() or b"Z" in Path(f"/proc/{bridge}/stat").read_bytes()
                 .rsplit(b")", 1)[1][:3], 30.0, "the orphaned bridge's exit")
    finally:
        d.close()


def test_ddrt_ros2_names_a_cyclone_configuration_it_cannot_use() -> None:
    """A CYCLONEDDS_URI Cyclone DDS refuses (an unknown element): exit 2, Cyclone's reason and
    ours, no traceback; the bridge's own settings (ddrt/ros2/node.py) do not hide the user's."""
    pytest.importorskip("cyclonedds", reason="the ros2 extra")
    import os

    env = dict(os.environ, CYCLONEDDS_URI="<CycloneDDS><Domain><Bogus>1</Bogus></Domain></CycloneDDS>")
    out = subprocess.run([sys.executable, "-m", "ddrt.cli", "ros2", "--socket", "/tmp/none.sock", "--domain-id", "7"],
                         cwd=REPO, capture_output=True, text=True, timeout=120, env=env)
    assert out.returncode == 2, out.stderr
    assert "Bogus: unknown element" in out.stderr
    assert "cannot join domain 7 (CYCLONEDDS_URI=" in out.stderr and "Traceback" not in out.stderr


def test_the_bridges_domain_ignores_fast_dds_type_information_and_keeps_the_users_settings(tmp_path: Path) -> None:
    """The node's domain gets IgnoreTypeInformation for eProsima (1.15), the Kilted fix, and a
    user's CYCLONEDDS_URI still applies after it (here: Cyclone's configuration trace, which
    shows both)."""
    pytest.importorskip("cyclonedds", reason="the ros2 extra")
    import os

    trace = tmp_path / "cyclone.log"
    user = f"<CycloneDDS><Domain><Tracing><Category>config</Category><OutputFile>{trace}</OutputFile></Tracing>" \
           "</Domain></CycloneDDS>"
    script = "from ddrt.ros2.node import Node; Node('probe', '/', 9)"
    out = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=120,
                         env=dict(os.environ, CYCLONEDDS_URI=user))
    assert out.returncode == 0, out.stderr
    text = trace.read_text()
    assert "Domain/Compatibility/IgnoreTypeInformation/#text: 1.15" in text
    assert "Domain/Tracing/Category/#text: config" in text
