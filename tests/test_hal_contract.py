"""One contract, every backend: the simulated HAL, and the real drivers on emulated devices.

The real backend here is hal.real.RealHal (Mpu6050 over an emulated I2C register file,
Bridge over protocol v2 to an emulated microcontroller), both backed by the same simulated
robot, wired in process through pyserial's URL mechanism (ddrtsim://); and the same with the
reference firmware in simavr as the microcontroller (simavr://, over a pseudo-terminal).
"""

from __future__ import annotations

import time

import pytest

from ddrt.config import load_config
from ddrt.loop import LoopState
from ddrt.path.spec import resolve_path
from ddrt.simrun.runner import run_sim
from hal.base import HalValueError, Sample
from hal.registry import open_hal
from tests.support.following import following, tick_rows
from tests.support.repo import REPO

SCENARIO = REPO / "configs" / "scenarios" / "figure8_slow.yaml"
EMULATED = {"hal": {"backend": "real", "imu": {"bus": "sim"},
                    "bridge": {"url": "ddrtsim://robot", "drive_timeout_ms": 100, "state_stale_s": 0.05}}}
FIRMWARE = {"hal": {"backend": "real", "imu": {"bus": "sim"},
                    "bridge": {"url": "simavr://", "drive_timeout_ms": 100, "state_stale_s": 0.05}}}
BACKENDS = {"sim": None, "real-emulated": EMULATED, "real-firmware": FIRMWARE}


@pytest.fixture(params=sorted(BACKENDS))
def backend(request):
    if request.param == "real-firmware":
        from tests.support.firmware import require

        require("all", "sim")
    cfg = load_config(SCENARIO, BACKENDS[request.param])
    hal = open_hal(cfg, start=(0.0, 0.0, 0.0))
    yield request.param, cfg, hal
    hal.close()


def _run_for(hal, seconds: float, duty: tuple[float, float] | None = None) -> Sample:
    t = hal.now()
    end = t + seconds
    while True:
        t += 0.005
        hal.sleep_until(t)
        if duty is not None:
            hal.write(*duty)
        sample = hal.read()
        if t >= end:
            return sample


def test_read_returns_a_sample_with_integers(backend):
    _, cfg, hal = backend
    s = _run_for(hal, 0.02)
    assert isinstance(s.encoder_count, int) and isinstance(s.gyro_z_raw, int)
    assert -32768 <= s.gyro_z_raw <= 32767
    assert hal.info.encoder_counts_per_rev == cfg.sensors.encoder_counts_per_rev
    assert hal.info.gyro_lsb_per_rad_s == pytest.approx(131.0 * 180.0 / 3.141592653589793, rel=1e-6)


@pytest.mark.parametrize("bad", [1.5, -1.01, float("nan"), float("inf")])
def test_out_of_range_duty_is_refused_and_nothing_moves(backend, bad):
    _, _, hal = backend
    with pytest.raises(HalValueError):
        hal.write(bad, 0.0)
    with pytest.raises(ValueError):  # HalValueError is a ValueError too
        hal.write(0.0, bad)
    before = _run_for(hal, 0.01).encoder_count
    x0, y0, _ = hal.robot.pose
    after = _run_for(hal, 0.3).encoder_count
    x1, y1, _ = hal.robot.pose
    assert abs(before - after) <= 1  # slip noise may jitter a resting wheel by a count
    assert abs(x1 - x0) + abs(y1 - y0) < 1e-4
    assert hal.robot.applied_duty == (0.0, 0.0)


def test_forward_duty_counts_up_and_left_turn_reads_positive(backend):
    _, _, hal = backend
    start = _run_for(hal, 0.01)
    fwd = _run_for(hal, 0.5, duty=(0.3, 0.3))
    assert fwd.encoder_count - start.encoder_count > 100  # drove forward
    hal.stop()
    _run_for(hal, 1.0)
    turn = _run_for(hal, 0.5, duty=(-0.3, 0.3))  # right wheel forward: turn left, omega > 0
    bias = 1.5 * 131.0  # the simulated gyro's zero-rate bias in LSB
    assert turn.gyro_z_raw > bias + 500


def test_stop_zeroes_the_motors(backend):
    _, _, hal = backend
    _run_for(hal, 0.2, duty=(0.5, -0.5))
    hal.stop()
    _run_for(hal, 0.02)
    assert hal.robot.applied_duty == (0.0, 0.0)


def test_close_is_idempotent_and_stops(backend):
    _, _, hal = backend
    _run_for(hal, 0.1, duty=(0.4, 0.4))
    hal.close()
    hal.close()
    assert hal.robot.applied_duty == (0.0, 0.0) or hal.robot.applied_duty == (0.4, 0.4)
    hal.robot.advance_to(hal.robot.t + 0.01)
    assert hal.robot.applied_duty == (0.0, 0.0)


def test_simulated_backends_own_time_and_follow_the_wall_clock_when_paced(backend):
    name, cfg, hal = backend
    assert hal.owns_time
    t0 = hal.robot.t
    hal.advance_to_wall_clock()  # unpaced: sim time waits for sleep_until
    assert hal.robot.t == t0
    paced = open_hal(cfg, start=(0.0, 0.0, 0.0), paced=True)
    try:
        t0 = paced.robot.t
        time.sleep(0.05)
        paced.advance_to_wall_clock()
        # (t0 may stand up to one plant step ahead of the wall clock: sleeps end on the grid)
        assert paced.robot.t - t0 >= 0.05 - paced.robot.step_s
        assert paced.now() >= paced.robot.t - 1e-9
    finally:
        paced.close()


