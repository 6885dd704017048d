"""Bridge (hal/bridge.py) over loop:// and against the MCU emulator over a pty and TCP, and
RealHal's fault reactions (hal/real.py) with faults injected (sim_hal/faults.py).

Thread/pty/socket tests bound every wait (a few seconds at most) and close what they open.
"""

from __future__ import annotations

import errno
import time
from pathlib import Path
from typing import Any, Iterator

import pytest

from ddrt.runtime.clock import MonotonicClock
from ddrt.config import Config, config_from_mapping
from hal.base import HalInitError, HalIOError, HalTimeoutError, HalValueError
from hal.bridge import Bridge
from hal.mpu6050 import Mpu6050
from hal.wire import (
    FEATURE_BATTERY, FEATURE_HW_ESTOP, FEATURE_WHEELS, FLAG_BAD_FRAME, FLAG_HW_ESTOP,
    FLAG_WATCHDOG, Drive, HelloReply, HelloReplyV1, Packet, State, StateV1, Stop, encode_frame,
)
from hal.real import RealHal
from sim_hal.faults import FaultyI2cBus, SerialFaults, reset_mcu
from sim_hal.mcu_emulator import DutyIntegratingEncoder, McuEmulator, PtyLink, TcpLink
from sim_hal.mpu_emulator import ConstantGyro, MpuEmulator
from tests.support.fake_bridge import FakeClock, FakeEncoder, FakeImu
from tests.support.repo import SIM_YAML

HELLO_REPLY = HelloReply(2, 8192, 200)


def real_config(hal: dict, **sections: dict) -> Config:
    """A validated config with `hal.backend: real` and the given hal section (the seed robot)."""
    import yaml

    robot = yaml.safe_load((SIM_YAML).read_text(encoding="utf-8"))["robot"]
    return config_from_mapping({"robot": robot, "hal": {"backend": "real", **hal}, **sections})


def wait_until(cond, timeout_s: float = 2.0, step_s: float = 0.001) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if cond():
            return True
        time.sleep(step_s)
    return cond()


# --------------------------------------------------------------------------------- loop://

def loop_bridge(clock=None, reply: HelloReply = HELLO_REPLY, **kw) -> Bridge:
    """A Bridge on loop:// whose HELLO_REPLY is queued in the loop before the handshake."""
    b = Bridge("loop://", connect=False, clock=clock, **kw)
    b.port.write(encode_frame(Packet(0, reply)))
    b.connect(flush_input=False)
    return b


def feed(b: Bridge, *pkts: Packet, extra: bytes = b"") -> None:
    b.port.write(extra + b"".join(encode_frame(p) for p in pkts))


def test_loop_hello_bytes_and_no_reply_is_init_error() -> None:
    b = Bridge("loop://", connect=False, hello_timeout_s=0.05, hello_resend_s=1.0)
    real_read = type(b.port).read
    b.port.read = lambda size=1: b""  # the MCU never answers
    t0 = time.monotonic()
    with pytest.raises(HalInitError, match="no HELLO_REPLY"):
        b.connect(flush_input=False)
    assert time.monotonic() - t0 < 1.0
    assert real_read(b.port, 100) == b"\x00" + b"\x02\x01\x03\x3e\x2e\x00"  # 0x00, HELLO seq 0
    b.close()


def test_loop_handshake_drive_stop_and_close_bytes() -> None:
    b = loop_bridge()
    assert (b.protocol_version, b.counts_per_rev, b.state_rate_hz) == (2, 8192, 200)
    b.drive(0.5, -0.25)
    assert b.port.read(100) == bytes.fromhex("08 02 01 88 13 3c f6 64 03 d4 c0 00")
    assert b.last_drive_seq == 1
    b.drive(-1.0, 1.0)
    assert b.port.read(100) == encode_frame(Packet(2, Drive(-10000, 10000, 100)))
    b.stop()
    assert b.port.read(100) == encode_frame(Packet(3, Stop()))
    sent: list[bytes] = []
    write = b.port.write
    b.port.write = lambda data: (sent.append(bytes(data)), write(data))[1]
    b.close()
    b.close()
    assert sent == [encode_frame(Packet(4, Stop()))]


