"""The config's sections: typed, frozen dataclasses whose field types and declarations are the schema.

Each field declares its unit, bounds, reload mode and description beside it (`setting`,
ddrt/params/decl.py); docs/reference/config.md is written from them. A section's
`validate()` holds only rules between fields.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, ClassVar, Literal, Mapping

from ddrt.params.robot import RobotParams
from ddrt.params.gyro_scale import GYRO_RANGES_DPS
from ddrt.params.motor import MotorParams
from ddrt.params.decl import NOT_EMPTY, Text
from ddrt.config.wiring import WiringConfig
from ddrt.config.schema import LIVE, NEXT_PATH, RESTART, ConfigError, Section, setting
from ddrt.config.sim_truth import SimConfig
from ddrt.config.ros2 import Ros2Config

# --------------------------------------------------------------------------- sections


@dataclass(frozen=True)
class SensorsConfig(Section):
    """Facts about the sensors both the controller and the simulated robot share."""

    APPLY: ClassVar[str] = RESTART  # the devices are configured when opened

    encoder_counts_per_rev: int = setting(
        8192, unit="counts/rev", ge=0,
        doc="Encoder counts per revolution of the front omni wheel; `0`: there is no front encoder, and then "
            "`sensors.wheel_counts_per_rev` must be > 0 (the drive wheels give the distance: "
            "ddrt/core/wheel_odometry.py). The real backend takes the count from the microcontroller instead.")
    gyro_range_dps: int = setting(
        250, unit="deg/s", choices=GYRO_RANGES_DPS,
        doc="Gyro full-scale range, the one source of it: the simulated gyro saturates at it, and the real "
            "backend configures the MPU (FS_SEL) with it. `limits.omega_max` must stay below 80 % of it.")
    wheel_counts_per_rev: int = setting(
        0, unit="counts/rev", ge=0,
        doc="Counts per revolution of each drive wheel (its motor encoder's lines x 4 x the gear ratio), when "
            "the drive wheels' encoders are counted (protocol v2, [protocol.md](protocol.md)); `0`: not counted. "
            "The emulated MCU and the firmware-sim backend count the simulated wheels at it; the real backend "
            "takes it from the microcontroller's HELLO_REPLY.")
    battery_scale: float = setting(
        1.0, ge=0.5, le=2.0,
        doc="Calibration of the microcontroller's battery divider: true voltage (multimeter) / reported "
            "voltage ([hardware.md](hardware.md#battery-voltage)). Used only when the microcontroller "
            "measures the battery.")
    # The two gyro keys below default per backend (`for_backend`): these values are the
    # simulated backend's, REAL_MPU_DEFAULTS a real MPU's (hal.backend: real).
    gyro_temp_hz: float = setting(
        0.0, unit="Hz", ge=0.0, le=50.0,
        doc="**`5.0` with `hal.backend: real`** (the robot's MPU, or the emulated one behind the real driver): "
            "how often the gyro's die temperature (TEMP_OUT, one extra 2-byte I2C read) is read. The estimator "
            "then compensates the zero-rate bias for temperature and re-learns it at every stop "
            "(ddrt/core/gyro_bias.py, [estimation.md](estimation.md)): a warming MPU-6050's bias moves by about "
            "0.1 deg/s per degC, which uncompensated turns the heading by degrees a minute. `0`: never read (the "
            "bias is re-learnt at stops only; the simulated backend's default, whose gyro does not warm unless "
            "`sim.gyro.warmup_rise_c` says so). 2 to 10 is plenty (the die's time constant is minutes).")
    gyro_fifo: bool = setting(
        False,
        doc="**`true` with `hal.backend: real`**: read the gyro through the MPU's FIFO (gyro z only; "
            "FIFO_COUNT then that many whole samples, one more I2C transaction a tick): every sample the gyro "
            "produced is delivered once (`Sample.gyro_n`, `gyro_sum_raw`) and the estimator integrates each "
            "batch over its samples' own period, learnt from their count against the loop's clock "
            "(ddrt/core/gyro_fifo.py), instead of the output register read at the tick, whose age varies from 0 "
            "to one sample period as the two clocks beat (docs/BENCHMARKS.md, \"Sensing: a warming gyro with the "
            "shipped config\"). A full, garbled or unreadable FIFO is reset and that read held, not fresh "
            "(`imu_fifo_reset`; the simulator's `imu_fifo_overflow`). The simulator then samples its gyro at "
            "1 kHz / (1 + `hal.imu.sample_rate_div`) on the part's clock (`sim.gyro.clock_ppm`). "
            "`false`: the output register read at the tick (the simulated backend's "
            "default: its default gyro has no sample clock to beat against).")

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
        if self.encoder_counts_per_rev == 0 and self.wheel_counts_per_rev == 0:
            raise ConfigError(f"{where}.encoder_counts_per_rev: 0 (no front encoder) needs the drive wheels' "
                              f"encoders ({where}.wheel_counts_per_rev > 0): the robot needs one distance sensor")


@dataclass(frozen=True)
class ImuConfig(Section):
    """The MPU-6050 on I2C (real backend). Its range is sensors.gyro_range_dps."""

    MOVED: ClassVar[dict[str, str]] = {
        "gyro_range_dps": "use sensors.gyro_range_dps, the one gyro range (the driver is configured from it)"}

    bus: int | str | None = setting(
        None, ge=0, text=Text(r"sim", "a bus number >= 0 or \"sim\""),
        doc="I2C bus number (`1` is /dev/i2c-1), or `\"sim\"` for an emulated bus handed in by the caller. "
            "Required with `hal.backend: real`.")
    address: int = setting(
        0x68, ge=0x03, le=0x77,
        doc="7-bit I2C address of the gyro (an MPU-6050, MPU-6500, MPU-9250 or ICM-20689, told apart by "
            "WHO_AM_I: [hardware.md](hardware.md)); 104 is 0x68.")
    dlpf_cfg: int = setting(
        2, ge=0, le=6, doc="The gyro's DLPF_CFG register (2 is 98 Hz on an MPU-6050, 92 Hz on the others).")
    sample_rate_div: int = setting(
        4, ge=0, le=255, doc="SMPLRT_DIV register: output rate = 1 kHz / (1 + div) with the DLPF on.")


@dataclass(frozen=True)
class BridgeConfig(Section):
    """The serial link to the microcontroller (real backend)."""

    url: str | None = setting(
        None, text=NOT_EMPTY,
        doc="Serial port or pyserial URL: `/dev/ttyACM0`, `socket://host:port`, `loop://`. Required with "
            "`hal.backend: real` unless `hal.imu.bus` is `\"sim\"`. With `hal.imu.bus: sim`: `ddrtsim://NAME` is "
            "the Python model of the microcontroller (protocol v2; `ddrtsim://NAME?v1` an MCU of protocol v1, to "
            "try the host's fallback), `simavr://[PATH.elf][?free-running]` the reference firmware in the simavr "
            "simulator (default firmware/build/ddrt_bridge.elf, PATH relative to the source tree; "
            "`free-running`: under `ddrt run` the simulator keeps the wall clock itself instead of being "
            "stepped by the daemon's tick). [hardware.md](hardware.md)")
    baudrate: int = setting(115200, unit="baud", ge=1, le=10_000_000, doc="Serial line speed.")
    drive_timeout_ms: int = setting(
        100, unit="ms", ge=1, le=1000,
        doc="Microcontroller watchdog: motors are zeroed when no DRIVE arrives for this long.")
    state_stale_s: float = setting(
        0.05, unit="s", gt=0, doc="Encoder STATE older than this is a timeout (the loop stops the robot).")


@dataclass(frozen=True)
class PwmSysfsConfig(Section):
    """Motors on the Linux PWM class plus direction GPIOs (real backend, hal.motors: pwm_sysfs)."""

    chip: int = setting(0, ge=0, le=1 << 16, doc="PWM chip number N of /sys/class/pwm/pwmchipN.")
    channels: tuple[int, int] = setting((0, 1), ge=0, doc="PWM channels of the left and right motor.")
    period_ns: int = setting(50_000, unit="ns", ge=1, le=1_000_000_000, doc="PWM period (50000 ns = 20 kHz).")
    direction_gpios: tuple[int, int] | None = setting(
        None, ge=0,
        doc="GPIO numbers of the left and right direction lines. Required with `hal.motors: pwm_sysfs`.")
    root: str = setting(
        "/sys", unit="directory", text=NOT_EMPTY,
        doc="sysfs root (a temporary directory in tests); a relative path is relative to the config file's "
            "folder.")


@dataclass(frozen=True)
class HalConfig(Section):
    """Which backend drives the robot, and the real backend's devices."""

    APPLY: ClassVar[str] = RESTART  # the devices are opened once

    backend: Literal["sim", "real"] = setting(
        "sim", doc="`sim` (simulated robot) or `real` (the gyro on I2C plus the microcontroller on a serial port).")
    motors: Literal["bridge", "pwm_sysfs"] = setting(
        "bridge",
        doc="Real backend's motor drive: `bridge` (the microcontroller's PWM) or `pwm_sysfs` (Linux PWM plus "
            "direction GPIOs).")
    imu: ImuConfig = setting(factory=ImuConfig, doc="The gyro (real backend).")
    bridge: BridgeConfig = setting(
        factory=BridgeConfig,
        doc="The serial link to the microcontroller (encoder and, with `hal.motors: bridge`, PWM).")
    pwm_sysfs: PwmSysfsConfig = setting(
        factory=PwmSysfsConfig, doc="Motors on the Linux PWM class (used only with `hal.motors: pwm_sysfs`).")
    hold_ticks: int | None = setting(
        None, unit="ticks", ge=0, le=1000,
        doc="Real backend: how long a reading with no new data may be repeated (flagged not fresh) before the "
            "read times out. `null`: as long as it is no older than `hal.bridge.state_stale_s` (10 ticks at "
            "200 Hz): one bound for a stale bridge. A number overrides that with a fixed count of ticks (3 at "
            "200 Hz is 15 ms, shorter than the bridge's own bound).")
    wiring: WiringConfig = setting(
        factory=WiringConfig,
        doc="How this robot's motors and sensors are wired, fixed in software for every backend (hal/wiring.py, "
            "around whatever `hal.backend` opens): `ddrt commission` measures and writes it "
            "([commissioning.md](commissioning.md)). The defaults are the wiring of [hardware.md](hardware.md).")

    def validate(self, where: str) -> None:
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
class OuterGains(Section):
    """Kanayama's tracking law (seed eq. 4.3)."""

    k_x: float = setting(10.0, unit="1/s", gt=0, doc="K_x: along-track error to forward speed.")
    k_y: float = setting(400.0, unit="1/m^2", gt=0, doc="K_y: cross-track error to yaw rate (times v_d).")
    k_theta: float = setting(40.0, unit="1/m", gt=0, doc="K_theta: heading error to yaw rate (times v_d).")


