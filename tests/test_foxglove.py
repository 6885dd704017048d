"""Foxglove and MCAP (ddrt/viz): the channels, the hand-off ring, the parameters, teleop,
`ddrt sim --mcap` read back with the mcap reader, and a websockets client on a running
daemon that speaks the protocol's opcodes itself (no SDK on the client side)."""

from __future__ import annotations

import asyncio
import csv
import json
import math
import re
import signal
import struct
from pathlib import Path
from typing import Any

import pytest

from ddrt.config import ConfigError, load_config
from ddrt.config.policy import value_at
from ddrt.loop import COLUMNS
from ddrt.viz import optional
from ddrt.viz.params import gain_declarations, gain_keys, plan_for
from ddrt.viz.ring import EXTRA, VizRing
from ddrt.viz.teleop import parse_twist
from tests.support.repo import REPO, SIM_YAML

needs_sdk = pytest.mark.skipif(not optional.available(), reason="foxglove-sdk not installed (pip install 'ddrt[foxglove]')")


# ---------------------------------------------------------------------------- pure parts

def test_ring_hands_over_every_tick_in_order_and_counts_what_it_overwrote() -> None:
    ring = VizRing(3, capacity=8)
    for i in range(5):
        ring.put([float(i), 1.0, 2.0], 0.1, 0.2, 10.0 + i, (1.0, 2.0, 3.0, 4.0, 5.0) if i % 2 else None)
    got = list(ring.take())
    assert [r[0] for r in got] == [0.0, 1.0, 2.0, 3.0, 4.0]
    assert len(got[0]) == 3 + len(EXTRA)
    assert got[1][3 + 8] == 1.0 and got[1][3 + 3:3 + 8] == (1.0, 2.0, 3.0, 4.0, 5.0)
    assert got[0][3 + 8] == 0.0
    assert list(ring.take()) == []
    for i in range(20):  # the reader fell behind: the newest capacity - 1 survive, whole
        ring.put([float(i), 0.0, 0.0], 0.0, 0.0, 0.0)
    got = list(ring.take())
    assert [r[0] for r in got] == [float(i) for i in range(20 - len(got), 20)]
    assert len(got) >= 7 and ring.dropped == 20 - len(got)


@pytest.mark.parametrize(("data", "field"), [
    (b"not json", "not JSON"), (b"[1, 2]", "expected an object"), (b'{"linear": 1}', "linear"),
    (b'{"linear": {"x": NaN}, "angular": {"z": 0}}', "NaN"), (b'{"linear": {"x": "fast"}, "angular": {}}', "linear.x"),
    (b'{"linear": {"x": 1e999}, "angular": {"z": 0}}', "linear.x"), (b'{"linear": {"x": true}, "angular": {}}', "linear.x"),
    (b'{"linear": {"x": 0.1}, "angular": {"z": [1]}}', "angular.z"), (b"\xff\xfe", "not JSON"),
    (b'{"linear": {"x": 0.1}, "angular": {"z": 0.1}, "pad": "' + b"x" * 5000 + b'"}', "bytes"),
    (b"[" * 4000, "not JSON"),
])
def test_teleop_garbage_is_refused_with_the_field(data: bytes, field: str) -> None:
    with pytest.raises(ValueError, match=re.escape(field)):
        parse_twist(data)


def test_teleop_twist_gives_linear_x_and_angular_z() -> None:
    assert parse_twist(b'{"linear": {"x": 0.25, "y": 0, "z": 0}, "angular": {"x": 0, "y": 0, "z": -0.5}}') == (0.25, -0.5)
    assert parse_twist(b'{"linear": {"x": 1}, "angular": {}}') == (1.0, 0.0)


def test_gain_parameters_are_the_live_numeric_controller_keys() -> None:
    keys = gain_keys()
    for k in ("controller.inner.kp", "controller.inner.ki", "controller.outer.k_y", "controller.outer.k_theta",
              "controller.wheel_pid.kp", "controller.heading_gain"):
        assert k in keys
    assert "controller.rate_hz" not in keys and "controller.mode" not in keys  # restart
    assert not any(k.startswith("controller.adaptation") for k in keys)  # restart
    assert not any(not k.startswith("controller.") for k in keys)
    # Each is a number the running config holds, with a unit or bounds and a meaning declared.
    cfg = load_config(SIM_YAML)
    for k in gain_declarations():
        assert isinstance(value_at(cfg, k.key), float) and len(k.decl.doc) > 10, k.key
    assert {k.key: k.decl.unit for k in gain_declarations()}["controller.outer.k_y"] == "1/m^2"


