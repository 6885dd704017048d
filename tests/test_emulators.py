"""The emulated devices themselves, deterministically (sim_hal/*): firmware model driven by
`receive`/`service` on a fake clock, the register file, and the fault injectors."""

from __future__ import annotations

import errno
import math

import pytest

from hal.wire import (
    FLAG_BAD_FRAME, FLAG_OUTPUTS_ON, FLAG_WATCHDOG, Drive, FrameDecoder, Hello, HelloReply,
    Packet, State, Stop, Unknown, encode_frame,
)
from sim_hal.faults import FaultyI2cBus, SerialFaults, reset_mcu
from sim_hal.mcu_emulator import DutyIntegratingEncoder, McuEmulator
from sim_hal.mpu_emulator import ConstantGyro, MpuEmulator, SineGyro


class FakeTime:
    def __init__(self) -> None:
        self.t = 0.0

    def __call__(self) -> float:
        return self.t


@pytest.fixture()
def rig():
    clock = FakeTime()
    plant = DutyIntegratingEncoder(clock, counts_per_s_at_full=10000.0)
    mcu = McuEmulator(plant, now=0.0, state_rate_hz=100)
    dec = FrameDecoder()
    return clock, plant, mcu, dec


def run(clock: FakeTime, mcu: McuEmulator, dec: FrameDecoder, until: float, step: float = 0.001):
    out = []
    while clock.t < until - 1e-12:
        clock.t = round(clock.t + step, 9)
        out += dec.feed(mcu.service(clock.t))
    return out


def test_boot_announces_and_streams(rig) -> None:
    clock, plant, mcu, dec = rig
    pkts = dec.feed(mcu.service(0.0))
    assert pkts[0] == Packet(0, HelloReply(2, 8192, 100))
    assert isinstance(pkts[1].msg, State) and pkts[1].seq == 1
    more = run(clock, mcu, dec, 0.1)
    assert len(more) == 10  # 100 Hz for 0.1 s
    assert [p.seq for p in more] == list(range(2, 12))
    assert [p.msg.t_us for p in more] == [10_000 * k for k in range(1, 11)]


def test_drive_applied_at_once_and_acked(rig) -> None:
    clock, plant, mcu, dec = rig
    clock.t = 0.0005
    mcu.receive(encode_frame(Packet(7, Drive(5000, -2500, 100))), clock.t)
    assert (plant.duty_l, plant.duty_r) == (0.5, -0.25)
    pkts = run(clock, mcu, dec, 0.05)
    last = pkts[-1].msg
    assert last.ack_seq == 7 and last.flags & FLAG_OUTPUTS_ON
    # the wheel integrates the mean duty (0.125 * 10000 counts/s for ~0.05 s)
    assert last.count == pytest.approx(0.125 * 10000 * (0.05 - 0.0005), abs=2)


def test_hello_answered(rig) -> None:
    clock, plant, mcu, dec = rig
    dec.feed(mcu.service(0.0))
    mcu.receive(encode_frame(Packet(0, Hello())), 0.001)
    assert any(isinstance(p.msg, HelloReply) for p in dec.feed(mcu.service(0.001)))


def test_watchdog_zeroes_after_timeout_and_flags(rig) -> None:
    clock, plant, mcu, dec = rig
    mcu.receive(encode_frame(Packet(1, Drive(3000, 3000, 50))), 0.0)
    run(clock, mcu, dec, 0.049)
    assert mcu.outputs == (0.3, 0.3)
    pkts = run(clock, mcu, dec, 0.051)
    assert mcu.outputs == (0.0, 0.0) and mcu.watchdog_trips == 1
    assert plant.history[-1] == (pytest.approx(0.050), 0.0, 0.0)
    pkts += run(clock, mcu, dec, 0.07)
    flags = [p.msg.flags for p in pkts if isinstance(p.msg, State)]
    assert flags[0] & FLAG_WATCHDOG and not flags[0] & FLAG_OUTPUTS_ON
    assert not any(f & FLAG_WATCHDOG for f in flags[1:])  # reported once


def test_stop_zeroes_and_disarms(rig) -> None:
    clock, plant, mcu, dec = rig
    mcu.receive(encode_frame(Packet(1, Drive(3000, 3000, 20))), 0.0)
    mcu.receive(encode_frame(Packet(2, Stop())), 0.005)
    assert mcu.outputs == (0.0, 0.0)
    run(clock, mcu, dec, 0.1)
    assert mcu.watchdog_trips == 0 and mcu.ack_seq == 2


@pytest.mark.parametrize("bad", [Drive(10001, 0, 100), Drive(0, -10001, 100),
                                 Drive(100, 100, 0), Drive(100, 100, 1001)])