@dataclass(frozen=True)
class PidGains(Section):
    """A PID on a speed error: kp, ki, kd and the clamp of the integrated error. Its two sections
    (InnerPid, WheelPid) declare their own units and defaults."""

    kp: float = setting(ge=0, doc="Proportional gain.")
    ki: float = setting(ge=0, doc="Integral gain.")
    kd: float = setting(ge=0, doc="Derivative gain (on the measurement).")
    integrator_limit: float = setting(gt=0, doc="Clamp of the integrated error.")


@dataclass(frozen=True)
class InnerPid(PidGains):
    """controller.inner: the dynamic mode's PID on eta_c - eta; its output is an acceleration."""

    kp: float = setting(20.0, unit="1/s", ge=0, doc="Proportional gain.")
    ki: float = setting(100.0, unit="1/s^2", ge=0, doc="Integral gain.")
    kd: float = setting(0.0, ge=0, doc="Derivative gain (on the measurement).")
    integrator_limit: float = setting(
        0.2, unit="m (v), rad (omega)", gt=0, doc="Clamp of the integrated error.")


@dataclass(frozen=True)
class WheelPid(PidGains):
    """controller.wheel_pid: the kinematic baseline's speed PID per wheel, output in duty."""

    kp: float = setting(0.15, unit="1/(rad/s)", ge=0, doc="Duty per rad/s of wheel-speed error.")
    ki: float = setting(1.5, unit="1/rad", ge=0, doc="Duty per rad of integrated wheel-speed error.")
    kd: float = setting(0.0, unit="1/(rad/s^2)", ge=0, doc="Duty per rad/s^2 of wheel acceleration.")
    integrator_limit: float = setting(0.3, unit="rad", gt=0, doc="Clamp of the integrated wheel-speed error.")


