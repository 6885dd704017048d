"""The velocity mode: commanded (v, omega) held through the same controller as a path.

`DriveReference` stands where a path's reference stands in the tick (read -> estimate ->
reference -> control -> write -> record): each tick it fills the `Setpoint` from the last
command, passed through a jerk-limited ramp per axis (ddrt/core/ramp.py) within
limits.accel and limits.alpha_max (drive.jerk_max, drive.angular_jerk_max), and it counts
the time since the last command: beyond daemon.command_timeout_s it brakes to a standstill
within the same limits, and is `done` there (the loop then zeroes the motors).

Why the reference pose is the robot's own pose (zero pose error): a velocity command says
nothing about where the robot should be, only how fast it should go. With zero errors
Kanayama's outer law passes (v_d, omega_d) through unchanged (v_c = v_d cos 0 + K_x 0,
omega_c = omega_d + v_d K_y 0 + K_theta sin 0), so the inner PID and the computed-torque
compensator hold the ramped velocities, with the ramp's accelerations fed forward, exactly
as they hold a path's. Integrating the commands into a virtual pose and tracking that was
the alternative; it makes a robot that was held back, pushed or slipping catch up on its
own afterwards (a surge nobody commanded), which a joystick or a navigation stack sending
cmd_vel does not expect. The PID's integrator still holds the speeds against load and slope.

`check_command` refuses what cannot be a velocity (not a number, a bool, not finite) and
what is far beyond the limits (more than REFUSE_FACTOR times: a unit error, mm/s or deg/s,
more likely than a wish), naming the field, and clamps the rest to limits.v_max and
limits.omega_max, saying which it clamped.
"""

from __future__ import annotations

import logging
import math

from ddrt.params.numbers import finite_float
from ddrt.config import DriveConfig, LimitsConfig
from ddrt.core.ramp import Ramp
from ddrt.core.types import Setpoint

log = logging.getLogger("ddrt.drive")

REFUSE_FACTOR = 10.0  # a command beyond this many times its limit is refused, not clamped
PIVOT_V = 1e-3  # m/s: below this the setpoint is a turn in place (the kinematic baseline needs it)
FIELDS = (("v", "m/s", "v_max"), ("omega", "rad/s", "omega_max"))


def check_command(v: object, omega: object, limits: LimitsConfig) -> tuple[float, float, tuple[str, ...]]:
    """(v, omega) within the limits, and the fields that were clamped; ValueError naming the
    field for anything that is not a plausible velocity."""
    out = []
    clamped = []
    for value, (name, unit, key), lim in zip((v, omega), FIELDS, (limits.v_max, limits.omega_max)):
        x = finite_float(value, name, unit=unit)
        if abs(x) > REFUSE_FACTOR * lim:
            raise ValueError(f"{name}: {x:g} {unit} is more than {REFUSE_FACTOR:g} x limits.{key} "
                             f"({lim:g} {unit}): refused as a likely unit error (up to that it is clamped)")
        if abs(x) > lim:
            x = math.copysign(lim, x)
            clamped.append(name)
        out.append(x)
    return out[0], out[1], tuple(clamped)