def test_a_parameter_set_is_planned_as_a_reload_and_refused_whole() -> None:
    cfg = load_config(SIM_YAML)
    keys = gain_keys()
    plan = plan_for(cfg, {"controller.inner.kp": 33, "controller.outer.k_y": 300.0}, keys)
    assert set(plan.live) == {"controller.inner.kp", "controller.outer.k_y"}
    assert plan.in_force.controller.inner.kp == 33.0
    for bad, field in [({"controller.inner.kp": 30.0, "controller.inner.ki": -1.0}, "controller.inner.ki"),
                       ({"controller.inner.kp": "abc"}, "controller.inner.kp"),
                       ({"controller.inner.kp": float("nan")}, "controller.inner.kp"),
                       ({"controller.rate_hz": 100.0}, "controller.rate_hz: not a gain parameter")]:
        with pytest.raises(ConfigError, match=re.escape(field)):
            plan_for(cfg, bad, keys)


def test_missing_sdk_is_a_clear_error_naming_the_key_and_the_pip_command(monkeypatch: pytest.MonkeyPatch,
                                                                        tmp_path: Path,
                                                                        capsys: pytest.CaptureFixture[str]) -> None:
    from ddrt.cli import main
    from ddrt.config import with_overrides
    from ddrt.viz.service import check_available

    monkeypatch.setattr(optional, "available", lambda: False)
    cfg = with_overrides(load_config(SIM_YAML), {"daemon": {"foxglove": {"enabled": True}}})
    with pytest.raises(ConfigError, match=re.escape("daemon.foxglove.enabled: true needs the foxglove-sdk") + ".*"
                       + re.escape("pip install 'ddrt[foxglove]'")):
        check_available(cfg)
    with pytest.raises(ConfigError, match="daemon.telemetry_format: mcap"):
        check_available(with_overrides(load_config(SIM_YAML), {"daemon": {"telemetry_format": "mcap"}}))
    check_available(load_config(SIM_YAML))  # csv, Foxglove off: nothing needed
    assert main(["sim", str(SIM_YAML), "--duration", "0.1", "--out", str(tmp_path), "--mcap", str(tmp_path / "r.mcap"),
                 "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "--mcap needs the foxglove-sdk package" in err and "pip install 'ddrt[foxglove]'" in err
    assert "Traceback" not in err and not (tmp_path / "metrics.json").exists()


def test_foxglove_config_is_typed() -> None:
    from ddrt.config import with_overrides

    cfg = load_config(SIM_YAML)
    assert (cfg.daemon.foxglove.enabled, cfg.daemon.foxglove.host, cfg.daemon.foxglove.port) == (False, "127.0.0.1", 8765)
    for bad, field in [({"foxglove": {"port": 70000}}, "daemon.foxglove.port"),
                       ({"foxglove": {"enabled": "yes"}}, "daemon.foxglove.enabled"),
                       ({"foxglove": {"host": ""}}, "daemon.foxglove.host"),
                       ({"telemetry_format": "parquet"}, "daemon.telemetry_format"),
                       ({"foxglove": {"bogus": 1}}, "daemon.foxglove.bogus")]:
        with pytest.raises(ConfigError, match=re.escape(field)):
            with_overrides(cfg, {"daemon": bad})


# ---------------------------------------------------------------------------- protobuf, by hand

def _varint(buf: bytes, i: int) -> tuple[int, int]:
    shift = value = 0
    while True:
        b = buf[i]
        i += 1
        value |= (b & 0x7F) << shift
        shift += 7
        if not b & 0x80:
            return value, i


def pb_fields(buf: bytes) -> dict[int, list[Any]]:
    """Field number -> values of one protobuf message (varint, double, bytes)."""
    out: dict[int, list[Any]] = {}
    i = 0
    while i < len(buf):
        key, i = _varint(buf, i)
        num, wire = key >> 3, key & 7
        if wire == 0:
            val, i = _varint(buf, i)
        elif wire == 1:
            val = struct.unpack_from("<d", buf, i)[0]
            i += 8
        elif wire == 2:
            n, i = _varint(buf, i)
            val = buf[i:i + n]
            i += n
        elif wire == 5:
            val = struct.unpack_from("<f", buf, i)[0]
            i += 4
        else:
            raise ValueError(f"wire type {wire}")
        out.setdefault(num, []).append(val)
    return out


def transform_of(buf: bytes) -> tuple[str, str, float, float, float]:
    """(parent, child, x, y, theta) of an encoded foxglove.FrameTransform."""
    f = pb_fields(buf)
    t = pb_fields(f[4][0]) if 4 in f else {}
    q = pb_fields(f[5][0]) if 5 in f else {}
    qz, qw = q.get(3, [0.0])[0], q.get(4, [0.0])[0]
    return (f[2][0].decode(), f[3][0].decode(), t.get(1, [0.0])[0], t.get(2, [0.0])[0], 2.0 * math.atan2(qz, qw))


@needs_sdk
def test_hand_parser_reads_the_sdks_frame_transform() -> None:
    from foxglove import messages as m

    msg = m.FrameTransform(parent_frame_id="odom", child_frame_id="base_link", translation=m.Vector3(x=1.5, y=-2.0, z=0.0),
                           rotation=m.Quaternion(x=0.0, y=0.0, z=math.sin(0.35), w=math.cos(0.35)))
    parent, child, x, y, th = transform_of(msg.encode())
    assert (parent, child, x, y) == ("odom", "base_link", 1.5, -2.0) and th == pytest.approx(0.7)


# ---------------------------------------------------------------------------- ddrt sim --mcap

@needs_sdk
def test_sim_mcap_has_one_message_per_tick_and_the_csvs_values(tmp_path: Path) -> None:
    pytest.importorskip("mcap", reason="the mcap reader is not installed (pip install 'ddrt[test]')")
    from mcap.reader import make_reader

    from ddrt.cli import main

    out = tmp_path / "out"
    assert main(["sim", str(SIM_YAML), "--duration", "3", "--out", str(out), "--mcap", str(out / "run.mcap"), "--quiet"]) in (0, 1)
    ticks = json.loads((out / "metrics.json").read_text())["ticks"]
    with open(out / "telemetry.csv", newline="") as f:
        reader = csv.reader(f)
        header = next(reader)
        rows = [dict(zip(header, map(float, r))) for r in reader]
    assert ticks == len(rows) > 500
    with open(out / "run.mcap", "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        counts = {c.topic: summary.statistics.channel_message_counts[i] for i, c in summary.channels.items()}
        schemas = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
        assert counts["/tf"] == counts["/tf_true"] == counts["/reference"] == counts["/state"] == ticks
        assert counts["/uncertainty"] == ticks and schemas["/uncertainty"] == "foxglove.SceneUpdate"
        assert counts["/path"] == 1
        assert schemas["/tf"] == "foxglove.FrameTransform" and schemas["/state"] == "ddrt.State"
        assert schemas["/path"] == schemas["/reference"] == "foxglove.SceneUpdate"
        states, tfs, truths, times = [], [], [], []
        for _schema, channel, message in reader.iter_messages(topics=["/state", "/tf", "/tf_true"]):
            if channel.topic == "/state":
                states.append(json.loads(message.data))
                times.append(message.log_time)
            elif channel.topic == "/tf":
                tfs.append(transform_of(message.data))
            else:
                truths.append(transform_of(message.data))
    assert len(states) == len(tfs) == len(truths) == ticks
    assert times == sorted(times)
    for i in (0, ticks // 2, ticks - 1):
        s, r = states[i], rows[i]
        assert times[i] == pytest.approx(r["t"] * 1e9, abs=1e3)
        for col in ("x_est", "y_est", "v_est", "omega_est", "v_ref", "omega_ref", "tau_l", "tau_r", "duty_l",
                    "cross_track_est", "gyro_bias"):
            assert s[col] == pytest.approx(r[col], rel=1e-8, abs=1e-12), col
        assert s["true_x"] == pytest.approx(r["x"], rel=1e-8) and s["true_v"] == pytest.approx(r["v"], rel=1e-8, abs=1e-12)
        assert s["err_v"] == pytest.approx(r["v_ref"] - r["v_est"], rel=1e-6, abs=1e-9)
        assert tfs[i][:2] == ("odom", "base_link") and truths[i][:2] == ("odom", "base_link_true")
        assert tfs[i][2] == pytest.approx(r["x_est"], rel=1e-8) and truths[i][3] == pytest.approx(r["y"], rel=1e-8, abs=1e-12)
        assert math.remainder(tfs[i][4] - r["theta_est"], 2 * math.pi) == pytest.approx(0.0, abs=1e-9)


# ---------------------------------------------------------------------------- a live daemon

WS_WAIT_S = 30.0  # cap on a message the daemon sends at once: only a hang takes longer


async def _recv_json(ws: Any, op: str, timeout: float = WS_WAIT_S, pred: Any = None) -> dict[str, Any]:
    """The next text message with this op (binary frames and other ops skipped)."""
    deadline = asyncio.get_running_loop().time() + timeout
    while True:
        left = deadline - asyncio.get_running_loop().time()
        msg = await asyncio.wait_for(ws.recv(), max(0.01, left))
        if isinstance(msg, str):
            doc = json.loads(msg)
            if doc.get("op") == op and (pred is None or pred(doc)):
                return doc


def _data_frame(msg: bytes) -> tuple[int, int, bytes]:
    """Server message data (opcode 0x01): subscription id, log time (ns), payload."""
    assert msg[0] == 0x01, msg[:1]
    sub, log_time = struct.unpack_from("<IQ", msg, 1)
    return sub, log_time, msg[13:]


@needs_sdk
@pytest.mark.slow
def test_a_websocket_client_sees_the_channels_sets_gains_and_cannot_hurt_the_daemon() -> None:
    websockets = pytest.importorskip("websockets", reason="websockets is not installed (pip install 'ddrt[test]')")
    from tests.support.daemon import START_TIMEOUT_S, start_daemon, wait_for

    d = start_daemon("--follow", daemon={"foxglove": {"enabled": True, "port": 0}})
    try:
        port = int(wait_for(lambda: (d.check_alive(), re.search(r"serving ws://127\.0\.0\.1:(\d+)", d.stderr()))[1],
                            START_TIMEOUT_S, "the Foxglove server").group(1))
        d.wait_ready()
        logs: list[str] = []

        async def session() -> None:
            async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"],
                                          max_size=None) as ws:
                info = await _recv_json(ws, "serverInfo")
                assert {"parameters", "clientPublish"} <= set(info["capabilities"]) and "json" in info["supportedEncodings"]
                channels: dict[str, dict[str, Any]] = {}
                while not {"/tf", "/tf_true", "/reference", "/state", "/timing", "/path", "/log"} <= set(channels):
                    adv = await _recv_json(ws, "advertise")
                    channels.update({c["topic"]: c for c in adv["channels"]})
                assert channels["/tf"]["schemaName"] == "foxglove.FrameTransform"
                assert channels["/tf"]["schemaEncoding"] == "protobuf"
                assert channels["/log"]["schemaName"] == "foxglove.Log"
                assert channels["/path"]["schemaName"] == "foxglove.SceneUpdate"
                state_schema = json.loads(channels["/state"]["schema"])
                assert channels["/state"]["encoding"] == "json" and set(COLUMNS) <= set(state_schema["properties"])
                subs = {1: "/state", 2: "/tf", 3: "/timing", 4: "/log", 5: "/tf_true"}
                await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                    {"id": i, "channelId": channels[t]["id"]} for i, t in subs.items()]}))
                got: dict[str, list[tuple[int, bytes]]] = {t: [] for t in subs.values()}
                while min(len(got[t]) for t in ("/state", "/tf", "/timing", "/tf_true")) < 20:
                    msg = await asyncio.wait_for(ws.recv(), WS_WAIT_S)
                    if isinstance(msg, bytes):
                        sub, log_time, payload = _data_frame(msg)
                        got[subs[sub]].append((log_time, payload))
                import time as _time

                state = json.loads(got["/state"][-1][1])
                assert state["state_name"] == "following" and math.isfinite(state["x_ref"]) and math.isfinite(state["v_est"])
                # Stamped with the tick's epoch time (not monotonic or sim time, hours or decades
                # away), however late this client got to read it.
                assert abs(_time.time_ns() - got["/state"][-1][0]) < 60e9
                parent, child, x, y, _th = transform_of(got["/tf"][-1][1])
                assert (parent, child) == ("odom", "base_link") and math.isfinite(x)
                assert transform_of(got["/tf_true"][-1][1])[1] == "base_link_true"
                timing = json.loads(got["/timing"][-1][1])
                assert 0.0 < timing["tick_us"] < 50_000
                # Parameters: the gains, named by their config keys.
                await ws.send(json.dumps({"op": "getParameters", "parameterNames": [], "id": "g1"}))
                vals = await _recv_json(ws, "parameterValues", pred=lambda m: m.get("id") == "g1")
                current = {p["name"]: p["value"] for p in vals["parameters"]}
                assert current["controller.inner.kp"] == 40.0 and "controller.outer.k_y" in current
                await ws.send(json.dumps({"op": "setParameters", "id": "s1",
                                          "parameters": [{"name": "controller.inner.kp", "value": 33.0}]}))
                vals = await _recv_json(ws, "parameterValues", pred=lambda m: m.get("id") == "s1")
                assert {p["name"]: p["value"] for p in vals["parameters"]}["controller.inner.kp"] == 33.0
                wait_for(lambda: d.request({"cmd": "gains"})["inner"]["kp"] == 33.0, WS_WAIT_S,
                         "kp 33 in the running controller")  # put in force between two ticks
                # Invalid: refused whole; neither value changes.
                await ws.send(json.dumps({"op": "setParameters", "id": "s2", "parameters": [
                    {"name": "controller.inner.kp", "value": 50.0}, {"name": "controller.inner.ki", "value": -5.0}]}))
                vals = await _recv_json(ws, "parameterValues", pred=lambda m: m.get("id") == "s2")
                assert {p["name"]: p["value"] for p in vals["parameters"]} == {"controller.inner.kp": 33.0,
                                                                              "controller.inner.ki": 100.0}
                for bad in ({"name": "controller.inner.kp", "value": "fast"}, {"name": "controller.rate_hz", "value": 1.0},
                            {"name": "controller.inner.kp"}):
                    await ws.send(json.dumps({"op": "setParameters", "id": "s3", "parameters": [bad]}))
                await asyncio.sleep(0.5)
                g = d.request({"cmd": "gains"})
                assert (g["inner"]["kp"], g["inner"]["ki"]) == (33.0, 100.0)
                # Teleop garbage on an advertised channel, an unknown channel, bad opcodes.
                await ws.send(json.dumps({"op": "advertise", "channels": [
                    {"id": 7, "topic": "/teleop", "encoding": "json", "schemaName": "geometry_msgs/Twist"}]}))
                await asyncio.sleep(0.2)
                for payload in (b"not json", b'{"linear": {"x": NaN}}', b'{"linear": {"x": "fast"}, "angular": {}}',
                                b"[1]", b"[" * 50000, b"\x00" * 10000, b'{"linear": {"x": 1e308}, "angular": {"z": 1e308}}'):
                    await ws.send(b"\x01" + struct.pack("<I", 7) + payload)
                await ws.send(b"\x01" + struct.pack("<I", 99) + b"{}")
                await ws.send(b"\xff\x00\x01")
                await ws.send("{not json")
                await ws.send(b"\x01" + struct.pack("<I", 7) + b'{"linear": {"x": 0.0}, "angular": {"z": 0.0}}')
                end = asyncio.get_running_loop().time() + WS_WAIT_S
                while asyncio.get_running_loop().time() < end and not any("teleop: message dropped" in x for x in logs):
                    try:
                        msg = await asyncio.wait_for(ws.recv(), 0.2)
                    except asyncio.TimeoutError:
                        continue
                    except websockets.ConnectionClosed:
                        break
                    if isinstance(msg, bytes) and _data_frame(msg)[0] == 4:
                        logs.append(json.dumps(pb_fields(_data_frame(msg)[2]).get(3, [b""])[0].decode()))

        asyncio.run(session())
        status = d.status()  # the daemon kept running, and estop is served
        assert status["state"] in ("following", "stopped", "stopping")
        assert d.request({"cmd": "estop"})["ok"] is True
        err = d.stderr()
        assert "parameters controller.inner.kp, controller.inner.ki refused" in err and "controller.inner.ki" in err
        assert "foxglove teleop: message dropped" in err and "Traceback" not in err
        assert any("teleop: message dropped" in line for line in logs)  # and on /log
        d.proc.send_signal(signal.SIGINT)
        assert d.proc.wait(timeout=START_TIMEOUT_S) == 0
        stats = json.loads(d.stats_json.read_text())
        assert stats["reloads"]["applied"] >= 1 and stats["error"] is None
    finally:
        d.close()


