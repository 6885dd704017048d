"""The reference stage: from the path and the estimated pose to the controller's Setpoint.

Path-following (default): pure pursuit's nearest point gives the reference pose (so the
cross-track and heading errors are purely geometric), and a schedule that runs along the
path's speed profile in time gives the reference speed and acceleration. The schedule is
held back whenever it would lead the robot's progress by more than `max_lead_m`, so a robot
that was stopped or slowed never has to race to catch up; `along_err` (schedule minus
progress) drives the outer law's K_x term. Time-indexed mode is the seed's own: the
reference is wherever the profile is at time t, whatever the robot does.

After a hold (the loop stopped the robot on a sensor gap), `resume` restarts the schedule
from rest where the robot is: the nearest point is found again from the robot's pose, and
the schedule's speed ramps up from zero at the profile's own acceleration limits until it
meets the profile, which it then follows.
"""

from __future__ import annotations

import math
from typing import Any

from ddrt.core.types import Setpoint
from ddrt.path.sampled import Path
from ddrt.path.pursuit import Projection, PurePursuit


# A robot this close to a turn in place when the schedule has begun the turn counts as arrived
# at its corner (pure pursuit's own tolerance, 1 mm, assumes it arrives).
CORNER_TOL_M = 0.003


class PathReference:
    """Nearest-point geometry plus a governed time schedule along the speed profile (a
    ddrt.core.reference.Reference)."""

    phase = "follow"  # the path itself (a StartReference's last phase)
    resumable = True

    def __init__(self, path: Path, lookahead_m: float, search_window_m: float, period_s: float,
                 max_lead_m: float = 0.05, time_indexed: bool = False) -> None:
        self.path = path
        self.pursuit = PurePursuit(path, lookahead_m=lookahead_m, search_window_m=search_window_m)
        self.period = period_s
        self.max_lead = max_lead_m
        self.time_indexed = time_indexed
        self.t_sched = 0.0
        self.sigma = 0.0
        self.cross_track = 0.0
        self.done = False
        self._stop_decel: float | None = None
        self._stop_v = 0.0
        self._stop_sigma = 0.0
        self._ramp = False  # restarting from rest after a hold (see resume)
        self._ramp_s = 0.0  # the ramp's schedule: progress and progress rate
        self._ramp_u = 0.0
        # The last schedule point read (time, path, point, the interval of its progress): a
        # tick reads at t_sched the point the tick before read at its t_next, so one PathPoint
        # a tick is reused, not rebuilt, and the next is searched from there.
        self._memo: tuple[float, Path | None, Any, int] = (math.nan, None, None, -1)

    def _at_time(self, t: float) -> Any:
        """self.path.at_time(t), reusing the last answer for the same time on the same path."""
        return self._at_time_index(t)[0]

    def _at_time_index(self, t: float) -> tuple[Any, int]:
        """(self._at_time(t), path.index of its progress)."""
        memo = self._memo
        path = self.path
        if t == memo[0] and path is memo[1]:
            return memo[2], memo[3]
        point, i = path.at_time_near(t, memo[3])
        self._memo = (t, path, point, i)
        return point, i

    def request_stop(self, decel: float) -> None:
        """Come to rest along the path at `decel` m/s^2 from the current schedule speed."""
        if self._stop_decel is None:
            if self._ramp:
                i = self.path.index(self._ramp_s)
                self._stop_v = 0.0 if self.path.seg_pivot[i] else self._ramp_u
                self._stop_sigma = self._ramp_s
                self._ramp = False
            else:
                point = self.path.at_time(self.t_sched)
                self._stop_v = 0.0 if point.pivot else abs(point.v)
                self._stop_sigma = point.sigma
            self._stop_decel = decel

    def resume(self, x: float, y: float, theta: float) -> None:
        """Restart from rest with the robot at (x, y, theta) (it was stopped by a hold).

        The nearest point is found again (forward from the last progress, within the search
        window, so a self-crossing path cannot make it jump branch); the schedule starts
        there at speed zero and accelerates at the profile's limits until it meets the
        profile. A pending stop is cancelled.
        """
        near = self.pursuit.project(x, y, theta)
        self.sigma = near.sigma
        self.cross_track = near.cross_track
        self._stop_decel = None
        self._ramp = True
        self._ramp_s = near.sigma
        self._ramp_u = 0.0
        self.done = False
        self.t_sched = self._time_at(near.sigma)

    def reprofiled(self, path: Path) -> None:
        """Go on along `path`, this path's samples under a new speed profile (a reload's new
        model, ddrt/loop/reload.py): the schedule's time and progress carry over."""
        self.pursuit.reprofiled(path)
        self.path = path

    def lead_at_most(self, max_lead_m: float) -> None:
        """How far the schedule may lead the robot's progress from now on (a start's join holds
        it shorter, ddrt/path/start.py)."""
        self.max_lead = max_lead_m

    @property
    def resuming(self) -> bool:
        """True while the schedule is ramping up after `resume`."""
        return self._ramp

    @property
    def stopping(self) -> bool:
        return self._stop_decel is not None

    def update(self, x: float, y: float, theta: float, sp: Setpoint, dt: float | None = None) -> None:
        """Fill `sp` for a robot at (x, y, theta), `dt` seconds after the previous call.

        The schedule advances by the time that really passed (a late or skipped tick moves
        it further), not by a nominal period."""
        near = self.pursuit.project(x, y, theta)
        self.sigma = near.sigma
        self.cross_track = near.cross_track
        path = self.path
        sp.active = True
        sp.pp_curvature = near.pp_curvature
        step = self.period if dt is None else dt
        if self._stop_decel is not None:
            self._update_stopping(near, sp, step)
            return
        if self._ramp and self._update_ramp(near, sp, step):
            return
        t_next = self.t_sched + step
        if not self.time_indexed and not near.pivot:
            near = self._onto_pivot(x, y, theta, near, t_next)
        if self.time_indexed:
            self.t_sched = t_next
            sched = self._at_time(t_next)
            sp.x_d, sp.y_d, sp.theta_d = sched.x, sched.y, sched.theta
            sp.v_d, sp.omega_d, sp.a_d, sp.alpha_d = sched.v, sched.omega, sched.a, sched.alpha
            sp.along_err = 0.0
            sp.path_frame = False
            sp.kappa = sched.kappa
            sp.pivot = sched.pivot
            self.done = t_next >= path.duration and near.done
            return
        d_near = path.direction[near.index]
        self._onto_cusp(near.sigma, d_near)
        t_next = self.t_sched + step
        sched, i_sched = self._at_time_index(t_next)
        if sched.sigma <= near.sigma + self.max_lead and not self._past_cusp(sched, i_sched, near.index, d_near):
            self.t_sched = t_next
            held = False
        else:
            sched = self._at_time(self.t_sched)
            held = True
        sp.x_d, sp.y_d, sp.theta_d = near.x_d, near.y_d, near.theta_d
        sp.path_frame = True
        sp.kappa = near.kappa
        sp.v_d = sched.v
        sp.a_d = 0.0 if held else sched.a
        sp.along_err = d_near * (sched.sigma - near.sigma)  # along the robot's heading
        sp.pivot = sched.pivot or near.pivot
        if sched.pivot:
            sp.omega_d = sched.omega
            sp.alpha_d = 0.0 if held else sched.alpha
        else:
            sp.omega_d = sched.v * near.kappa
            sp.alpha_d = 0.0 if held else sched.alpha  # d(v kappa)/dt: a kappa + v^2 dkappa/ds
        self.done = near.done and self.t_sched >= path.duration

    def _onto_cusp(self, s_near: float, d_near: float) -> None:
        """Pursuit takes a robot within its arrival tolerance of a cusp as arrived, and from then
        on projects it on the leg beyond; a schedule still braking onto the cusp would then be
        a forward speed in the reverse leg's frame. Within CORNER_TOL_M of the cusp, the
        schedule is taken to it (at rest), as at a turn in place."""
        p = self.path
        now, i = self._at_time_index(self.t_sched)
        if now.pivot or now.sigma >= s_near:
            return
        end = p.piece_end[i]
        if p.direction[i] != d_near and end <= s_near and end - now.sigma <= CORNER_TOL_M:
            self.t_sched = max(self.t_sched, self._time_at(end))

    def _past_cusp(self, sched, i: int, j: int, d_near: float) -> bool:
        """Would the schedule (at `sched`, in interval i; the robot in interval j) be driving
        the other way than the robot's piece (it has passed a cusp the robot has not
        reached)? It waits at the cusp until the robot arrives."""
        p = self.path
        return (sched.sigma > self.sigma and not p.seg_pivot[i] and not p.seg_pivot[j]
                and p.direction[i] != d_near)

    # ------------------------------------------------------------------ resuming from rest

    def _rate_at(self, s: float) -> tuple[int, float]:
        """(interval, the profile's progress rate u) at progress s."""
        p = self.path
        i = p.index(s)
        uu = p.u[i] * p.u[i] + 2.0 * p.acc_u[i] * (s - p.sigma[i])
        return i, math.sqrt(uu) if uu > 0.0 else 0.0

    def _time_at(self, s: float) -> float:
        i = self.path.index(s)
        return self.path.dynamics(i, s)[4]

    def _ramp_accel(self, i: int, u: float) -> float:
        """The acceleration limit on interval i at progress rate u (progress units per s^2): the
        profile's caps and, for a path built for a robot, what its motors give at that speed
        (limits.accel may be unbounded then: the motors are the limit)."""
        p = self.path
        lim = p.limits
        if p.seg_pivot[i]:
            b = p.pivot_radius
            return b * lim.turn_accel_at(p.turn[i] * u / b)
        k0, k1 = p.kappa[i], p.kappa[i + 1]
        d = p.direction[i]
        return lim.accel_at(d * u, k0 if abs(k0) >= abs(k1) else k1, d)

    def _update_ramp(self, near, sp: Setpoint, dt: float) -> bool:
        """The schedule after `resume`: from rest at the profile's acceleration until it
        meets the profile. Returns False once it has (the caller then follows the profile)."""
        p = self.path
        s = self._ramp_s
        i, u_prof = self._rate_at(s)
        acc = self._ramp_accel(i, self._ramp_u)
        u_new = self._ramp_u + acc * dt
        if u_new >= u_prof:
            self._ramp = False  # merged: the profile from here on (at_time is exact)
            self.t_sched = self._time_at(s)
            return False
        s_next = s + 0.5 * (self._ramp_u + u_new) * dt
        held = not self.time_indexed and s_next > near.sigma + self.max_lead
        if not held:
            self._ramp_s = s = min(s_next, p.length)
            self._ramp_u = u_new
        i = p.index(s)
        pivot = p.seg_pivot[i]
        u = self._ramp_u
        a = 0.0 if held else acc
        d = p.direction[i]
        if self.time_indexed:
            x, y, th, k = p.geometry(i, s)
            sp.x_d, sp.y_d, sp.theta_d = x, y, th
            sp.kappa = 0.0 if pivot else k
            sp.path_frame = False
            sp.along_err = 0.0
        else:
            sp.x_d, sp.y_d, sp.theta_d = near.x_d, near.y_d, near.theta_d
            sp.kappa = near.kappa
            sp.path_frame = True
            sp.along_err = d * (s - near.sigma)
        if pivot:
            sp.v_d = 0.0
            sp.a_d = 0.0
            sp.omega_d = p.turn[i] * u / p.pivot_radius
            sp.alpha_d = p.turn[i] * a / p.pivot_radius
        else:
            sp.v_d = d * u
            sp.a_d = d * a
            sp.omega_d = sp.v_d * sp.kappa
            sp.alpha_d = sp.a_d * sp.kappa
        sp.pivot = pivot
        self.done = False
        return True

    def _onto_pivot(self, x: float, y: float, theta: float, near: Projection, t_next: float) -> Projection:
        """A robot that stopped just short of a turn in place (it braked harder than it could
        follow) while the schedule has begun the turn: take it as arrived at the corner."""
        path = self.path
        end = path.piece_end[near.index]
        if not 0.0 < end - near.sigma <= CORNER_TOL_M:
            return near
        j = path.index(end, near.index)
        if not path.seg_pivot[j] or path.sigma[j] != end or t_next <= path.t[j]:
            return near
        self.pursuit.reset(end)
        near = self.pursuit.project(x, y, theta)
        self.sigma = near.sigma
        self.cross_track = near.cross_track
        return near

    def _update_stopping(self, near, sp: Setpoint, dt: float) -> None:
        """The stop's speed is a magnitude (progress rate); reversing, v_d and a_d take the sign."""
        decel = self._stop_decel or 1.0
        v0 = self._stop_v
        env = self.path.limits.envelope
        d = self.path.direction[self.path.index(self._stop_sigma)]
        if env is not None and v0 > 0.0:
            # No harder than the motors brake here (within the profile's headroom).
            decel = min(decel, max(env.decel_at(d * v0, near.kappa), 1e-3))
        v = v0 - decel * dt
        if v > 0.0:
            # Never faster than the path's own profile ahead (it slows for curves and comes to
            # rest before every turn in place and every cusp).
            ahead = abs(self.path.at(self._stop_sigma + 0.5 * (v0 + v) * dt).v)
            v = min(v, ahead)
        if v <= 0.0:
            v = 0.0
        a = 0.0 if v <= 0.0 else ((v - v0) / dt if dt > 0.0 else -decel)
        self._stop_sigma += 0.5 * (v0 + v) * dt
        self._stop_v = v
        sp.x_d, sp.y_d, sp.theta_d = near.x_d, near.y_d, near.theta_d
        sp.path_frame = True
        sp.kappa = near.kappa
        sp.v_d = d * v
        sp.a_d = d * a
        sp.omega_d = sp.v_d * near.kappa
        sp.alpha_d = sp.a_d * near.kappa
        lead = max(-self.max_lead, min(self.max_lead, self._stop_sigma - near.sigma))
        sp.along_err = d * lead if v > 0 else 0.0
        sp.pivot = False
        self.done = v == 0.0
