"""`ddrt calibrate`: gyro at rest, dynamic identification, odometry (UMBmark style).

Every procedure drives the robot only through a `ControlLoop` around a `hal.base.Hal`, so the
same commands run on the simulated robot (`hal.backend: sim`) and on the real one. Results
are config fragments (YAML text with a comment of what was measured and how well) to merge
into the robot's config; nothing is written into an existing config.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import yaml

from ddrt.errors import DdrtError
from ddrt.core.adapt import NAMES, DynamicsAdapter
from ddrt.config import Config
from ddrt.core.types import Setpoint
from ddrt.core.wrap import wrap_angle
from ddrt.loop import ControlLoop, LoopState
from ddrt.core.model import Dynamics
from ddrt.params.robot import RobotParams
from ddrt.core.split import Split, physical_split
from ddrt.path import Path, load_path
from ddrt.path.start import TurnProfile
from hal.base import Hal

DEG = math.pi / 180.0


class CalibrationRunError(DdrtError, RuntimeError):
    """A calibration run could not finish (fault, timeout, bad area or measurement)."""


# --------------------------------------------------------------------------- driving


def clock_for(hal: Hal) -> Any:
    """A HAL whose robot runs in simulated time is its own clock; hardware runs on the
    monotonic clock."""
    if hal.owns_time:
        return hal
    from ddrt.runtime.clock import MonotonicClock

    return MonotonicClock()


def run_until_stopped(loop: ControlLoop, clock: Any, limit_s: float) -> None:
    """Tick on absolute deadlines until the loop stops; fault or timeout raise."""
    t0 = clock.now()
    holds = loop.recovery.holds
    for i in range(int(math.ceil(limit_s / loop.period))):
        clock.sleep_until(t0 + (i + 1) * loop.period)
        loop.tick()
        if loop.recovery.holds != holds:
            # A sensor gap stopped the robot mid-run: what it measured is not the run asked for.
            cause = loop.recovery.last_cause
            loop.estop("calibration run interrupted")
            raise CalibrationRunError(f"the calibration run was interrupted ({cause}): run it again")
        if loop.state == LoopState.ESTOP:  # the robot's emergency-stop input (ddrt/loop/power.py)
            raise CalibrationRunError(f"the robot was stopped ({loop.fault}): the motors are off; release the "
                                      "emergency stop and run again")
        if loop.state == LoopState.STOPPED:
            return
        if loop.state == LoopState.FAULT:
            raise CalibrationRunError(f"the robot faulted during calibration: {loop.fault}")
    loop.estop("calibration run timed out")
    raise CalibrationRunError(f"the calibration run did not finish within {limit_s:.0f} s")


def start_loop(cfg: Config, hal: Hal) -> tuple[ControlLoop, Any]:
    loop = ControlLoop(cfg, hal)
    clock = clock_for(hal)
    loop.calibrate(clock.sleep_until, clock.now)
    return loop, clock


# --------------------------------------------------------------------------- gyro


@dataclass(frozen=True)
class GyroResult:
    bias_rad_s: float
    std_rad_s: float
    seconds: float


def calibrate_gyro_at_rest(cfg: Config, hal: Hal) -> GyroResult:
    """Bias and per-sample noise of the gyro with the motors held at zero."""
    loop = ControlLoop(cfg, hal)
    clock = clock_for(hal)
    bias, std = loop.calibrate(clock.sleep_until, clock.now)
    return GyroResult(bias, std, cfg.estimator.calibration_s)


def gyro_fragment(res: GyroResult) -> str:
    head = (f"# ddrt calibrate gyro: {res.seconds:.1f} s at rest; bias {res.bias_rad_s / DEG:+.4f} deg/s "
            f"(re-measured at every start, not a config key), noise {res.std_rad_s / DEG:.4f} deg/s per sample\n")
    return head + yaml.safe_dump({"estimator": {"gyro_noise_dps": round(max(res.std_rad_s / DEG, 1e-4), 5)}},
                                 sort_keys=False)


# --------------------------------------------------------------------------- identification


# A term that accounts for less than this many times the fit's residual is not separated from
# what the model leaves out: reported as such rather than as a measured value.
SEEN_MIN = 3.0


@dataclass(frozen=True)
class IdentifyResult:
    """Batch least squares over one excitation run: values, standard errors, fit quality."""

    values: dict[str, float]
    std_err: dict[str, float]
    r2: float
    residual_rms_n: float
    rows: int
    duration_s: float
    area: tuple[float, float]
    # The rms force (N) each parameter's term accounts for over the run. A term no larger than
    # the residual is one the run cannot tell from what the model leaves out (two motors that
    # differ, say), however small its formal standard error.
    effect_n: dict[str, float] = field(default_factory=dict)

    def seen(self, name: str) -> float:
        """How many times the fit's residual the term `name` accounts for."""
        return self.effect_n[name] / self.residual_rms_n if self.residual_rms_n > 0 else math.inf
    normal: np.ndarray | None = field(default=None, repr=False, compare=False)  # phi^T phi, NAMES order


