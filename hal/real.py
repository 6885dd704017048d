"""The `real` backend: the gyro on I2C and the microcontroller on a serial port, as a `Hal`.

Fault reactions (the same for the emulated devices, which is how they are tested):
- an I/O error on a read is retried once (named "<dev>_retry" in Sample.faults);
- a read that yields no new data (no STATE since the last tick, or the retry failed too)
  repeats the last value with `fresh=False` for at most `hold_ticks` ticks in a row
  ("<dev>_hold");
- beyond that, or when the STATE stream is older than the bridge's bound, HalTimeoutError,
  so the loop performs a safe stop. A value is never invented: with no previous value the
  error is raised at once.
"""

from __future__ import annotations

from typing import Any, Callable, Mapping, Protocol, Sequence

from ddrt.core.types import Clock
from ddrt.service.clock import MonotonicClock
from hal.base import (
    Hal, HalError, HalInfo, HalIOError, HalTimeoutError, Sample,
)
from hal.bridge import Bridge
from hal.mpu6050 import DEFAULT_ADDRESS, Mpu6050, gyro_scale, open_i2c_bus

__all__ = ["EncoderReader", "Imu", "Motors", "RealHal"]

_MISSING = object()
# bridge counters whose growth is reported in Sample.faults, and the name used there
_WATCHED = (("lost_packets", "lost_packets"), ("crc_errors", "crc_error"),
            ("undecodable", "bad_frame"), ("oversize", "bad_frame"),
            ("mcu_resets", "mcu_reset"), ("watchdog_trips", "mcu_watchdog"),
            ("mcu_bad_frames", "mcu_bad_frame"))


class Imu(Protocol):
    """A gyro: raw z reading and its configured range."""

    gyro_range_dps: int
    gyro_delay_s: float  # group delay of its low-pass

    def read_gyro_z_raw(self) -> int: ...


class EncoderReader(Protocol):
    """The encoder side of the Bridge: `state()` returns an object with `count`, `new` and
    `resets` (hal.bridge.BridgeState) and raises HalTimeoutError when stale."""

    counts_per_rev: int

    def state(self) -> Any: ...
    def close(self) -> None: ...


class Motors(Protocol):
    def drive(self, duty_l: float, duty_r: float) -> None: ...
    def stop(self) -> None: ...
    def close(self) -> None: ...


