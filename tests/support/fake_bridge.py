"""Fakes for RealHal's parts (the bridge to the MCU, the IMU, the clock), deterministic."""

from __future__ import annotations

from hal.base import GyroCaps, HalIOError


class FakeClock:
    """Manually advanced clock for deterministic staleness tests."""

    def __init__(self) -> None:
        self.t = 100.0

    def now(self) -> float:
        return self.t

    def sleep_until(self, deadline: float) -> float:
        self.t = max(self.t, deadline)
        return self.t


class FakeState:
    def __init__(self, count: int, new: bool, resets: int = 0) -> None:
        self.count, self.new, self.resets = count, new, resets
        self.battery_mv, self.hw_estop, self.count_left, self.count_right = 0, False, 0, 0

    def count_at(self, t: float) -> int:
        return self.count  # no rate: the count as it came

    def wheel_counts_at(self, t: float) -> tuple[int, int]:
        return self.count_left, self.count_right


class FakeEncoder:
    """A bridge whose STATEs follow `script`: "new" (10 counts more), anything else (not new),
    or an exception (raised); "new" once the script is used up."""

    counts_per_rev = 8192
    wheel_counts_per_rev = 0
    battery_measured = False
    hw_estop_wired = False
    drive_timeout_s = None  # no watchdog of its own
    stats: dict[str, int] = {}

    def __init__(self, state_stale_s: float = 0.05) -> None:
        self.state_stale_s = state_stale_s
        self.script: list = []
        self.count = 0
        self.drives: list = []
        self.closed = 0

    def state(self) -> FakeState:
        item = self.script.pop(0) if self.script else "new"
        if isinstance(item, Exception):
            raise item
        if item == "new":
            self.count += 10
        return FakeState(self.count, item == "new")

    def drive(self, l: float, r: float) -> None:
        self.drives.append((l, r))

    def stop(self) -> None:
        raise HalIOError("gone")

    def close(self) -> None:
        self.closed += 1


class FakeImu:
    gyro_range_dps = 500
    gyro_delay_s = 0.0019
    fault_counts = {"retries": 0, "errors": 0}
    gyro_part = "a fake gyro"
    caps = GyroCaps(age_s=gyro_delay_s)  # the register at the tick, no temperature

    def read_gyro_z_raw(self) -> int:
        return 42