INNER_PID = InnerPid()
WHEEL_PID = WheelPid()


@dataclass(frozen=True)
class AdaptationConfig(Section):
    """Online estimation of the lumped dynamic parameters: on, as measured over a population of
    robots (docs/adaptation.md, "On by default"); false for the configured model alone."""

    enabled: bool = setting(
        True,
        doc="The online estimation of the lumped dynamics; the compensator (and with `update_estimator` the "
            "estimator's prediction) uses the estimate once trusted. On by default: over a population of 40 "
            "robots it makes no run's true-pose RMS worse by more than 25 % or 0.1 mm and the median no worse "
            "([adaptation.md](adaptation.md#on-by-default)). `false`: the configured model alone (a "
            "commissioning choice: `ddrt commission` identifies that model).")
    forgetting: float = setting(
        0.999, ge=0.9, le=1.0,
        doc="Recursive least squares forgetting factor per excited tick (1: no forgetting).")
    min_excitation: float = setting(
        0.05, unit="m/s^2", ge=0,
        doc="Filtered forward acceleration (or yaw acceleration times the half track) below which the "
            "estimate is not updated.")
    filter_hz: float = setting(
        2.0, unit="Hz", gt=0,
        doc="Cut-off of the second-order low-pass (two first-order stages) both sides of the regression pass "
            "through.")
    min_updates: int = setting(
        200, ge=0, doc="Excited updates before the estimate may replace the configured model.")
    bound_ratio: float = setting(
        3.0, gt=1, doc="m + k and I stay within [1/ratio, ratio] times the configured values.")
    max_com_shift_m: float = setting(
        0.05, unit="m", gt=0,
        doc="mbar and m_x stay within this times (m + k) times bound_ratio of the configured values.")
    max_friction_nm: float = setting(
        0.1, unit="N m", gt=0, doc="Bound on the extra Coulomb friction estimated at each wheel.")
    min_wheel_speed: float = setting(
        1.0, unit="rad/s", ge=0,
        doc="No update unless both wheels turn faster than this (friction flips sign and sticks near zero); "
            "below it the learnt extra friction fades out linearly.")
    blend_s: float = setting(
        1.0, unit="s", ge=0,
        doc="Time constant with which the model in use follows the estimate (or falls back to the configured "
            "one).")
    update_estimator: bool = setting(
        False,
        doc="Also give the model in use to the estimator's model-based prediction: the true pose gains a "
            "quarter where the configured model is wrong, but loses up to 15 % on a robot whose model was "
            "right (docs/adaptation.md).")
    min_improvement: float = setting(
        0.2, ge=0.0, lt=1.0,
        doc="The estimate replaces the configured model only while its running RMS torque residual is at least "
            "this fraction below the configured model's.")
    noise_accel: float = setting(
        0.3, unit="m/s^2", gt=0,
        doc="The residual one filtered row may carry, per kg of the configured m + k; with the ticks inside "
            "the filter's time constant it sets how much the configured values weigh against the data (larger: "
            "the estimate moves less and later). The same on a light robot and a heavy one, and at any rate.")


@dataclass(frozen=True)
class ControllerConfig(Section):
    """The three-stage controller (or the kinematic baseline, or the seed's own method)."""

    APPLY: ClassVar[str] = LIVE  # gains are retuned between two ticks, bumplessly

    mode: Literal["dynamic", "kinematic", "seed"] = setting(
        "dynamic", reload=RESTART,
        doc="`dynamic`: outer Kanayama law, inner PID, computed torque. `kinematic`: pure-pursuit curvature and "
            "a speed PID per wheel (baseline). `seed`: the report's own method and fixed gains, for comparison "
            "only.")
    rate_hz: float = setting(200.0, unit="Hz", ge=1.0, le=2000.0, reload=RESTART, doc="Control loop rate.")
    outer: OuterGains = setting(factory=OuterGains, doc="Kanayama tracking law gains (seed eq. 4.3).")
    inner: InnerPid = setting(
        factory=InnerPid,
        doc="Dynamic mode: PID on eta_c - eta, the same for v and omega; its output is an acceleration.")
    wheel_pid: WheelPid = setting(factory=WheelPid, doc="Kinematic mode: speed PID per wheel, output in duty.")
    heading_gain: float = setting(
        8.0, unit="1/s", gt=0,
        doc="Dynamic: lower bound of the heading gain v_d k_theta, so heading is held at low speed and in "
            "pivots. Kinematic: gain of the heading-error term.")
    adaptation: AdaptationConfig = setting(
        factory=AdaptationConfig, reload=RESTART,  # the adapter is built at start
        doc="Online estimation of the lumped dynamic parameters m + k, mbar, I, m_x and each wheel's extra "
            "friction (ddrt/core/adapt.py, docs/adaptation.md); dynamic mode only.")


