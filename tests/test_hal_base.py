"""The Hal base class: `write` checks before the backend moves anything, `close` runs once."""

from __future__ import annotations

import math

import pytest

from hal.base import Hal, HalInfo, HalValueError, Sample

INFO = HalInfo(encoder_counts_per_rev=8192, gyro_lsb_per_rad_s=131.0 * 180.0 / math.pi,
               gyro_full_scale_rad_s=250.0 * math.pi / 180.0)


class Recorder(Hal):
    """A backend that only records what the base class hands it."""

    def __init__(self, fail_in_init: bool = False) -> None:
        if fail_in_init:
            raise OSError("device missing")
        self.info = INFO
        self.writes: list[tuple[float, float]] = []
        self.closes = 0

    def read(self) -> Sample:
        return Sample(t=0.0, encoder_count=0, gyro_z_raw=0)

    def _write(self, duty_l: float, duty_r: float) -> None:
        self.writes.append((duty_l, duty_r))

    def stop(self) -> None:
        self.writes.append((0.0, 0.0))

    def _close(self) -> None:
        self.closes = getattr(self, "closes", 0) + 1


@pytest.mark.parametrize("bad", [1.0000001, -1.5, math.nan, math.inf, -math.inf])
def test_write_checks_both_duties_before_the_backend_sees_them(bad: float) -> None:
    hal = Recorder()
    with pytest.raises(HalValueError, match="duty_l"):
        hal.write(bad, 0.0)
    with pytest.raises(HalValueError, match="duty_r"):
        hal.write(0.0, bad)
    assert hal.writes == []


def test_write_hands_floats_in_range_to_the_backend() -> None:
    hal = Recorder()
    hal.write(1, -1)
    hal.write(0.25, 0.5)
    assert hal.writes == [(1.0, -1.0), (0.25, 0.5)]
    assert all(type(d) is float for pair in hal.writes for d in pair)


def test_close_runs_the_backend_once_and_the_context_manager_closes() -> None:
    with Recorder() as hal:
        pass
    hal.close()
    hal.close()
    assert hal.closes == 1


def test_close_is_safe_on_a_half_built_object() -> None:
    hal = Recorder.__new__(Recorder)  # as left by a constructor that raised
    hal.close()
    hal.close()
    assert hal.closes == 1


def test_hardware_does_not_own_time_by_default() -> None:
    hal = Recorder()
    assert hal.owns_time is False
    hal.advance_to_wall_clock()  # a no-op, never an error
    assert hal.writes == []


def test_a_backend_must_implement_the_abstract_methods() -> None:
    class Incomplete(Hal):
        def read(self) -> Sample:
            return Sample(t=0.0, encoder_count=0, gyro_z_raw=0)

    with pytest.raises(TypeError, match="_close|_write|stop"):
        Incomplete()  # type: ignore[abstract]