def test_loop_drive_rejects_bad_duty_without_sending() -> None:
    b = loop_bridge()
    with pytest.raises(HalValueError, match="duty_l"):
        b.drive(1.5, 0.0)
    with pytest.raises(HalValueError, match="duty_r"):
        b.drive(0.0, float("nan"))
    assert b.port.read(100) == b""
    b.close()


def test_loop_wrong_version_is_init_error() -> None:
    with pytest.raises(HalInitError, match="version 3"):
        loop_bridge(reply=HelloReply(3, 8192, 200))
    # each version in its own layout: a 7-byte reply saying 2, a 12-byte one saying 1
    with pytest.raises(HalInitError, match="version 2 .in a 7-byte"):
        loop_bridge(reply=HelloReplyV1(2, 8192, 200))
    with pytest.raises(HalInitError, match="version 1 .in a 12-byte"):
        loop_bridge(reply=HelloReply(1, 8192, 200))


def test_loop_state_rate_too_slow_for_stale_bound_is_init_error() -> None:
    with pytest.raises(HalInitError, match="10 Hz"):
        loop_bridge(reply=HelloReply(2, 8192, 10))


V2_FULL = HelloReply(2, 0, 250, FEATURE_BATTERY | FEATURE_HW_ESTOP | FEATURE_WHEELS, 1320)


def test_loop_v2_handshake_features_battery_estop_and_wheels(caplog) -> None:
    """A v2 MCU with everything (and no front encoder): the facts from HELLO_REPLY, the
    STATE's battery, estop flag and wheel counts (stitched across a reset like `count`)."""
    clock = FakeClock()
    with caplog.at_level("WARNING", logger="hal.bridge"):
        b = loop_bridge(clock, reply=V2_FULL)
    assert not caplog.records  # the battery is measured: nothing to say
    assert (b.protocol_version, b.counts_per_rev, b.wheel_counts_per_rev) == (2, 0, 1320)
    assert b.battery_measured and b.hw_estop_wired
    feed(b, Packet(1, State(1000, 0, 0, 0, 11_873, 500, -700)),
         Packet(2, State(5000, 0, FLAG_HW_ESTOP, 3, 11_850, 540, -740)))
    st = b.state()
    assert (st.battery_mv, st.count_left, st.count_right, st.hw_estop) == (11_850, 540, -740, True)
    assert st.left_per_s == pytest.approx(40 / 0.004) and st.right_per_s == pytest.approx(-40 / 0.004)
    assert b.stats["hw_estop_states"] == 1
    # a reboot (clock backwards): the wheel counts continue from where they were
    feed(b, Packet(0, V2_FULL), Packet(1, State(0, 0, 0, 0, 11_800, 0, 0)),
         Packet(2, State(4000, 0, 0, 0, 11_800, 10, -10)))
    st = b.state()
    assert b.stats["mcu_resets"] == 1 and not st.hw_estop
    assert (st.count_left, st.count_right) == (550, -750)
    b.close()


def test_loop_wheel_count_jump_is_a_reset() -> None:
    b = loop_bridge(FakeClock(), reply=V2_FULL)
    feed(b, Packet(1, State(100_000, 0, 0, 0, 0, 40_000, 0)),
         Packet(2, State(104_000, 0, 0, 0, 0, 0, 0)))  # 40 000 counts back in 4 ms: a reboot
    assert b.state().count_left == 40_000 and b.stats["mcu_resets"] == 1
    b.close()


def test_loop_v1_mcu_is_accepted_and_warned_about_once(caplog) -> None:
    """A v1 MCU (7-byte HELLO_REPLY, 10-byte STATEs): driven as before, nothing measured,
    and one warning that the config's supply_v stands in for the battery."""
    clock = FakeClock()
    with caplog.at_level("WARNING", logger="hal.bridge"):
        b = loop_bridge(clock, reply=HelloReplyV1(1, 8192, 200))
        assert (b.protocol_version, b.features, b.wheel_counts_per_rev) == (1, 0, 0)
        assert not b.battery_measured and not b.hw_estop_wired
        feed(b, Packet(1, StateV1(1000, 10, 0, 0)), Packet(2, StateV1(6000, 20, 0x02, 0)))
        st = b.state()
        assert (st.count, st.flags, st.battery_mv, st.count_left, st.hw_estop) == (20, 2, 0, 0, False)
        b.port.write(encode_frame(Packet(3, HelloReplyV1(1, 8192, 200))))
        b.connect(flush_input=False)  # a second handshake does not repeat the warning
        b.drive(0.5, -0.25)
    warnings = [r.getMessage() for r in caplog.records]
    assert len(warnings) == 1, warnings
    assert "protocol v1" in warnings[0] and "supply_v" in warnings[0]
    assert b.port.read(100)[-12:] == encode_frame(Packet(b.last_drive_seq, Drive(5000, -2500, 100)))
    b.close()


