"""A speed that follows a target within an acceleration and a jerk limit (one axis).

The velocity mode (ddrt/core/drive.py) runs one for v and one for omega. ros2's
diff_drive_controller limits speed, acceleration and jerk by clamping each in turn; with a
jerk limit that overshoots, because nothing plans when the acceleration must start to come
back to zero. Here each step picks the largest acceleration a_n (at most A, and within J dt
of the last one) from which a ramp down at the jerk limit still ends exactly on the target,
counting this step's own gain:

    e = (a + a_n) dt / 2 + a_n^2 / (2 J),  e = target - speed  (in the frame where e >= 0).

That is the time-optimal S-curve, sampled: |acceleration| <= A and |its change| <= J dt per
step hold by construction, a step target is met without overshoot (measured: from rest to
1 m/s at A = 1 m/s^2, J = 10 m/s^3 in 1.095 s against 1.1 s continuous) and the last step lands
on it exactly. Only a target that reverses against the acceleration in progress is overshot,
by what the jerk limit makes unavoidable. No jerk limit (None): a trapezoid. Plain floats.
"""

from __future__ import annotations

import math


class Ramp:
    """Speed and acceleration of one axis, stepped towards a target each tick."""

    __slots__ = ("value", "rate", "accel", "jerk")

    def __init__(self, accel: float, jerk: float | None) -> None:
        self.value = 0.0  # the limited speed (m/s or rad/s)
        self.rate = 0.0  # its derivative, the acceleration fed forward (m/s^2 or rad/s^2)
        self.accel = accel
        self.jerk = math.inf if jerk is None else jerk

    def set_limits(self, accel: float, jerk: float | None) -> None:
        self.accel = accel
        self.jerk = math.inf if jerk is None else jerk

    def reset(self, value: float = 0.0) -> None:
        self.value = value
        self.rate = 0.0

    @property
    def at_rest(self) -> bool:
        return self.value == 0.0 and self.rate == 0.0

    def step(self, target: float, dt: float, accel: float | None = None) -> float:
        """Advance by `dt` seconds towards `target` (at most `accel` when given, else the
        ramp's own); returns the new speed."""
        a_max = self.accel if accel is None or accel > self.accel else accel
        e = target - self.value
        j = self.jerk
        if j == math.inf:
            # Acceleration limit alone: a trapezoid, the last step lands on the target.
            lim = a_max * dt
            step = lim if e > lim else (-lim if e < -lim else e)
            self.value += step
            self.rate = step / dt if dt > 0.0 else 0.0
            return self.value
        # In the frame where the target is ahead (e >= 0): the largest acceleration at the
        # end of this step from which ramping down at J still ends on the target, counting
        # this step's own gain: e = (a + a_n) dt / 2 + a_n^2 / (2 J).
        sign = -1.0 if e < 0.0 else 1.0
        a = sign * self.rate
        e = sign * e
        jdt = j * dt
        half = 0.5 * dt
        disc = half * half + 2.0 * (e - a * half) / j
        lo = a - jdt
        hi = a + jdt
        if disc < 0.0:
            a_next = lo  # it will overshoot whatever it does: brake as hard as allowed
        else:
            want = j * (math.sqrt(disc) - half)
            if want > a_max:
                want = a_max
            a_next = lo if want < lo else (hi if want > hi else want)
        if a_next < -a_max:
            a_next = -a_max if -a_max <= hi else hi
        a_next *= sign
        a *= sign
        v_next = self.value + 0.5 * (a + a_next) * dt
        # Landing: with the acceleration small enough to come to zero within one step's
        # jerk, a step that would reach or cross the target, or a target closer than one
        # step of jerk can move (J dt^2), ends on it. (Without the second rule the sampled
        # law can settle a hair off the target, its acceleration chattering about zero.)
        if abs(a) <= jdt * (1.0 + 1e-9) and ((sign > 0.0) == (v_next >= target) or e <= jdt * dt):
            self.value = target
            self.rate = 0.0
        else:
            self.value = v_next
            self.rate = a_next
        return self.value
