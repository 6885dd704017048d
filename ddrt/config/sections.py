"""The config's sections: typed, frozen dataclasses whose field types are the schema.

docs/config.md documents every key once, with its unit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal, Mapping

from ddrt.params.robot import RobotParams
from ddrt.params.gyro_scale import GYRO_RANGES_DPS
from ddrt.params.motor import MotorParams
from ddrt.config.wiring import WiringConfig
from ddrt.config.schema import (
    LIVE, NEXT_PATH, RESTART, ConfigError, applies, non_negative, positive, restart,
)
from ddrt.config.sim_truth import SimConfig
from ddrt.config.ros2 import Ros2Config

# --------------------------------------------------------------------------- sections


@dataclass(frozen=True)
class SensorsConfig:
    """Facts about the sensors both the controller and the simulated robot share."""

    APPLY: ClassVar[str] = RESTART  # the devices are configured when opened

    encoder_counts_per_rev: int = 8192  # the front omni wheel's encoder; 0: none (then the drive wheels' are needed)
    gyro_range_dps: int = 250
    wheel_counts_per_rev: int = 0  # drive-wheel encoders (protocol v2); 0: not counted
    battery_scale: float = 1.0  # true / reported supply voltage (divider calibration)
    # The two gyro keys below default per backend (`for_backend`): these values are the
    # simulated backend's, REAL_MPU_DEFAULTS a real MPU's (hal.backend: real).
    gyro_temp_hz: float = 0.0  # Hz: how often the gyro's TEMP_OUT is read (temperature-compensated bias); 0: never
    gyro_fifo: bool = False  # read every gyro sample once through the MPU's FIFO (their mean and count); False: the register at the tick

    # On a real MPU (the robot's, or the emulated one behind the real driver) its die warms by
    # degrees after power-up and its zero-rate output with it, and its sample clock beats
    # against the loop's: TEMP_OUT read and the FIFO on measured better there (docs/BENCHMARKS.md,
    # "Sensing: a warming gyro with the shipped config"). The simulated backend's default gyro
    # neither warms nor has a sample clock, so it keeps both off (and integrates in its C kernel).
    REAL_MPU_DEFAULTS: ClassVar[dict[str, Any]] = {"gyro_temp_hz": 5.0, "gyro_fifo": True}

    @classmethod
    def for_backend(cls, backend: str) -> "SensorsConfig":
        """The section's defaults for `hal.backend` (a missing key takes these)."""
        return cls(**cls.REAL_MPU_DEFAULTS) if backend == "real" else cls()

    def validate(self, where: str) -> None:
        non_negative(where, encoder_counts_per_rev=self.encoder_counts_per_rev,
                     wheel_counts_per_rev=self.wheel_counts_per_rev)
        if self.encoder_counts_per_rev == 0 and self.wheel_counts_per_rev == 0:
            raise ConfigError(f"{where}.encoder_counts_per_rev: 0 (no front encoder) needs the drive wheels' "
                              f"encoders ({where}.wheel_counts_per_rev > 0): the robot needs one distance sensor")
        if not 0.0 <= self.gyro_temp_hz <= 50.0:
            raise ConfigError(f"{where}.gyro_temp_hz: must be in [0, 50] Hz (0: TEMP_OUT not read), "
                              f"got {self.gyro_temp_hz}")
        if not 0.5 <= self.battery_scale <= 2.0:
            raise ConfigError(f"{where}.battery_scale: must be in [0.5, 2] (true / reported "
                              f"voltage), got {self.battery_scale}")
        if self.gyro_range_dps not in GYRO_RANGES_DPS:
            raise ConfigError(f"{where}.gyro_range_dps: must be one of {', '.join(map(str, GYRO_RANGES_DPS))}, "
                              f"got {self.gyro_range_dps}")


def _in_range(where: str, key: str, value: int, lo: int, hi: int) -> None:
    if not lo <= value <= hi:
        raise ConfigError(f"{where}.{key}: must be {lo}..{hi}, got {value}")