def test_loop_v2_mcu_without_battery_is_warned_about_too(caplog) -> None:
    with caplog.at_level("WARNING", logger="hal.bridge"):
        b = loop_bridge(reply=HelloReply(2, 8192, 250, FEATURE_HW_ESTOP))
    assert len(caplog.records) == 1 and "firmware does not measure" in caplog.records[0].getMessage()
    b.close()


def test_loop_mcu_back_with_other_features_is_an_error() -> None:
    b = loop_bridge(FakeClock(), reply=V2_FULL)
    feed(b, Packet(0, HelloReply(2, 0, 250, FEATURE_BATTERY, 0)))
    with pytest.raises(HalIOError, match="came back as protocol v2"):
        b.state()
    b.close()


def test_loop_state_newest_kept_and_staleness() -> None:
    clock = FakeClock()
    b = loop_bridge(clock)
    feed(b, Packet(1, State(1000, 10, 0, 0)), Packet(2, State(6000, 20, 0, 0)))
    st = b.state()
    assert (st.count, st.t_us, st.new) == (20, 6000, True)
    clock.t += 0.03
    st = b.state()
    assert st.new is False and st.age_s == pytest.approx(0.03)
    clock.t += 0.03
    with pytest.raises(HalTimeoutError, match="ms old"):
        b.state()
    assert b.stats["stale"] == 1
    b.close()


def test_loop_no_state_after_handshake_times_out() -> None:
    clock = FakeClock()
    b = loop_bridge(clock)
    clock.t += 0.06
    with pytest.raises(HalTimeoutError, match="no STATE"):
        b.state()
    b.close()


def test_loop_counts_lost_packets_flags_and_garbage() -> None:
    b = loop_bridge(FakeClock())
    feed(b, Packet(1, State(1000, 0, 0, 0)), Packet(2, State(2000, 1, FLAG_WATCHDOG, 0)),
         Packet(5, State(5000, 4, FLAG_BAD_FRAME, 0)))
    bad = bytearray(encode_frame(Packet(6, State(6000, 5, 0, 0))))
    bad[4] ^= 0x01
    feed(b, Packet(7, State(7000, 6, 0, 0)), extra=b"\x13\x37garbage\x00" + bytes(bad))
    st = b.state()
    s = b.stats
    assert st.count == 6
    assert s["lost_packets"] == 2 + 1  # seq 3, 4 and the corrupted 6
    assert s["watchdog_trips"] == 1 and s["mcu_bad_frames"] == 1
    assert s["crc_errors"] + s["undecodable"] == 2
    assert s["mcu_resets"] == 0
    b.close()


def test_loop_wraps_are_not_resets() -> None:
    b = loop_bridge(FakeClock())
    feed(b, Packet(1, State(0xFFFFF000, 2**31 - 10, 0, 0)),
         Packet(2, State(0x00000800, -(2**31) + 10, 0, 0)))  # 6 ms later, 20 counts on
    st = b.state()
    assert b.stats["mcu_resets"] == 0
    assert st.count == -(2**31) + 10
    b.close()


def test_loop_reset_by_hello_reply_keeps_count_continuous() -> None:
    b = loop_bridge(FakeClock())
    feed(b, Packet(1, State(50_000, 7000, 0, 0)), Packet(2, State(55_000, 7100, 0, 0)))
    assert b.state().count == 7100
    feed(b, Packet(0, HELLO_REPLY), Packet(1, State(0, 0, 0, 0)), Packet(2, State(5000, 30, 0, 0)))
    st = b.state()
    assert b.stats["mcu_resets"] == 1 and st.resets == 1
    assert b.stats["lost_packets"] == 0
    assert (st.count, st.raw_count) == (7130, 30)
    b.close()


