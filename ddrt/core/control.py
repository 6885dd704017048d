"""The controllers: the seed's three-stage design, a kinematic baseline, and the seed's own.

Dynamic (default), the seed's Chapter 4 with the corrected model of docs/model.md:
  1. outer: Kanayama's law (eq. 4.3) turns the pose error into commanded speeds eta_c;
  2. inner: PID on e = eta_c - eta, with the reference's acceleration fed forward,
     integrator clamping and conditional integration (anti-windup), derivative on the
     measurement (a setpoint step gives no kick);
  3. compensator: tau = H_hat nu + h_hat, then the inverse motor model gives the duty. The
     back-EMF and friction are fed forward at the *commanded* wheel speeds, not the measured
     ones: the motor then keeps its own damping about the command instead of having it
     cancelled.
When a wheel saturates, both duties are scaled by the same factor so the robot keeps its
curve and slows down along it.

Kinematic baseline: pure pursuit's curvature gives (v, omega); a PID per wheel on wheel
speed, with back-EMF feed-forward, gives the duty (what ros2's diff_drive_controller with
a wheel PID does).

Seed: the report's own method, for comparison only: time-indexed reference, the report's
model (h = 0, its smaller I), K_P = 1.732, K_I = K_D = 0.5 on the error eta_c - eta, outer
gains 10/64/16, and torque turned into duty by cancelling the measured back-EMF.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ddrt.config import ControllerConfig, LimitsConfig, OuterGains, PidGains
from ddrt.core.model import Dynamics
from ddrt.core.motor import Motor
from ddrt.core.types import Setpoint
from ddrt.core.wrap import TWO_PI, wrap_angle

SEED_INNER = PidGains(kp=1.732, ki=0.5, kd=0.5, integrator_limit=100.0)
SEED_OUTER = OuterGains(k_x=10.0, k_y=64.0, k_theta=16.0)
HOLD_SPEED = 0.005  # m/s: below this reference speed a heading-hold term fades in


@dataclass(slots=True)
class Command:
    """The controller's output for one tick, kept for telemetry."""

    duty_l: float = 0.0
    duty_r: float = 0.0
    tau_l: float = 0.0
    tau_r: float = 0.0
    v_c: float = 0.0
    omega_c: float = 0.0
    saturated: bool = False


class _Pid:
    """One PID channel with clamped, conditionally-integrating integrator."""

    __slots__ = ("kp", "ki", "kd", "limit", "integral", "prev_meas", "prev_err", "on_error")

    def __init__(self, gains: PidGains, on_error: bool = False) -> None:
        self.kp = gains.kp
        self.ki = gains.ki
        self.kd = gains.kd
        self.limit = gains.integrator_limit
        self.on_error = on_error  # the seed differentiates the error, we the measurement
        self.integral = 0.0
        self.prev_meas: float | None = None
        self.prev_err = 0.0

    def output(self, err: float, meas: float, dt: float, hold_integral: bool) -> float:
        if not hold_integral:
            integral = self.integral + err * dt
            lim = self.limit
            self.integral = lim if integral > lim else (-lim if integral < -lim else integral)
        if self.on_error:
            deriv = (err - self.prev_err) / dt if self.prev_meas is not None else 0.0
        else:
            deriv = -(meas - self.prev_meas) / dt if self.prev_meas is not None else 0.0
        self.prev_meas = meas
        self.prev_err = err
        return self.kp * err + self.ki * self.integral + self.kd * deriv

    def retune(self, gains: PidGains, err: float) -> None:
        """New gains, with the integrator re-seeded so the output does not step (bumpless)."""
        p_old = self.kp * err + self.ki * self.integral
        self.kp, self.kd, self.limit = gains.kp, gains.kd, gains.integrator_limit
        self.ki = gains.ki
        if gains.ki > 0.0:
            target = (p_old - gains.kp * err) / gains.ki
            lim = self.limit
            self.integral = lim if target > lim else (-lim if target < -lim else target)
        else:
            self.integral = 0.0

    def reset(self) -> None:
        self.integral = 0.0
        self.prev_meas = None
        self.prev_err = 0.0