@dataclass(frozen=True)
class ImuConfig:
    """The MPU-6050 on I2C (real backend). Its range is sensors.gyro_range_dps."""

    MOVED: ClassVar[dict[str, str]] = {
        "gyro_range_dps": "use sensors.gyro_range_dps, the one gyro range (the driver is configured from it)"}

    bus: int | str | None = None  # I2C bus number or "sim"; required with hal.backend: real
    address: int = 0x68
    dlpf_cfg: int = 2
    sample_rate_div: int = 4

    def validate(self, where: str) -> None:
        if isinstance(self.bus, str) and self.bus != "sim":
            raise ConfigError(f"{where}.bus: expected a bus number or 'sim', got {self.bus!r}")
        if isinstance(self.bus, int) and self.bus < 0:
            raise ConfigError(f"{where}.bus: expected a bus number >= 0 or 'sim', got {self.bus}")
        _in_range(where, "address", self.address, 0x03, 0x77)
        _in_range(where, "dlpf_cfg", self.dlpf_cfg, 0, 6)
        _in_range(where, "sample_rate_div", self.sample_rate_div, 0, 255)


@dataclass(frozen=True)
class BridgeConfig:
    """The serial link to the microcontroller (real backend)."""

    url: str | None = None  # required with hal.backend: real, unless hal.imu.bus is "sim"
    baudrate: int = 115200
    drive_timeout_ms: int = 100
    state_stale_s: float = 0.05

    def validate(self, where: str) -> None:
        if self.url is not None and not self.url:
            raise ConfigError(f"{where}.url: expected a serial port or URL, got ''")
        _in_range(where, "baudrate", self.baudrate, 1, 10_000_000)
        _in_range(where, "drive_timeout_ms", self.drive_timeout_ms, 1, 1000)
        positive(where, state_stale_s=self.state_stale_s)


@dataclass(frozen=True)
class PwmSysfsConfig:
    """Motors on the Linux PWM class plus direction GPIOs (real backend, hal.motors: pwm_sysfs)."""

    chip: int = 0
    channels: tuple[int, int] = (0, 1)
    period_ns: int = 50_000
    direction_gpios: tuple[int, int] | None = None  # required with hal.motors: pwm_sysfs
    root: str = "/sys"

    def validate(self, where: str) -> None:
        _in_range(where, "chip", self.chip, 0, 1 << 16)
        _in_range(where, "period_ns", self.period_ns, 1, 1_000_000_000)
        for key in ("channels", "direction_gpios"):
            pair = getattr(self, key)
            if pair is not None and min(pair) < 0:
                raise ConfigError(f"{where}.{key}: expected two numbers >= 0, got {list(pair)}")
        if not self.root:
            raise ConfigError(f"{where}.root: expected a directory, got ''")


@dataclass(frozen=True)
class HalConfig:
    """Which backend drives the robot, and the real backend's devices."""

    APPLY: ClassVar[str] = RESTART  # the devices are opened once

    backend: Literal["sim", "real"] = "sim"
    motors: Literal["bridge", "pwm_sysfs"] = "bridge"
    imu: ImuConfig = field(default_factory=ImuConfig)
    bridge: BridgeConfig = field(default_factory=BridgeConfig)
    pwm_sysfs: PwmSysfsConfig = field(default_factory=PwmSysfsConfig)
    hold_ticks: int | None = None  # None: hold a stale value as long as hal.bridge.state_stale_s allows
    wiring: WiringConfig = field(default_factory=WiringConfig)  # motor and sensor directions, fixed in software

    def validate(self, where: str) -> None:
        if self.hold_ticks is not None:
            _in_range(where, "hold_ticks", self.hold_ticks, 0, 1000)
        if self.backend == "real":
            self.check_real(where)

    def check_real(self, where: str = "hal") -> None:
        """The keys the real backend needs that have no default (also checked when it opens)."""
        if self.imu.bus is None:
            raise ConfigError(f"{where}.imu.bus: missing (required with hal.backend: real)")
        if self.bridge.url is None and self.imu.bus != "sim":
            raise ConfigError(f"{where}.bridge.url: missing (required with hal.backend: real)")
        if self.motors == "pwm_sysfs" and self.pwm_sysfs.direction_gpios is None:
            raise ConfigError(f"{where}.pwm_sysfs.direction_gpios: missing (required with hal.motors: pwm_sysfs)")