@dataclass(frozen=True)
class EstimatorConfig(Section):
    """Kalman filter tuning and sensor supervision."""

    APPLY: ClassVar[str] = LIVE  # the estimator re-derives its scales and noises between two ticks

    calibration_s: float = setting(
        1.0, unit="s", ge=0, le=60.0, reload=RESTART,  # the robot stands still this long at every start
        doc="Time at rest at start-up over which the gyro bias is averaged before the loop is READY (at least "
            "10 ticks). While the robot stands still afterwards the estimator keeps refining the bias.")
    calibration_max_std_dps: float = setting(
        0.5, unit="deg/s", gt=0, reload=RESTART,
        doc="Calibration fails if the gyro's spread over that time exceeds this (the robot moved).")
    accel_noise: float = setting(
        0.5, unit="m/s^2", gt=0,
        doc="Forward acceleration the model does not explain (as a 5 ms step's; scaled by sqrt(5 ms / period) "
            "at other rates, like the other three process noises, so the filters trust the model equally at "
            "every `controller.rate_hz`), for the speed the controller feeds back (a smooth filter: the PID "
            "does not chatter on encoder quantisation).")
    odometry_accel_noise: float = setting(
        20.0, unit="m/s^2", gt=0,
        doc="The same for the second filter on the encoder, whose speed the dead-reckoned pose integrates: "
            "larger trusts the encoder over the model, so an unknown payload bends the pose less "
            "(docs/design.md).")
    yaw_accel_noise: float = setting(
        5.0, unit="rad/s^2", gt=0,
        doc="Yaw acceleration the model does not explain, for the yaw rate the controller feeds back.")
    odometry_yaw_accel_noise: float = setting(
        50.0, unit="rad/s^2", gt=0,
        doc="The same for the second yaw filter, whose rate the heading integrates: larger trusts the gyro "
            "over the model.")
    gyro_bias_walk: float = setting(
        1e-5, unit="rad/s per sqrt(s)", ge=0, doc="Random walk of the gyro's zero-rate bias.")
    gyro_scale: float = setting(
        1.0, gt=0, doc="Believed gyro scale factor (1 + scale error), from calibration.")
    gyro_noise_dps: float = setting(
        0.07, unit="deg/s", gt=0, doc="Standard deviation of one gyro sample after the MPU's low-pass.")
    gyro_delay_s: float | None = setting(
        None, unit="s", ge=0.0, le=0.05,
        doc="Lag of the gyro's low-pass behind the encoder, undone by a lead `z + tau dz/dt`. `null`: what the "
            "HAL reports (the real MPU-6050: the datasheet's delay for `hal.imu.dlpf_cfg`, 2.8 ms at the "
            "default 2, plus half its output register's hold, one sample period 1 kHz / (1 + `sample_rate_div`), "
            "2.5 ms at the default 4: 5.3 ms; the simulated gyro: its low-pass's delay, 1.17 ms at 98 Hz, plus "
            "half the hold with `sim.gyro.register_hold`). `0` turns the lead off.")
    gyro_bias_per_c_dps: float | None = setting(
        None, unit="deg/s per degC", ge=-1.0, le=1.0,
        doc="The gyro's zero-rate bias's temperature slope k in b(T) = b0 + k (T - T0), from commissioning "
            "(`ddrt commission`'s rest step measures it from two rests at least 2 degC apart, "
            "[commissioning.md](commissioning.md)); `null`: learnt from the (bias, temperature) pairs of the "
            "stops (ddrt/core/gyro_bias.py). Used only with `sensors.gyro_temp_hz` > 0 (the default on a real "
            "MPU).")
    gate_sigma: float = setting(
        5.0, unit="sigma", gt=0,
        doc="Innovations beyond this many standard deviations are rejected as outliers.")
    max_rejects: int = setting(
        10, unit="count", gt=0, doc="Outliers in a row after which the filter re-syncs and reports it.")
    stale_ticks: int = setting(
        20, unit="ticks", gt=0,
        doc="Stale samples in a row, while moving, after which the loop holds the robot (a controlled stop; "
            "see `estimator.fault_latch_s`).")
    max_gap_s: float = setting(
        0.05, unit="s", gt=0,
        doc="Longer than this and than 10 ticks without a fresh sample while the robot is commanded to move "
            "(the loop stalled, or the sensors went stale) and the loop holds the robot: a controlled stop along "
            "the path, or the motors to zero at once when the robot has been blind for longer than "
            "`estimator.zero_motors_after_s`; when samples return the estimate re-anchors and the path resumes "
            "(`daemon.on_recover`). Standing still, a gap is harmless and only re-anchors the estimate.")
    fault_latch_s: float = setting(
        0.5, unit="s", gt=0,
        doc="No fresh sample for this long while the loop runs (stale samples, read timeouts) latches a fault: "
            "motors to zero, the run ends (`ddrt run` exits 1). More than `estimator.max_gap_s`. Shorter gaps "
            "are held and recovered; so is a stall of the loop itself, however long (the first sample after it "
            "is fresh, and the motors' watchdog stopped them meanwhile).")
    max_holds: int = setting(
        5, unit="count", ge=0,
        doc="More holds on the sensors' account (stale samples, read timeouts) than this within "
            "`estimator.hold_window_s` latch a fault: sensors that keep failing end the run, and the restart "
            "re-opens the devices. Gaps because the loop itself did not run (a busy host) are held but not "
            "counted: each is safe, and a restart cannot cure the host.")
    hold_window_s: float = setting(60.0, unit="s", gt=0, doc="The window of `estimator.max_holds`.")
    zero_motors_after_s: float | None = setting(
        None, unit="s", gt=0,
        doc="In a hold, blind (no fresh sample) for this long: the motors go to zero at once instead of the "
            "controlled stop. `null`: the HAL's motor watchdog (the microcontroller's "
            "`hal.bridge.drive_timeout_ms`, 100 ms; the simulated driver has the same), or 0.1 s for motors "
            "without one (sysfs PWM).")
    stuck_gyro_ticks: int = setting(
        100, unit="ticks", gt=0, doc="Identical raw gyro readings in a row that mean a stuck sensor.")
    encoder_stuck_s: float = setting(
        0.3, unit="s", gt=0, doc="Commanded motion with no encoder count for this long means a stuck encoder.")
    # The pose's uncertainty and pose fixes (docs/estimation.md).
    encoder_scale_std: float = setting(
        0.01, ge=0, le=0.5,
        doc="1-sigma relative error of `robot.r_3` (metres per count): how well the encoder wheel's rolling "
            "radius is known. It is what the pose's uncertainty grows from with distance "
            "([estimation.md](estimation.md)); after `ddrt calibrate odometry`, the relative precision of the "
            "distance measured there.")
    gyro_scale_std: float = setting(
        0.0173, ge=0, le=0.5,
        doc="1-sigma relative error of `estimator.gyro_scale`: the MPU-6050's sensitivity tolerance, +-3 %, "
            "taken as uniform (3 % / sqrt(3)); smaller once the scale is calibrated. The heading's uncertainty "
            "grows with the angle turned by it.")
    fix_history_s: float = setting(
        2.0, unit="s", ge=0.05, le=30.0,
        doc="How much odometry history is kept: a pose fix may arrive this late after the moment it describes.")
    fix_gate_chi2: float = setting(
        16.27, gt=0,
        doc="A pose fix whose squared Mahalanobis distance from the estimate exceeds this is an outlier: "
            "counted, not fused. 16.27 is the chi-square (3 degrees of freedom) value a consistent fix exceeds "
            "0.1 % of the time.")
    map_blend_s: float = setting(
        0.5, unit="s", ge=0,
        doc="A path followed in the `map` frame takes a fix's jump over this time, critically damped (59 % of "
            "it after this time, 91 % after twice it, starting from the speed the reference had), so the motor "
            "command does not step; 0: at once.")
    uncertainty_bias_walk: float = setting(
        3e-4, unit="rad/s per sqrt(s)", ge=0,
        doc="The drift of the gyro's bias that the pose's error model allows for: the reported uncertainty's "
            "heading grows by it between rests, and pose fixes are gated and weighed with it "
            "([estimation.md](estimation.md)). The model takes the larger of this and "
            "`estimator.gyro_bias_walk`. The default covers a warming MPU-6050 (about 0.01 deg/s per second) "
            "over the few seconds between fixes; 0 leaves only `gyro_bias_walk`, with which such a drift makes "
            "fixes outliers.")
    # With drive-wheel encoders (sensors.wheel_counts_per_rev > 0; ddrt/core/wheel_odometry.py).
    wheel_bias_walk: float = setting(
        1e-4, unit="rad/s per sqrt(s)", ge=0,
        doc="With drive-wheel encoders: how fast the gyro's bias may drift while moving; the wheels' turn "
            "tracks it at this rate (larger: a drift is followed sooner, the bias is noisier). A step is caught "
            "apart from it: three bias windows in a row beyond 3 sigma that agree re-sync the bias. Unused "
            "without wheel encoders.")
    wheel_scale_std: float = setting(
        0.02, ge=0, le=0.5,
        doc="With drive-wheel encoders: 1-sigma relative error of r_L and r_R (tyres under load). Sets the "
            "slip check's tolerance, the start of the learnt radius difference (2 x this) and, without a front "
            "encoder, the pose uncertainty's distance scale error.")

    def validate(self, where: str) -> None:
        if self.fault_latch_s <= self.max_gap_s:
            raise ConfigError(f"{where}.fault_latch_s: must exceed max_gap_s ({self.max_gap_s:g} s), "
                              f"got {self.fault_latch_s:g}")