class DriveReference:
    """Velocity commands with a timeout, as a reference stage (a ddrt.core.reference.Reference)."""

    sigma = 0.0  # no path: no progress along one, no cross-track error
    cross_track = 0.0
    phase = "drive"
    resumable = False  # a drive interrupted by a hold ends stopped: the sender drives again

    def __init__(self, limits: LimitsConfig, drive: DriveConfig, timeout_s: float, period_s: float) -> None:
        self.period = period_s
        self.v = Ramp(limits.accel, drive.jerk_max)
        self.w = Ramp(limits.alpha_max, drive.angular_jerk_max)
        self.timeout_s = timeout_s
        self.commanded = (0.0, 0.0)  # as sent
        self.target = (0.0, 0.0)  # as clamped to the limits
        self.age_s = 0.0  # since the last command, in the loop's time
        self.braking = ""  # why it is braking to a stop: "timeout", "stop", "hold"; "" while driving
        self.commands = 0
        self.timeouts = 0
        self.source = ""
        self._decel: float | None = None

    def configure(self, limits: LimitsConfig, drive: DriveConfig, timeout_s: float) -> None:
        """New limits between two ticks (a reload): the ramps go on from where they are, and
        the command being held is clamped to the new top speeds, so a lower limits.v_max or
        omega_max brakes the robot to it along the ramp (within the accelerations and jerks)."""
        self.v.set_limits(limits.accel, drive.jerk_max)
        self.w.set_limits(limits.alpha_max, drive.angular_jerk_max)
        self.timeout_s = timeout_s
        v, w = self.target
        self.target = (max(-limits.v_max, min(limits.v_max, v)), max(-limits.omega_max, min(limits.omega_max, w)))

    def over(self, v_max: float, omega_max: float) -> bool:
        """Is the ramped setpoint still beyond these top speeds (braking down to new limits)?"""
        return abs(self.v.value) > v_max or abs(self.w.value) > omega_max

    def command(self, v: float, omega: float, commanded: tuple[float, float], source: str = "") -> None:
        """Hold (v, omega) (already checked and clamped) from the next tick; restarts the timeout."""
        self.commanded = commanded
        self.target = (v, omega)
        self.age_s = 0.0
        self.braking = ""
        self._decel = None
        self.commands += 1
        if source:
            self.source = source

    def request_stop(self, decel: float, why: str = "stop") -> None:
        """Brake both axes to zero, the forward speed at no more than `decel` m/s^2."""
        if not self.braking:
            self.braking = why
            self._decel = decel

    @property
    def stopping(self) -> bool:
        return bool(self.braking)

    def resume(self, x: float, y: float, theta: float) -> None:
        raise ValueError("a drive is not resumed: send drive again")

    @property
    def done(self) -> bool:
        """Braked to a standstill (the loop zeroes the motors once the robot is at rest)."""
        return bool(self.braking) and self.v.at_rest and self.w.at_rest

    def update(self, x: float, y: float, theta: float, sp: Setpoint, dt: float | None = None) -> None:
        """Fill `sp` for the robot at (x, y, theta), `dt` seconds after the previous tick."""
        step = self.period if dt is None else dt
        self.age_s += step
        if not self.braking and self.age_s > self.timeout_s:
            self.braking = "timeout"
            self.timeouts += 1
            log.warning("drive: no command for %.2f s (daemon.command_timeout_s = %g s): braking to a stop",
                        self.age_s, self.timeout_s)
        if self.braking:
            v = self.v.step(0.0, step, self._decel)
            w = self.w.step(0.0, step)
        else:
            v = self.v.step(self.target[0], step)
            w = self.w.step(self.target[1], step)
        sp.x_d = x
        sp.y_d = y
        sp.theta_d = theta
        sp.v_d = v
        sp.omega_d = w
        sp.a_d = self.v.rate
        sp.alpha_d = self.w.rate
        sp.along_err = 0.0
        sp.kappa = 0.0
        slow = -PIVOT_V < v < PIVOT_V
        sp.pp_curvature = 0.0 if slow else w / v
        sp.pivot = slow
        sp.path_frame = False
        sp.active = True

    def status(self) -> dict[str, object]:
        """What `ddrt ctl status` shows under "drive"."""
        return {
            "phase": "braking" if self.braking else "driving",
            "braking_for": self.braking or None,
            "commanded": {"v": self.commanded[0], "omega": self.commanded[1]},
            "limited": {"v": self.target[0], "omega": self.target[1]},
            "setpoint": {"v": self.v.value, "omega": self.w.value, "a": self.v.rate, "alpha": self.w.rate},
            "since_command_s": self.age_s,
            "timeout_s": self.timeout_s,
            "commands": self.commands,
            "timeouts": self.timeouts,
            "source": self.source,
        }