@dataclass(frozen=True)
class OuterGains:
    """Kanayama's tracking law (seed eq. 4.3): K_x (1/s), K_y (1/m^2), K_theta (1/m)."""

    k_x: float = 10.0
    k_y: float = 400.0
    k_theta: float = 40.0

    def validate(self, where: str) -> None:
        positive(where, k_x=self.k_x, k_y=self.k_y, k_theta=self.k_theta)


@dataclass(frozen=True)
class PidGains:
    """A PID on a speed error: kp, ki, kd and the clamp of the integrated error. Two sections take
    it with their own defaults and units (INNER_PID, WHEEL_PID): a key missing from one takes
    that section's default (the walker builds a section over its field's default)."""

    kp: float
    ki: float
    kd: float
    integrator_limit: float

    def validate(self, where: str) -> None:
        non_negative(where, kp=self.kp, ki=self.ki, kd=self.kd)
        positive(where, integrator_limit=self.integrator_limit)


# controller.inner: PID on a velocity error. Units follow the loop: kp (1/s), ki (1/s^2), kd (-).
INNER_PID = PidGains(kp=20.0, ki=100.0, kd=0.0, integrator_limit=0.2)
# controller.wheel_pid: the kinematic baseline's per-wheel speed PID: duty per rad/s of wheel-speed error.
WHEEL_PID = PidGains(kp=0.15, ki=1.5, kd=0.0, integrator_limit=0.3)


@dataclass(frozen=True)
class AdaptationConfig:
    """Online estimation of the lumped dynamic parameters: on, as measured over a population of
    robots (docs/adaptation.md, "On by default"); false for the configured model alone."""

    enabled: bool = True
    forgetting: float = 0.999
    min_excitation: float = 0.05  # m/s^2 (yaw: times the half track) of filtered acceleration
    filter_hz: float = 2.0  # cut-off of the low-pass both sides of the regression pass through
    min_updates: int = 200  # excited updates before the estimate replaces the configured model
    bound_ratio: float = 3.0  # m + k and I stay within [1/ratio, ratio] x configured
    max_com_shift_m: float = 0.05  # mbar, m_x move at most this x (m + k) x ratio from configured
    max_friction_nm: float = 0.1  # bound on the extra Coulomb friction at each wheel (N m)
    min_wheel_speed: float = 1.0  # rad/s: both wheels faster than this, else no update
    blend_s: float = 1.0  # time constant with which the model in use follows the estimate
    update_estimator: bool = False  # also hand the estimate to the estimator's prediction
    min_improvement: float = 0.2  # the estimate is used once its RMS residual is this fraction below the configured model's
    noise_accel: float = 0.3  # m/s^2: residual of one filtered row / (m + k); sets how fast data outweighs the configured values

    def validate(self, where: str) -> None:
        if not 0.9 <= self.forgetting <= 1.0:
            raise ConfigError(f"{where}.forgetting: must be in [0.9, 1], got {self.forgetting}")
        non_negative(where, min_excitation=self.min_excitation, min_updates=self.min_updates,
                     blend_s=self.blend_s, min_wheel_speed=self.min_wheel_speed)
        positive(where, filter_hz=self.filter_hz, max_com_shift_m=self.max_com_shift_m,
                 max_friction_nm=self.max_friction_nm, noise_accel=self.noise_accel)
        if not 0.0 <= self.min_improvement < 1.0:
            raise ConfigError(f"{where}.min_improvement: must be in [0, 1), got {self.min_improvement}")
        if not self.bound_ratio > 1.0:
            raise ConfigError(f"{where}.bound_ratio: must be > 1, got {self.bound_ratio}")


@dataclass(frozen=True)
class ControllerConfig:
    """The three-stage controller (or the kinematic baseline, or the seed's own method)."""

    APPLY: ClassVar[str] = LIVE  # gains are retuned between two ticks, bumplessly

    mode: Literal["dynamic", "kinematic", "seed"] = restart("dynamic")
    rate_hz: float = restart(200.0)
    outer: OuterGains = field(default_factory=OuterGains)
    inner: PidGains = INNER_PID
    wheel_pid: PidGains = WHEEL_PID
    heading_gain: float = 8.0
    adaptation: AdaptationConfig = restart(factory=AdaptationConfig)  # the adapter is built at start

    def validate(self, where: str) -> None:
        positive(where, rate_hz=self.rate_hz, heading_gain=self.heading_gain)
        if self.rate_hz > 2000:
            raise ConfigError(f"{where}.rate_hz: above 2000 Hz is not supported, got {self.rate_hz}")
        if self.rate_hz < 1.0:
            raise ConfigError(f"{where}.rate_hz: below 1 Hz is not supported, got {self.rate_hz}")