@needs_sdk
@pytest.mark.slow
def test_foxglove_teleop_drives_the_robot_and_stops_when_it_stops_publishing() -> None:
    """A client-published Twist is the velocity mode (source foxglove) with the same
    daemon.command_timeout_s: publishing at 20 Hz holds the robot at the command, silence
    brings it to rest by the timeout. The timeout is 2 s here, not 0.5, so a loaded host
    that holds this client back between two messages cannot make it look silent."""
    websockets = pytest.importorskip("websockets", reason="websockets is not installed (pip install 'ddrt[test]')")
    from tests.support.daemon import START_TIMEOUT_S, STATE_TIMEOUT_S, start_daemon, wait_for

    d = start_daemon(daemon={"foxglove": {"enabled": True, "port": 0}, "command_timeout_s": 2.0})
    try:
        port = int(wait_for(lambda: (d.check_alive(), re.search(r"serving ws://127\.0\.0\.1:(\d+)", d.stderr()))[1],
                            START_TIMEOUT_S, "the Foxglove server").group(1))
        d.wait_ready()
        seen: dict[str, Any] = {}

        async def session() -> None:
            async with websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"],
                                          max_size=None) as ws:
                await _recv_json(ws, "serverInfo")
                await ws.send(json.dumps({"op": "advertise", "channels": [
                    {"id": 3, "topic": "/cmd_vel", "encoding": "json", "schemaName": "geometry_msgs/Twist"}]}))
                await asyncio.sleep(0.2)
                twist = b'{"linear": {"x": 0.3, "y": 0, "z": 0}, "angular": {"x": 0, "y": 0, "z": 0.5}}'
                for _ in range(40):  # 2 s at 20 Hz
                    await ws.send(b"\x01" + struct.pack("<I", 3) + twist)
                    await asyncio.sleep(0.05)
                seen["driving"] = d.status()
                # Silence: the timeout, then a controlled stop.
                seen["after"] = wait_for(lambda: (st := d.status())["state"] == "stopped" and st, STATE_TIMEOUT_S,
                                         "the robot stopped by the timeout")

        asyncio.run(session())
        st = seen["driving"]
        assert st["state"] == "driving" and st["mode"] == "drive", st
        drive = st["drive"]
        assert drive["source"] == "foxglove" and drive["limited"] == {"v": 0.3, "omega": 0.5}
        assert drive["setpoint"]["v"] == pytest.approx(0.3, abs=1e-6)
        after = seen["after"]
        assert after["state"] == "stopped" and after["drive"]["timeouts"] == 1, after
        assert after["drive"]["braking_for"] == "timeout", after["drive"]
        assert "Traceback" not in d.stderr()
    finally:
        d.close()


def test_the_layout_plots_only_fields_the_channels_carry() -> None:
    from ddrt.viz.channels import STATE_FIELDS, TIMING_FIELDS, TOPICS

    layout = json.loads((REPO / "docs" / "foxglove-layout.json").read_text())
    text = json.dumps(layout)
    paths = re.findall(r'"(/[a-z_]+)\.([a-z_]+)"', text)
    assert len(paths) > 15
    for topic, field in paths:
        assert topic in TOPICS, topic
        assert field in {"/state": STATE_FIELDS, "/timing": TIMING_FIELDS}[topic], f"{topic}.{field}"
