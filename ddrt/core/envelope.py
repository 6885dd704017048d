"""What the motors can give: the torque envelope the speed profile and the controller's clamps use.

Each wheel's net torque (after friction, at the wheel) is bounded by the motor model of
ddrt/core/motor.py at that wheel's speed w, with a fraction `headroom` of the voltage kept
for feedback:

    tau + b w + tau_c tanh(w / w_s) + (K^2 / R_a) w  in  [-V_h, +V_h],   V_h = K (1 - headroom) d_max V / R_a

(the duty the inverse motor model would command stays within (1 - headroom) d_max), and by
the torque limit |tau| <= (1 - headroom) T_max, where T_max is limits.torque_max_nm or, when
that is null, the stall torque K d_max V / R_a. The torques a motion needs come from the
dynamic model (docs/model.md): tau = Bbar^-1 (H d(eta)/dt + h(eta)).

`resolve_limits` turns the config's limits (v_max, accel and torque_max_nm may be null) into
numbers for the controller's clamps: what the user gave, never above what the motors give
(a larger value is kept out and reported), else what the motors give.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

from ddrt.core.model import Dynamics
from ddrt.params.robot import RobotParams
from ddrt.params.motor import MotorParams

if TYPE_CHECKING:
    from ddrt.config.sections import LimitsConfig


@dataclass(frozen=True)
class Envelope:
    """The motors' torque envelope at the wheels, with the model that maps motion to torque."""

    dyn: Dynamics
    motor: MotorParams
    headroom: float = 0.25  # fraction of the voltage (and of the torque limit) kept for feedback
    duty_max: float = 1.0
    torque_max_nm: float | None = None  # the user's cap on |tau|; None: the stall torque

    def __post_init__(self) -> None:
        if not 0.0 <= self.headroom < 1.0:
            raise ValueError(f"Envelope.headroom: must be in [0, 1), got {self.headroom!r}")
        if not 0.0 < self.duty_max <= 1.0:
            raise ValueError(f"Envelope.duty_max: must be in (0, 1], got {self.duty_max!r}")

    # -- the motor's figures -------------------------------------------------------------
    @property
    def stall_torque_nm(self) -> float:
        """Torque at rest at the largest duty, before headroom (N m)."""
        return self.duty_max * self.motor.stall_torque_nm

    @property
    def torque_cap_nm(self) -> float:
        """The torque limit before headroom: the user's, never above the stall torque."""
        stall = self.stall_torque_nm
        return stall if self.torque_max_nm is None else min(self.torque_max_nm, stall)

    @property
    def voltage_bound_nm(self) -> float:
        """V_h in torque units: K (1 - headroom) d_max V / R_a."""
        return (1.0 - self.headroom) * self.stall_torque_nm

    @property
    def torque_bound_nm(self) -> float:
        """(1 - headroom) T_max: the largest |tau| the profile asks of a wheel."""
        return (1.0 - self.headroom) * self.torque_cap_nm

    @property
    def emf_damping(self) -> float:
        """K^2 / R_a + b: the drive torque one rad/s of wheel speed costs (N m s/rad)."""
        m = self.motor
        return m.k_nm_per_a * m.k_nm_per_a / m.resistance_ohm + m.viscous_nms

    def with_headroom(self, headroom: float) -> "Envelope":
        return replace(self, headroom=headroom)

    def wheel_speed_limit(self) -> float:
        """The wheel speed (rad/s) at which the voltage bound just covers friction: no torque is left."""
        m = self.motor
        vh, kv, tc, ws = self.voltage_bound_nm, self.emf_damping, m.coulomb_nm, m.coulomb_smoothing_rad_s
        if not vh > tc:
            return 0.0  # not even at rest does the voltage beat Coulomb friction
        # Solve vh = kv w + tc tanh(w / ws) (increasing in w): Newton from the saturated guess.
        w = max((vh - tc) / kv, 0.0)
        for _ in range(50):
            th = math.tanh(w / ws)
            f = kv * w + tc * th - vh
            df = kv + tc * (1.0 - th * th) / ws
            step = f / df
            w = max(w - step, 0.5 * w)
            if abs(step) <= 1e-15 * max(w, 1e-300):
                break
        return w

    def top_speed(self) -> float:
        """Fastest straight-line speed (m/s): the no-load speed of the faster-turning wheel."""
        return self.wheel_speed_limit() * min(self.dyn.r_L, self.dyn.r_R)

    def accel_at_rest(self) -> float:
        """Largest straight-line acceleration from rest (m/s^2) within the envelope."""
        tl, tr = self.dyn.inverse(0.0, 0.0, 1.0, 0.0)
        bound = min(self.torque_bound_nm, self.voltage_bound_nm)
        return bound / max(abs(tl), abs(tr))

    def decel_at(self, v: float, kappa: float = 0.0) -> float:
        """Largest deceleration (m/s^2, > 0: |v| shrinking) along a curve of curvature `kappa` at
        speed v (either sign: reversing brakes with a positive dv/dt).

        The continuous-time figure (the yaw acceleration v^2 dkappa/ds is left out): what a
        controlled stop may ask for."""
        sign = -1.0 if v >= 0.0 else 1.0
        return self.rate_limit(v, v * kappa, sign, sign * kappa)

    def accel_at(self, v: float, kappa: float = 0.0, direction: float = 1.0) -> float:
        """Largest acceleration (m/s^2, > 0: |v| growing) along the robot's curvature `kappa` at
        speed v; at v = 0 towards `direction` (+1 forward, -1 reversing)."""
        sign = (1.0 if v > 0.0 else -1.0) if v != 0.0 else (1.0 if direction >= 0.0 else -1.0)
        return self.rate_limit(v, v * kappa, sign, sign * kappa)

    def turn_accel_at(self, omega: float) -> float:
        """Largest |d(omega)/dt| (rad/s^2) speeding up a turn in place at yaw rate omega."""
        sign = 1.0 if omega >= 0.0 else -1.0
        return self.rate_limit(0.0, omega, 0.0, sign)

    def rate_limit(self, v: float, omega: float, dv: float, domega: float) -> float:
        """Largest d >= 0 for which the motion (v, omega) accelerating at d (dv, domega) keeps both
        wheels' torques within the envelope (0 if not even d = 0 does)."""
        dyn, m = self.dyn, self.motor
        tl0, tr0 = dyn.inverse(v, omega, 0.0, 0.0)
        tl1, tr1 = dyn.inverse(v, omega, dv, domega)
        tl1 -= tl0
        tr1 -= tr0
        best = math.inf
        for t0, t1, c in ((tl0, tl1, (v - dyn.L * omega) / dyn.r_L), (tr0, tr1, (v + dyn.R * omega) / dyn.r_R)):
            drive = self.emf_damping * c + m.coulomb_nm * math.tanh(c / m.coulomb_smoothing_rad_s)
            lo = max(-self.torque_bound_nm, -self.voltage_bound_nm - drive)
            hi = min(self.torque_bound_nm, self.voltage_bound_nm - drive)
            # t0 + t1 d within [lo, hi] for d >= 0.
            if t1 > 0.0:
                best = min(best, (hi - t0) / t1)
            elif t1 < 0.0:
                best = min(best, (lo - t0) / t1)
        return max(best, 0.0)