@dataclass(frozen=True)
class EstimatorConfig:
    """Kalman filter tuning and sensor supervision."""

    APPLY: ClassVar[str] = LIVE  # the estimator re-derives its scales and noises between two ticks

    calibration_s: float = restart(1.0)  # used by the start-up calibration; the bias keeps being refined afterwards while the robot stands still
    calibration_max_std_dps: float = restart(0.5)
    accel_noise: float = 0.5  # m/s^2 white acceleration the model does not explain (speed for feedback)
    odometry_accel_noise: float = 20.0  # the same for the speed the pose integrates (trusts the encoder)
    yaw_accel_noise: float = 5.0  # rad/s^2 likewise for yaw
    odometry_yaw_accel_noise: float = 50.0  # the same for the yaw rate the heading integrates
    gyro_bias_walk: float = 1e-5  # rad/s per sqrt(s): drift of the zero-rate bias
    gyro_scale: float = 1.0  # believed gyro scale factor (1 + scale error), from calibration
    gyro_noise_dps: float = 0.07  # std of one gyro sample (deg/s) after the MPU's low-pass
    gyro_delay_s: float | None = None  # lag of the gyro's low-pass to undo; None: what the HAL reports
    # deg/s per degC: the zero-rate bias's temperature slope (commissioning); None: learnt at
    # the stops (ddrt/core/gyro_bias.py; only with sensors.gyro_temp_hz > 0)
    gyro_bias_per_c_dps: float | None = None
    gate_sigma: float = 5.0  # innovations beyond this many sigma are outliers
    max_rejects: int = 10  # after this many outliers in a row, re-sync and report
    stale_ticks: int = 20  # ticks without a fresh sample while moving: hold (controlled stop)
    max_gap_s: float = 0.05  # longer than this (and 10 ticks) without a fresh sample while moving: hold
    fault_latch_s: float = 0.5  # without a fresh sample this long: the fault latches (run ends)
    max_holds: int = 5  # more sensor holds (not loop stalls) than this within hold_window_s: the fault latches
    hold_window_s: float = 60.0
    zero_motors_after_s: float | None = None  # blind this long in a hold: motors to zero; None: the HAL's DRIVE watchdog
    stuck_gyro_ticks: int = 100  # identical raw gyro readings in a row = stuck sensor
    encoder_stuck_s: float = 0.3  # commanded motion but no encoder counts for this long
    # The pose's uncertainty and pose fixes (docs/estimation.md).
    encoder_scale_std: float = 0.01  # 1 sigma relative error of r_3 (metres per count)
    gyro_scale_std: float = 0.0173  # 1 sigma relative error of gyro_scale (MPU-6050: +-3 %, uniform)
    fix_history_s: float = 2.0  # how late a pose fix may arrive (s of odometry kept)
    fix_gate_chi2: float = 16.27  # Mahalanobis^2 beyond which a fix is an outlier (chi-square 3 dof, 0.999)
    map_blend_s: float = 0.5  # a path in `map` follows a fix's correction with this time constant
    # rad/s per sqrt(s): the bias drift the pose's error model allows for (the reported
    # uncertainty, the fixes' gate and gain), at least gyro_bias_walk: a warming MPU-6050
    # drifts ~0.01 deg/s per s, i.e. 3e-4 over the few seconds between fixes (docs/estimation.md)
    uncertainty_bias_walk: float = 3e-4
    # With drive-wheel encoders (sensors.wheel_counts_per_rev > 0; ddrt/core/wheel_odometry.py).
    wheel_bias_walk: float = 1e-4  # rad/s per sqrt(s): the bias drift the wheels track on the move
    wheel_scale_std: float = 0.02  # 1 sigma relative error of r_L, r_R (tyres under load)

    def validate(self, where: str) -> None:
        non_negative(where, encoder_scale_std=self.encoder_scale_std, gyro_scale_std=self.gyro_scale_std,
                     map_blend_s=self.map_blend_s, uncertainty_bias_walk=self.uncertainty_bias_walk)
        positive(where, fix_gate_chi2=self.fix_gate_chi2)
        non_negative(where, wheel_bias_walk=self.wheel_bias_walk, wheel_scale_std=self.wheel_scale_std)
        for key in ("encoder_scale_std", "gyro_scale_std", "wheel_scale_std"):
            if getattr(self, key) > 0.5:
                raise ConfigError(f"{where}.{key}: at most 0.5 (a relative error), got {getattr(self, key)}")
        if not 0.05 <= self.fix_history_s <= 30.0:
            raise ConfigError(f"{where}.fix_history_s: must be in [0.05, 30] s, got {self.fix_history_s}")
        positive(where, max_gap_s=self.max_gap_s, accel_noise=self.accel_noise,
                 odometry_accel_noise=self.odometry_accel_noise, yaw_accel_noise=self.yaw_accel_noise,
                 odometry_yaw_accel_noise=self.odometry_yaw_accel_noise,
                 gate_sigma=self.gate_sigma, gyro_scale=self.gyro_scale, gyro_noise_dps=self.gyro_noise_dps,
                 calibration_max_std_dps=self.calibration_max_std_dps, encoder_stuck_s=self.encoder_stuck_s)
        non_negative(where, calibration_s=self.calibration_s, gyro_bias_walk=self.gyro_bias_walk)
        if self.calibration_s > 60.0:  # the robot stands still this long at every start
            raise ConfigError(f"{where}.calibration_s: at most 60 s, got {self.calibration_s}")
        if self.gyro_delay_s is not None and not 0.0 <= self.gyro_delay_s <= 0.05:
            raise ConfigError(f"{where}.gyro_delay_s: must be null or in [0, 0.05] s, got {self.gyro_delay_s}")
        if self.gyro_bias_per_c_dps is not None and not abs(self.gyro_bias_per_c_dps) <= 1.0:
            raise ConfigError(f"{where}.gyro_bias_per_c_dps: must be null (learn it) or in [-1, 1] deg/s per degC, "
                              f"got {self.gyro_bias_per_c_dps}")
        positive(where, max_rejects=self.max_rejects, stale_ticks=self.stale_ticks,
                 stuck_gyro_ticks=self.stuck_gyro_ticks, fault_latch_s=self.fault_latch_s,
                 hold_window_s=self.hold_window_s)
        non_negative(where, max_holds=self.max_holds)
        if self.zero_motors_after_s is not None:
            positive(where, zero_motors_after_s=self.zero_motors_after_s)
        if self.fault_latch_s <= self.max_gap_s:
            raise ConfigError(f"{where}.fault_latch_s: must exceed max_gap_s ({self.max_gap_s:g} s), "
                              f"got {self.fault_latch_s:g}")


