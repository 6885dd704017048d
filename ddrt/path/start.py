"""The start of a path the robot is not lined up with: turn in place to its heading, then join
it at bounded speed.

`PathReference` assumes the robot starts on the path, facing along it. Sent a path that
starts behind it or beside it, the outer law's gains (tuned for millimetres of error) and the
schedule's 5 cm lead asked for far more than the path does: a path at 0.3 m/s that started
135 degrees off the robot's heading swung it 0.3 m sideways at 0.67 m/s; one 180 degrees off
faulted 0.3 m away. `StartReference` wraps the path's reference for such a start:

1. **turn** (only when the start heading differs from the robot's by more than
   `pursuit.max_start_heading_deg`): a turn in place about the robot's position to the path's
   start heading, on a trapezoid of the path's `omega_max` and `alpha_max` (which never
   exceed the config's limits), the position held. It ends once the heading is within
   TURN_TOL_RAD of the target (or TURN_GRACE_S after the trapezoid ends, whatever is left is
   the join's).
2. **join**: the path's own reference, with the schedule's lead kept to JOIN_LEAD_M (so the
   along-track gain cannot surge the robot), the commanded speed capped at the schedule's
   speed plus JOIN_SPEED_MARGIN (never faster than the path there) and the yaw rate at the
   path's `omega_max` and at `lateral_accel / v_cap`. The outer law sees at most `y_cap` of
   lateral error (the loop passes K_theta sin(JOIN_APPROACH_RAD) / K_y): its yaw demand
   `v K_y y` then balances `v K_theta sin(heading error)` at an approach angle of
   JOIN_APPROACH_RAD, instead of saturating the yaw rate and circling (a robot 0.2 m beside
   a line, capped at the line's speed, turned circles at omega_max for ever). The reference
   point itself stays the nearest point of the path, so the loop's `limits.max_path_error_m`
   check holds throughout. The join ends once the robot is within JOIN_DONE_M of the path
   and JOIN_DONE_RAD of its heading.
3. **release**: the margin of the speed cap over the schedule's speed rises at a quarter of
   the path's `accel` until it reaches `v_max`, the lead still at JOIN_LEAD_M, so lifting
   them steps nothing and a schedule that accelerates away from the robot just joined
   cannot make it surge after it; then the path's reference alone (**follow**).

A stop during the turn brakes the turn at `alpha_max` and ends there (the path is never
started); during the other phases it is the path's own controlled stop. After a hold (a sensor
gap, a loop stall) `resume` plans a new turn from the robot's heading, or resumes the path's
schedule from rest within the join or release, as `daemon.on_recover: resume` expects. In time-indexed mode
(`pursuit.mode: time`, the seed's method) only the turn applies: its schedule runs on the
clock whatever the robot does, and capping the robot would only let it fall behind.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ddrt.core.types import Setpoint
from ddrt.core.wrap import wrap_angle
from ddrt.path.profile import SpeedLimits
from ddrt.path.reference import PathReference

__all__ = ["StartReference", "TurnProfile", "start_heading_offset", "needs_join"]

TURN_TOL_RAD = math.radians(3.0)
TURN_GRACE_S = 2.0
TURN_HOLD_V = 0.05  # m/s: while turning the robot only holds its position
JOIN_LEAD_M = 0.005
JOIN_SPEED_MARGIN = 0.01  # m/s above the schedule's speed
JOIN_APPROACH_RAD = math.radians(30.0)
JOIN_LATERAL_FRACTION = 0.25
JOIN_DONE_M = 0.005
RELEASE_ACCEL_FRACTION = 0.25
JOIN_DONE_RAD = math.radians(3.0)
# A start farther than this from the path's first point, or turned more than this from its
# heading, is joined (phase 2); a closer one is the path's reference alone.
JOIN_NEEDED_M = 0.005
JOIN_NEEDED_RAD = math.radians(3.0)


def start_heading_offset(path_theta0: float, theta: float) -> float:
    """The turn (rad, in (-pi, pi]) from heading `theta` to the path's start heading."""
    return wrap_angle(path_theta0 - theta)