@dataclass(frozen=True)
class PursuitConfig(Section):
    """How the reference is taken from the path."""

    APPLY: ClassVar[str] = NEXT_PATH  # the reference stage is built for each path

    mode: Literal["path", "time"] = setting(
        "path",
        doc="`path`: the reference is the path point nearest the robot. `time`: the point the speed profile "
            "reaches at time t (the seed's way; `controller.mode: seed` always uses it).")
    lookahead_m: float = setting(
        0.05, unit="m", gt=0,
        doc="Distance ahead along the path of the pure-pursuit goal point (its curvature steers the kinematic "
            "mode).")
    search_window_m: float = setting(
        0.3, unit="m", gt=0,
        doc="How far ahead one tick may search for the nearest point, so a self-crossing path cannot make it "
            "jump branch.")
    max_start_heading_deg: float = setting(
        30.0, unit="deg", ge=0.0, le=180.0,
        doc="A path whose start heading differs from the robot's by more than this is turned to in place first "
            "(`start_turn: turn`) or refused (`start_turn: refuse`).")
    start_turn: Literal["turn", "refuse"] = setting(
        "turn",
        doc="`turn`: turn in place to the path's start heading (a trapezoid within the path's `omega_max` and "
            "`alpha_max`, the position held), then start. `refuse`: refuse the path, naming the angle and this "
            "key. Either way a start off the path (within `limits.max_path_error_m`) or off its heading is "
            "joined at no more than the path's speed there, at a bounded approach angle, yaw rate and lateral "
            "acceleration (ddrt/path/start.py).")


MAX_HEADROOM = 0.8  # limits.feedback_headroom: beyond it the profile has almost nothing to plan with