@dataclass(frozen=True)
class PursuitConfig:
    """How the reference is taken from the path."""

    APPLY: ClassVar[str] = NEXT_PATH  # the reference stage is built for each path

    mode: Literal["path", "time"] = "path"
    lookahead_m: float = 0.05
    search_window_m: float = 0.3
    # A path whose start heading differs from the robot's by more than this: turn in place
    # to it first, or refuse the path (ddrt/path/start.py).
    max_start_heading_deg: float = 30.0
    start_turn: Literal["turn", "refuse"] = "turn"

    def validate(self, where: str) -> None:
        positive(where, lookahead_m=self.lookahead_m, search_window_m=self.search_window_m)
        if not 0.0 <= self.max_start_heading_deg <= 180.0:
            raise ConfigError(f"{where}.max_start_heading_deg: must be in [0, 180] deg, "
                              f"got {self.max_start_heading_deg}")


@dataclass(frozen=True)
class LimitsConfig:
    """Hard limits: the speed profile respects the motion ones, the controller the rest.

    v_max, accel and torque_max_nm are optional caps: null takes what the robot's motors give
    (ddrt/core/envelope.py); a value can only lower that, and one above it is reported."""

    APPLY: ClassVar[str] = NEXT_PATH  # the speed profile and the controller's acceleration clamps are set per path

    v_max: float | None = None
    accel: float | None = None
    lateral_accel: float = 1.5
    omega_max: float = 3.0  # well inside the gyro's range (250 deg/s = 4.36 rad/s)
    alpha_max: float = 20.0
    duty_max: float = applies(LIVE, 1.0)
    torque_max_nm: float | None = applies(LIVE, None)
    max_path_error_m: float = applies(LIVE, 0.3)  # farther than this from the reference: stop following (fault)
    feedback_headroom: float = 0.25  # fraction of the voltage (and torque) the profile leaves to feedback
    battery_min_v: float | None = applies(LIVE, None)  # measured supply below this: controlled stop (None: off)

    def validate(self, where: str) -> None:
        caps = {k: getattr(self, k) for k in ("v_max", "accel", "torque_max_nm", "battery_min_v")
                if getattr(self, k) is not None}
        positive(where, lateral_accel=self.lateral_accel, omega_max=self.omega_max, alpha_max=self.alpha_max,
                 duty_max=self.duty_max, max_path_error_m=self.max_path_error_m, **caps)
        if self.duty_max > 1.0:
            raise ConfigError(f"{where}.duty_max: must be <= 1, got {self.duty_max}")
        if not 0.0 <= self.feedback_headroom <= MAX_HEADROOM:
            raise ConfigError(f"{where}.feedback_headroom: must be in [0, {MAX_HEADROOM}], got {self.feedback_headroom}")