@dataclass(frozen=True)
class ResolvedLimits:
    """The numbers behind the config's limits for one robot, and what was said about them."""

    limits: "LimitsConfig"  # every limit a number: the user's where given (never above the motors')
    envelope: Envelope
    profile_v_max: float  # top speed the profile may plan (at the headroom)
    notes: tuple[str, ...] = field(default=(), compare=False)


def resolve_limits(limits: "LimitsConfig", robot: RobotParams, motor: MotorParams) -> ResolvedLimits:
    """The config's limits with null replaced by what the motors give, and notes on caps above it.

    The controller's clamps (v_max, accel, torque_max_nm) take the motors' full capability
    (no headroom: feedback may use it); the profile plans within the headroom.
    """
    dyn = Dynamics.from_params(robot)
    env = Envelope(dyn, motor, headroom=limits.feedback_headroom, duty_max=limits.duty_max,
                   torque_max_nm=limits.torque_max_nm)
    full = env.with_headroom(0.0)
    notes: list[str] = []
    h = limits.feedback_headroom
    at = f"at {1.0 - h:.0%} of the voltage, limits.feedback_headroom = {h:g}"

    stall = env.stall_torque_nm
    if limits.torque_max_nm is not None and limits.torque_max_nm > stall:
        notes.append(f"limits.torque_max_nm: {limits.torque_max_nm:g} N m is above what the motors give "
                     f"(stall torque {stall:.3g} N m); the controller and the profile keep to {stall:.3g} N m")
    torque = env.torque_cap_nm

    v_top = env.top_speed()
    v_full = full.top_speed()
    if v_top <= 0.0:
        raise ValueError("robot.motor: the motors cannot overcome their own friction at "
                         f"{1.0 - h:.0%} of the voltage (limits.feedback_headroom = {h:g})")
    if limits.v_max is not None and limits.v_max > v_top:
        notes.append(f"limits.v_max: {limits.v_max:g} m/s is above what the motors give ({v_top:.3g} m/s {at}); "
                     f"the speed profile keeps to {v_top:.3g} m/s")
    v_max = v_full if limits.v_max is None else min(limits.v_max, v_full)
    profile_v = v_top if limits.v_max is None else min(limits.v_max, v_top)

    a_rest = env.accel_at_rest()
    if limits.accel is not None and limits.accel > a_rest:
        notes.append(f"limits.accel: {limits.accel:g} m/s^2 is above what the motors give from rest "
                     f"({a_rest:.3g} m/s^2 {at}); the speed profile keeps to what they give")
    a_full = full.accel_at_rest()
    accel = a_full if limits.accel is None else min(limits.accel, a_full)
    resolved = replace(limits, v_max=v_max, accel=accel, torque_max_nm=torque)
    return ResolvedLimits(resolved, env, profile_v, tuple(notes))
