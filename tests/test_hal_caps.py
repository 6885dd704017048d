"""RealHal builds its HalInfo from what its drivers declare (hal.base.GyroCaps, the link's stale
bound and counters, the motors' watchdog), and asks them nothing else."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from hal.base import GyroCaps, HalIOError
from hal.mpu6050 import Mpu6050
from hal.pwm_sysfs import PwmSysfsMotors
from hal.real import RealHal
from sim_hal.mpu_emulator import ConstantGyro, MpuEmulator
from tests.support.fake_bridge import FakeClock, FakeEncoder, FakeImu

REPO = Path(__file__).resolve().parents[1]


def test_real_hal_probes_no_driver() -> None:
    # getattr/hasattr on a driver would be a capability found by trying; the drivers declare them.
    tree = ast.parse((REPO / "hal" / "real.py").read_text(encoding="utf-8"))
    calls = sorted({n.func.id for n in ast.walk(tree)
                    if isinstance(n, ast.Call) and isinstance(n.func, ast.Name) and n.func.id in ("getattr", "hasattr")})
    assert calls == []


class _Imu(FakeImu):
    """A gyro that declares what it delivers, and records which reads were asked of it."""

    def __init__(self, caps: GyroCaps) -> None:
        self.caps = caps  # type: ignore[misc]
        self.calls: list[str] = []

    def read_gyro_z_raw(self) -> int:
        self.calls.append("register")
        return 7

    def read_gyro_fifo(self):  # noqa: ANN201 - a batch of three samples
        from hal.mpu6050 import FifoBatch

        self.calls.append("fifo")
        return FifoBatch(3, 21, 7)

    def read_temp_c(self) -> float:
        self.calls.append("temp")
        return 31.5


@pytest.mark.parametrize("caps", [GyroCaps(), GyroCaps(age_s=0.004), GyroCaps(age_s=0.002, fifo_period_s=0.005),
                                  GyroCaps(age_s=0.003, die_temp=True),
                                  GyroCaps(age_s=0.001, fifo_period_s=0.001, die_temp=True)])
def test_the_info_and_the_reads_follow_the_declared_caps(caps: GyroCaps) -> None:
    imu = _Imu(caps)
    hal = RealHal(imu, FakeEncoder(), FakeClock(), temp_hz=5.0)
    assert hal.info.gyro_delay_s == caps.age_s
    assert hal.info.gyro_fifo_period_s == caps.fifo_period_s
    assert hal.info.gyro_temp_hz == (5.0 if caps.die_temp else 0.0)
    s = hal.read()
    assert ("fifo" in imu.calls) == (caps.fifo_period_s > 0.0)
    assert ("register" in imu.calls) == (caps.fifo_period_s == 0.0)
    assert ("temp" in imu.calls) == caps.die_temp
    assert (s.gyro_temp_c == 31.5) == caps.die_temp
    assert (s.gyro_n, s.gyro_sum_raw) == ((3, 21) if caps.fifo_period_s > 0.0 else (0, 0))


def test_the_mpu_declares_its_configuration() -> None:
    for fifo in (False, True):
        imu = Mpu6050(MpuEmulator(ConstantGyro()), fifo=fifo)
        assert imu.caps == GyroCaps(imu.sample_age_s, imu.fifo_period_s, True)
        assert (imu.caps.fifo_period_s > 0.0) == fifo


def test_the_watchdog_is_the_motor_drivers_declaration() -> None:
    enc = FakeEncoder()
    assert RealHal(FakeImu(), enc, FakeClock()).info.drive_timeout_s is None  # the fake link declares none
    assert PwmSysfsMotors.drive_timeout_s is None

    class _Watched(FakeEncoder):
        drive_timeout_s = 0.12

    assert RealHal(FakeImu(), _Watched(), FakeClock()).info.drive_timeout_s == 0.12


def test_the_hold_bound_is_the_links_stale_bound() -> None:
    enc = FakeEncoder(state_stale_s=0.02)
    clock = FakeClock()
    hal = RealHal(FakeImu(), enc, clock)
    assert hal.hold_s == 0.02
    hal.read()
    enc.script = ["late", "late"]
    clock.t += 0.015
    assert not hal.read().fresh  # 15 ms old: held
    clock.t += 0.010
    with pytest.raises(HalIOError, match="stale bound"):
        hal.read()  # 25 ms old: beyond the link's 20 ms