@dataclass(frozen=True)
class LimitsConfig(Section):
    """Hard limits: the speed profile respects the motion ones, the controller the rest.

    v_max, accel and torque_max_nm are optional caps: null takes what the robot's motors give
    (ddrt/core/envelope.py); a value can only lower that, and one above it is reported."""

    APPLY: ClassVar[str] = NEXT_PATH  # the speed profile and the controller's acceleration clamps are set per path

    v_max: float | None = setting(
        None, unit="m/s", gt=0,
        doc="Forward speed cap. `null`: the speed at which the faster-turning wheel reaches its motor's "
            "no-load speed at (1 - `feedback_headroom`) of the voltage (the profile's top speed; the "
            "controller's clamp takes the full voltage's).")
    accel: float | None = setting(
        None, unit="m/s^2", gt=0,
        doc="Forward acceleration and braking cap. `null`: no cap beyond what the motors give at each speed "
            "(the controller's clamp on its commanded acceleration, twice this, takes the straight-line "
            "acceleration from rest at the full voltage).")
    lateral_accel: float = setting(1.5, unit="m/s^2", gt=0, doc="Centripetal acceleration v^2 kappa in curves.")
    omega_max: float = setting(
        3.0, unit="rad/s", gt=0,
        doc="Yaw rate; at most 80 % of the gyro's range (`sensors.gyro_range_dps`), so a turn never saturates "
            "the sensor the estimator needs.")
    alpha_max: float = setting(20.0, unit="rad/s^2", gt=0, doc="Yaw acceleration.")
    duty_max: float = setting(
        1.0, gt=0, le=1.0, reload=LIVE,
        doc="Largest PWM duty magnitude; both wheels are scaled together to respect it.")
    torque_max_nm: float | None = setting(
        None, unit="N m", gt=0, reload=LIVE,
        doc="Largest commanded wheel torque; both wheels are scaled together. `null`: the stall torque at "
            "`duty_max` (K duty_max V / R_a of `robot.motor`). The profile plans within (1 - "
            "`feedback_headroom`) of it.")
    max_path_error_m: float = setting(
        0.3, unit="m", gt=0, reload=LIVE,
        doc="Farther than this from the reference point (the nearest point of the path; in time-indexed mode "
            "the scheduled point) while following: fault, motors to zero. A path that starts farther than this "
            "from the robot is refused.")
    feedback_headroom: float = setting(
        0.25, ge=0.0, le=MAX_HEADROOM,
        doc="Fraction of the voltage (duty_max x supply_v) and of the torque limit the speed profile leaves to "
            "feedback: it plans every wheel's torque within (1 - headroom) of what the motor gives at that "
            "wheel's speed; 0: the profile rides the motors' limits.")
    battery_min_v: float | None = setting(
        None, unit="V", gt=0, reload=LIVE,
        doc="Low-battery stop (only where the supply is measured; `null`: off). The measured supply, "
            "low-passed at 1 s, within 5 % above it: a warning, once; below it: the controlled stop along the "
            "path (as `stop`, not estop), the reason in status (`supply.reason`), and follow, drive and resume "
            "are refused until it is back 3 % above it; then a resume continues the path from where it stopped.")


@dataclass(frozen=True)
class FoxgloveConfig(Section):
    """The opt-in Foxglove WebSocket server (docs/foxglove.md); needs `pip install 'ddrt[foxglove]'`."""

    enabled: bool = setting(
        False,
        doc="Serve the Foxglove WebSocket protocol: the live view, the gains as parameters, teleop. Needs "
            "`pip install 'ddrt[foxglove]'`. [foxglove.md](foxglove.md)")
    host: str = setting(
        "127.0.0.1", text=NOT_EMPTY,
        doc="Address the server binds to; it has no authentication, keep it on loopback (ssh -L).")
    port: int = setting(8765, ge=0, le=65535, doc="TCP port (0: any free port, logged at start).")


MAX_COMMAND_TIMEOUT_S = 5.0  # a robot that drives on longer after its last command is not stopped by it


@dataclass(frozen=True)
class DaemonConfig(Section):
    """The long-running service: socket, telemetry files, real-time setup, safety bounds."""

    APPLY: ClassVar[str] = RESTART  # the process's own set-up

    socket: str | None = setting(
        "/run/ddrt/ddrt.sock", unit="path",
        doc="Unix socket for commands and status (`ddrt ctl`); `ddrt run --socket PATH` overrides it; `null` "
            "or `\"\"`: no control socket. A relative path is relative to the config file's folder.")
    telemetry_dir: str = setting(
        "/var/lib/ddrt/telemetry", unit="path",
        doc="Folder of the telemetry files; a relative path is relative to the config file's folder.")
    telemetry_max_bytes: int = setting(
        20_000_000, unit="bytes", gt=0, reload=LIVE, doc="A telemetry file is rotated once it reaches this size.")
    telemetry_max_files: int = setting(
        5, unit="count", gt=0, reload=LIVE, doc="Rotated telemetry files kept, the current one included.")
    rt_priority: int = setting(
        0, ge=0, le=99, doc="SCHED_FIFO priority of the loop; 0 leaves the scheduler alone.")
    cpus: tuple[int, ...] = setting((), unit="CPU numbers", doc="CPUs to pin the daemon to; empty: no pinning.")
    lock_memory: bool = setting(
        False,
        doc="mlockall() so no page fault stalls a tick; it also pins every shared library (resident memory "
            "grows to ~110 MB), so it is off unless asked for (configs/robot.yaml turns it on).")
    timer_slack_ns: int = setting(
        1000, unit="ns", doc="How late the kernel may fire the loop's timers to batch wake-ups.")
    spin_us: int = setting(
        0, unit="us", ge=0, le=2000, reload=LIVE,
        doc="Wake this long before each deadline and poll the clock up to it: the wake-up no longer depends "
            "on the kernel's timer latency, at the cost of that much CPU per tick (200 us at 200 Hz is 4 % of a "
            "core).")
    watch_config: bool = setting(
        False, reload=LIVE,
        doc="Reload this file when it changes (checked once a second: its inode, size and modification time; "
            "a base it `extends:` is not watched).")
    stop_decel: float = setting(
        0.5, unit="m/s^2", gt=0, reload=LIVE,
        doc="Deceleration of a controlled stop along the path, never more than the motors give there (within "
            "`limits.feedback_headroom`), and never faster than the path's own profile.")
    on_recover: Literal["resume", "wait"] = setting(
        "resume", reload=LIVE,
        doc="When a hold ends (fresh samples again, the robot at rest): `resume` the path from where the robot "
            "is (the schedule restarts from rest at the profile's acceleration, never harder than the motors "
            "give at that speed), or `wait`: stop there (state `stopped`) until a command (`follow`).")
    command_timeout_s: float = setting(
        0.5, unit="s", gt=0, le=MAX_COMMAND_TIMEOUT_S, reload=LIVE,
        doc="Velocity mode (`drive`): when no drive command has arrived for this long, the robot brakes to a "
            "standstill within `limits.accel`, `limits.alpha_max` and the `drive:` jerk limits, then stands "
            "with the motors at zero (state `stopped`), as ros2 diff_drive_controller's `cmd_vel_timeout`.")
    telemetry_format: Literal["csv", "mcap", "both", "rosbag2"] = setting(
        "csv",
        doc="`csv`, `mcap` (rotated `telemetry.mcap`, `telemetry.1.mcap` ... on the Foxglove channels, same "
            "rotation keys), `both`, or `rosbag2` (the CSV, and the ROS 2 bridge's topics recorded as rosbag2 "
            "with MCAP storage: folders `rosbag2-<UTC time>`, a new one every `telemetry_max_bytes` of "
            "messages, `telemetry_max_files` kept; the bridge process records them, joining ROS 2 only if "
            "`daemon.ros2.enabled`). `mcap` needs `pip install 'ddrt[foxglove]'`, `rosbag2` "
            "`pip install 'ddrt[ros2]'`. [foxglove.md](foxglove.md), [ros2.md](ros2.md)")
    foxglove: FoxgloveConfig = setting(factory=FoxgloveConfig, doc="The Foxglove WebSocket server.")
    ros2: Ros2Config = setting(
        factory=Ros2Config,
        doc="The ROS 2 bridge, a process of its own the daemon starts and restarts; needs "
            "`pip install 'ddrt[ros2]'` and the control socket. [ros2.md](ros2.md)")