def test_loop_reset_by_count_jump_or_clock_backwards() -> None:
    b = loop_bridge(FakeClock())
    feed(b, Packet(1, State(50_000, 100, 0, 0)),
         Packet(2, State(55_000, 900_000, 0, 0)))  # 5 ms: impossible jump
    assert b.state().count == 100 and b.stats["mcu_resets"] == 1
    feed(b, Packet(3, State(1_000, 900_010, 0, 0)))  # clock went backwards
    assert b.state().count == 100 and b.stats["mcu_resets"] == 2  # held over the reset
    feed(b, Packet(4, State(6_000, 900_030, 0, 0)))
    assert b.state().count == 120 and b.stats["mcu_resets"] == 2
    b.close()


def test_bad_arguments_name_the_field() -> None:
    with pytest.raises(ValueError, match="drive_timeout_ms"):
        Bridge("loop://", drive_timeout_ms=0, connect=False)
    with pytest.raises(ValueError, match="state_stale_s"):
        Bridge("loop://", state_stale_s=-1, connect=False)
    with pytest.raises(HalInitError, match="nonexistent"):
        Bridge("/dev/nonexistent-tty-for-test")


# ------------------------------------------------------------------ emulator over pty / TCP

@pytest.fixture(params=["pty", "tcp"])
def emu(request) -> Iterator[tuple]:
    plant = DutyIntegratingEncoder(time.monotonic)
    mcu = McuEmulator(plant, now=time.monotonic(), state_rate_hz=500)
    link = (PtyLink if request.param == "pty" else TcpLink)(mcu)
    link.start()
    yield plant, mcu, link
    link.close()


def test_emulator_handshake_drive_state_and_stop_on_close(emu) -> None:
    plant, mcu, link = emu
    with Bridge(link.url, drive_timeout_ms=200) as b:
        assert b.counts_per_rev == 8192 and b.state_rate_hz == 500
        b.drive(0.6, -0.2)
        assert wait_until(lambda: (plant.duty_l, plant.duty_r) == (0.6, -0.2))
        assert mcu.outputs == (0.6, -0.2)
        first = None
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline:
            b.drive(0.6, -0.2)
            time.sleep(0.01)
            st = b.state()
            first = st.count if first is None else first
            if st.count - first > 100:
                break
        assert st.count - first > 100  # mean duty 0.2 turns the wheel forward
        assert st.ack_seq == b.last_drive_seq or mcu.ack_seq == b.last_drive_seq
    assert wait_until(lambda: mcu.stops == 1)
    assert mcu.outputs == (0.0, 0.0) and plant.duty_l == 0.0


def test_emulator_watchdog_zeroes_within_drive_timeout(emu) -> None:
    plant, mcu, link = emu
    b = Bridge(link.url, drive_timeout_ms=60)
    try:
        b.drive(0.4, 0.4)  # then the host stops talking
        assert wait_until(lambda: plant.duty_l == 0.4)
        t_on = plant.history[-1][0]
        assert wait_until(lambda: plant.duty_l == 0.0, timeout_s=2.0)
        t_off = plant.history[-1][0]
        # 60 ms on the MCU's clock; the margins are the emulator thread's scheduling jitter
        assert 0.055 <= t_off - t_on <= 0.060 + 0.05
        assert mcu.watchdog_trips == 1
        assert wait_until(lambda: (b.poll(), b.stats["watchdog_trips"])[1] == 1)
    finally:
        b.close()


def test_emulator_wrong_version_is_init_error() -> None:
    mcu = McuEmulator(DutyIntegratingEncoder(), now=time.monotonic(), protocol_version=3)
    with PtyLink(mcu) as link:
        link.start()
        with pytest.raises(HalInitError, match="version 3"):
            Bridge(link.url)


def test_emulator_that_never_answers_is_init_error_in_bound() -> None:
    mute = SerialFaults()
    mute.mute = True
    mcu = McuEmulator(DutyIntegratingEncoder(), now=time.monotonic())
    with TcpLink(mcu, to_host=mute) as link:
        link.start()
        t0 = time.monotonic()
        with pytest.raises(HalInitError, match="no HELLO_REPLY"):
            Bridge(link.url, hello_timeout_s=0.2)
        assert time.monotonic() - t0 < 1.0
        assert wait_until(lambda: mcu.hellos >= 2)  # it did ask again


