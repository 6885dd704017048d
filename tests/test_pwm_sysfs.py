"""PwmSysfsMotors against a temp dir laid out like sysfs (hal/pwm_sysfs.py)."""

from __future__ import annotations

import threading
import time
from pathlib import Path

import pytest

from hal.base import HalInitError, HalValueError
from hal.pwm_sysfs import PwmSysfsMotors

PERIOD = 50_000


class FakeKernel:
    """Creates pwmN/ and gpioN/ nodes when a number is written to an export file, like the
    kernel does (asynchronously, from another thread)."""

    def __init__(self, root: Path, chip: int = 0) -> None:
        self.chip_dir = root / "class" / "pwm" / f"pwmchip{chip}"
        self.gpio_dir = root / "class" / "gpio"
        self.chip_dir.mkdir(parents=True)
        self.gpio_dir.mkdir(parents=True)
        (self.chip_dir / "export").write_text("")
        (self.gpio_dir / "export").write_text("")
        self.exports: list[str] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        deadline = time.monotonic() + 120.0  # until closed (bounded should a test forget to)
        while not self._stop.is_set() and time.monotonic() < deadline:
            for export, prefix, files in (
                    (self.chip_dir / "export", "pwm", ("period", "duty_cycle", "enable")),
                    (self.gpio_dir / "export", "gpio", ("direction", "value"))):
                text = export.read_text().strip()
                if text:
                    export.write_text("")
                    self.exports.append(f"{prefix}{text}")
                    staging = export.parent / f".staging-{prefix}{text}"
                    staging.mkdir()
                    for name in files:
                        (staging / name).write_text("0")
                    staging.rename(export.parent / f"{prefix}{text}")  # appears whole
            time.sleep(0.001)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)

    def pwm(self, ch: int, name: str) -> str:
        return (self.chip_dir / f"pwm{ch}" / name).read_text()

    def gpio(self, n: int, name: str) -> str:
        return (self.gpio_dir / f"gpio{n}" / name).read_text()


@pytest.fixture()
def kernel(tmp_path: Path):
    k = FakeKernel(tmp_path)
    yield k
    k.close()


def make(kernel: FakeKernel, tmp_path: Path, **kw) -> PwmSysfsMotors:
    return PwmSysfsMotors(0, (0, 1), PERIOD, (17, 27), root=tmp_path, **kw)


def test_init_exports_sets_period_and_enables(kernel: FakeKernel, tmp_path: Path) -> None:
    m = make(kernel, tmp_path)
    assert sorted(kernel.exports) == ["gpio17", "gpio27", "pwm0", "pwm1"]
    for ch in (0, 1):
        assert kernel.pwm(ch, "period") == str(PERIOD)
        assert kernel.pwm(ch, "duty_cycle") == "0"
        assert kernel.pwm(ch, "enable") == "1"
    assert kernel.gpio(17, "direction") == "low"
    m.close()


def test_plus_minus_half_duty_and_direction(kernel: FakeKernel, tmp_path: Path) -> None:
    with make(kernel, tmp_path) as m:
        m.drive(0.5, -0.5)
        assert kernel.pwm(0, "duty_cycle") == str(PERIOD // 2)
        assert kernel.pwm(1, "duty_cycle") == str(PERIOD // 2)
        assert kernel.gpio(17, "value") == "1"  # forward
        assert kernel.gpio(27, "value") == "0"  # reverse
        m.drive(-0.25, 1.0)
        assert kernel.pwm(0, "duty_cycle") == str(PERIOD // 4)
        assert kernel.pwm(1, "duty_cycle") == str(PERIOD)
        assert kernel.gpio(17, "value") == "0"
        assert kernel.gpio(27, "value") == "1"


def test_zero_and_disable_on_close_twice(kernel: FakeKernel, tmp_path: Path) -> None:
    m = make(kernel, tmp_path)
    m.drive(0.8, 0.8)
    m.close()
    m.close()
    for ch in (0, 1):
        assert kernel.pwm(ch, "duty_cycle") == "0"
        assert kernel.pwm(ch, "enable") == "0"


def test_out_of_range_moves_nothing(kernel: FakeKernel, tmp_path: Path) -> None:
    with make(kernel, tmp_path) as m:
        m.drive(0.3, 0.3)
        with pytest.raises(HalValueError, match="duty_r"):
            m.drive(0.1, float("nan"))
        assert kernel.pwm(0, "duty_cycle") == str(round(0.3 * PERIOD))


class RecordingDirection:
    def __init__(self, kernel: FakeKernel) -> None:
        self.kernel = kernel
        self.log: list[tuple[int, bool, str]] = []

    def set_direction(self, motor: int, forward: bool) -> None:
        # record the duty at the moment the line flips: must be 0
        self.log.append((motor, forward, self.kernel.pwm(motor, "duty_cycle")))

    def close(self) -> None:
        pass


def test_pluggable_direction_and_zero_before_reversal(kernel: FakeKernel, tmp_path: Path) -> None:
    d = RecordingDirection(kernel)
    with PwmSysfsMotors(0, (0, 1), PERIOD, root=tmp_path, direction=d,
                        invert=(False, True)) as m:
        assert d.log[:2] == [(0, True, "0"), (1, False, "0")]  # right motor mirrored
        m.drive(0.5, 0.5)
        m.drive(-0.5, 0.5)
        assert d.log[-1] == (0, False, "0")
        assert kernel.pwm(0, "duty_cycle") == str(PERIOD // 2)
    assert not kernel.gpio_dir.joinpath("gpio17").exists()


def test_missing_chip_is_init_error_naming_path(tmp_path: Path) -> None:
    with pytest.raises(HalInitError, match="pwmchip3"):
        PwmSysfsMotors(3, (0, 1), PERIOD, (17, 27), root=tmp_path)


def test_export_that_never_appears_times_out(tmp_path: Path) -> None:
    chip = tmp_path / "class" / "pwm" / "pwmchip0"
    chip.mkdir(parents=True)
    (chip / "export").write_text("")
    with pytest.raises(HalInitError, match="pwm0"):
        PwmSysfsMotors(0, (0, 1), PERIOD, (17, 27), root=tmp_path, export_timeout_s=0.05)


def test_bad_arguments_name_the_field(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="period_ns"):
        PwmSysfsMotors(0, (0, 1), 0, (17, 27), root=tmp_path)
    with pytest.raises(ValueError, match="channels"):
        PwmSysfsMotors(0, (0,), PERIOD, (17, 27), root=tmp_path)
