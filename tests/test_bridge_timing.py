"""The count as of the host's tick (hal/bridge.py BridgeState.count_at, used by hal/real.py).

A microcontroller streams STATE on its own clock, not in step with the host's control ticks,
so the newest count's age at a tick varies by up to one STATE period. The firmware in
simavr showed what that does: on the slow figure-eight, at 500 STATE/s and 200 ticks/s, the
estimator gated out every encoder sample as an outlier (0.3 m/s x 2 ms = 0.6 mm of jitter
against a 0.04 mm count). The bridge maps the MCU's t_us onto the host clock and carries the
count forward at its rate; this holds it to the truth on a synthetic stream. The frame's own
time on the line (a v2 STATE: 26 bytes, 2.3 ms at 115200 baud) is a fixed part of the delay
the clock map cannot see; the bridge takes it off (Bridge.byte_time_s).
"""

from __future__ import annotations

import statistics

from hal.bridge import Bridge
from hal.wire import HelloReply, Packet, State, encode_frame, wire_bytes


class FakeClock:
    def __init__(self, t: float) -> None:
        self.t = t

    def now(self) -> float:
        return self.t

    def sleep_until(self, deadline: float) -> float:
        self.t = max(self.t, deadline)
        return self.t


def test_count_at_removes_the_jitter_of_an_unsynchronised_stream() -> None:
    boot = 3.0  # host time of the MCU's t_us = 0
    rate = 12000.0  # counts/s
    period = 0.004  # STATE every 4 ms on the MCU's clock (250 Hz)
    transport = wire_bytes(State.FMT.size) * 10 / 115200  # a 26-byte frame at 115200 baud
    slow = 1.003  # the MCU's resonator runs 0.3 % slow: the phases sweep, the map must follow
    clock = FakeClock(boot + 0.0005)
    bridge = Bridge("loop://", connect=False, clock=clock)
    bridge.port.write(encode_frame(Packet(0, HelloReply(2, 8192, 250))))
    bridge.connect(flush_input=False)
    k = 0
    raw_err, fixed_err = [], []
    tick = clock.t
    for i in range(400):
        tick += 0.005
        clock.t = tick
        # every STATE whose last byte arrived by this tick is in the port now
        while boot + k * period * slow + transport <= tick:
            t_mcu = k * period
            bridge.port.write(encode_frame(Packet((k + 1) & 0xFF, State(round(t_mcu * 1e6), int(rate * t_mcu), 0, 0))))
            k += 1
        st = bridge.state()
        truth = rate * (tick - boot) / slow  # the count at the tick: the line's time taken off
        if i >= 20:  # the clock map settles over the first ticks
            raw_err.append(st.count - truth)
            fixed_err.append(st.count_at(tick) - truth)
    # What the estimator cannot take is the jump from tick to tick; a slowly varying lag (the
    # clock map's bias, at most part of a STATE period) it takes like any sensor latency.
    jumps = lambda e: max(abs(b - a) for a, b in zip(e, e[1:]))  # noqa: E731
    assert jumps(raw_err) > 0.4 * rate * period
    assert jumps(fixed_err) <= 3  # counts: rounding, the rate estimate, the map settling
    # at most a quarter period (12 counts): the line's 2.3 ms alone would be 27
    assert abs(statistics.mean(fixed_err)) <= 0.25 * rate * period
    bridge.close()


def test_count_at_is_the_count_when_the_stream_is_in_step() -> None:
    """The Python MCU model streams exactly at the host's ticks, in process (no line, no
    frame time): nothing changes there."""
    clock = FakeClock(10.0)
    bridge = Bridge("loop://", connect=False, clock=clock)
    bridge.byte_time_s = 0.0  # as sim_hal/emulated.py sets it
    bridge.port.write(encode_frame(Packet(0, HelloReply(2, 8192, 200))))
    bridge.connect(flush_input=False)
    for k in range(50):
        clock.t = 10.0 + k * 0.005
        bridge.port.write(encode_frame(Packet(k + 1, State(k * 5000, 37 * k, 0, 0))))
        st = bridge.state()
        assert st.count_at(clock.t) == st.count == 37 * k
    bridge.close()