class PumpingClock(MonotonicClock):
    """The closed-loop wiring: no thread; the clock services the emulator while it waits."""

    def __init__(self, link: PtyLink) -> None:
        self.link = link

    def sleep_until(self, deadline: float) -> float:
        while True:
            now = time.monotonic()
            self.link.pump(now)
            if now >= deadline:
                return now
            time.sleep(min(0.0002, deadline - now))


def test_pump_mode_without_thread() -> None:
    plant = DutyIntegratingEncoder(time.monotonic)
    mcu = McuEmulator(plant, now=time.monotonic(), state_rate_hz=500)
    with PtyLink(mcu) as link:
        clock = PumpingClock(link)
        b = Bridge(link.url, clock=clock)
        for _ in range(5):
            b.drive(0.3, 0.1)
            clock.sleep_until(clock.now() + 0.005)
        assert mcu.outputs == (0.3, 0.1)
        assert b.state().new
        b.close()
        clock.sleep_until(clock.now() + 0.005)
        assert mcu.stops == 1


# ------------------------------------------------------------- RealHal and injected faults

@pytest.fixture()
def rig() -> Iterator[tuple]:
    """RealHal on the real drivers, wired to emulators: MCU on a pty, gyro on a faulty bus."""
    plant = DutyIntegratingEncoder(time.monotonic)
    mcu = McuEmulator(plant, now=time.monotonic(), state_rate_hz=500)
    to_host, to_mcu = SerialFaults(seed=1), SerialFaults(seed=2)
    link = PtyLink(mcu, to_host=to_host, to_mcu=to_mcu).start()
    i2c = FaultyI2cBus(MpuEmulator(ConstantGyro(0.25)))
    hal = None
    try:
        # a noise-free gyro: its repeated word is not a frozen part here (watch_repeats=False)
        hal = RealHal(Mpu6050(i2c, watch_repeats=False), Bridge(link.url, state_stale_s=0.2), hold_ticks=3)
        yield hal, mcu, link, i2c, to_host, to_mcu
    finally:
        if hal is not None:
            hal.close()
        link.close()


def ticks(hal: RealHal, n: int, dt: float = 0.01, duty: float = 0.2) -> list:
    out = []
    for _ in range(n):
        hal.write(duty, duty)
        time.sleep(dt)
        out.append(hal.read())
    return out


def test_realhal_nominal(rig) -> None:
    hal, mcu, link, i2c, *_ = rig
    assert hal.info.encoder_counts_per_rev == 8192
    assert hal.info.gyro_lsb_per_rad_s == pytest.approx(131.0 * 180 / 3.141592653589793)
    samples = ticks(hal, 10)
    # A starved emulator thread (loaded machine) shows as a hold; a starved reader as what a
    # UART does when nobody reads it: the bytes the full pty refused are lost (the emulator
    # counts them), which the bridge names as lost or broken frames. Nothing else, ever.
    allowed = {"", "encoder_hold"}
    if link.tx_dropped:
        allowed |= {"lost_packets", "bad_frame", "crc_error"}
    assert sum(s.fresh for s in samples) >= 7
    assert all(set(s.faults.split(",")) <= allowed for s in samples), ([s.faults for s in samples], link.tx_dropped)
    assert samples[-1].gyro_z_raw == round(0.25 * 180 / 3.141592653589793 * 131)
    assert samples[-1].encoder_count > samples[0].encoder_count
    assert all(b.t > a.t for a, b in zip(samples, samples[1:]))


def test_serial_corruption_is_counted_never_raised(rig) -> None:
    hal, mcu, link, i2c, to_host, to_mcu = rig
    hal.hold_ticks = 6
    to_host.corrupt_prob, to_host.garbage_prob = 0.003, 0.05
    to_mcu.corrupt_prob = 0.03
    samples = ticks(hal, 40)
    c = hal.fault_counters
    assert to_host.corrupted + to_host.garbage_bytes > 0 and to_mcu.corrupted > 0
    assert c["bridge.crc_errors"] + c["bridge.undecodable"] + c["bridge.lost_packets"] > 0
    assert mcu.bad_frames > 0 and c["bridge.mcu_bad_frames"] > 0
    named = ",".join(s.faults for s in samples)
    assert any(k in named for k in ("crc_error", "bad_frame", "lost_packets"))
    assert samples[-1].encoder_count > samples[0].encoder_count


