"""Protocol v2 conformance (docs/protocol.md), one suite over both microcontroller models:
the Python model (sim_hal/mcu_emulator.py) and the reference firmware (firmware/) running in
simavr (sim_hal/firmware_sim.py). Every test runs on both; times are simulated. The v1
fallback (a v2 host and a v1 MCU) is tests/test_mcu_v1_fallback.py.

The models differ where hardware does, and the suite allows exactly that: the firmware's
PWM has 400 steps (duty +-1/400), its bytes take their time on a 115200-baud line (a
command acts when its last byte is in, `send` returns that time), its clock ticks every
100 us (the DRIVE watchdog fires up to one tick after its deadline, never before; the estop
input is read at each tick), and its battery reading is a 10-bit ADC behind a divider
(BATTERY_TOL_MV).
"""

from __future__ import annotations

import random
from dataclasses import dataclass

import pytest

from hal.wire import (
    FEATURE_BATTERY, FEATURE_HW_ESTOP, FEATURE_WHEELS, FLAG_BAD_FRAME, FLAG_HW_ESTOP,
    FLAG_OUTPUTS_ON, FLAG_WATCHDOG, Drive, FrameDecoder, Hello, HelloReply, Packet, State, Stop,
    Unknown, encode_frame, seq_gap, wire_bytes,
)
from tests.support.firmware import require
from sim_hal.mcu_emulator import McuEmulator

DUTY_TOL = 1.0 / 400 + 1e-6  # the firmware's PWM resolution (Timer1 TOP = 400)
ACT_S = 0.0003  # a command acts this soon after its last byte is in (frame decode, next PWM period)
STATE_HZ = 250  # the firmware's stream rate; the Python model is built with the same
FEATURES = FEATURE_BATTERY | FEATURE_HW_ESTOP  # the default build's (no drive-wheel encoders)
BOOT_REPLY = HelloReply(2, 8192, STATE_HZ, FEATURES, 0)
WHEEL_CPR = 1320  # the wheel build's drive-wheel counts/rev (11 lines x 4 x 30:1)
# the firmware's battery reading: 10-bit ADC on 1.1 V behind 100k/5.6k is 20.3 mV a step;
# two steps, and simavr scales its ADC by 1023 (not 1024): 0.1 %
BATTERY_TOL_MV = 2 * 20.3 + 0.001 * 16800
# a STATE's bytes on the firmware's line (simavr paces 11 bits a byte; UBRR 16 in U2X mode)
STATE_WIRE_S = wire_bytes(State.FMT.size) * 11 / (16e6 / (8 * 17))
FAST_BAUD, FAST_STATE_HZ = 1_000_000, 1000  # the highest STATE rate docs/protocol.md claims


@pytest.fixture(scope="session")
def firmware_built() -> None:
    require("all", "hang", "sim")


# ---------------------------------------------------------------------- the two models

class _ScriptedEncoder:
    """The Python model's plant: encoders moved by the test, outputs recorded."""

    def __init__(self, owner: "PythonMcu") -> None:
        self.owner = owner
        self.count = 0
        self.wheels = (0, 0)
        self.battery_v = 12.0
        self.duty = (0.0, 0.0)

    def set_duty(self, duty_l: float, duty_r: float) -> None:
        self.duty = (duty_l, duty_r)
        self.owner.events.append((self.owner.now, duty_l, duty_r))

    def encoder_count(self) -> int:
        return self.count


class PythonMcu:
    """McuEmulator behind the same interface as sim_hal.firmware_sim.FirmwareMcu."""

    STEP = 50e-6  # the model is serviced this often

    def __init__(self, wheel_cpr: int = 0, state_rate_hz: int = STATE_HZ) -> None:
        self.now = 0.0
        self.events: list[tuple[float, float, float]] = []
        self.reset_causes: list[tuple[float, int]] = []
        self.plant = plant = _ScriptedEncoder(self)
        wheels = dict(wheel_counts=lambda: plant.wheels, wheel_counts_per_rev=wheel_cpr) if wheel_cpr else {}
        self.mcu = McuEmulator(plant, now=0.0, state_rate_hz=state_rate_hz,
                               battery_v=lambda: plant.battery_v, estop_wired=True, **wheels)
        self.cpu = "running"

    def set_battery(self, volts: float) -> None:
        self.plant.battery_v = volts

    def set_estop(self, open_: bool) -> None:
        self.mcu.set_estop(open_, self.now)

    @property
    def outputs(self) -> tuple[float, float]:
        return self.plant.duty

    def send(self, data: bytes) -> float:
        self.mcu.receive(bytes(data), self.now)
        return self.now

    def advance(self, dt: float, counts: int = 0, wheels: tuple[int, int] = (0, 0)) -> list[tuple[float, bytes]]:
        n = max(1, round(dt / self.STEP))
        base = self.plant.count
        wl, wr = self.plant.wheels
        out = []
        for k in range(1, n + 1):
            self.now = round(self.now + dt / n, 9)
            self.plant.count = base + int(round(counts * k / n))
            self.plant.wheels = (wl + int(round(wheels[0] * k / n)), wr + int(round(wheels[1] * k / n)))
            data = self.mcu.service(self.now)
            if data:
                out.append((self.now, data))
        return out

    def reset(self) -> None:
        self.mcu.reset(self.now)

    def close(self) -> None:
        pass


