"""Protocol v2 through the real drivers, and the v1 fallback (docs/protocol.md).

- A v1 MCU (the Python model with `protocol_version=1`, `ddrtsim://NAME?v1`) sends exactly
  v1's bytes, and a v2 host still drives the robot with it: a closed loop follows a short
  path, the Sample says nothing is measured, and the host says so once, as a warning.
- A v2 MCU, the Python model and the firmware in simavr: RealHal's Sample carries the
  battery, the hardware estop input and the drive-wheel counts, HalInfo what the MCU has.
"""

from __future__ import annotations

import logging
import math
import time

import pytest

from ddrt.config import load_config
from ddrt.loop import LoopState
from ddrt.path.spec import resolve_path
from ddrt.simrun.runner import run_sim
from hal.bridge import Bridge
from hal.wire import (
    FLAG_OUTPUTS_ON, FrameDecoder, Hello, HelloReplyV1, Packet, StateV1, encode_frame,
)
from sim_hal.mcu_emulator import DutyIntegratingEncoder, McuEmulator, TcpLink
from tests.support.firmware import require
from tests.support.following import following, tick_rows
from tests.support.repo import REPO

SCENARIO = REPO / "configs" / "scenarios" / "s_curve.yaml"
FIRMWARE_CFG = REPO / "configs" / "firmware-sim.yaml"


def emulated(url: str = "ddrtsim://robot", **sensors) -> dict:
    over: dict = {"hal": {"backend": "real", "imu": {"bus": "sim"},
                          "bridge": {"url": url, "drive_timeout_ms": 100, "state_stale_s": 0.05}}}
    if sensors:
        over["sensors"] = sensors
    return over


# ---------------------------------------------------------------------- v1 on the wire

def test_the_v1_model_sends_exactly_v1_bytes() -> None:
    """7-byte HELLO_REPLY (version 1), 10-byte STATEs, and nothing of v2 in the flags."""
    enc = DutyIntegratingEncoder(time_source=lambda: 0.0)
    mcu = McuEmulator(enc, now=0.0, state_rate_hz=200, protocol_version=1)
    out = mcu.service(0.0)
    # boot HELLO_REPLY seq 0 then STATE seq 1 at t=0: type, seq, payload, CRC, COBS
    hello, state = [f for f in out.split(b"\x00") if f][:2]
    assert len(hello) == 1 + 2 + 7 + 2 and len(state) == 1 + 2 + 10 + 2
    pkts = FrameDecoder().feed(out)
    assert pkts[0] == Packet(0, HelloReplyV1(1, 8192, 200))
    assert pkts[1] == Packet(1, StateV1(0, 0, 0, 0))
    mcu.receive(encode_frame(Packet(0, Hello())), 0.001)
    assert FrameDecoder().feed(mcu.service(0.001))[0].msg == HelloReplyV1(1, 8192, 200)
    with pytest.raises(ValueError, match="v1 MCU"):
        McuEmulator(enc, protocol_version=1, estop_wired=True)


def test_a_v2_bridge_drives_a_v1_mcu_over_a_socket(caplog) -> None:
    mcu = McuEmulator(DutyIntegratingEncoder(), now=time.monotonic(), protocol_version=1)
    with TcpLink(mcu) as link, caplog.at_level(logging.WARNING, logger="hal.bridge"):
        link.start()
        with Bridge(link.url) as b:
            assert (b.protocol_version, b.features, b.wheel_counts_per_rev) == (1, 0, 0)
            assert not b.battery_measured and not b.hw_estop_wired
            b.drive(0.5, 0.5)
            deadline = time.monotonic() + 2.0
            while time.monotonic() < deadline:
                b.drive(0.5, 0.5)
                st = b.state() if b.stats["states"] else None
                if st is not None and st.flags & FLAG_OUTPUTS_ON and st.count > 0:
                    break
                time.sleep(0.005)
            st = b.state()
            assert st.flags & FLAG_OUTPUTS_ON and st.count > 0
            assert (st.battery_mv, st.count_left, st.count_right, st.hw_estop) == (0, 0, 0, False)
            assert mcu.outputs == (0.5, 0.5)
    warnings = [r.getMessage() for r in caplog.records]
    assert len(warnings) == 1 and "protocol v1" in warnings[0] and "supply_v" in warnings[0]


