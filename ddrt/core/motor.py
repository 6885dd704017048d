"""A brushed DC gearmotor, referred to the wheel: duty and speed in, torque out, and back.

Electrical time constant (L/R, about a millisecond) is neglected: the current follows the
voltage within one plant step. All constants are at the wheel (after the gearbox):

    i        = (duty * V - K * w) / R_a
    tau_net  = K * i - b * w - tau_c * tanh(w / w_s)

with K = k_t * G = k_e * G (N m/A = V s/rad). The Coulomb term is smoothed over `w_s` so a
fixed-step integrator does not chatter at rest; w_s is small (0.02 rad/s) against any speed
the robot drives at.
The default constants are `MotorParams`'s (ddrt/params/motor.py), with where each comes from.

The supply voltage V starts as `MotorParams.supply_v` (the config's) and follows the measured,
filtered voltage when the hardware measures it (`set_supply_v`, once a tick from
ddrt/loop/power.py): one float, so the controller, the estimator and the adapter that share
this object all see the voltage the driver has now.
"""

from __future__ import annotations

import math

from ddrt.params.motor import MotorParams


class Motor:
    """Forward and inverse motor model with the constants of `MotorParams` cached as floats."""

    __slots__ = ("params", "_v", "_r", "_k", "_b", "_tc", "_ws")

    def __init__(self, params: MotorParams) -> None:
        self.params = params
        self._v = params.supply_v
        self._r = params.resistance_ohm
        self._k = params.k_nm_per_a
        self._b = params.viscous_nms
        self._tc = params.coulomb_nm
        self._ws = params.coulomb_smoothing_rad_s

    @property
    def supply_v(self) -> float:
        """The supply voltage the model uses now (V)."""
        return self._v

    def set_supply_v(self, volts: float) -> None:
        """Use `volts` (finite, > 0) as the driver's supply from now on; the caller filters it."""
        self._v = volts

    def friction(self, wheel_speed: float) -> float:
        """Friction torque (N m) opposing rotation at `wheel_speed` rad/s."""
        return self._b * wheel_speed + self._tc * math.tanh(wheel_speed / self._ws)

    def electromagnetic_torque(self, duty: float, wheel_speed: float) -> float:
        """Torque the armature produces before friction (N m at the wheel)."""
        return self._k * (duty * self._v - self._k * wheel_speed) / self._r

    def torque(self, duty: float, wheel_speed: float) -> float:
        """Net torque at the wheel (N m) for `duty` in [-1, 1] at `wheel_speed` (rad/s)."""
        if not (-1.0 <= duty <= 1.0):
            raise ValueError(f"duty {duty!r} is outside [-1, 1]")
        return self.electromagnetic_torque(duty, wheel_speed) - self.friction(wheel_speed)

    def duty_for_torque(self, torque: float, wheel_speed: float, emf_speed: float | None = None,
                        friction_speed: float | None = None) -> tuple[float, bool]:
        """Duty that yields net `torque` at `wheel_speed`; returns (duty, saturated).

        The duty is NOT clipped: `saturated` is True when |duty| > 1 and the caller decides how
        to limit it (the controller scales both wheels together). `emf_speed` (default
        `wheel_speed`) is the speed whose back-EMF is fed forward: passing the reference speed
        rather than the measured one keeps the motor's own damping about the reference.
        `friction_speed` (default `wheel_speed`) likewise picks the speed friction is
        compensated at.
        """
        ws = wheel_speed if emf_speed is None else emf_speed
        fs = wheel_speed if friction_speed is None else friction_speed
        drive = torque + self.friction(fs)
        duty = (self._r * drive / self._k + self._k * ws) / self._v
        return duty, not (-1.0 <= duty <= 1.0)

    # The pairs below are the methods above for both wheels in one call, written out (the same
    # arithmetic, bit for bit): the estimator and the controller call them every tick.

    def net_torques(self, duty_l: float, wl: float, duty_r: float, wr: float) -> tuple[float, float]:
        """(electromagnetic_torque(duty_l, wl) - friction(wl), the same for the right wheel)."""
        k, v, r, b, tc, ws = self._k, self._v, self._r, self._b, self._tc, self._ws
        tanh = math.tanh
        return (k * (duty_l * v - k * wl) / r - (b * wl + tc * tanh(wl / ws)),
                k * (duty_r * v - k * wr) / r - (b * wr + tc * tanh(wr / ws)))

    def duties_at(self, tau_l: float, wl: float, tau_r: float, wr: float) -> tuple[float, float]:
        """The duties of duty_for_torque(tau_l, _, wl, wl) and duty_for_torque(tau_r, _, wr, wr):
        back-EMF and friction both at the given wheel speeds; not clipped."""
        k, v, r, b, tc, ws = self._k, self._v, self._r, self._b, self._tc, self._ws
        tanh = math.tanh
        return ((r * (tau_l + (b * wl + tc * tanh(wl / ws))) / k + k * wl) / v,
                (r * (tau_r + (b * wr + tc * tanh(wr / ws))) / k + k * wr) / v)