MAX_HEADROOM = 0.8  # limits.feedback_headroom: beyond it the profile has almost nothing to plan with


@dataclass(frozen=True)
class FoxgloveConfig:
    """The opt-in Foxglove WebSocket server (docs/foxglove.md); needs `pip install 'ddrt[foxglove]'`."""

    enabled: bool = False
    host: str = "127.0.0.1"  # loopback by default: the server has no authentication
    port: int = 8765  # 0: any free port (tests)

    def validate(self, where: str) -> None:
        if not self.host:
            raise ConfigError(f"{where}.host: expected a host name or address, got ''")
        _in_range(where, "port", self.port, 0, 65535)


@dataclass(frozen=True)
class DaemonConfig:
    """The long-running service: socket, telemetry files, real-time setup, safety bounds."""

    APPLY: ClassVar[str] = RESTART  # the process's own set-up

    socket: str | None = "/run/ddrt/ddrt.sock"  # null or "": no control socket; --socket overrides
    telemetry_dir: str = "/var/lib/ddrt/telemetry"
    telemetry_max_bytes: int = applies(LIVE, 20_000_000)
    telemetry_max_files: int = applies(LIVE, 5)
    rt_priority: int = 0  # SCHED_FIFO priority; 0 leaves the scheduler alone
    cpus: tuple[int, ...] = ()
    lock_memory: bool = False  # mlockall; pins every mapped page, shared libraries too
    timer_slack_ns: int = 1000
    spin_us: int = applies(LIVE, 0)  # wake this long before each deadline and poll the clock up to it
    watch_config: bool = applies(LIVE, False)  # reload when the file changes
    stop_decel: float = applies(LIVE, 0.5)  # m/s^2 for a controlled stop
    on_recover: Literal["resume", "wait"] = applies(LIVE, "resume")  # after a hold: resume the path, or stop and wait
    # Velocity mode (`drive`): no command for this long and the robot brakes to a stop.
    command_timeout_s: float = applies(LIVE, 0.5)
    telemetry_format: Literal["csv", "mcap", "both", "rosbag2"] = "csv"  # mcap: foxglove extra; rosbag2: ros2
    foxglove: FoxgloveConfig = field(default_factory=FoxgloveConfig)
    ros2: Ros2Config = field(default_factory=Ros2Config)

    def validate(self, where: str) -> None:
        if not 0 <= self.rt_priority <= 99:
            raise ConfigError(f"{where}.rt_priority: must be 0..99, got {self.rt_priority}")
        if not 0 <= self.spin_us <= 2000:
            raise ConfigError(f"{where}.spin_us: must be 0..2000, got {self.spin_us}")
        positive(where, telemetry_max_bytes=self.telemetry_max_bytes,
                 telemetry_max_files=self.telemetry_max_files, stop_decel=self.stop_decel,
                 command_timeout_s=self.command_timeout_s)
        if self.command_timeout_s > MAX_COMMAND_TIMEOUT_S:
            raise ConfigError(f"{where}.command_timeout_s: at most {MAX_COMMAND_TIMEOUT_S:g} s (a robot that "
                              f"drives on that long after its last command is not stopped by it), "
                              f"got {self.command_timeout_s:g}")