@pytest.fixture(params=["python", "firmware"])
def mcu(request):
    if request.param == "python":
        m = PythonMcu()
    else:
        request.getfixturevalue("firmware_built")
        from sim_hal.firmware_sim import FirmwareMcu

        m = FirmwareMcu()
    yield m
    m.close()


@pytest.fixture(params=["python", "firmware"])
def wheel_mcu(request):
    """Both models with the drive wheels' encoders counted (the firmware's WHEEL_CPR build)."""
    if request.param == "python":
        m = PythonMcu(wheel_cpr=WHEEL_CPR)
    else:
        request.getfixturevalue("firmware_built")
        from sim_hal.firmware_sim import FirmwareMcu, firmware_for

        m = FirmwareMcu(firmware_for(8192, WHEEL_CPR))
    yield m
    m.close()


# ---------------------------------------------------------------------- the host side

@dataclass
class Rx:
    t: float
    pkt: Packet


class Host:
    """A scripted host: frames what it sends, decodes what the MCU sends, stamps packets."""

    def __init__(self, mcu) -> None:
        self.mcu = mcu
        self.dec = FrameDecoder()
        self.rx: list[Rx] = []
        self.seq = 0
        self.to_host_filter = None

    def send_raw(self, data: bytes) -> float:
        return self.mcu.send(data)

    def send(self, msg, seq: int | None = None) -> float:
        if seq is None:
            seq = self.seq
            self.seq = (self.seq + 1) & 0xFF
        return self.mcu.send(encode_frame(Packet(seq, msg)))

    def run(self, dt: float, counts: int = 0, step: float = 0.001,
            wheels: tuple[int, int] = (0, 0)) -> list[Rx]:
        """Advance `dt`, the front encoder moving `counts` and the drive wheels `wheels`
        evenly; returns the packets received."""
        n = max(1, round(dt / step))
        got: list[Rx] = []
        done = 0
        done_w = [0, 0]
        for k in range(1, n + 1):
            c = round(counts * k / n) - done
            done += c
            w = tuple(round(wheels[i] * k / n) - done_w[i] for i in (0, 1))
            done_w = [done_w[0] + w[0], done_w[1] + w[1]]
            for t, data in self.mcu.advance(dt / n, c, w):
                if self.to_host_filter is not None:
                    data = self.to_host_filter(data)
                got += [Rx(t, p) for p in self.dec.feed(data)]
        self.rx += got
        return got

    def run_until(self, t: float, **kw) -> list[Rx]:
        return self.run(max(0.0, t - self.mcu.now), **kw) if t > self.mcu.now else []

    def states(self, rx: list[Rx] | None = None) -> list[Rx]:
        return [r for r in (self.rx if rx is None else rx) if isinstance(r.pkt.msg, State)]

    def boot(self) -> HelloReply:
        got = self.run(0.02)
        first = got[0].pkt
        assert isinstance(first.msg, HelloReply) and first.seq == 0
        return first.msg


def outputs_at(mcu, t: float) -> tuple[float, float]:
    """The outputs at time t (the last change at or before t)."""
    out = (0.0, 0.0)
    for te, l, r in mcu.events:
        if te <= t + 1e-9:
            out = (l, r)
    return out


def first_zero_after(mcu, t: float) -> float | None:
    for te, l, r in mcu.events:
        if te >= t - 1e-9 and l == 0.0 and r == 0.0:
            return te
    return None