def test_out_of_range_drive_ignored(rig, bad: Drive) -> None:
    clock, plant, mcu, dec = rig
    mcu.receive(encode_frame(Packet(1, Drive(2000, 2000, 100))), 0.0)
    mcu.receive(encode_frame(Packet(2, bad)), 0.001)
    assert mcu.outputs == (0.2, 0.2) and mcu.ack_seq == 1 and mcu.drives_rejected == 1


def test_unknown_type_ignored_and_bad_crc_flagged(rig) -> None:
    clock, plant, mcu, dec = rig
    dec.feed(mcu.service(0.0))
    mcu.receive(encode_frame(Packet(1, Unknown(0x33, b"xy"))), 0.001)
    frame = bytearray(encode_frame(Packet(2, Drive(1, 1, 10))))
    frame[3] ^= 0x10
    mcu.receive(bytes(frame), 0.002)
    assert mcu.outputs == (0.0, 0.0) and mcu.bad_frames == 1
    states = [p.msg for p in run(clock, mcu, dec, 0.03)]
    assert states[0].flags & FLAG_BAD_FRAME and not states[1].flags & FLAG_BAD_FRAME


def test_reset_restarts_seq_clock_and_count(rig) -> None:
    clock, plant, mcu, dec = rig
    mcu.receive(encode_frame(Packet(1, Drive(10000, 10000, 1000))), 0.0)
    run(clock, mcu, dec, 0.1)
    plant.add_counts(5000)
    reset_mcu(mcu, clock.t)
    assert mcu.outputs == (0.0, 0.0) and mcu.boots == 2
    pkts = dec.feed(mcu.service(clock.t))
    assert pkts[0] == Packet(0, HelloReply(2, 8192, 100))
    assert pkts[1].seq == 1 and pkts[1].msg.t_us == 0 and pkts[1].msg.count == 0


def test_t_us_and_count_wrap(rig) -> None:
    clock, plant, mcu, dec = rig
    mcu.t_us_offset = 0xFFFFFFFF - 5000
    plant.add_counts(2**31 - 10)
    mcu.reset(0.0)  # count restarts at 0 after reset: move again past the i32 edge
    plant.add_counts(2**31 + 5)
    states = [p.msg for p in run(clock, mcu, dec, 0.02) if isinstance(p.msg, State)]
    assert states[0].t_us > states[-1].t_us  # wrapped past 2^32
    assert states[-1].count == -(2**31) + 5


def test_serial_faults_are_seeded_and_counted() -> None:
    data = bytes(range(1, 200)) * 5
    a = SerialFaults(seed=4, drop_prob=0.05, corrupt_prob=0.05, garbage_prob=1.0)
    b = SerialFaults(seed=4, drop_prob=0.05, corrupt_prob=0.05, garbage_prob=1.0)
    out = a(data)
    assert out == b(data) and out != data
    assert a.dropped > 0 and a.corrupted > 0 and a.garbage_bytes > 0
    assert len(out) == len(data) - a.dropped + a.garbage_bytes
    a.mute = True
    assert a(data) == b""


def test_faulty_i2c_bus_burst_and_dead() -> None:
    bus = FaultyI2cBus(MpuEmulator(ConstantGyro()))
    bus.fail_next(2, errno.EIO)
    for _ in range(2):
        with pytest.raises(OSError) as ei:
            bus.read_byte_data(0x68, 0x75)
        assert ei.value.errno == errno.EIO
    assert bus.read_byte_data(0x68, 0x75) == 0x68
    bus.stop_answering(errno.ETIMEDOUT)
    with pytest.raises(OSError):
        bus.read_i2c_block_data(0x68, 0x47, 2)
    bus.resume()
    assert bus.read_i2c_block_data(0x68, 0x47, 2) == [0, 0]
    assert bus.injected == 3


def test_mpu_emulator_quantises_at_configured_range() -> None:
    bus = MpuEmulator(ConstantGyro(math.radians(100.0)))
    bus.write_byte_data(0x68, 0x6B, 0x01)
    bus.write_byte_data(0x68, 0x1B, 3 << 3)  # +-2000 dps, 16.4 LSB/dps
    hi, lo = bus.read_i2c_block_data(0x68, 0x47, 2)
    assert (hi << 8) | lo == 1640
    with pytest.raises(OSError):
        bus.read_byte_data(0x69, 0x75)


def test_sine_gyro_follows_time() -> None:
    t = FakeTime()
    g = SineGyro(2.0, 1.0, t)
    t.t = 0.25
    assert g.gyro_z_rad_s() == pytest.approx(2.0)