MAX_COMMAND_TIMEOUT_S = 5.0


@dataclass(frozen=True)
class DriveConfig:
    """The velocity mode's own limits (ddrt/core/drive.py); speeds and accelerations are
    limits.*, shared with paths. Jerk limits as ros2 diff_drive_controller's
    linear/angular max_jerk; null: none (its has_jerk_limits: false)."""

    APPLY: ClassVar[str] = LIVE  # the velocity mode takes them between two ticks

    jerk_max: float | None = 10.0  # m/s^3: limits.accel (1 m/s^2) is reached in 0.1 s
    angular_jerk_max: float | None = 200.0  # rad/s^3: limits.alpha_max (20 rad/s^2) in 0.1 s

    def validate(self, where: str) -> None:
        if self.jerk_max is not None:
            positive(where, jerk_max=self.jerk_max)
        if self.angular_jerk_max is not None:
            positive(where, angular_jerk_max=self.angular_jerk_max)


# The smallest radius, side or pivot radius a path may have (m): below it a path is a point
# and its curvature beyond what the profile's floats can hold.
MIN_PATH_SIZE_M = 0.001
MAX_TOLERANCE_M = 1.0  # paths.tolerance_m and a path's tolerance: at most this (m)


@dataclass(frozen=True)
class PathsConfig:
    """How paths are sampled, and how much work one path may ask for (checked before it is built)."""

    APPLY: ClassVar[str] = NEXT_PATH  # read when a path is built

    sample_step_m: float = 0.002
    pivot_radius_m: float = 0.1  # a path's pivot_radius: overrides it
    corner_pivot_deg: float = 30.0  # likewise corner_pivot_deg:
    blend_max_m: float = 0.15  # likewise blend_max:
    # A polyline's samples: the reference stays this close (m), or "auto": set from the points'
    # noise, never below 10 mm (a path's tolerance: overrides).
    tolerance_m: float | Literal["auto"] = "auto"
    waypoint_spacing_m: float = 0.25  # a polyline this sparse (median spacing) is waypoints, as given
    max_samples: int = 2_000_000
    max_points: int = 10_000
    max_extent_m: float = 10_000.0
    # A polyline that states no unit and reaches farther than this is refused as likely in
    # mm, cm or inches (path/units.py); beyond 0.3 of it (15 m), a warning.
    workspace_m: float = 50.0
    max_duration_s: float = 3_600.0
    # The daemon reads and builds a path in a worker process, within these bounds.
    max_file_bytes: int = 4_000_000  # a path file (and a CSV it names) larger than this is refused unread
    build_timeout_s: float = 30.0  # the worker is stopped if the path is not ready by then

    def validate(self, where: str) -> None:
        positive(where, sample_step_m=self.sample_step_m, max_extent_m=self.max_extent_m,
                 workspace_m=self.workspace_m, max_duration_s=self.max_duration_s)
        _in_range(where, "max_file_bytes", self.max_file_bytes, 1, 1_000_000_000)
        if not 0.1 <= self.build_timeout_s <= 3600.0:
            raise ConfigError(f"{where}.build_timeout_s: must be in [0.1, 3600] s, got {self.build_timeout_s}")
        non_negative(where, corner_pivot_deg=self.corner_pivot_deg)
        if self.sample_step_m > 1.0:
            raise ConfigError(f"{where}.sample_step_m: must be <= 1 m, got {self.sample_step_m}")
        if self.tolerance_m != "auto":
            non_negative(where, tolerance_m=self.tolerance_m)
            if self.tolerance_m > MAX_TOLERANCE_M:
                raise ConfigError(f"{where}.tolerance_m: must be at most {MAX_TOLERANCE_M:g} m, got {self.tolerance_m}")
        if not MIN_PATH_SIZE_M <= self.waypoint_spacing_m <= self.max_extent_m:
            raise ConfigError(f"{where}.waypoint_spacing_m: must be in [{MIN_PATH_SIZE_M}, max_extent_m], "
                              f"got {self.waypoint_spacing_m}")
        for key in ("pivot_radius_m", "blend_max_m"):
            value = getattr(self, key)
            if not MIN_PATH_SIZE_M <= value <= self.max_extent_m:
                raise ConfigError(f"{where}.{key}: must be in [{MIN_PATH_SIZE_M}, max_extent_m], got {value}")
        _in_range(where, "max_samples", self.max_samples, 10, 100_000_000)
        _in_range(where, "max_points", self.max_points, 2, 10_000_000)

    def check_pose(self, pose: tuple[float, ...], where: str) -> None:
        """A start pose (or point) inside the workspace: |x|, |y| <= max_extent_m."""
        if max(abs(pose[0]), abs(pose[1])) > self.max_extent_m:
            raise ConfigError(f"{where}: ({pose[0]:.6g}, {pose[1]:.6g}) is beyond paths.max_extent_m "
                              f"= {self.max_extent_m:g} m from the origin")