def parse_area(text: str) -> tuple[float, float]:
    """'2x1.5' -> (2.0, 1.5) metres."""
    try:
        w, h = (float(v) for v in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"--area: expected WIDTHxHEIGHT in metres (e.g. 2x1.5), got {text!r}") from None
    if not (w > 0 and h > 0 and math.isfinite(w) and math.isfinite(h)):
        raise ValueError(f"--area: width and height must be > 0, got {text!r}")
    return w, h


def footprint_margin(p: RobotParams) -> float:
    """How far the robot reaches from point A, plus 5 cm: the path keeps this off the edges."""
    return max(p.L, p.R, p.H) + 0.05


MIN_EXCITATION_WIDTH_M = 0.3  # a figure-eight narrower than this hardly excites the dynamics


def excitation_path(cfg: Config, width: float, height: float, max_s: float = 30.0,
                    speed: float | None = None) -> Path:
    """A figure-eight centred on the start that stays `footprint_margin` inside the area.

    Its lobes turn both ways (yaw acceleration of both signs) and the lateral-acceleration
    limit makes the speed rise and fall along it (forward acceleration): the whole regressor
    is excited. As many laps as fit in `max_s`.
    """
    margin = footprint_margin(cfg.robot)
    w, h = width - 2.0 * margin, height - 2.0 * margin
    if w < MIN_EXCITATION_WIDTH_M or h < 0.15:
        raise ValueError(f"--area {width}x{height}: too small for the robot (needs at least "
                         f"{0.3 + 2 * margin:.2f} x {0.15 + 2 * margin:.2f} m)")
    if h > 0.5 * w:  # Gerono's lemniscate gets a cusp-like waist when taller than half its width
        h = 0.5 * w
    from ddrt.path.spec import speed_limits

    v = min(speed_limits(cfg).v_max, 0.8) if speed is None else speed

    spec = {"shape": "figure_eight", "width": w, "height": h, "speed": v}
    one = load_path(spec, speed_limits(cfg), paths=cfg.paths)
    # A free area larger than one lap in max_s needs: use only what it needs (a smaller
    # figure-eight in its middle), shrinking until a lap fits.
    for _ in range(20):
        if one.duration <= max_s or spec["width"] * 0.9 < MIN_EXCITATION_WIDTH_M:
            break
        shrink = max(0.5, min(0.9, 0.95 * max_s / one.duration))
        spec = dict(spec, width=spec["width"] * shrink, height=spec["height"] * shrink)
        one = load_path(spec, speed_limits(cfg), paths=cfg.paths)
    laps = max(1, int(max_s // one.duration))
    if laps == 1 and one.duration > max_s:
        raise ValueError(f"one lap takes {one.duration:.1f} s even at {spec['width']:.2f} x {spec['height']:.2f} m, "
                         f"more than --duration {max_s:.0f} s: give a longer duration or a higher speed")
    return load_path(dict(spec, laps=float(laps)), speed_limits(cfg), paths=cfg.paths)


def identify(cfg: Config, hal: Hal, width: float, height: float, max_s: float = 30.0,
             speed: float | None = None) -> IdentifyResult:
    """Drive the excitation path and fit (m_k, mbar, I, m_x, c_L, c_R) by least squares."""
    path = excitation_path(cfg, width, height, max_s, speed)
    loop, clock = start_loop(cfg, hal)
    adapter = DynamicsAdapter(loop.dyn, loop.motor, cfg.controller.adaptation, loop.period)
    adapter.recorder = []
    prev = [0.0, 0.0]

    def feed(lp: ControlLoop) -> None:
        if lp.state in (LoopState.FOLLOWING, LoopState.STOPPING):
            adapter.update(lp.estimator.v, lp.estimator.yaw.w, prev[0], prev[1])
        prev[0], prev[1] = lp.duty_l, lp.duty_r

    loop.each_tick(feed)
    loop.follow(path, path.start_pose)
    run_until_stopped(loop, clock, path.duration + 15.0)
    return fit(adapter.recorder, path.duration, (width, height))


def fit(rows: list[tuple[list[float], float]], duration_s: float, area: tuple[float, float]) -> IdentifyResult:
    """Least squares over the recorded regressor rows, with standard errors and R^2."""
    if len(rows) < 50:
        raise CalibrationRunError(f"only {len(rows)} excited samples: the run did not excite the dynamics "
                                  f"(larger area or higher speed)")
    phi = np.array([r[0] for r in rows])
    y = np.array([r[1] for r in rows])
    theta, *_ = np.linalg.lstsq(phi, y, rcond=None)
    res = y - phi @ theta
    dof = max(1, len(y) - phi.shape[1])
    s2 = float(res @ res) / dof
    cov = s2 * np.linalg.pinv(phi.T @ phi)
    ss = float(((y - y.mean()) ** 2).sum())
    r2 = 1.0 - float(res @ res) / ss if ss > 0 else 0.0
    return IdentifyResult(values=dict(zip(NAMES, (float(v) for v in theta))),
                          std_err=dict(zip(NAMES, (float(math.sqrt(max(c, 0.0))) for c in np.diag(cov)))),
                          r2=r2, residual_rms_n=math.sqrt(s2), rows=len(rows), duration_s=duration_s, area=area,
                          effect_n={n: float(np.sqrt(np.mean((phi[:, i] * theta[i]) ** 2))) for i, n in enumerate(NAMES)},
                          normal=phi.T @ phi)


def platform_split(cfg: Config, res: IdentifyResult) -> Split:
    """The platform's m_p, d_xc, d_yc, I_p and each wheel's extra friction that make
    `Dynamics.from_params` give the fit, held physical (ddrt/core/split.py).

    The lumped model has four mass parameters; the platform's four are the ones a payload
    changes, so the wheels' own values stay as configured. When the fit leaves no physical
    platform (the configured wheels too heavy, say), the split is the physical one closest to
    the fit in its own metric, and `held` names each parameter it could not separate.
    """
    try:
        return physical_split(cfg.robot, cfg.robot_motor.coulomb_nm, res.values, res.normal, res.std_err)
    except ValueError as exc:
        raise CalibrationRunError(f"the identified model cannot be split into the platform's parameters: {exc}") \
            from None


def held_lines(split: Split) -> list[str]:
    """One line per parameter the run could not separate, for the user and the config's comments."""
    if not split.held:
        return []
    return ([f"{len(split.held)} parameter(s) came out physically impossible: the run could not separate them, "
             "so each is held at its physical bound and the rest refitted:"]
            + [f"  {h.describe()}" for h in split.held])


def identify_fragment(cfg: Config, res: IdentifyResult) -> str:
    """robot: keys for the identified platform and motor friction, with a comment of the fit."""
    split = platform_split(cfg, res)
    coulomb = max(0.0, cfg.robot_motor.coulomb_nm + 0.5 * (split.friction["fric_l"] + split.friction["fric_r"]))
    m = cfg.robot_motor
    motor = {"supply_v": m.supply_v, "resistance_ohm": m.resistance_ohm, "k_nm_per_a": m.k_nm_per_a,
             "viscous_nms": m.viscous_nms}
    motor["coulomb_nm"] = round(coulomb, 5)
    robot = {k: float(f"{v:.6g}") for k, v in split.platform.items()}
    robot["motor"] = motor
    v, e = res.values, res.std_err
    lines = [
        f"# ddrt calibrate identify: {res.duration_s:.1f} s figure-eight in a {res.area[0]:g} x {res.area[1]:g} m area,",
        f"# {res.rows} excited regression rows, R^2 = {res.r2:.4f}, residual rms {res.residual_rms_n:.3f} N.",
        "# Identified (value +- standard error; how many times the fit's residual force its term accounts for):",
    ]
    units = {"m_k": "kg", "mbar": "kg m", "I": "kg m^2", "m_x": "kg m", "fric_l": "N m", "fric_r": "N m"}
    for name in NAMES:
        seen = res.seen(name)
        lines.append(f"#   {name:7s} {v[name]:+.5f} +- {e[name]:.5f} {units[name]:6s} {seen:5.1f}x the residual"
                     + (": not separated from what the model leaves out" if seen < SEEN_MIN else ""))
    if split.held:
        lines += [f"# {line}" for line in held_lines(split)]
        lines.append("# Platform parameters below give, within those bounds, the model closest to the fit:")
        lines += [f"#   {name:7s} {split.lumped[name]:+.5f} {units[name]}" for name in NAMES]
        lines.append("# Wheel friction is the mean of both wheels' extra Coulomb friction added to the motor's.")
    else:
        lines.append("# Platform parameters below reproduce m_k, mbar, I, m_x exactly; wheel friction is the mean")
        lines.append("# of both wheels' extra Coulomb friction added to the motor's.")
    return "\n".join(lines) + "\n" + yaml.safe_dump({"robot": robot}, sort_keys=False)


# --------------------------------------------------------------------------- odometry


class SpinReference:
    """Turn in place by `angle` rad about the start pose (trapezoidal yaw rate); a
    ddrt.core.reference.Reference whose stop ends the turn at once (it is never part way
    through a stop) and which is never resumed (an interrupted run is run again)."""

    stopping = False
    phase = "turn"
    resumable = False

    def __init__(self, pose: tuple[float, float, float], angle: float, omega_max: float, alpha_max: float,
                 period_s: float) -> None:
        self.x0, self.y0, self.th0 = pose
        self.angle = angle
        self.sign = 1.0 if angle >= 0.0 else -1.0
        self.turn = TurnProfile.plan(abs(angle), omega_max, alpha_max)
        self.period = period_s
        self.t = 0.0
        self.sigma = 0.0
        self.cross_track = 0.0
        self.done = False

    def request_stop(self, decel: float) -> None:
        self.t = max(self.t, self.turn.t_end)

    def resume(self, x: float, y: float, theta: float) -> None:
        raise ValueError("a calibration spin is not resumed: run the calibration again")

    def update(self, x: float, y: float, theta: float, sp: Setpoint, dt: float | None = None) -> None:
        self.t += self.period if dt is None else dt
        ang, w, alpha = self.turn.at(self.t)
        s = self.sign
        sp.turn_in_place(self.x0, self.y0, self.th0 + s * ang, s * w, s * alpha)
        self.sigma = ang
        self.cross_track = math.hypot(x - self.x0, y - self.y0)
        self.done = self.t >= self.turn.t_end


@dataclass(frozen=True)
class OdometryRun:
    """What the robot believes it did, and (simulation only) what it really did."""

    distance_cmd_m: float
    est_distance_m: float
    est_turn_rad: float
    true_distance_m: float | None = None
    true_turn_rad: float | None = None
    wheel_delta: float | None = None  # the drive wheels' radius difference learnt (None: not counted)


def _truth(hal: Hal) -> tuple[float, float, float] | None:
    robot = hal.robot
    return None if robot is None else robot.pose


def odometry_run(cfg: Config, hal: Hal, distance: float = 1.0, turns: float = 1.0) -> OdometryRun:
    """Drive `distance` m straight ahead, stop, then turn in place `turns` full turns."""
    if not distance > 0.0 or not turns > 0.0:
        raise ValueError("odometry: distance and turns must be > 0")
    loop, clock = start_loop(cfg, hal)
    from ddrt.path.spec import speed_limits

    line = load_path({"shape": "line", "length": distance, "speed": min(0.3, speed_limits(cfg).v_max)}, speed_limits(cfg),
                     paths=cfg.paths)
    true0 = _truth(hal)
    loop.follow(line, (0.0, 0.0, 0.0))
    run_until_stopped(loop, clock, line.duration + 15.0)
    settle(loop, clock)
    x1, y1, th1 = loop.estimator_pose()
    true1 = _truth(hal)
    wheels = loop.estimator.wheels
    angle = 2.0 * math.pi * turns
    spin = SpinReference((x1, y1, th1), angle, min(1.5, cfg.limits.omega_max), min(3.0, cfg.limits.alpha_max),
                         loop.period)
    loop.follow_reference(spin)
    run_until_stopped(loop, clock, spin.turn.t_end + 15.0)
    settle(loop, clock)
    th2 = loop.estimator_pose()[2]
    true2 = _truth(hal)
    true_d = true_t = None
    if true0 is not None and true1 is not None and true2 is not None:
        true_d = math.hypot(true1[0] - true0[0], true1[1] - true0[1])
        true_t = angle + wrap_angle((true2[2] - true1[2]) - angle)
    return OdometryRun(distance, math.hypot(x1, y1), th2 - th1, true_d, true_t,
                       wheels.delta if wheels is not None else None)


def settle(loop: ControlLoop, clock: Any, seconds: float = 0.5) -> None:
    """Stand still a moment (zero duty) so the robot has stopped before measuring."""
    t0 = clock.now()
    for i in range(int(seconds / loop.period)):
        clock.sleep_until(t0 + (i + 1) * loop.period)
        loop.tick()


def corrected_radii(cfg: Config, d_ratio: float, wheel_delta: float | None) -> dict[str, float]:
    """The `robot:` radii an odometry run corrects. The distance sensor's scale with the measured
    over the estimated distance: the front encoder's r_3, or on a robot without one the drive
    wheels' r_L and r_R together. And on a robot that counts its drive wheels, their radius
    difference the estimator learnt on the straight (`wheel_delta`, the right's relative error
    less the left's, ddrt/core/wheel_odometry.py), split evenly so their mean is kept."""
    front = cfg.sensors.encoder_counts_per_rev > 0
    out = {"r_3": cfg.robot.r_3 * d_ratio} if front else {}
    if wheel_delta is not None:
        scale, h = (1.0 if front else d_ratio), 0.5 * wheel_delta
        out["r_L"], out["r_R"] = cfg.robot.r_L * scale * (1.0 - h), cfg.robot.r_R * scale * (1.0 + h)
    return out


@dataclass(frozen=True)
class OdometryCorrection:
    radii: dict[str, float]  # corrected_radii
    gyro_scale: float
    distance_ratio: float
    turn_ratio: float

    @property
    def r_3(self) -> float | None:
        """The front encoder's radius, when it is the distance sensor."""
        return self.radii.get("r_3")


def odometry_correction(cfg: Config, run: OdometryRun, measured_distance: float,
                        measured_turn_rad: float) -> OdometryCorrection:
    """Encoder radius and gyro scale that make the estimates match what was measured.

    The estimated distance is counts x radius (r_3, or the drive wheels' without a front
    encoder: scale with the measured distance); the estimated turn is the gyro's integral /
    gyro_scale (so the scale goes with estimated / measured).
    """
    if not measured_distance > 0.0:
        raise ValueError(f"--measured-distance: must be > 0 m, got {measured_distance}")
    if not measured_turn_rad > 0.0:
        raise ValueError(f"--measured-turn-deg: must be > 0, got {measured_turn_rad / DEG}")
    d_ratio = measured_distance / run.est_distance_m
    t_ratio = run.est_turn_rad / measured_turn_rad
    if not (0.8 < d_ratio < 1.25 and 0.8 < t_ratio < 1.25):
        raise CalibrationRunError(f"measurements are {d_ratio:.3f} x the encoder distance and "
                                  f"{1 / t_ratio:.3f} x the gyro's turn: more than 20% off, check them")
    radii = corrected_radii(cfg, d_ratio, run.wheel_delta)
    return OdometryCorrection(radii, cfg.estimator.gyro_scale * t_ratio, d_ratio, t_ratio)


def odometry_fragment(cfg: Config, run: OdometryRun, corr: OdometryCorrection, measured_distance: float,
                      measured_turn_rad: float, source: str) -> str:
    before = asdict(cfg.robot)
    head = (f"# ddrt calibrate odometry ({source}): drove {run.distance_cmd_m:g} m, encoder said "
            f"{run.est_distance_m:.4f} m, measured {measured_distance:.4f} m; turned, gyro said "
            f"{run.est_turn_rad / DEG:.2f} deg, measured {measured_turn_rad / DEG:.2f} deg.\n"
            f"# {', '.join(f'{k} {before[k]:.5f} -> {v:.5f} m' for k, v in corr.radii.items())}, "
            f"gyro_scale {cfg.estimator.gyro_scale:.5f} -> {corr.gyro_scale:.5f}\n")
    body = {"robot": {k: float(f"{v:.6g}") for k, v in corr.radii.items()},
            "estimator": {"gyro_scale": float(f"{corr.gyro_scale:.6g}")}}
    return head + yaml.safe_dump(body, sort_keys=False)


def true_values(cfg: Config) -> dict[str, float]:
    """The simulated robot's lumped parameters (for benchmarks and tests)."""
    d = Dynamics.from_params(cfg.plant)
    return {"m_k": d.m_k, "mbar": d.mbar, "I": d.I, "m_x": d.m_x}