def test_mcu_going_silent_holds_then_times_out(rig) -> None:
    hal, mcu, link, i2c, to_host, _ = rig
    last = ticks(hal, 3)[-1]
    to_host.mute = True
    held = []
    with pytest.raises(HalTimeoutError):
        for _ in range(10):
            held += ticks(hal, 1)
    stale = [s for s in held if not s.fresh]
    assert 1 <= len(stale) <= hal.hold_ticks
    assert all("encoder_hold" in s.faults for s in stale)
    assert all(s.encoder_count == stale[0].encoder_count for s in stale)
    assert len(held) <= hal.hold_ticks + 2  # at most one sample still in flight
    assert last.fresh
    hal.stop()  # the loop's safe stop does not raise, and reaches the MCU
    assert wait_until(lambda: mcu.outputs == (0.0, 0.0))
    assert hal.fault_counters["timeouts"] == 1


def test_mcu_reset_reported_and_count_continuous(rig) -> None:
    hal, mcu, link, *_ = rig
    before = ticks(hal, 5)
    reset_mcu(link)
    after = ticks(hal, 5)
    named = [s.faults for s in after]
    assert sum("mcu_reset" in f for f in named) == 1
    c = hal.fault_counters
    assert c["bridge.mcu_resets"] == 1 and c["bridge.lost_packets"] == 0
    # 0.2 duty turns ~8192 counts/s: two 10 ms ticks move ~170 counts, not the reset's jump
    assert abs(after[0].encoder_count - before[-1].encoder_count) < 1000
    assert after[-1].encoder_count > before[-1].encoder_count
    assert mcu.boots == 2 and mcu.outputs == (0.2, 0.2)  # the next DRIVE re-applied


def test_i2c_bursts_retry_then_hold_then_timeout(rig) -> None:
    hal, mcu, link, i2c, *_ = rig
    good = ticks(hal, 1)[0]
    i2c.fail_next(1, errno.EIO)  # the driver's own retry absorbs it
    s = ticks(hal, 1)[0]
    assert s.fresh and s.faults == "" and hal.imu.retries == 1
    i2c.fail_next(2, errno.EIO)  # driver gives up, RealHal retries once
    s = ticks(hal, 1)[0]
    assert s.fresh and s.faults == "imu_retry" and s.gyro_z_raw == good.gyro_z_raw
    i2c.fail_next(4, errno.EIO)  # both attempts fail: hold the last value
    s = ticks(hal, 1)[0]
    assert not s.fresh and "imu_hold" in s.faults and s.gyro_z_raw == good.gyro_z_raw
    assert ticks(hal, 1)[0].fresh  # the burst is over
    i2c.stop_answering(errno.ETIMEDOUT)
    held = []
    with pytest.raises(HalTimeoutError, match="imu"):
        for _ in range(6):
            held += ticks(hal, 1)
    assert len(held) == hal.hold_ticks and not any(s.fresh for s in held)
    c = hal.fault_counters
    assert c["imu_holds"] == 1 + hal.hold_ticks and c["imu_retries"] >= 2


# ------------------------------------------------------- RealHal with fakes (deterministic)

def test_realhal_encoder_retry_hold_and_timeout_exactly() -> None:
    enc = FakeEncoder()
    hal = RealHal(FakeImu(), enc, FakeClock(), hold_ticks=2)
    assert hal.info.gyro_full_scale_rad_s == pytest.approx(500 * 3.141592653589793 / 180)
    assert hal.info.gyro_delay_s == 0.0019  # the IMU's own figure reaches the estimator
    assert hal.read().encoder_count == 10
    enc.script = [HalIOError("x")]
    s = hal.read()
    assert s.fresh and s.faults == "encoder_retry" and s.encoder_count == 20
    enc.script = [HalIOError("x"), HalIOError("y"), "old", "old"]
    s1, s2 = hal.read(), hal.read()
    assert [s1.fresh, s2.fresh] == [False, False] and s1.encoder_count == s2.encoder_count == 20
    assert s1.faults == "encoder_retry,encoder_hold" and s2.faults == "encoder_hold"
    with pytest.raises(HalTimeoutError, match="hold_ticks=2"):
        hal.read()
    assert hal.read().fresh  # a new STATE ends the hold
    enc.script = [HalTimeoutError("stale")]
    with pytest.raises(HalTimeoutError, match="stale"):
        hal.read()