@dataclass(frozen=True)
class Config:
    """Everything ddrt needs, validated. `robot` is what the controller believes, `plant`
    what the simulated robot is (missing plant keys default to robot's)."""

    robot: RobotParams = applies(LIVE)  # the model in the controller, estimator and adapter
    robot_motor: MotorParams = applies(LIVE, key="robot.motor")
    plant: RobotParams = restart()  # the simulated robot is built once
    plant_motor_l: MotorParams = applies(RESTART, key="plant.motor_l")
    plant_motor_r: MotorParams = applies(RESTART, key="plant.motor_r")
    sim: SimConfig = applies(RESTART)
    sensors: SensorsConfig = applies(RESTART)
    hal: HalConfig = applies(RESTART)
    controller: ControllerConfig = applies(LIVE)
    estimator: EstimatorConfig = applies(LIVE)
    pursuit: PursuitConfig = applies(NEXT_PATH)
    limits: LimitsConfig = applies(NEXT_PATH)
    daemon: DaemonConfig = applies(RESTART)
    drive: DriveConfig = applies(LIVE, factory=DriveConfig)
    paths: PathsConfig = applies(NEXT_PATH, factory=PathsConfig)
    path: Any = restart(None)  # a path mapping or file name, followed at start (ddrt run --follow, ddrt sim)
    start: tuple[float, float, float] | None = restart(None)
    # Where the config came from: not settings, so never reported by a reload.
    source: str = field(default="<memory>", compare=False)
    base_dir: str = field(default=".", compare=False)
    raw: Mapping[str, Any] = field(default_factory=dict, repr=False, compare=False)

    def validate(self, where: str = "") -> None:
        """Rules across sections (each section checked its own when it was built)."""
        # The envelope's voltage bound at rest (ddrt/core/envelope.py), from the motor alone.
        voltage_bound_nm = (1.0 - self.limits.feedback_headroom) * self.limits.duty_max * self.robot_motor.stall_torque_nm
        if not voltage_bound_nm > self.robot_motor.coulomb_nm:
            raise ConfigError(
                f"robot.motor: at {1.0 - self.limits.feedback_headroom:.0%} of limits.duty_max x supply_v "
                "(limits.feedback_headroom) the motors cannot overcome their own Coulomb friction (coulomb_nm)")
        gyro_limit = GYRO_MARGIN * math.radians(self.sensors.gyro_range_dps)
        if self.limits.omega_max > gyro_limit:
            raise ConfigError(
                f"limits.omega_max: {self.limits.omega_max} rad/s leaves no margin below the gyro's range "
                f"(sensors.gyro_range_dps = {self.sensors.gyro_range_dps} deg/s): at most {gyro_limit:.2f} rad/s, "
                "or raise the range")


GYRO_MARGIN = 0.8  # limits.omega_max stays within this fraction of the gyro's full scale