def _scale_to_limit(a: float, b: float, limit: float) -> tuple[float, float, bool]:
    """Scale (a, b) together so neither exceeds `limit` in magnitude; report if it had to."""
    m = abs(a)
    mb = abs(b)
    if mb > m:  # max(|a|, |b|) without the builtin's call
        m = mb
    if m > limit:
        s = limit / m
        return a * s, b * s, True
    return a, b, False


class _Controller:
    """What both controllers share: a model to swap, PIDs to reset, the last command."""

    dyn: Dynamics
    cmd: Command
    _pids: tuple[_Pid, ...] = ()

    def reset(self) -> None:
        for pid in self._pids:
            pid.reset()
        self.cmd = Command()

    def set_dynamics(self, dyn: Dynamics) -> None:
        """Swap the model (the adaptive law's estimate) between ticks."""
        self.dyn = dyn

    def set_limits(self, limits: LimitsConfig) -> None:
        """New limits alone (no gains), between ticks."""
        self.limits = limits

    def set_model(self, dyn: Dynamics, motor: Motor) -> None:
        """A new robot description (a reload): the dynamic and the motor model, between ticks."""
        self.dyn = dyn
        self.motor = motor


class DynamicController(_Controller):
    """Outer Kanayama law, inner PID, computed-torque compensator, inverse motor model."""

    def __init__(self, dyn: Dynamics, motor: Motor, cfg: ControllerConfig, limits: LimitsConfig,
                 period_s: float, seed_method: bool = False) -> None:
        self.dyn = dyn
        self.motor = motor
        self.period = period_s
        self.seed_method = seed_method
        outer = SEED_OUTER if seed_method else cfg.outer
        inner = SEED_INNER if seed_method else cfg.inner
        self.outer = outer
        self.heading_gain = cfg.heading_gain
        self.pid_v = _Pid(inner, on_error=seed_method)
        self.pid_w = _Pid(inner, on_error=seed_method)
        self._pids = (self.pid_v, self.pid_w)
        self.cmd = Command()
        self._set_limits(limits)

    def set_limits(self, limits: LimitsConfig) -> None:
        self._set_limits(limits)

    def _set_limits(self, limits: LimitsConfig) -> None:
        """Limits, and the commanded accelerations they allow (twice the profile's)."""
        self.limits = limits
        self._nu_max = 2.0 * limits.accel
        self._alpha_max = 2.0 * limits.alpha_max

    def retune(self, cfg: ControllerConfig, limits: LimitsConfig) -> None:
        """Apply new gains and limits between two ticks without a step in the command.

        The seed's method keeps the report's fixed gains: only the limits change there."""
        self._set_limits(limits)
        if self.seed_method:
            return
        self.outer = cfg.outer
        self.heading_gain = cfg.heading_gain
        self.pid_v.retune(cfg.inner, self._last_err_v)
        self.pid_w.retune(cfg.inner, self._last_err_w)

    _last_err_v = 0.0
    _last_err_w = 0.0

    def update(self, x: float, y: float, theta: float, v: float, w: float, sp: Setpoint) -> Command:
        cmd = self.cmd
        dt = self.period
        # 1. Outer law (seed eq. 4.3) in the robot frame.
        dx = sp.x_d - x
        dy = sp.y_d - y
        # Time-indexed: Kanayama's robot-frame errors. Path-following: the reference is the
        # nearest point, so the errors are taken in the path's frame there, where the
        # along-track part is exactly the schedule's lead and the lateral part is the
        # cross-track error (in the robot's frame a heading error would leak the
        # cross-track offset into x_e and make the robot surge).
        frame = sp.theta_d if sp.path_frame else theta
        c = math.cos(frame)
        s = math.sin(frame)
        x_e = c * dx + s * dy + sp.along_err
        y_e = -s * dx + c * dy
        if y_e > sp.y_cap:  # joining a path from off it: approach at a bounded angle
            y_e = sp.y_cap
        elif y_e < -sp.y_cap:
            y_e = -sp.y_cap
        # wrap_angle(sp.theta_d - theta), written out (the same operations): this runs every tick.
        th_e = math.fmod(sp.theta_d - theta + math.pi, TWO_PI)
        if th_e <= 0.0:
            th_e += TWO_PI
        th_e -= math.pi
        o = self.outer
        v_d = sp.v_d
        cos_e = math.cos(th_e)
        v_c = v_d * cos_e + o.k_x * x_e
        # Kanayama's heading feedback vanishes with v_d; below HOLD_SPEED a heading-hold term
        # fades in so the robot keeps its heading while turning in place or at rest. Above
        # it the law is Kanayama's alone, whose convergence is fixed in distance, not time.
        # |v_d|: reversing, Kanayama's Lyapunov function still decreases (-K_x x_e^2 -
        # |v_d| K_theta sin^2(th_e) / K_y) when the heading term keeps its sign and the lateral
        # one (v_d K_y y_e) takes v_d's.
        k_th = abs(v_d) * o.k_theta
        if not self.seed_method and (sp.pivot or abs(v_d) < HOLD_SPEED):
            k_th += self.heading_gain * (1.0 if sp.pivot else 1.0 - abs(v_d) / HOLD_SPEED)
        w_c = sp.omega_d + v_d * o.k_y * y_e + k_th * math.sin(th_e)
        if sp.pivot and not self.seed_method:
            w_c += o.k_x * sp.along_err / sp.pivot_radius * (1.0 if sp.omega_d >= 0.0 else -1.0)
            v_c = v_d * cos_e + o.k_x * (c * dx + s * dy)
        lim = self.limits
        vm = lim.v_max if lim.v_max < sp.v_cap else sp.v_cap
        wm = lim.omega_max if lim.omega_max < sp.omega_cap else sp.omega_cap
        # max(-vm, min(vm, v_c)) and the same for w_c, without the builtins' calls.
        v_c = v_c if v_c < vm else vm
        v_c = v_c if v_c > -vm else -vm
        w_c = w_c if w_c < wm else wm
        w_c = w_c if w_c > -wm else -wm

        # 2. Inner PID on eta_c - eta with acceleration feed-forward.
        e_v = v_c - v
        e_w = w_c - w
        self._last_err_v = e_v
        self._last_err_w = e_w
        hold = cmd.saturated
        nu_v = sp.a_d + self.pid_v.output(e_v, v, dt, hold)
        nu_w = sp.alpha_d + self.pid_w.output(e_w, w, dt, hold)
        lim_v, lim_w = self._nu_max, self._alpha_max
        nu_v = nu_v if nu_v < lim_v else lim_v
        nu_v = nu_v if nu_v > -lim_v else -lim_v
        nu_w = nu_w if nu_w < lim_w else lim_w
        nu_w = nu_w if nu_w > -lim_w else -lim_w

        # 3. Computed torque with the model, then the inverse motor model.
        dyn = self.dyn
        tau_l, tau_r = dyn.inverse(v, w, nu_v, nu_w)
        # _scale_to_limit(tau_l, tau_r, torque_max_nm), written out (no call, no tuple): every tick.
        m = abs(tau_l)
        mb = abs(tau_r)
        if mb > m:
            m = mb
        sat_t = m > lim.torque_max_nm
        if sat_t:
            k = lim.torque_max_nm / m
            tau_l, tau_r = tau_l * k, tau_r * k
        motor = self.motor
        if self.seed_method:
            wl = (v - dyn.L * w) / dyn.r_L
            wr = (v + dyn.R * w) / dyn.r_R
            duty_l, _ = motor.duty_for_torque(tau_l, wl, friction_speed=0.0)
            duty_r, _ = motor.duty_for_torque(tau_r, wr, friction_speed=0.0)
        else:
            wl_c = (v_c - dyn.L * w_c) / dyn.r_L
            wr_c = (v_c + dyn.R * w_c) / dyn.r_R
            # Positional: emf_speed and friction_speed both the commanded wheel speed.
            duty_l, duty_r = motor.duties_at(tau_l, wl_c, tau_r, wr_c)
        m = abs(duty_l)  # _scale_to_limit(duty_l, duty_r, duty_max), written out
        mb = abs(duty_r)
        if mb > m:
            m = mb
        sat_d = m > lim.duty_max
        if sat_d:
            k = lim.duty_max / m
            duty_l, duty_r = duty_l * k, duty_r * k

        cmd.duty_l = duty_l
        cmd.duty_r = duty_r
        cmd.tau_l = tau_l
        cmd.tau_r = tau_r
        cmd.v_c = v_c
        cmd.omega_c = w_c
        cmd.saturated = sat_t or sat_d
        return cmd