def test_realhal_first_read_never_invents_a_value() -> None:
    enc = FakeEncoder()
    enc.script = [HalIOError("x"), HalIOError("y")]
    hal = RealHal(FakeImu(), enc, FakeClock())
    with pytest.raises(HalTimeoutError):
        hal.read()


def test_realhal_write_stop_close() -> None:
    enc = FakeEncoder()
    hal = RealHal(FakeImu(), enc, FakeClock())
    assert not hal.owns_time  # hardware: the loop keeps the wall clock
    hal.write(0.5, -0.5)
    with pytest.raises(HalValueError, match="duty_r"):
        hal.write(0.1, 2.0)
    assert enc.drives == [(0.5, -0.5)]
    hal.stop()  # the device raised; stop() must not
    hal.close()
    hal.close()
    assert enc.closed == 1 and hal.fault_counters["stop_errors"] == 2


# ------------------------------------------------------------------------ from_config

def test_from_config_sim_bus_and_pty_url() -> None:
    mcu = McuEmulator(DutyIntegratingEncoder(time.monotonic), now=time.monotonic(),
                      state_rate_hz=500)
    with PtyLink(mcu) as link:
        link.start()
        cfg = real_config({"imu": {"bus": "sim"}, "bridge": {"url": link.url, "drive_timeout_ms": 200}},
                          sensors={"gyro_range_dps": 1000})  # the driver's range comes from sensors:
        hal = RealHal.from_config(cfg, MonotonicClock(),
                                  i2c_bus=MpuEmulator(ConstantGyro(1.0)))
        try:
            hal.write(0.1, 0.1)
            time.sleep(0.01)
            s = hal.read()
            assert s.fresh and s.gyro_z_raw == round(1.0 * 180 / 3.141592653589793 * 32.8)
            assert hal.encoder.drive_timeout_ms == 200
        finally:
            hal.close()
        assert wait_until(lambda: mcu.stops >= 1) and mcu.outputs == (0.0, 0.0)


@pytest.mark.parametrize("hal, sections, key", [
    ({"imu": {"bus": 1}}, {}, "hal.bridge.url"),
    ({"bridge": {"url": "loop://"}}, {}, "hal.imu.bus"),
    ({"imu": {"bus": "two"}, "bridge": {"url": "loop://"}}, {}, "hal.imu.bus"),
    ({"imu": {"bus": -1}, "bridge": {"url": "loop://"}}, {}, "hal.imu.bus"),
    ({"imu": {"bus": "sim"}, "bridge": {"url": "loop://"}}, {}, "hal.imu.bus"),
    ({"imu": {"bus": 1}, "bridge": {"url": "loop://"}}, {"sensors": {"gyro_range_dps": 300}},
     "sensors.gyro_range_dps"),
    ({"imu": {"bus": 1, "address": 0x78}, "bridge": {"url": "loop://"}}, {}, "hal.imu.address"),
    ({"imu": {"bus": 1, "dlpf_cfg": 9}, "bridge": {"url": "loop://"}}, {}, "hal.imu.dlpf_cfg"),
    ({"imu": {"bus": 1, "sample_rate_div": 256}, "bridge": {"url": "loop://"}}, {}, "hal.imu.sample_rate_div"),
    ({"imu": {"bus": 1}, "bridge": {"url": "loop://", "state_stale_s": 0}}, {}, "hal.bridge.state_stale_s"),
    ({"imu": {"bus": 1}, "bridge": {"url": "loop://", "drive_timeout_ms": 0}}, {}, "hal.bridge.drive_timeout_ms"),
    ({"imu": {"bus": 1}, "bridge": {"url": "loop://", "baudrate": 0}}, {}, "hal.bridge.baudrate"),
    ({"imu": {"bus": 1}, "bridge": {"url": ""}}, {}, "hal.bridge.url"),
    ({"imu": {"bus": 1}, "bridge": {"url": "loop://"}, "motors": "can"}, {}, "hal.motors"),
    ({"imu": {"bus": 1}, "bridge": {"url": "loop://"}, "hold_ticks": 1001}, {}, "hal.hold_ticks"),
    ({"imu": {"bus": 1}, "bridge": {"url": "loop://"}, "motors": "pwm_sysfs",
      "pwm_sysfs": {"channels": [0]}}, {}, "hal.pwm_sysfs.channels"),
    ({"imu": {"bus": 1}, "bridge": {"url": "loop://"}, "motors": "pwm_sysfs"}, {},
     "hal.pwm_sysfs.direction_gpios"),
    ({"imu": {"bus": 1}, "bridge": {"url": "loop://"}, "pwm_sysfs": {"root": 5}}, {}, "hal.pwm_sysfs.root"),
])
def test_real_backend_config_errors_name_the_key(hal: dict, sections: dict, key: str) -> None:
    """The walker checks the real backend's keys when the file loads; from_config what only
    opening needs (the emulated bus)."""
    with pytest.raises(ValueError, match=r"(^|\s)" + key.replace(".", r"\.") + ":"):
        RealHal.from_config(real_config(hal, **sections), FakeClock())