class RealHal(Hal):
    """`RealHal(imu, bridge, clock=...)`; the bridge also drives the motors unless `motors`
    (e.g. PwmSysfsMotors) is given. `closeables` are closed last (e.g. the SMBus)."""

    def __init__(self, imu: Imu, bridge: EncoderReader, clock: Clock | None = None, *,
                 motors: Motors | None = None, hold_ticks: int = 3,
                 closeables: Sequence[Any] = ()) -> None:
        if isinstance(hold_ticks, bool) or not isinstance(hold_ticks, int) or hold_ticks < 0:
            raise ValueError(f"hold_ticks: expected a non-negative int, got {hold_ticks!r}")
        self.imu = imu
        self.encoder = bridge
        self.motors: Motors = motors if motors is not None else bridge  # type: ignore[assignment]
        self.clock = clock if clock is not None else MonotonicClock()
        self.hold_ticks = hold_ticks
        self._closeables = list(closeables)
        lsb, full = gyro_scale(imu.gyro_range_dps)
        self.info = HalInfo(encoder_counts_per_rev=int(bridge.counts_per_rev),
                            gyro_lsb_per_rad_s=lsb, gyro_full_scale_rad_s=full,
                            gyro_delay_s=float(imu.gyro_delay_s))
        self._count: int | None = None
        self._read_t = 0.0
        self._gyro: int | None = None
        self._enc_missing = 0
        self._gyro_missing = 0
        self._last_error: BaseException | None = None
        self._bridge_seen = self._bridge_stats()
        self._counters = {
            "reads": 0, "stale_reads": 0, "encoder_retries": 0, "encoder_holds": 0,
            "imu_retries": 0, "imu_holds": 0, "timeouts": 0, "write_errors": 0,
            "stop_errors": 0, "close_errors": 0,
        }

    # -- Hal ------------------------------------------------------------------------------

    def read(self) -> Sample:
        faults: list[str] = []
        t = self.clock.now()
        self._read_t = t
        count, enc_fresh = self._read_encoder(faults)
        gyro, gyro_fresh = self._read_gyro(faults)
        self._note_bridge_faults(faults)
        fresh = enc_fresh and gyro_fresh
        self._counters["reads"] += 1
        if not fresh:
            self._counters["stale_reads"] += 1
        return Sample(t=t, encoder_count=count, gyro_z_raw=gyro, fresh=fresh,
                      faults=",".join(faults))

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
        if not hasattr(self, "_counters"):
            return  # the constructor failed before any device was taken over
        self.stop()
        done: list[int] = []
        for obj in (self.motors, self.encoder, self.imu, *self._closeables):
            close = getattr(obj, "close", None)
            if close is None or id(obj) in done:
                continue
            done.append(id(obj))
            try:
                close()
            except Exception:  # noqa: BLE001 - release everything else regardless
                self._counters["close_errors"] += 1

    @property
    def fault_counters(self) -> dict[str, int]:
        """Every fault counter of this backend and its devices, for telemetry and status."""
        out = dict(self._counters)
        for k, v in self._bridge_stats().items():
            out[f"bridge.{k}"] = v
        for k in ("retries", "errors"):
            v = getattr(self.imu, k, None)
            if isinstance(v, int):
                out[f"imu.{k}"] = v
        return out

    # -- internals ------------------------------------------------------------------------

    def _bridge_stats(self) -> dict[str, int]:
        stats = getattr(self.encoder, "stats", None)
        return dict(stats) if isinstance(stats, Mapping) else {}

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

    def _hold(self, dev: str, missing: int, have_last: bool, faults: list[str]) -> None:
        if missing > self.hold_ticks or not have_last:
            self._counters["timeouts"] += 1
            cause = getattr(self, "_last_error", None)
            raise HalTimeoutError(f"{dev}: no new data for {missing} tick(s) "
                                  f"(hold_ticks={self.hold_ticks})") from cause
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
            self._hold("encoder", self._enc_missing, self._count is not None, faults)
            if st is not _MISSING:
                self._count = st.count  # same value; keeps a stitched count consistent
            return self._count, False  # type: ignore[return-value]
        self._enc_missing = 0
        # the count as of this read: the MCU streams on its own clock, so the newest STATE's
        # age varies from tick to tick (BridgeState.count_at; devices without it report as is)
        count_at = getattr(st, "count_at", None)
        count = count_at(self._read_t) if count_at is not None else st.count
        self._count = count
        return count, True

    def _read_gyro(self, faults: list[str]) -> tuple[int, bool]:
        self._last_error = None
        try:
            raw = self._retry_once(self.imu.read_gyro_z_raw, "imu", faults)
        except HalTimeoutError as e:
            raw = _MISSING
            self._last_error = e
        if raw is _MISSING:
            self._gyro_missing += 1
            self._hold("imu", self._gyro_missing, self._gyro is not None, faults)
            return self._gyro, False  # type: ignore[return-value]
        self._gyro_missing = 0
        self._gyro = raw
        return raw, True

    def _note_bridge_faults(self, faults: list[str]) -> None:
        now = self._bridge_stats()
        seen = self._bridge_seen
        for key, name in _WATCHED:
            if now.get(key, 0) != seen.get(key, 0) and name not in faults:
                faults.append(name)
        self._bridge_seen = now

    # -- construction from config ----------------------------------------------------------

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any], clock: Clock | None = None, *,
                    i2c_bus: Any = None) -> "RealHal":
        """Build from the `hal` section of a config (nested mappings, or flat dotted keys).

        `hal.imu.bus: sim` needs the emulated bus passed as `i2c_bus`. Every value is
        validated before any device is opened; errors name the key.
        """
        g = _ConfigReader(cfg)
        bus_spec = g.get("hal.imu.bus")
        if isinstance(bus_spec, bool) or not (
                (isinstance(bus_spec, int) and bus_spec >= 0) or bus_spec == "sim"):
            raise ValueError(f"hal.imu.bus: expected a bus number or 'sim', got {bus_spec!r}")
        if bus_spec == "sim" and i2c_bus is None:
            raise ValueError("hal.imu.bus: 'sim' needs the emulated bus passed as i2c_bus=")
        address = g.integer("hal.imu.address", DEFAULT_ADDRESS, 0x03, 0x77)
        rng = g.get("hal.imu.gyro_range_dps", 250)
        try:
            gyro_scale(rng)
        except ValueError as e:
            raise ValueError(f"hal.imu.{e}") from None
        dlpf = g.integer("hal.imu.dlpf_cfg", 2, 0, 6)
        div = g.integer("hal.imu.sample_rate_div", 4, 0, 255)
        url = g.get("hal.bridge.url")
        if not isinstance(url, str) or not url:
            raise ValueError(f"hal.bridge.url: expected a serial port or URL string, got {url!r}")
        baud = g.integer("hal.bridge.baudrate", 115200, 1, 10_000_000)
        drive_ms = g.integer("hal.bridge.drive_timeout_ms", 100, 1, 1000)
        stale = g.pos_float("hal.bridge.state_stale_s", 0.05)
        hold = g.integer("hal.hold_ticks", 3, 0, 1000)
        motors_kind = g.get("hal.motors", "bridge")
        if motors_kind not in ("bridge", "pwm_sysfs"):
            raise ValueError(f"hal.motors: expected 'bridge' or 'pwm_sysfs', got {motors_kind!r}")
        pwm: dict[str, Any] = {}
        if motors_kind == "pwm_sysfs":
            pwm["chip"] = g.integer("hal.pwm_sysfs.chip", 0, 0, 1 << 16)
            pwm["channels"] = g.int_pair("hal.pwm_sysfs.channels", (0, 1))
            pwm["period_ns"] = g.integer("hal.pwm_sysfs.period_ns", 50_000, 1, 1_000_000_000)
            pwm["direction_gpios"] = g.int_pair("hal.pwm_sysfs.direction_gpios")
            root = g.get("hal.pwm_sysfs.root", "/sys")
            if not isinstance(root, str) or not root:
                raise ValueError(f"hal.pwm_sysfs.root: expected a directory path, got {root!r}")
            pwm["root"] = root

        opened: list[Any] = []
        try:
            bus = i2c_bus if i2c_bus is not None else open_i2c_bus(bus_spec)
            if i2c_bus is None:
                opened.append(bus)
            imu = Mpu6050(bus, address, rng, dlpf, div)
            bridge = Bridge(url, baud, drive_ms, stale, clock=clock)
            opened.append(bridge)
            motors = None
            if motors_kind == "pwm_sysfs":
                from hal.pwm_sysfs import PwmSysfsMotors

                motors = PwmSysfsMotors(**pwm)
                opened.append(motors)
            owned = [bus] if i2c_bus is None else []
            return cls(imu, bridge, clock, motors=motors, hold_ticks=hold, closeables=owned)
        except BaseException:
            for obj in reversed(opened):
                try:
                    obj.close()
                except Exception:  # noqa: BLE001
                    pass
            raise