class KinematicController(_Controller):
    """Pure pursuit curvature plus a speed PID per wheel: the baseline to beat."""

    _last_err_l = 0.0
    _last_err_r = 0.0

    def __init__(self, dyn: Dynamics, motor: Motor, cfg: ControllerConfig, limits: LimitsConfig,
                 period_s: float) -> None:
        self.dyn = dyn
        self.motor = motor
        self.limits = limits
        self.period = period_s
        self.heading_gain = cfg.heading_gain
        self.pid_l = _Pid(cfg.wheel_pid)
        self.pid_r = _Pid(cfg.wheel_pid)
        self._pids = (self.pid_l, self.pid_r)
        self.cmd = Command()

    def retune(self, cfg: ControllerConfig, limits: LimitsConfig) -> None:
        self.pid_l.retune(cfg.wheel_pid, self._last_err_l)
        self.pid_r.retune(cfg.wheel_pid, self._last_err_r)
        self.heading_gain = cfg.heading_gain
        self.limits = limits

    def update(self, x: float, y: float, theta: float, v: float, w: float, sp: Setpoint) -> Command:
        cmd = self.cmd
        lim = self.limits
        th_e = wrap_angle(sp.theta_d - theta)
        if sp.pivot:
            v_c = 0.0
            w_c = sp.omega_d + self.heading_gain * math.sin(th_e)
        else:
            v_c = sp.v_d + 10.0 * sp.along_err
            w_c = v_c * sp.pp_curvature
            if abs(sp.v_d) < 1e-3:
                w_c += self.heading_gain * math.sin(th_e)
        vm = lim.v_max if lim.v_max < sp.v_cap else sp.v_cap
        wm = lim.omega_max if lim.omega_max < sp.omega_cap else sp.omega_cap
        v_c = max(-vm, min(vm, v_c))
        w_c = max(-wm, min(wm, w_c))
        dyn = self.dyn
        wl_c = (v_c - dyn.L * w_c) / dyn.r_L
        wr_c = (v_c + dyn.R * w_c) / dyn.r_R
        wl = (v - dyn.L * w) / dyn.r_L
        wr = (v + dyn.R * w) / dyn.r_R
        motor = self.motor
        hold = cmd.saturated
        ff_l, _ = motor.duty_for_torque(0.0, wl_c)
        ff_r, _ = motor.duty_for_torque(0.0, wr_c)
        self._last_err_l = wl_c - wl
        self._last_err_r = wr_c - wr
        duty_l = ff_l + self.pid_l.output(self._last_err_l, wl, self.period, hold)
        duty_r = ff_r + self.pid_r.output(self._last_err_r, wr, self.period, hold)
        duty_l, duty_r, sat = _scale_to_limit(duty_l, duty_r, lim.duty_max)
        cmd.duty_l = duty_l
        cmd.duty_r = duty_r
        cmd.tau_l, cmd.tau_r = motor.net_torques(duty_l, wl, duty_r, wr)
        cmd.v_c = v_c
        cmd.omega_c = w_c
        cmd.saturated = sat
        return cmd


def make_controller(mode: str, dyn_true_model: Dynamics, dyn_seed_model: Dynamics, motor: Motor,
                    cfg: ControllerConfig, limits: LimitsConfig, period_s: float) -> DynamicController | KinematicController:
    """The controller named by `controller.mode`."""
    if mode == "dynamic":
        return DynamicController(dyn_true_model, motor, cfg, limits, period_s)
    if mode == "kinematic":
        return KinematicController(dyn_true_model, motor, cfg, limits, period_s)
    if mode == "seed":
        return DynamicController(dyn_seed_model, motor, cfg, limits, period_s, seed_method=True)
    raise ValueError(f"controller.mode: unknown mode {mode!r}")