@dataclass(frozen=True)
class DriveConfig(Section):
    """The velocity mode's own limits (ddrt/core/drive.py); speeds and accelerations are
    limits.*, shared with paths. Jerk limits as ros2 diff_drive_controller's
    linear/angular max_jerk; null: none (its has_jerk_limits: false)."""

    APPLY: ClassVar[str] = LIVE  # the velocity mode takes them between two ticks

    jerk_max: float | None = setting(
        10.0, unit="m/s^3", gt=0,  # limits.accel (1 m/s^2) is reached in 0.1 s
        doc="Largest rate of change of the forward acceleration; `null`: no jerk limit (a trapezoid at "
            "`limits.accel`).")
    angular_jerk_max: float | None = setting(
        200.0, unit="rad/s^3", gt=0,  # limits.alpha_max (20 rad/s^2) in 0.1 s
        doc="Largest rate of change of the yaw acceleration; `null`: no jerk limit.")


# The smallest radius, side or pivot radius a path may have (m): below it a path is a point
# and its curvature beyond what the profile's floats can hold.
MIN_PATH_SIZE_M = 0.001
MAX_TOLERANCE_M = 1.0  # paths.tolerance_m and a path's tolerance: at most this (m)


@dataclass(frozen=True)
class PathsConfig(Section):
    """How paths are sampled, and how much work one path may ask for (checked before it is built)."""

    APPLY: ClassVar[str] = NEXT_PATH  # read when a path is built

    sample_step_m: float = setting(
        0.002, unit="m", gt=0, le=1.0,
        doc="Distance between two samples of a path (linear interpolation between them).")
    pivot_radius_m: float = setting(
        0.1, unit="m", ge=MIN_PATH_SIZE_M,
        doc="b: progress per radian of turn in a pivot (its angular speed cap is b x omega_max); at most "
            "`max_extent_m`. A path's own `pivot_radius:` replaces it.")
    corner_pivot_deg: float = setting(
        30.0, unit="deg", ge=0, lt=180,
        doc="Corners of a polyline turning by more than this become turns in place; gentler ones are blended "
            "(below 180: a reversal always turns in place). A path's own `corner_pivot_deg:` replaces it.")
    blend_max_m: float = setting(
        0.15, unit="m", ge=MIN_PATH_SIZE_M,
        doc="Longest tangent of a gentle corner's curvature-continuous blend; at most `max_extent_m`. A path's "
            "own `blend_max:` replaces it.")
    tolerance_m: float | Literal["auto"] = setting(
        "auto", unit="m", ge=0.0, le=MAX_TOLERANCE_M,
        doc="A polyline whose points are samples of a curve (a recording, a planner's output, an exported "
            "curve) is followed as a smoothing spline that stays within this distance of every point. `auto`: "
            "set from the points' estimated noise (sigma x (sqrt(2 ln 2n) + 1) for n points: the largest "
            "excursion the noise makes, plus the fit's own error), never below 10 mm; a grid plan given cell by "
            "cell gets half a cell. A number is held to: where no curve that leaves the noise out "
            "(ddrt/path/noise.py) can stay within it, the path is refused naming the point, the noise and the "
            "tolerance that would work. 0 reads every point as a waypoint. A path's own `tolerance:` replaces "
            "it ([config.md](config.md#polylines-waypoints-or-samples)).")
    waypoint_spacing_m: float = setting(
        0.25, unit="m", ge=MIN_PATH_SIZE_M,
        doc="A polyline whose points are at least this far apart (median spacing) is a list of waypoints, "
            "driven as given: straight segments, turns in place at corners sharper than `corner_pivot_deg`, "
            "blends at gentler ones. Denser points are samples of a curve. At most `max_extent_m`.")
    max_samples: int = setting(
        2_000_000, unit="samples", ge=10, le=100_000_000,
        doc="Most samples one path may have (a 2 million sample path is 4 km at 2 mm; it takes about 2 s of "
            "CPU and 1.6 GB of memory to build with no robot, and with the motor envelope of a config's robot up "
            "to 9 s and 2 GB): lower it on a small computer.")
    max_points: int = setting(
        10_000, unit="waypoints", ge=2, le=10_000_000,
        doc="Most waypoints of a CSV file or an inline `points:` list, and most corners of a rectangle over "
            "all its laps (each corner costs about 0.2 ms to build).")
    max_extent_m: float = setting(
        10_000.0, unit="m", gt=0,
        doc="Every waypoint, centre, origin and start pose of a path, and every sample, lies within this "
            "distance of the origin along x and y.")
    workspace_m: float = setting(
        50.0, unit="m", gt=0,
        doc="How far a polyline (a CSV, `points:`) that does not state its unit may reach from the origin, or "
            "span, before it is refused as likely in millimetres, centimetres or inches (ddrt/path/units.py); "
            "beyond 0.3 of it (15 m), a warning. A file that states its unit (a header `x_mm,y_mm`, "
            "`x_cm,y_cm`, `x_in,y_in`, `x_m,y_m`, or `units:` in a YAML spec) is not held to it.")
    max_duration_s: float = setting(
        3_600.0, unit="s", gt=0,
        doc="Longest time the speed profile may take along one path (a speed of 1e-9 m/s would make "
            "`ddrt sim` run for ever).")
    # The daemon reads and builds a path in a worker process, within these bounds.
    max_file_bytes: int = setting(
        4_000_000, unit="bytes", ge=1, le=1_000_000_000,
        doc="The daemon refuses, before reading it, a path file (and a CSV that an inline `file:` names) "
            "larger than this; only regular files are read. A CSV is also held to 128 bytes a waypoint "
            "(`paths.max_points` x 128 + 64 KiB: 1.3 MB at the default 10000 points), whichever is smaller; "
            "the error names the setting that refused it.")
    build_timeout_s: float = setting(
        30.0, unit="s", ge=0.1, le=3600.0,
        doc="The daemon reads and builds each path in a worker process; one not ready within this time is "
            "refused and its worker stopped (a 2 million sample path takes about 2 s on a desktop CPU, several "
            "times that on a Pi).")

    def validate(self, where: str) -> None:
        for key, value in (("waypoint_spacing_m", self.waypoint_spacing_m), ("pivot_radius_m", self.pivot_radius_m),
                           ("blend_max_m", self.blend_max_m)):
            if value > self.max_extent_m:
                raise ConfigError(f"{where}.{key}: must be at most max_extent_m ({self.max_extent_m:g} m), "
                                  f"got {value}")

    def check_pose(self, pose: tuple[float, ...], where: str) -> None:
        """A start pose (or point) inside the workspace: |x|, |y| <= max_extent_m."""
        if max(abs(pose[0]), abs(pose[1])) > self.max_extent_m:
            raise ConfigError(f"{where}: ({pose[0]:.6g}, {pose[1]:.6g}) is beyond paths.max_extent_m "
                              f"= {self.max_extent_m:g} m from the origin")


