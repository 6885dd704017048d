"""The `real` backend: the gyro on I2C and the microcontroller on a serial port, as a `Hal`.

Fault reactions (the same for the emulated devices, which is how they are tested):
- an I/O error on a read is retried once (named "<dev>_retry" in Sample.faults);
- a read that yields no new data (no STATE since the last tick, or the retry failed too)
  repeats the last value with `fresh=False` ("<dev>_hold") while that value is no older than
  the bridge's stale bound (`hal.bridge.state_stale_s`, 50 ms): the loop holds for as many
  ticks as fit in that bound at its rate (10 at 200 Hz, 50 at 1 kHz), so a STATE pause the
  bridge accepts is one the HAL accepts too. `hal.hold_ticks`, if set, overrides this with a
  fixed number of ticks;
- beyond that, or when the STATE stream is older than the bridge's bound, HalTimeoutError:
  the loop holds the robot (a controlled stop) and resumes when data returns, or latches a
  fault if it does not (docs/design.md). A value is never invented: with no previous value
  the error is raised at once.

Each driver declares what it delivers (the gyro its hal.base.GyroCaps, the link its stale bound
and counters, the motors their watchdog); nothing here probes a driver for a capability.

The gyro through its FIFO (`sensors.gyro_fifo`, GyroCaps.fifo_period_s > 0): every read
drains it; the samples of a read whose Sample is not fresh (the encoder's STATE was late) are
carried over to the next fresh one, so the estimator sees each sample once (Sample.gyro_n,
gyro_sum_raw). A batch that lost samples (the driver reset its FIFO) is "imu_fifo_reset":
held like a failed read, and what was carried is dropped with it.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, Callable, Mapping, Protocol, Sequence

from ddrt.core.types import Clock
from ddrt.runtime.clock import MonotonicClock
from hal.base import (
    GyroCaps, Hal, HalError, HalInfo, HalInitError, HalIOError, HalTimeoutError, Sample,
)
from hal.bridge import Bridge
from hal.mpu6050 import FifoBatch, Mpu6050, gyro_scale, open_i2c_bus

if TYPE_CHECKING:
    from ddrt.config import Config

__all__ = ["Closeable", "EncoderReader", "EncoderState", "Imu", "Motors", "RealHal"]

_MISSING = object()
# bridge counters whose growth is reported in Sample.faults, and the name used there
_WATCHED = (("lost_packets", "lost_packets"), ("crc_errors", "crc_error"),
            ("undecodable", "bad_frame"), ("oversize", "bad_frame"),
            ("mcu_resets", "mcu_reset"), ("watchdog_trips", "mcu_watchdog"),
            ("mcu_bad_frames", "mcu_bad_frame"))


class Imu(Protocol):
    """A gyro: raw z reading, its configured range, and what else it delivers (`caps`):
    `read_gyro_fifo()` is called only when caps.fifo_period_s > 0, `read_temp_c()` only when
    caps.die_temp. It holds no resource of its own (the bus it is on is a closeable)."""

    gyro_range_dps: int
    fault_counts: Mapping[str, int]  # what it counted of the faults it saw (status: imu.<name>)
    gyro_part: str  # which part it is, as reports print it (HalInfo.gyro_part)

    @property
    def caps(self) -> GyroCaps: ...

    def read_gyro_z_raw(self) -> int: ...
    def read_gyro_fifo(self) -> FifoBatch: ...
    def read_temp_c(self) -> float: ...


class EncoderState(Protocol):
    """One STATE as the link reports it (hal.bridge.BridgeState)."""

    count: int
    new: bool
    battery_mv: int
    count_left: int
    count_right: int

    @property
    def hw_estop(self) -> bool: ...

    def count_at(self, t: float) -> int: ...
    def wheel_counts_at(self, t: float) -> tuple[int, int]: ...


class Closeable(Protocol):
    def close(self) -> None: ...


class EncoderReader(Protocol):
    """The encoder side of the Bridge: `state()` returns an EncoderState, and raises
    HalTimeoutError when the stream is older than `state_stale_s`. The MCU's facts from its
    handshake say what a STATE carries: no wheel counts while `wheel_counts_per_rev` is 0, no
    battery unless `battery_measured`. `stats`: its fault and traffic counters."""

    counts_per_rev: int
    wheel_counts_per_rev: int
    battery_measured: bool
    hw_estop_wired: bool
    state_stale_s: float

    @property
    def stats(self) -> Mapping[str, int]: ...

    def state(self) -> EncoderState: ...
    def close(self) -> None: ...


class Motors(Protocol):
    """Two motors. `drive_timeout_s`: their driver's own watchdog (it zeroes them when no
    command arrived for this long); None when they have none."""

    @property
    def drive_timeout_s(self) -> float | None: ...

    def drive(self, duty_l: float, duty_r: float) -> None: ...
    def stop(self) -> None: ...
    def close(self) -> None: ...


class RealHal(Hal):
    """`RealHal(imu, bridge, clock=...)`; the bridge also drives the motors unless `motors`
    (e.g. PwmSysfsMotors) is given. `closeables` are closed last (e.g. the SMBus)."""

    _ready = False  # the constructor finished: there are devices to stop and close
    _last_error: BaseException | None = None  # the I/O error behind the latest missing read

    def __init__(self, imu: Imu, bridge: EncoderReader, clock: Clock | None = None, *,
                 motors: Motors | None = None, hold_ticks: int | None = None,
                 closeables: Sequence[Closeable] = (), battery_scale: float = 1.0, temp_hz: float = 0.0) -> None:
        self.imu = imu
        self.encoder = bridge
        self.motors: Motors = motors if motors is not None else bridge  # type: ignore[assignment]
        self.clock = clock if clock is not None else MonotonicClock()
        self.hold_s = float(bridge.state_stale_s)  # the bridge's own bound: the HAL and it agree on what is stale
        self.hold_ticks = hold_ticks  # None: hold while the value is within hold_s (derived)
        self._closeables = list(closeables)
        if int(bridge.counts_per_rev) <= 0 and int(bridge.wheel_counts_per_rev) <= 0:
            # protocol v2 allows an MCU without a front encoder; the estimator then needs the wheels'
            raise HalInitError("the microcontroller reports no front encoder (encoder_counts_per_rev 0 "
                               "in its HELLO_REPLY) and no drive-wheel encoders: ddrt's estimator needs one "
                               "of them to measure distance")
        lsb, full = gyro_scale(imu.gyro_range_dps)
        caps = imu.caps
        self.info = HalInfo(encoder_counts_per_rev=int(bridge.counts_per_rev),
                            gyro_lsb_per_rad_s=lsb, gyro_full_scale_rad_s=full,
                            gyro_delay_s=float(caps.age_s), gyro_fifo_period_s=float(caps.fifo_period_s),
                            drive_timeout_s=self.motors.drive_timeout_s,
                            wheel_counts_per_rev=int(bridge.wheel_counts_per_rev),
                            battery_measured=bool(bridge.battery_measured),
                            hw_estop_wired=bool(bridge.hw_estop_wired),
                            gyro_temp_hz=float(temp_hz) if caps.die_temp else 0.0,
                            gyro_part=imu.gyro_part)
        self._temp_next_t = -math.inf  # clock time of the next TEMP_OUT read
        # V per mV the MCU reports: its divider's calibration against a multimeter
        # (sensors.battery_scale, docs/hardware.md), 1.0 when the firmware's is right
        self._v_per_mv = float(battery_scale) / 1000.0 if self.info.battery_measured else math.nan
        self._battery_v = math.nan
        self._hw_estop = False
        self._wheels = (0, 0)
        self._count: int | None = None
        self._read_t = 0.0
        self._gyro: int | None = None
        self._fifo_n = self._fifo_sum = 0  # FIFO samples read but not yet delivered in a fresh Sample
        self._enc_missing = 0
        self._gyro_missing = 0
        self._enc_new_t = self._gyro_new_t = 0.0  # clock time of each device's newest value
        self._bridge_seen = self._bridge_stats()
        self._counters = {
            "reads": 0, "stale_reads": 0, "encoder_retries": 0, "encoder_holds": 0,
            "imu_retries": 0, "imu_holds": 0, "timeouts": 0, "write_errors": 0,
            "stop_errors": 0, "close_errors": 0, "temp_errors": 0, "imu_fifo_resets": 0,
        }
        self._ready = True

    @property
    def hold_ticks(self) -> int | None:
        """A fixed hold in ticks (`hal.hold_ticks`), or None: hold within `hold_s`."""
        return self._hold_ticks

    @hold_ticks.setter
    def hold_ticks(self, value: int | None) -> None:
        if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 0):
            raise ValueError(f"hold_ticks: expected None or a non-negative int, got {value!r}")
        self._hold_ticks = value

    # -- Hal ------------------------------------------------------------------------------

    def read(self) -> Sample:
        faults: list[str] = []
        t = self.clock.now()
        self._read_t = t
        count, enc_fresh = self._read_encoder(faults)
        gyro, gyro_fresh = self._read_gyro(faults)
        temp_c = self._read_temp(t) if self.info.gyro_temp_hz > 0.0 and t >= self._temp_next_t else math.nan
        self._note_bridge_faults(faults)
        fresh = enc_fresh and gyro_fresh
        self._counters["reads"] += 1
        if not fresh:
            self._counters["stale_reads"] += 1
        n = total = 0
        if fresh and self._fifo_n:  # the samples since the last fresh Sample, delivered once
            n, total = self._fifo_n, self._fifo_sum
            self._fifo_n = self._fifo_sum = 0
        return Sample(t=t, encoder_count=count, gyro_z_raw=gyro, fresh=fresh,
                      faults=",".join(faults), battery_v=self._battery_v, hw_estop=self._hw_estop,
                      count_left=self._wheels[0], count_right=self._wheels[1], gyro_temp_c=temp_c,
                      gyro_n=n, gyro_sum_raw=total)

    def _read_temp(self, t: float) -> float:
        """TEMP_OUT, at most `gyro_temp_hz` times a second; NaN (counted) if it fails: a missing
        temperature only leaves the bias where it was, so it is no fault."""
        period = 1.0 / self.info.gyro_temp_hz
        nxt = self._temp_next_t + period
        self._temp_next_t = nxt if nxt > t else t + period  # no burst to catch up
        try:
            return float(self.imu.read_temp_c())
        except HalError:
            self._counters["temp_errors"] += 1
            return math.nan

    def _write(self, duty_l: float, duty_r: float) -> None:
        try:
            self.motors.drive(duty_l, duty_r)
        except HalIOError:
            self._counters["write_errors"] += 1
            raise

    def stop(self) -> None:
        try:
            self.motors.stop()
        except (HalError, OSError):
            self._counters["stop_errors"] += 1  # the device is gone; its watchdog stops it

    def _close(self) -> None:
        if not self._ready:
            return  # the constructor failed before any device was taken over
        self.stop()
        done: list[int] = []
        devices: tuple[Closeable, ...] = (self.motors, self.encoder, *self._closeables)
        for obj in devices:  # the gyro holds nothing: its bus is a closeable
            if id(obj) in done:
                continue
            done.append(id(obj))
            try:
                obj.close()
            except Exception:  # noqa: BLE001 - release everything else regardless
                self._counters["close_errors"] += 1

    @property
    def fault_counters(self) -> dict[str, int]:
        """Every fault counter of this backend and its devices, for telemetry and status."""
        out = dict(self._counters)
        for k, v in self._bridge_stats().items():
            out[f"bridge.{k}"] = v
        for k, v in self.imu.fault_counts.items():
            out[f"imu.{k}"] = v
        return out

    # -- internals ------------------------------------------------------------------------

    def _bridge_stats(self) -> dict[str, int]:
        return dict(self.encoder.stats)

    def _retry_once(self, fn: Callable[[], Any], dev: str, faults: list[str]) -> Any:
        """Call fn; on HalIOError (not a timeout: that bound is already spent) call it again.
        Returns _MISSING when the retry failed too."""
        try:
            return fn()
        except HalTimeoutError:
            raise
        except HalIOError:
            self._counters[f"{dev}_retries"] += 1
            faults.append(f"{dev}_retry")
        try:
            return fn()
        except HalTimeoutError:
            raise
        except HalIOError as e:
            self._last_error = e
            return _MISSING

    def _hold(self, dev: str, missing: int, since: float, have_last: bool, faults: list[str]) -> None:
        """Repeat the last value of `dev` (no new data for `missing` reads, the newest from
        clock time `since`), or raise HalTimeoutError when that is beyond the hold bound."""
        if self._hold_ticks is not None:
            over = missing > self._hold_ticks
            bound = f"hold_ticks={self._hold_ticks}"
        else:
            age = self.clock.now() - since
            over = age > self.hold_s + 1e-9
            bound = f"{age * 1e3:.1f} ms, beyond the {self.hold_s * 1e3:.1f} ms stale bound"
        if over or not have_last:
            self._counters["timeouts"] += 1
            cause = self._last_error
            last = f"; last error: {cause}" if cause is not None else ""
            raise HalTimeoutError(f"{dev}: no new data for {missing} tick(s) ({bound}){last}") from cause
        self._counters[f"{dev}_holds"] += 1
        faults.append(f"{dev}_hold")

    def _read_encoder(self, faults: list[str]) -> tuple[int, bool]:
        self._last_error = None
        try:
            st = self._retry_once(self.encoder.state, "encoder", faults)
        except HalTimeoutError:
            self._counters["timeouts"] += 1
            raise
        if st is _MISSING or not st.new:
            self._enc_missing += 1
            self._hold("encoder", self._enc_missing, self._enc_new_t, self._count is not None, faults)
            if st is not _MISSING:
                self._count = st.count  # same value; keeps a stitched count consistent
                self._note_v2(st, None)
            return self._count, False  # type: ignore[return-value]
        self._enc_missing = 0
        self._enc_new_t = self.clock.now()
        # the count as of this read: the MCU streams on its own clock, so the newest STATE's
        # age varies from tick to tick (BridgeState.count_at)
        count = st.count_at(self._read_t)
        self._count = count
        self._note_v2(st, self._read_t)
        return count, True

    def _note_v2(self, st: EncoderState, t: float | None) -> None:
        """Protocol v2's parts of a STATE: the supply (V; NaN when not measured), the
        hardware estop input, the drive-wheel counts (at the read time `t` when new)."""
        self._battery_v = st.battery_mv * self._v_per_mv  # NaN * anything: not measured
        self._hw_estop = bool(st.hw_estop)
        if self.info.wheel_counts_per_rev > 0:
            self._wheels = st.wheel_counts_at(t) if t is not None else (st.count_left, st.count_right)

    def _read_gyro(self, faults: list[str]) -> tuple[int, bool]:
        self._last_error = None
        fifo = self.info.gyro_fifo_period_s > 0.0
        try:
            raw = self._retry_once(self.imu.read_gyro_fifo if fifo else self.imu.read_gyro_z_raw, "imu", faults)
        except HalTimeoutError as e:
            raw = _MISSING
            self._last_error = e
        if fifo and raw is not _MISSING:
            raw = self._take_batch(raw, faults)
        if raw is _MISSING:
            self._gyro_missing += 1
            self._hold("imu", self._gyro_missing, self._gyro_new_t, self._gyro is not None, faults)
            return self._gyro, False  # type: ignore[return-value]
        self._gyro_missing = 0
        self._gyro_new_t = self.clock.now()
        self._gyro = raw
        return raw, True

    def _take_batch(self, batch: Any, faults: list[str]) -> Any:
        """A FIFO batch: carried until the next fresh Sample; its newest sample (the last one's
        when it has none) as the reading, or _MISSING when it lost samples."""
        if batch.lost:
            self._counters["imu_fifo_resets"] += 1
            faults.append("imu_fifo_reset")
            self._fifo_n = self._fifo_sum = 0
            return _MISSING
        if batch.n:
            self._fifo_n += batch.n
            self._fifo_sum += batch.sum_raw
            return batch.last_raw
        if self._gyro is not None:
            return self._gyro
        try:  # nothing yet at the very first read: the register gives a value to start from
            return self.imu.read_gyro_z_raw()
        except HalError:
            return _MISSING

    def _note_bridge_faults(self, faults: list[str]) -> None:
        now = self._bridge_stats()
        seen = self._bridge_seen
        for key, name in _WATCHED:
            if now.get(key, 0) != seen.get(key, 0) and name not in faults:
                faults.append(name)
        self._bridge_seen = now

    # -- construction from config ----------------------------------------------------------

    @classmethod
    def from_config(cls, cfg: "Config", clock: Clock | None = None, *,
                    i2c_bus: Any = None, watch_repeats: bool = True) -> "RealHal":
        """Build from a validated config: its `hal` section and `sensors.gyro_range_dps`.

        The walker (ddrt.config) has checked every value and range; what is left here is
        what only opening needs: `hal.imu.bus: sim` needs the emulated bus passed as `i2c_bus`.
        `watch_repeats=False` (an emulated gyro quieter than any real part only): the driver
        does not take a repeated output word for a frozen part.
        """
        clock = clock if clock is not None else MonotonicClock()
        hal = cfg.hal
        hal.check_real("hal")  # a config loaded for the sim backend may lack the devices
        imu_cfg, link, pwm_cfg = hal.imu, hal.bridge, hal.pwm_sysfs
        if imu_cfg.bus == "sim" and i2c_bus is None:
            raise ValueError("hal.imu.bus: 'sim' needs the emulated bus passed as i2c_bus=")
        if link.url is None:
            raise ValueError("hal.bridge.url: missing (only the emulated devices provide their own)")
        opened: list[Any] = []
        try:
            bus = i2c_bus if i2c_bus is not None else open_i2c_bus(imu_cfg.bus)
            if i2c_bus is None:
                opened.append(bus)
            imu = Mpu6050(bus, imu_cfg.address, cfg.sensors.gyro_range_dps, imu_cfg.dlpf_cfg,
                          imu_cfg.sample_rate_div, fifo=cfg.sensors.gyro_fifo, clock=clock.now,
                          watch_repeats=watch_repeats)
            bridge = Bridge(link.url, link.baudrate, link.drive_timeout_ms, link.state_stale_s, clock=clock)
            opened.append(bridge)
            motors = None
            if hal.motors == "pwm_sysfs":
                from hal.pwm_sysfs import PwmSysfsMotors

                motors = PwmSysfsMotors(chip=pwm_cfg.chip, channels=pwm_cfg.channels,
                                        period_ns=pwm_cfg.period_ns,
                                        direction_gpios=pwm_cfg.direction_gpios, root=pwm_cfg.root)
                opened.append(motors)
            owned = [bus] if i2c_bus is None else []
            return cls(imu, bridge, clock, motors=motors, hold_ticks=hal.hold_ticks, closeables=owned,
                       battery_scale=cfg.sensors.battery_scale, temp_hz=cfg.sensors.gyro_temp_hz)
        except BaseException:
            for obj in reversed(opened):
                try:
                    obj.close()
                except Exception:  # noqa: BLE001
                    pass
            raise