def approx(a: tuple[float, float], b: tuple[float, float]) -> bool:
    return abs(a[0] - b[0]) <= DUTY_TOL and abs(a[1] - b[1]) <= DUTY_TOL


# ---------------------------------------------------------------------- tests

def test_boot_announces_itself_and_streams_state(mcu) -> None:
    host = Host(mcu)
    got = host.run(0.1)
    assert got[0].pkt == Packet(0, BOOT_REPLY)
    states = host.states(got)
    assert len(states) == pytest.approx(0.1 * STATE_HZ, abs=2)
    assert [s.pkt.seq for s in states] == list(range(1, len(states) + 1))
    t_us = [s.pkt.msg.t_us for s in states][1:]  # (the Python model's first one is at boot)
    assert all(b - a == 1_000_000 // STATE_HZ for a, b in zip(t_us, t_us[1:]))
    assert all(s.pkt.msg.count == 0 and s.pkt.msg.flags == 0 and s.pkt.msg.ack_seq == 0
               and s.pkt.msg.count_left == s.pkt.msg.count_right == 0 for s in states)
    assert mcu.outputs == (0.0, 0.0)
    assert all((l, r) == (0.0, 0.0) for _, l, r in mcu.events)


def test_hello_is_answered_in_the_mcu_numbering(mcu) -> None:
    host = Host(mcu)
    host.boot()
    host.run(0.0105)
    host.send_raw(b"\x00")  # what the host sends before its first HELLO
    host.send(Hello())
    got = host.run(0.005)
    replies = [r for r in got if isinstance(r.pkt.msg, HelloReply)]
    assert len(replies) == 1 and replies[0].pkt.msg == BOOT_REPLY
    seqs = [r.pkt.seq for r in host.rx]
    assert seqs == list(range(len(seqs)))  # one numbering across types, no gap


def test_drive_acts_at_once_and_is_acknowledged(mcu) -> None:
    host = Host(mcu)
    host.boot()
    t_in = host.send(Drive(5000, -2500, 100), seq=7)
    host.run(0.01)
    assert approx(outputs_at(mcu, t_in + ACT_S), (0.5, -0.25))
    assert outputs_at(mcu, t_in - 1e-6) == (0.0, 0.0)
    after = [s.pkt.msg for s in host.states() if s.t > t_in + 0.0035]
    assert after and all(m.ack_seq == 7 and m.flags & FLAG_OUTPUTS_ON for m in after)


@pytest.mark.parametrize("bad", [Drive(10001, 0, 100), Drive(0, -10001, 100), Drive(100, 100, 0),
                                 Drive(100, 100, 1001), Drive(-32768, 32767, 65535)],
                         ids=["left>100%", "right<-100%", "timeout0", "timeout1001", "all"])
def test_an_out_of_range_drive_is_ignored_entirely(mcu, bad: Drive) -> None:
    host = Host(mcu)
    host.boot()
    t1 = host.send(Drive(2000, 2000, 50), seq=1)
    host.run(0.02)
    host.send(bad, seq=2)
    host.run(0.02)
    # no output change, no ack
    assert approx(mcu.outputs, (0.2, 0.2))
    assert all(s.pkt.msg.ack_seq == 1 for s in host.states() if s.t > t1 + 0.004)
    # the watchdog was not re-armed: the first DRIVE's deadline still stands
    host.run(0.02)
    t_zero = first_zero_after(mcu, t1)
    assert t_zero is not None and t1 + 0.050 <= t_zero <= t1 + 0.051
    flags = [s.pkt.msg.flags for s in host.states()]
    assert not any(f & FLAG_BAD_FRAME for f in flags)  # a valid frame, just out of range


@pytest.mark.parametrize("timeout_ms", [1, 20, 100, 1000])
def test_a_silent_host_is_stopped_by_the_drive_watchdog(mcu, timeout_ms: int) -> None:
    """Outputs go to zero within timeout_ms + 1 ms of the last DRIVE (never before), and the
    trip is reported once, in the next STATE."""
    host = Host(mcu)
    host.boot()
    t_in = host.send(Drive(3000, -3000, timeout_ms))
    host.run(timeout_ms / 1000 + 0.02)
    t_zero = first_zero_after(mcu, t_in + ACT_S)
    assert t_zero is not None, mcu.events
    assert t_in + timeout_ms / 1000 <= t_zero <= t_in + timeout_ms / 1000 + 0.001
    assert approx(outputs_at(mcu, t_in + min(timeout_ms / 1000, 0.0009)), (0.3, -0.3))
    host.run(0.2)  # and stays off
    # reported once, in the first STATE taken after the trip (one may be on the wire then)
    tripped = [s for s in host.states() if s.pkt.msg.flags & FLAG_WATCHDOG]
    assert len(tripped) == 1, tripped
    assert t_zero <= tripped[0].t <= t_zero + 1 / STATE_HZ + STATE_WIRE_S + 0.0005
    assert not tripped[0].pkt.msg.flags & FLAG_OUTPUTS_ON
    assert not any(s.pkt.msg.flags & FLAG_OUTPUTS_ON for s in host.states() if s.t > tripped[0].t)
    assert mcu.outputs == (0.0, 0.0)


def test_stop_zeroes_now_and_disarms_the_watchdog(mcu) -> None:
    host = Host(mcu)
    host.boot()
    host.send(Drive(4000, -4000, 30), seq=10)
    host.run(0.005)
    t_stop = host.send(Stop(), seq=11)
    host.run(0.1)
    assert approx(outputs_at(mcu, t_stop - 1e-6), (0.4, -0.4))
    assert outputs_at(mcu, t_stop + ACT_S) == (0.0, 0.0)
    late = [s.pkt.msg for s in host.states() if s.t > t_stop + 0.004]
    assert late and all(m.ack_seq == 11 and m.flags == 0 for m in late)  # no watchdog trip later


def test_garbage_and_corrupted_frames_to_the_mcu_are_dropped(mcu) -> None:
    host = Host(mcu)
    host.boot()
    rng = random.Random(3)
    good = bytearray(encode_frame(Packet(1, Drive(7000, 7000, 500))))
    flipped = bytes(good[:4]) + bytes([good[4] ^ 0x04]) + bytes(good[5:])
    attacks = [
        bytes(rng.randrange(256) for _ in range(40)) + b"\x00",  # garbage (zeros in it too)
        flipped,  # one bit flipped: CRC
        bytes([0x55] * 70) + b"\x00",  # oversize
        bytes(good[:6]) + b"\x00",  # cut short, then the delimiter
        encode_frame(Packet(2, Unknown(0x02, b"\x10\x27"))),  # a DRIVE of the wrong length
    ]
    for attack in attacks:
        t = host.send_raw(attack)
        got = host.run_until(t + 1 / STATE_HZ + 0.004)
        assert mcu.outputs == (0.0, 0.0), attack
        flagged = [s for s in host.states(got) if s.pkt.msg.flags & FLAG_BAD_FRAME]
        # reported once, in the first STATE taken after the frame (one may be on the wire)
        assert len(flagged) == 1 and t < flagged[0].t <= t + 1 / STATE_HZ + STATE_WIRE_S + 0.0005, attack
    # an unknown type with a valid CRC is ignored without a flag
    t = host.send(Unknown(0x7E, b"\x01\x02\x03"))
    got = host.run_until(t + 1 / STATE_HZ + 0.004)
    assert not any(s.pkt.msg.flags & FLAG_BAD_FRAME for s in host.states(got) if s.t > t)
    # and the receiver is in sync: the next valid DRIVE acts
    t = host.send(Drive(7000, 7000, 500), seq=42)
    host.run(0.01)
    assert approx(outputs_at(mcu, t + ACT_S), (0.7, 0.7))
    assert host.states()[-1].pkt.msg.ack_seq == 42


def test_corrupted_bytes_from_the_mcu_are_dropped_and_the_host_resyncs(mcu) -> None:
    host = Host(mcu)
    host.boot()
    rng = random.Random(5)
    hits = [0]

    def corrupt(data: bytes) -> bytes:
        b = bytearray(data)
        for i in range(len(b)):
            if rng.random() < 0.01:
                b[i] ^= 1 << rng.randrange(8)
                hits[0] += 1
        if rng.random() < 0.05:
            b[rng.randrange(len(b) + 1):0] = bytes(rng.randrange(256) for _ in range(rng.randint(1, 20)))
        return bytes(b)

    host.to_host_filter = corrupt
    got = host.run(0.5)
    assert hits[0] > 10 and host.dec.errors > 0
    assert all(isinstance(r.pkt.msg, (State, HelloReply)) for r in got)  # nothing invented
    host.to_host_filter = None
    got = host.run(0.05)
    seqs = [r.pkt.seq for r in host.states(got)]
    assert len(seqs) >= 0.05 * STATE_HZ - 2
    assert all(seq_gap(a, b) == 0 for a, b in zip(seqs[1:], seqs[2:]))


def test_a_silent_host_sees_the_stream_go_on(mcu) -> None:
    host = Host(mcu)
    host.run(2.0, step=0.002)
    states = host.states()
    assert len(states) == pytest.approx(2.0 * STATE_HZ, abs=2)
    assert all(s.pkt.msg.flags == 0 for s in states)
    assert mcu.outputs == (0.0, 0.0)


def test_sequence_numbers_wrap_and_gaps_are_counted(mcu) -> None:
    host = Host(mcu)
    host.boot()
    host.send(Hello())
    host.run(300 / STATE_HZ)
    seqs = [r.pkt.seq for r in host.rx]
    assert len(seqs) > 256
    assert all(seq_gap(a, b) == 0 for a, b in zip(seqs, seqs[1:]))  # +1 mod 256, across types
    # a frame lost on the way counts as one lost packet: drop the bytes from one delimiter
    # to the next
    state = {"mode": "wait"}

    def drop_one(data: bytes) -> bytes:
        out = bytearray()
        for b in data:
            if state["mode"] == "drop":
                if b == 0:
                    state["mode"] = "done"
                continue
            out.append(b)
            if b == 0 and state["mode"] == "wait":
                state["mode"] = "drop"
        return bytes(out)

    last = host.rx[-1].pkt.seq
    host.to_host_filter = drop_one
    got = host.run(0.02)
    host.to_host_filter = None
    seqs = [last] + [r.pkt.seq for r in got]
    assert sum(seq_gap(a, b) for a, b in zip(seqs, seqs[1:])) == 1
    # the MCU does not care about gaps in the host's numbering: it acks what it accepted
    for seq in (1, 5, 200, 3):
        host.send(Drive(1000, 1000, 100), seq=seq)
        host.run(1 / STATE_HZ + 0.004)
        assert host.states()[-1].pkt.msg.ack_seq == seq


def test_reset_restarts_everything_with_outputs_zero(mcu) -> None:
    host = Host(mcu)
    host.boot()
    host.send(Drive(6000, 6000, 1000), seq=9)
    host.run(0.05, counts=300)
    assert approx(mcu.outputs, (0.6, 0.6))
    while not host.states(host.run(0.0002, step=0.0002)):
        pass  # reset on an idle line: a frame cut short would swallow the boot HELLO_REPLY
    t_reset = mcu.now
    mcu.reset()
    got = host.run(0.2)
    assert outputs_at(mcu, t_reset + 1e-4) == (0.0, 0.0)
    assert all((l, r) == (0.0, 0.0) for te, l, r in mcu.events if te > t_reset + 1e-4)
    assert got[0].pkt == Packet(0, BOOT_REPLY)
    first = host.states(got)[0]
    assert first.pkt.seq == 1 and first.pkt.msg.t_us <= 1e6 / STATE_HZ + 500 and first.pkt.msg.count == 0
    assert first.pkt.msg.ack_seq == 0
    assert all(s.pkt.msg.flags & FLAG_OUTPUTS_ON == 0 for s in host.states(got))


@pytest.mark.parametrize("pattern", ["reversals", "sweep"])
def test_quadrature_is_exact_at_60000_counts_per_s_and_through_reversals(mcu, pattern: str) -> None:
    host = Host(mcu)
    host.boot()
    if pattern == "reversals":
        # +-60 counts per ms (60 000 counts/s), reversing every 10 ms
        steps = [60 if (k // 10) % 2 == 0 else -60 for k in range(200)]
    else:
        # every ms a new rate from -60 000 to +60 000 counts/s, reversals included
        rng = random.Random(11)
        steps = [rng.randint(-60, 60) for _ in range(300)]
    expected = 0
    for c in steps:
        host.run(0.001, counts=c)
        expected += c
    host.run(0.01)  # at rest: the next STATEs carry the final count
    assert host.states()[-1].pkt.msg.count == expected
    # and while moving, every STATE's count was on the trajectory (never a lost count)
    counts = [s.pkt.msg.count for s in host.states()]
    assert max(abs(b - a) for a, b in zip(counts, counts[1:])) <= 2 * 60 * 1000 // STATE_HZ + 1


def test_quadrature_margin_above_the_required_rate(mcu) -> None:
    """Twice the required rate: 120 000 counts/s for 100 ms each way."""
    host = Host(mcu)
    host.boot()
    host.run(0.1, counts=12000)
    host.run(0.1, counts=-12000 - 77)
    host.run(0.01)
    assert host.states()[-1].pkt.msg.count == -77


def test_the_hang_build_is_reset_by_the_hardware_watchdog(firmware_built) -> None:
    """Firmware only (the Python model has no main loop to hang): a test build whose main
    loop hangs on packet 0x7E; the AVR's watchdog (60 ms) resets it, outputs zero."""
    from sim_hal.firmware_sim import FirmwareMcu

    mcu = FirmwareMcu(hang=True)
    try:
        host = Host(mcu)
        host.boot()
        host.send(Drive(5000, 5000, 1000))  # the DRIVE watchdog alone would wait 1 s
        host.run(0.01)
        assert approx(mcu.outputs, (0.5, 0.5))
        t_hang = host.send(Unknown(0x7E, b""))
        got = host.run(0.2)
        t_zero = first_zero_after(mcu, t_hang)
        assert t_zero is not None and 0.040 <= t_zero - t_hang <= 0.080  # WDTO_60MS (+-)
        assert mcu.outputs == (0.0, 0.0)
        wdt = [(t, c) for t, c in mcu.reset_causes if t > t_hang]
        assert wdt and wdt[0][1] & 0x08  # MCUSR.WDRF: the watchdog did it
        boot = [r for r in got if isinstance(r.pkt.msg, HelloReply)]
        assert boot and boot[0].pkt.seq == 0 and boot[0].t > t_hang
        after = [s.pkt.msg for s in host.states(got) if s.t > boot[0].t]
        assert len(after) > 0.1 * STATE_HZ and all(m.flags & FLAG_OUTPUTS_ON == 0 for m in after)
        # the normal build ignores 0x7E (an unknown type): test_garbage_and_corrupted_frames...
    finally:
        mcu.close()


@pytest.mark.parametrize("duties", [(5000, -2500), (-10000, 10000), (1, -1)])
def test_the_drv8871_build_drives_the_same(firmware_built, duties: tuple[int, int]) -> None:
    """DRIVER=DRIVER_DRV8871 (PWM on IN1, direction on IN2, the PWM inverted in reverse):
    each H-bridge's mean drive is the commanded duty, as with the default build."""
    from sim_hal import firmware_build
    from sim_hal.firmware_sim import FirmwareMcu

    firmware_build.build("all", extra=("BUILD=build/drv8871", "DRIVER=DRIVER_DRV8871"))
    mcu = FirmwareMcu(firmware_build.artifact("drv8871/ddrt_bridge.elf"), driver="drv8871")
    try:
        host = Host(mcu)
        host.boot()
        t_in = host.send(Drive(duties[0], duties[1], 100))
        host.run(0.01)
        assert approx(outputs_at(mcu, t_in + ACT_S), (duties[0] / 10000, duties[1] / 10000))
        t_stop = host.send(Stop())
        host.run(0.01)
        assert outputs_at(mcu, t_stop + ACT_S) == (0.0, 0.0)
    finally:
        mcu.close()


# ---------------------------------------------------------------------- protocol v2's inputs

def test_hello_reply_v2_announces_the_features_of_the_build(mcu, wheel_mcu) -> None:
    """12 bytes: version 2, front counts/rev, STATE rate, features, wheel counts/rev."""
    assert Host(mcu).boot() == HelloReply(2, 8192, STATE_HZ, FEATURE_BATTERY | FEATURE_HW_ESTOP, 0)
    assert Host(wheel_mcu).boot() == HelloReply(
        2, 8192, STATE_HZ, FEATURE_BATTERY | FEATURE_HW_ESTOP | FEATURE_WHEELS, WHEEL_CPR)


@pytest.mark.parametrize("volts", [6.0, 9.2, 11.1, 12.6, 16.8])
def test_the_battery_is_reported_in_mv(mcu, volts: float) -> None:
    """STATE.battery_mv follows the battery (the firmware: the divider at ADC0, low-passed
    with a time constant of about 10 ms, so within 60 ms of a change)."""
    host = Host(mcu)
    host.boot()
    host.run(0.05)
    before = host.states()[-1].pkt.msg.battery_mv
    assert abs(before - 12000) <= BATTERY_TOL_MV  # the harness's and the model's 12 V at boot
    t = mcu.now
    mcu.set_battery(volts)
    host.run(0.1)
    settled = [s.pkt.msg.battery_mv for s in host.states() if s.t > t + 0.06]
    assert settled and all(abs(mv - volts * 1000) <= BATTERY_TOL_MV for mv in settled), settled
    # and never outside the two levels on the way (a low-pass, no overshoot)
    lo, hi = sorted((before, volts * 1000))
    assert all(lo - BATTERY_TOL_MV <= s.pkt.msg.battery_mv <= hi + BATTERY_TOL_MV
               for s in host.states() if s.t > t)


def test_the_hardware_estop_holds_the_outputs_at_zero(mcu) -> None:
    """Open: outputs zero at once (the firmware: at its next 100 us tick), flag bit3 in every
    STATE, DRIVE acknowledged but not applied. Closed again: nothing applied until the next
    DRIVE, which applies; the flag clears."""
    host = Host(mcu)
    host.boot()
    host.send(Drive(5000, -5000, 1000), seq=1)
    host.run(0.01)
    assert approx(mcu.outputs, (0.5, -0.5))
    t_open = mcu.now
    mcu.set_estop(True)
    host.run(0.01)
    assert outputs_at(mcu, t_open + ACT_S) == (0.0, 0.0)
    t_drive = host.send(Drive(8000, 8000, 1000), seq=2)
    host.run(0.02)
    assert mcu.outputs == (0.0, 0.0)
    assert all((l, r) == (0.0, 0.0) for te, l, r in mcu.events if te > t_open + ACT_S)
    during = [s.pkt.msg for s in host.states() if s.t > t_open + STATE_WIRE_S + 1 / STATE_HZ]
    assert during and all(m.flags & FLAG_HW_ESTOP and not m.flags & FLAG_OUTPUTS_ON for m in during)
    acked = [m for m in during if m.ack_seq == 2]
    assert acked and acked[-1] is during[-1]  # acknowledged, though not applied
    assert host.states()[-1].t > t_drive + STATE_WIRE_S
    t_close = mcu.now
    mcu.set_estop(False)
    host.run(0.05)
    assert mcu.outputs == (0.0, 0.0)  # no restart from a command given while open
    after = [s.pkt.msg for s in host.states() if s.t > t_close + STATE_WIRE_S + 1 / STATE_HZ]
    assert after and not any(m.flags & (FLAG_HW_ESTOP | FLAG_OUTPUTS_ON) for m in after)
    t_in = host.send(Drive(3000, 3000, 1000), seq=3)
    host.run(0.01)
    assert approx(outputs_at(mcu, t_in + ACT_S), (0.3, 0.3))


def test_a_short_estop_opening_is_reported_in_the_next_state(mcu) -> None:
    """Open for 0.5 ms, between two STATE snapshots: the outputs go to zero and stay there,
    and the next STATE carries flag bit3 once."""
    host = Host(mcu)
    host.boot()
    host.send(Drive(4000, 4000, 1000), seq=1)
    # just after a snapshot (every 1/STATE_HZ from boot), so the opening falls between two
    host.run_until(round(mcu.now * STATE_HZ + 1) / STATE_HZ + 0.0005, step=0.0005)
    t = mcu.now
    mcu.set_estop(True)
    host.run(0.0005, step=0.0005)
    mcu.set_estop(False)
    host.run(0.03)
    assert mcu.outputs == (0.0, 0.0)
    flagged = [s for s in host.states() if s.pkt.msg.flags & FLAG_HW_ESTOP]
    assert len(flagged) == 1 and t < flagged[0].t <= t + 1 / STATE_HZ + STATE_WIRE_S + 0.0005


def test_a_v1_length_packet_to_the_mcu_is_no_command(mcu) -> None:
    """The MCU takes the host's types only; a host-bound v1 STATE (10 bytes) sent to it has a
    valid length and CRC and is ignored without a flag, like any MCU-bound type."""
    host = Host(mcu)
    host.boot()
    t = host.send(Unknown(0x82, bytes(10)))  # a v1 STATE's layout
    got = host.run_until(t + 1 / STATE_HZ + STATE_WIRE_S + 0.001)
    assert mcu.outputs == (0.0, 0.0)
    assert not any(s.pkt.msg.flags & FLAG_BAD_FRAME for s in host.states(got))


def _wheel_trajectory(host: Host, rng: random.Random, steps: int, peak: int) -> tuple[int, int]:
    """Each ms a new rate per wheel in -peak..peak counts/ms; returns the totals."""
    total = [0, 0]
    for _ in range(steps):
        w = (rng.randint(-peak, peak), rng.randint(-peak, peak))
        host.run(0.001, counts=w[0] + w[1], wheels=w)
        total = [total[0] + w[0], total[1] + w[1]]
    return total[0], total[1]


def test_wheel_counts_are_exact_at_the_default_state_rate(wheel_mcu) -> None:
    """Both drive wheels at up to 20 000 counts/s each (15 rev/s at 1320 counts/rev: far
    beyond any drive wheel), rates changing every ms, reversals included, with the front
    encoder moving too: every count arrives, and every STATE is on the trajectory."""
    host = Host(wheel_mcu)
    host.boot()
    left, right = _wheel_trajectory(host, random.Random(23), 300, 20)
    host.run(0.02)
    last = host.states()[-1].pkt.msg
    assert (last.count_left, last.count_right, last.count) == (left, right, left + right)
    states = [s.pkt.msg for s in host.states()]
    step = 2 * 20 * 1000 // STATE_HZ + 1
    assert max(abs(b.count_left - a.count_left) for a, b in zip(states, states[1:])) <= step


def test_wheel_counts_at_the_highest_state_rate_the_docs_claim(firmware_built) -> None:
    """docs/protocol.md: STATE up to 1000 Hz at 1 Mbaud. The firmware built so, and the
    Python model at the same rate: a STATE every ms without a gap in seq or time, the line
    under 70 % busy, and the wheel counts exact."""
    from sim_hal import firmware_build
    from sim_hal.firmware_sim import FirmwareMcu

    firmware_build.build("all", extra=("BUILD=build/fast", f"BAUD={FAST_BAUD}",
                                       f"STATE_HZ={FAST_STATE_HZ}", f"WHEEL_CPR={WHEEL_CPR}"))
    assert wire_bytes(State.FMT.size) * 10 * FAST_STATE_HZ <= 0.7 * FAST_BAUD
    for mcu in (PythonMcu(wheel_cpr=WHEEL_CPR, state_rate_hz=FAST_STATE_HZ),
                FirmwareMcu(firmware_build.artifact("fast/ddrt_bridge.elf"))):
        try:
            host = Host(mcu)
            assert host.boot().state_rate_hz == FAST_STATE_HZ
            left, right = _wheel_trajectory(host, random.Random(29), 300, 20)
            host.run(0.01)
            states = host.states()
            last = states[-1].pkt.msg
            assert (last.count_left, last.count_right) == (left, right)
            seqs = [s.pkt.seq for s in states]
            assert all(seq_gap(a, b) == 0 for a, b in zip(seqs, seqs[1:]))
            t_us = [s.pkt.msg.t_us for s in states][1:]
            assert all(b - a == 1_000_000 // FAST_STATE_HZ for a, b in zip(t_us, t_us[1:]))
            assert len(states) == pytest.approx(mcu.now * FAST_STATE_HZ, abs=3)
        finally:
            mcu.close()


def test_the_firmware_fits_its_budget(firmware_built) -> None:
    """Done-when: flash (text + data) at most 28 KiB, static RAM (data + bss) at most 1.5 KiB,
    measured with avr-size on the default build and on the one with everything (wheels);
    and `make`'s own size step refuses a build over a budget."""
    import subprocess

    from sim_hal import firmware_build
    from sim_hal.firmware_sim import firmware_for

    for elf in (firmware_build.artifact("ddrt_bridge.elf"), firmware_for(8192, WHEEL_CPR)):
        out = subprocess.run(["avr-size", str(elf)], capture_output=True, text=True, check=True).stdout
        text, data, bss = (int(v) for v in out.splitlines()[1].split()[:3])
        assert text + data <= 28 * 1024 and data + bss <= 1536, (elf, text, data, bss)
        assert text > 2000 and bss > 300  # it measured the firmware, not an empty file
    with pytest.raises(firmware_build.BuildError, match="flash over budget"):
        firmware_build.build("all", extra=("BUILD=build/budget", "FLASH_MAX=2000"))
    with pytest.raises(firmware_build.BuildError, match="RAM over budget"):
        firmware_build.build("all", extra=("BUILD=build/budget", "RAM_MAX=100"))