GYRO_MARGIN = 0.8  # limits.omega_max stays within this fraction of the gyro's full scale


@dataclass(frozen=True)
class Config(Section):
    """Everything ddrt needs, validated. `robot` is what the controller believes, `plant`
    what the simulated robot is (missing plant keys default to robot's)."""

    robot: RobotParams = setting(
        reload=LIVE, missing="required",  # the model in the controller, estimator and adapter
        doc="The robot the controller believes in: geometry and mass properties (or `estimate:`, "
            "[config.md](config.md#robot)).")
    robot_motor: MotorParams = setting(
        name="robot.motor", reload=LIVE,
        doc="The gearmotor and driver the controller believes in, the same for both wheels; constants at the "
            "wheel (after the gearbox).")
    plant: RobotParams = setting(
        reload=RESTART, missing="`robot:`'s",  # the simulated robot is built once
        doc="The simulated robot's truth: `robot:`'s keys, each missing one taking `robot:`'s value.")
    plant_motor_l: MotorParams = setting(
        name="plant.motor_l", reload=RESTART, missing="`plant.motor`'s",
        doc="The simulated left gearmotor: `robot.motor`'s keys, merged over `plant.motor` (itself over "
            "`robot.motor`).")
    plant_motor_r: MotorParams = setting(
        name="plant.motor_r", reload=RESTART, missing="`plant.motor`'s",
        doc="The simulated right gearmotor, as `plant.motor_l`.")
    sim: SimConfig = setting(factory=SimConfig, reload=RESTART, doc="The simulated backend's own settings.")
    sensors: SensorsConfig = setting(factory=SensorsConfig, reload=RESTART, doc="Encoder and gyro facts.")
    hal: HalConfig = setting(factory=HalConfig, reload=RESTART, doc="Which hardware backend drives the robot, and its devices.")
    controller: ControllerConfig = setting(factory=ControllerConfig, reload=LIVE, doc="Control law and gains.")
    estimator: EstimatorConfig = setting(factory=EstimatorConfig, reload=LIVE, doc="Kalman filter tuning and sensor supervision.")
    pursuit: PursuitConfig = setting(factory=PursuitConfig, reload=NEXT_PATH, doc="How the reference point is taken from the path.")
    limits: LimitsConfig = setting(factory=LimitsConfig, reload=NEXT_PATH, doc="Speed, acceleration, duty and torque limits.")
    daemon: DaemonConfig = setting(factory=DaemonConfig, reload=RESTART, doc="The long-running service.")
    drive: DriveConfig = setting(factory=DriveConfig, reload=LIVE, doc="The velocity mode's jerk limits.")
    paths: PathsConfig = setting(
        factory=PathsConfig, reload=NEXT_PATH, doc="How paths are sampled and how much work one path may ask for.")
    path: Any = setting(
        None, unit="file name or mapping", reload=RESTART,
        doc="Path to follow at start (`ddrt run`, `ddrt sim`): a `.yaml`/`.yml`/`.csv` file, or an inline path "
            "mapping (ddrt/path/spec.py). A relative name (and an inline path's relative `file:`) is taken from "
            "the folder of the file that gives it. The command line's `--path` overrides it.")
    start: tuple[float, float, float] | None = setting(
        None, unit="[m, m, rad]", reload=RESTART,
        doc="Initial pose `[x, y, theta]` of the robot, x and y within `paths.max_extent_m`; `null`: the "
            "path's start pose.")
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