def test_closed_loop_through_real_drivers_matches_sim_backend():
    """Done-when of the hardware-layer issue: same accuracy through the real drivers."""
    sim_cfg = load_config(SCENARIO)
    emu_cfg = load_config(SCENARIO, EMULATED)
    path = resolve_path(sim_cfg)
    sim = run_sim(sim_cfg, path).metrics
    emu = run_sim(emu_cfg, path).metrics
    assert sim["completed"] and emu["completed"]
    assert emu["rms_tracking_m"] < 0.3e-3
    assert emu["rms_tracking_m"] < 1.5 * sim["rms_tracking_m"] + 0.02e-3
    assert emu["rms_cross_track_m"] < 2e-3


def test_corrupted_serial_bytes_are_counted_and_the_loop_keeps_going():
    cfg = load_config(SCENARIO, EMULATED)
    hal, loop = following(cfg)
    import random

    rng = random.Random(7)

    def corrupt(data: bytes) -> bytes:
        b = bytearray(data)
        if b and rng.random() < 0.05:
            b[rng.randrange(len(b))] ^= 0x10
        return bytes(b)

    hal.devices.link.to_host_filter = corrupt
    rows = tick_rows(hal, loop, 400)
    assert loop.state == LoopState.FOLLOWING, loop.fault
    counters = hal.fault_counters
    assert counters["bridge.crc_errors"] + counters["bridge.undecodable"] > 0
    assert rows[-1]["hal_fault_ticks"] > 0  # the reaction is visible in telemetry
    hal.close()


def test_a_silent_microcontroller_ends_in_a_safe_stop():
    # A read timeout is a transient fault until it persists for estimator.fault_latch_s
    # (0.5 s by default, so a 400 ms freeze is survived; tests/test_recovery.py). This test
    # pins the latch itself within 20 ticks, so it asks for a short one.
    cfg = load_config(SCENARIO, {**EMULATED, "estimator": {"fault_latch_s": 0.08}})
    hal, loop = following(cfg)
    tick_rows(hal, loop, 200)
    assert loop.state == LoopState.FOLLOWING
    hal.devices.link.to_host_filter = lambda data: b""  # the MCU stops answering
    rows = tick_rows(hal, loop, 100)
    assert loop.state == LoopState.FAULT
    assert "STATE" in loop.fault or "no new data" in loop.fault or "stale" in loop.fault
    assert len(rows) <= 20  # held for a bounded number of ticks, then stopped
    assert rows[-1]["fresh"] == 0.0 or rows[-1]["state"] == 5.0
    assert (loop.duty_l, loop.duty_r) == (0.0, 0.0)
    # The host's STOP never reaches the motors through a dead link only if the host side
    # is dead; here the host->MCU direction still works, so the MCU applied the STOP.
    hal.sleep_until(hal.now() + 0.01)
    assert hal.robot.applied_duty == (0.0, 0.0)
    hal.close()


def test_a_host_that_stops_talking_is_stopped_by_the_mcu_watchdog():
    cfg = load_config(SCENARIO, EMULATED)
    hal, loop = following(cfg)
    tick_rows(hal, loop, 200)
    assert hal.robot.applied_duty != (0.0, 0.0)
    t_dead = hal.now()  # the host process dies: no more DRIVE, no STOP
    while hal.robot.applied_duty != (0.0, 0.0) and hal.now() < t_dead + 1.0:
        hal.sleep_until(hal.now() + 0.001)
    timeout = cfg.hal.bridge.drive_timeout_ms / 1000.0
    assert hal.robot.applied_duty == (0.0, 0.0)
    assert hal.now() - t_dead <= timeout + cfg.sim.command_latency_s + 0.006
    hal.devices.close()


def test_microcontroller_reset_is_reported_and_the_count_stays_continuous():
    cfg = load_config(SCENARIO, EMULATED)
    hal, loop = following(cfg)
    tick_rows(hal, loop, 200)
    hal.devices.mcu.reset(hal.now())
    rows = tick_rows(hal, loop, 200)
    assert hal.fault_counters["bridge.mcu_resets"] >= 1
    # The MCU zeroed its outputs on reboot; the loop's next DRIVE re-applies them and the
    # stitched count keeps the estimator on the path.
    assert loop.state in (LoopState.FOLLOWING, LoopState.FAULT)
    if loop.state == LoopState.FOLLOWING:
        assert abs(loop.reference.cross_track) < 0.005
    hal.close()


def test_robot_config_validates_and_names_real_devices():
    cfg = load_config(REPO / "configs" / "robot.yaml")
    assert cfg.hal.backend == "real"
    assert cfg.hal.imu.bus == 1 and cfg.hal.imu.address == 0x68
    assert cfg.hal.bridge.url.startswith("/dev/")
    assert cfg.path is None  # the robot waits for `ddrt ctl follow`
    # Opening it here must fail cleanly (no I2C bus on this machine), never half-open.
    from hal.base import HalError

    with pytest.raises((HalError, OSError, ValueError)):
        hal = open_hal(cfg)
        hal.close()