class _ConfigReader:
    """Looks up dotted keys in nested mappings (or flat dotted keys) and validates them."""

    def __init__(self, cfg: Mapping[str, Any]) -> None:
        if not isinstance(cfg, Mapping):
            raise ValueError(f"config: expected a mapping, got {type(cfg).__name__}")
        self.cfg = cfg

    def get(self, key: str, default: Any = _MISSING) -> Any:
        if key in self.cfg:
            return self.cfg[key]
        node: Any = self.cfg
        for part in key.split("."):
            if not isinstance(node, Mapping) or part not in node:
                if default is _MISSING:
                    raise ValueError(f"{key}: missing")
                return default
            node = node[part]
        return node

    def integer(self, key: str, default: Any, lo: int, hi: int) -> int:
        v = self.get(key, default)
        if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
            raise ValueError(f"{key}: expected an int in {lo}..{hi}, got {v!r}")
        return v

    def pos_float(self, key: str, default: Any) -> float:
        v = self.get(key, default)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0 < v < float("inf"):
            raise ValueError(f"{key}: expected a positive number, got {v!r}")
        return float(v)

    def int_pair(self, key: str, default: Any = _MISSING) -> tuple[int, int]:
        v = self.get(key, default)
        if (not isinstance(v, (list, tuple)) or len(v) != 2
                or not all(isinstance(x, int) and not isinstance(x, bool) and x >= 0 for x in v)):
            raise ValueError(f"{key}: expected two non-negative ints, got {v!r}")
        return int(v[0]), int(v[1])