def needs_join(dist_m: float, heading_rad: float) -> bool:
    return dist_m > JOIN_NEEDED_M or abs(heading_rad) > JOIN_NEEDED_RAD


@dataclass(frozen=True)
class TurnProfile:
    """A turn in place by `span` rad with a trapezoidal yaw rate: up at `alpha`, at most
    `omega_max`, down at `alpha` (a triangle when the turn is too short to reach it). The one
    timing law for every turn in place: the start stage's and calibration's spin."""

    span: float  # rad, >= 0
    alpha: float  # rad/s^2
    w: float  # peak rate, rad/s
    t_ramp: float  # s, to reach w
    t_end: float  # s, the whole turn

    @classmethod
    def plan(cls, span: float, omega_max: float, alpha: float) -> "TurnProfile":
        w = min(omega_max, math.sqrt(span * alpha)) if span > 0.0 else 0.0
        t_ramp = w / alpha
        return cls(span, alpha, w, t_ramp, span / w + t_ramp if w > 0.0 else 0.0)

    def at(self, t: float) -> tuple[float, float, float]:
        """(angle turned, rate, acceleration) at time t, all >= 0 but the braking acceleration."""
        w, a, tr, te = self.w, self.alpha, self.t_ramp, self.t_end
        if t <= 0.0 or w == 0.0:
            return 0.0, 0.0, 0.0
        if t < tr:
            return 0.5 * a * t * t, a * t, a
        if t < te - tr:
            return 0.5 * a * tr * tr + w * (t - tr), w, 0.0
        if t < te:
            r = te - t
            return self.span - 0.5 * a * r * r, a * r, -a
        return self.span, 0.0, 0.0