def test_a_v1_mcu_still_drives_the_robot_along_a_path(caplog) -> None:
    """Done-when: the S-curve lane change through the real drivers to a v1 MCU, closed loop:
    completed, on the path within the same bound as through the v2 MCU, the battery not
    measured (NaN) and said once."""
    results = {}
    for url in ("ddrtsim://robot?v1", "ddrtsim://robot"):
        cfg = load_config(SCENARIO, emulated(url))
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="hal.bridge"):
            results[url] = run_sim(cfg, resolve_path(cfg)).metrics
        said = [r.getMessage() for r in caplog.records if "battery voltage not measured" in r.getMessage()]
        assert len(said) == (1 if url.endswith("?v1") else 0), said
    v1, v2 = results["ddrtsim://robot?v1"], results["ddrtsim://robot"]
    print(f"\ncross-track RMS (true): v1 MCU {v1['rms_cross_track_m'] * 1e3:.3f} mm, "
          f"v2 MCU {v2['rms_cross_track_m'] * 1e3:.3f} mm")
    assert v1["completed"] and v2["completed"], (v1["fault"], v2["fault"])
    assert v1["max_cross_track_m"] < 2e-3
    # the same robot and controller: only the STATE's extra bytes differ, nothing they steer by
    assert v1["rms_cross_track_m"] == pytest.approx(v2["rms_cross_track_m"], rel=0.2, abs=5e-5)


def test_the_v1_sample_measures_nothing() -> None:
    cfg = load_config(SCENARIO, emulated("ddrtsim://robot?v1", wheel_counts_per_rev=1320))
    hal, loop = following(cfg)
    try:
        info = hal.info
        assert (info.battery_measured, info.hw_estop_wired, info.wheel_counts_per_rev) == (False, False, 0)
        tick_rows(hal, loop, 50)
        s = hal.read()
        assert math.isnan(s.battery_v) and not s.hw_estop and (s.count_left, s.count_right) == (0, 0)
        assert loop.state == LoopState.FOLLOWING
    finally:
        hal.close()


# ---------------------------------------------------------------------- v2 through RealHal

def _check_v2_samples(hal, loop, tol_v: float, wheel_tol: int) -> None:
    """The Sample's battery, wheel counts and estop against the simulated robot's truth."""
    info = hal.info
    assert info.battery_measured and info.hw_estop_wired and info.wheel_counts_per_rev == 1320
    tick_rows(hal, loop, 100)
    assert loop.state == LoopState.FOLLOWING, loop.fault
    s = hal.read()
    assert abs(s.battery_v - hal.robot.battery_v) <= tol_v
    assert not s.hw_estop
    left, right = hal.robot.read_wheel_counts()
    assert left > 200 and right > 200  # the robot moved (0.5 s from rest)
    # counted since the MCU's boot, which is where the robot's counters started
    assert abs(s.count_left - left) <= wheel_tol and abs(s.count_right - right) <= wheel_tol
    hal.devices.set_estop(True)
    hal.sleep_until(hal.now() + 0.02)
    s = hal.read()
    assert s.hw_estop
    hal.sleep_until(hal.now() + 0.05)
    assert hal.robot.applied_duty == (0.0, 0.0)  # the MCU holds the outputs, whatever comes
    hal.write(0.3, 0.3)
    hal.sleep_until(hal.now() + 0.02)
    assert hal.robot.applied_duty == (0.0, 0.0) and hal.read().hw_estop
    hal.devices.set_estop(False)
    hal.sleep_until(hal.now() + 0.02)
    assert not hal.read().hw_estop


def test_the_v2_python_model_fills_the_sample() -> None:
    cfg = load_config(SCENARIO, emulated(wheel_counts_per_rev=1320))
    hal, loop = following(cfg)
    try:
        # the model reports whole mV; the wheel counts are carried to the read time at their
        # rate, and the robot's are of the latest plant step: a few counts apart
        _check_v2_samples(hal, loop, tol_v=0.0005, wheel_tol=8)
    finally:
        hal.close()


def test_the_firmware_fills_the_sample() -> None:
    require("all", "sim")
    cfg = load_config(FIRMWARE_CFG, {"sensors": {"wheel_counts_per_rev": 1320}})
    hal, loop = following(cfg)
    try:
        _check_v2_samples(hal, loop, tol_v=0.06, wheel_tol=8)
    finally:
        hal.close()