def test_imu_gyro_range_key_is_gone_and_says_where_it_went() -> None:
    with pytest.raises(ValueError, match=r"hal\.imu\.gyro_range_dps: .*sensors\.gyro_range_dps"):
        real_config({"imu": {"bus": 1, "gyro_range_dps": 250}, "bridge": {"url": "loop://"}})


def test_from_config_refuses_a_config_without_the_real_devices() -> None:
    """A config loaded for the sim backend has no bus or URL: opening it for real says so."""
    from dataclasses import replace

    cfg = real_config({"imu": {"bus": 1}, "bridge": {"url": "loop://"}})
    sim_cfg = replace(cfg, hal=replace(cfg.hal, backend="sim", imu=replace(cfg.hal.imu, bus=None)))
    with pytest.raises(ValueError, match=r"hal\.imu\.bus: missing"):
        RealHal.from_config(sim_cfg, FakeClock())


def first_read(hal: RealHal, cap_s: float = 30.0) -> Any:
    """The first Sample once the emulated MCU's first STATE is in (its thread may not have run
    yet on a loaded host); the cap is only against a hang."""
    deadline = time.monotonic() + cap_s
    while True:
        try:
            return hal.read()
        except HalTimeoutError as exc:
            if "no STATE received yet" not in str(exc) or time.monotonic() > deadline:
                raise
            time.sleep(0.005)


def test_from_config_pwm_sysfs_motors(tmp_path: Path) -> None:
    for rel in ("class/pwm/pwmchip0/pwm0", "class/pwm/pwmchip0/pwm1",
                "class/gpio/gpio5", "class/gpio/gpio6"):
        (tmp_path / rel).mkdir(parents=True)
    mcu = McuEmulator(DutyIntegratingEncoder(time.monotonic), now=time.monotonic(),
                      state_rate_hz=500)
    with TcpLink(mcu) as link:
        link.start()
        cfg = real_config({"imu": {"bus": "sim"}, "bridge": {"url": link.url},
                           "motors": "pwm_sysfs",
                           "pwm_sysfs": {"chip": 0, "channels": [0, 1], "period_ns": 40000,
                                         "direction_gpios": [5, 6], "root": str(tmp_path)}})
        hal = RealHal.from_config(cfg, MonotonicClock(), i2c_bus=MpuEmulator(ConstantGyro()))
        pwm0 = tmp_path / "class/pwm/pwmchip0/pwm0"
        try:
            hal.write(0.5, -0.25)
            assert (pwm0 / "duty_cycle").read_text() == "20000"
            assert (tmp_path / "class/gpio/gpio6/value").read_text() == "0"
            assert mcu.drives_accepted == 0  # the MCU only counts the encoder here
            assert first_read(hal).encoder_count == 0
        finally:
            hal.close()
        assert (pwm0 / "duty_cycle").read_text() == "0"
        assert (pwm0 / "enable").read_text() == "0"


def test_realhal_refuses_an_mcu_without_a_front_encoder_clearly() -> None:
    """Protocol v2 lets an MCU say it has no front encoder; the estimator needs one, so the
    backend says so at start instead of dividing by zero later."""
    enc = FakeEncoder()
    enc.counts_per_rev = 0
    with pytest.raises(HalInitError, match="no front encoder"):
        RealHal(FakeImu(), enc, FakeClock())