class StartReference:
    """Turn in place (optional), join at bounded speed, then the path's reference as is.

    A ddrt.core.reference.Reference, with the path's too (`path`). Resumable: after a hold
    stopped it, the start picks up from rest where the robot stands (`resume`).
    """

    resumable = True

    def __init__(self, inner: PathReference, pose: tuple[float, float, float], limits: SpeedLimits,
                 period_s: float, *, turn: bool, join: bool, y_cap: float = math.inf) -> None:
        self.inner = inner
        self.path = inner.path
        self.limits = limits
        self.period = period_s
        self.join = join and not inner.time_indexed
        self.y_cap = y_cap
        # Turning in from the approach angle to the path's heading within y_cap of it is an arc
        # of radius about y_cap / (1 - cos(approach)): at v_join its lateral acceleration is
        # JOIN_LATERAL_FRACTION of the path's limit (the outer law turns in more sharply than
        # that arc).
        radius = y_cap / (1.0 - math.cos(JOIN_APPROACH_RAD))
        self.v_join = max(JOIN_SPEED_MARGIN, math.sqrt(JOIN_LATERAL_FRACTION * limits.lateral_accel * radius))
        self._lead = inner.max_lead
        self.x0, self.y0, self.th0 = pose
        self.angle = start_heading_offset(self.path.at(0.0).theta, self.th0)
        self.sign = 1.0 if self.angle >= 0.0 else -1.0
        self.turn = TurnProfile.plan(abs(self.angle), limits.omega_max, limits.alpha_max)
        self.t = 0.0
        self._brake: tuple[float, float, float] | None = None  # (angle, rate, time) when a stop came
        self._turn_sigma = 0.0
        self._turn_ct = 0.0
        self._release_v = 0.0
        self._cap = 0.0
        self.phase = "turn" if turn and self.turn.span > 0.0 else ("join" if self.join else "follow")
        if self.phase == "join":
            inner.lead_at_most(min(self._lead, JOIN_LEAD_M))

    # -- PathReference's interface --------------------------------------------------------------
    @property
    def sigma(self) -> float:
        return self._turn_sigma if self.phase == "turn" else self.inner.sigma

    @property
    def cross_track(self) -> float:
        return self._turn_ct if self.phase == "turn" else self.inner.cross_track

    @property
    def done(self) -> bool:
        if self.phase == "turn":
            return self._brake is not None and self._turn_rate() == 0.0
        return self.inner.done

    @property
    def stopping(self) -> bool:
        return self._brake is not None or self.inner.stopping

    def request_stop(self, decel: float) -> None:
        if self.phase == "turn":
            if self._brake is None:
                ang, w, _ = self.turn.at(self.t)
                self._brake = (ang, w, self.t)
        else:
            self.inner.request_stop(decel)

    def resume(self, x: float, y: float, theta: float) -> None:
        """Restart from rest with the robot at (x, y, theta) after a hold stopped it.

        In the turn: a new turn in place from this pose to the path's start heading (the
        braked one is over). Later: the path's own resume, in the same phase, so a join or a
        release keeps its caps."""
        if self.phase == "turn":
            self.x0, self.y0, self.th0 = x, y, theta
            self.angle = start_heading_offset(self.path.at(0.0).theta, theta)
            self.sign = 1.0 if self.angle >= 0.0 else -1.0
            self.turn = TurnProfile.plan(abs(self.angle), self.limits.omega_max, self.limits.alpha_max)
            self.t = 0.0
            self._brake = None
        else:
            self.inner.resume(x, y, theta)

    def update(self, x: float, y: float, theta: float, sp: Setpoint, dt: float | None = None) -> None:
        step = self.period if dt is None else dt
        if self.phase == "turn":
            self.t += step
            if self._turn(x, y, theta, sp):
                return
            # Lined up: the path's reference from this tick on.
            self.phase = "join" if self.join else "follow"
            if self.join:
                self.inner.lead_at_most(min(self._lead, JOIN_LEAD_M))
            sp.v_cap = sp.omega_cap = sp.y_cap = math.inf
        self.inner.update(x, y, theta, sp, dt)
        if self.phase == "join":
            lim = self.limits
            v_cap = min(abs(sp.v_d) + JOIN_SPEED_MARGIN, self.v_join)
            self._cap = v_cap
            sp.v_cap = v_cap
            sp.omega_cap = min(lim.omega_max, lim.lateral_accel / v_cap)
            sp.y_cap = self.y_cap
            if (math.hypot(sp.x_d - x, sp.y_d - y) <= JOIN_DONE_M
                    and abs(wrap_angle(sp.theta_d - theta)) <= JOIN_DONE_RAD):
                self.phase = "release"
                self._release_v = JOIN_SPEED_MARGIN
                sp.omega_cap = sp.y_cap = math.inf
        elif self.phase == "release":
            accel = self.limits.accel_at(sp.v_d)  # finite: the motors bound it
            self._release_v += RELEASE_ACCEL_FRACTION * accel * step
            if self._release_v >= self.limits.v_max:
                self.phase = "follow"
                self.inner.lead_at_most(self._lead)
                sp.v_cap = math.inf
            else:
                self._cap = min(abs(sp.v_d) + self._release_v, self._cap + accel * step)
                sp.v_cap = self._cap

    # -- the turn in place ---------------------------------------------------------------------
    def _turn_rate(self) -> float:
        if self._brake is None:
            return self.turn.at(self.t)[1]
        _, w0, t0 = self._brake
        return max(0.0, w0 - self.limits.alpha_max * (self.t - t0))

    def _turn(self, x: float, y: float, theta: float, sp: Setpoint) -> bool:
        """Fill `sp` for the turn; False once it is over (and the path should take over)."""
        a = self.limits.alpha_max
        if self._brake is None:
            ang, w, alpha = self.turn.at(self.t)
        else:
            ang0, w0, t0 = self._brake
            w = self._turn_rate()
            ang = min(abs(self.angle), ang0 + (w0 * w0 - w * w) / (2.0 * a))
            alpha = -a if w > 0.0 else 0.0
        s = self.sign
        sp.turn_in_place(self.x0, self.y0, self.th0 + s * ang, s * w, s * alpha)
        sp.v_cap = TURN_HOLD_V
        sp.omega_cap = self.limits.omega_max
        self._turn_ct = math.hypot(x - self.x0, y - self.y0)
        if self._brake is not None:
            return True
        if self.t < self.turn.t_end:
            return True
        left = abs(wrap_angle(self.th0 + s * abs(self.angle) - theta))
        return left > TURN_TOL_RAD and self.t < self.turn.t_end + TURN_GRACE_S
