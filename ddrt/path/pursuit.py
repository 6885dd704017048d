"""The reference the controller tracks: the path's point nearest the robot, or the point due now.

`PurePursuit` (path following) projects the robot onto the path and returns that point as
q_d with the profile's speeds there. Progress only moves forward: each call walks on from
the last interval while the robot's projection lies beyond the interval's end, never more
than `search_window_m` ahead, so the search is amortised O(1) and cannot jump to another
branch where the path passes near itself (a figure-eight's crossing). A pivot has all its
samples at one point, so xy cannot tell how far it has gone: inside a pivot, progress follows
the robot's heading (how far it has turned), and the xy walk never crosses into a pivot.

Reversing (a piece with `Path.direction` -1): the projection runs along the direction of
travel, which is the robot's heading reversed, and pure pursuit's look-ahead point lies
behind the robot; its curvature 2 y_goal_body / dist^2 is then the robot's own (omega = v
kappa with v < 0). The look-ahead stops at a cusp.

Starting from rest: the profile is 0 where the path starts and on both sides of every pivot,
and a reference taken strictly at the projection would hold a robot at rest there forever
(v_d = 0 while the projection cannot move). Where the profile accelerates, the speeds are
therefore taken `start_kick_m` further on when that is faster (at most half-way to the piece's
end): a robot at rest gets a small nonzero v_d (or omega_d), and the kick merges with the
profile as it speeds up. Decelerating to a stop needs no help (the profile reaches 0 in
finite time), and the last `arrive_tol_m` before a stop is snapped.

The seed's own time-indexed mode (the reference is where the profile is at time t, whatever
the robot does) is PathReference's, in ddrt/path/reference.py; it uses this class's
projection for the robot's progress and cross-track.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ddrt.core.wrap import wrap_angle
from ddrt.path.sampled import Path, interval_index

__all__ = ["Projection", "Reference", "PurePursuit"]

TWO_PI = 2.0 * math.pi


@dataclass(slots=True)
class Reference:
    """What the controller tracks at one tick (SI units; theta_d continuous, see ddrt.path)."""

    sigma: float  # progress of the reference point
    x_d: float
    y_d: float
    theta_d: float
    v_d: float
    omega_d: float
    a_d: float  # dv_d/dt
    alpha_d: float  # domega_d/dt
    kappa: float
    cross_track: float  # signed lateral offset of the robot from the path, left positive
    lookahead_x: float
    lookahead_y: float
    pp_curvature: float  # classic pure pursuit: 2 * y_goal_body / dist^2
    pivot: bool
    done: bool


@dataclass(slots=True)
class Projection:
    """The robot projected on the path: `Reference` without the profile's speeds, which a
    PathReference takes from its schedule instead (`PurePursuit.project`, every tick)."""

    sigma: float  # progress of the nearest point
    index: int  # the interval that holds it (Path.index(sigma))
    x_d: float
    y_d: float
    theta_d: float
    kappa: float
    cross_track: float
    lookahead_x: float
    lookahead_y: float
    pp_curvature: float
    pivot: bool
    done: bool


def _foot(g0: float, g1: float) -> float:
    """Fraction of an interval where the robot's foot point lies, in [0, 1].

    g0 and g1 are the robot's along-track offsets from the normals at the interval's two
    samples. Interpolating between the normals (not projecting on the chord) keeps the foot
    exact on arcs whatever the robot's lateral offset: on a circle g_k = rho sin(phi - phi_k).
    """
    if g0 <= 0.0:
        return 0.0
    if g1 >= 0.0:
        return 1.0
    return g0 / (g0 - g1)


class PurePursuit:
    """Path-following reference: nearest point, moving forward only, O(1) amortised per call."""

    def __init__(self, path: Path, lookahead_m: float = 0.05, search_window_m: float = 0.3, *,
                 start_kick_m: float = 0.002, arrive_tol_m: float = 0.001, pivot_tol_rad: float = 0.005) -> None:
        for name, value in (("lookahead_m", lookahead_m), ("search_window_m", search_window_m),
                            ("start_kick_m", start_kick_m), ("arrive_tol_m", arrive_tol_m),
                            ("pivot_tol_rad", pivot_tol_rad)):
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0.0):
                raise ValueError(f"PurePursuit.{name}: must be a finite number >= 0, got {value!r}")
        if search_window_m <= 0.0:
            raise ValueError(f"PurePursuit.search_window_m: must be > 0, got {search_window_m!r}")
        self.path = path
        self.lookahead_m = float(lookahead_m)
        self.search_window_m = float(search_window_m)
        self.start_kick_m = float(start_kick_m)
        self.arrive_tol_m = float(arrive_tol_m)
        self.pivot_tol_rad = float(pivot_tol_rad)
        self._last = len(path.sigma) - 2  # index of the last interval
        self._i = 0
        self._s = 0.0
        self._goal_i = -1  # the look-ahead's last interval (a hint for the next: Path.index)
        self.reset()

    @property
    def sigma(self) -> float:
        return self._s

    def reset(self, sigma: float = 0.0) -> None:
        """Restart progress at `sigma` (clamped to the path)."""
        s = min(max(float(sigma), 0.0), self.path.length)
        self._s = s
        self._i = self.path.index(s)

    def reprofiled(self, path: Path) -> None:
        """Go on along `path`, this path's samples under a new speed profile (a reload's new
        model): where it stands, an index into the same samples, stays valid."""
        self.path = path

    def _settle(self, s: float) -> None:
        """Store progress s and move the interval index forward to the one that holds it."""
        p = self.path
        sig, i, last = p.sigma, self._i, self._last
        while i < last and s >= sig[i + 1]:
            i += 1
        self._i, self._s = i, s

    def _advance(self, x: float, y: float, theta: float) -> None:
        p = self.path
        sig, xs, ys = p.sigma, p.x, p.y
        piv, last = p.seg_pivot, self._last
        i, s = self._i, self._s
        limit = s + self.search_window_m
        if piv[i]:
            # Turning in place: progress follows how far the robot has turned.
            s0 = sig[i]
            th_ref = p.theta[i] + (s - s0) / (sig[i + 1] - s0) * (p.theta[i + 1] - p.theta[i])
            turned = p.turn[i] * wrap_angle(theta - th_ref)
            end = p.piece_end[i]
            if turned > 0.0:
                s = min(s + p.pivot_radius * turned, end, limit)
            if end - s <= p.pivot_radius * self.pivot_tol_rad:
                s = end
            self._settle(s)
            return
        # Driving: walk on while the robot lies beyond the normal at the interval's end. The
        # direction of travel is the heading times the interval's direction (-1 reversing); the
        # walk never crosses a cusp (the robot arrives there, as at a pivot, see below).
        tx, ty, dirs = p.tx, p.ty, p.direction
        d = dirs[i]
        g0 = d * ((x - xs[i]) * tx[i] + (y - ys[i]) * ty[i])
        while True:
            g1 = d * ((x - xs[i + 1]) * tx[i + 1] + (y - ys[i + 1]) * ty[i + 1])
            if g1 >= 0.0 and i < last and not piv[i + 1] and dirs[i + 1] == d and sig[i + 1] < limit:
                i += 1
                g0 = g1
                continue
            break
        # _foot(g0, g1) and, at the end, _settle(s), written out: this runs every tick.
        f = 0.0 if g0 <= 0.0 else (1.0 if g1 >= 0.0 else g0 / (g0 - g1))
        cand = sig[i] + f * (sig[i + 1] - sig[i])
        if cand > limit:
            cand = limit
        if cand > s:
            s = cand
        self._i = i
        end = p.piece_end[i]
        if end - s <= self.arrive_tol_m and (i == last or p.u[self._index_at(end)] == 0.0):
            s = end
        while i < last and s >= sig[i + 1]:
            i += 1
        self._i, self._s = i, s

    def _index_at(self, s: float) -> int:
        """Sample index of the piece end at progress s (the sample where the piece ends)."""
        return self.path.index(s, self._i) + (1 if s >= self.path.sigma[-1] else 0)

    def update(self, x: float, y: float, theta: float) -> Reference:
        """Advance progress from the robot pose and return the reference there."""
        pr = self.project(x, y, theta)
        p = self.path
        i, s = pr.index, pr.sigma
        dyn = p.dynamics(i, s)
        if p.acc_u[i] > 0.0 and self.start_kick_m > 0.0:
            sk = s + min(self.start_kick_m, 0.5 * (p.piece_end[i] - s))
            ik = p.index(sk, i)
            alt = p.dynamics(ik, sk)
            if abs(alt[0]) + abs(alt[1]) * p.pivot_radius > abs(dyn[0]) + abs(dyn[1]) * p.pivot_radius:
                dyn = alt
        v, w, a, al, _ = dyn
        return Reference(s, pr.x_d, pr.y_d, pr.theta_d, v, w, a, al, pr.kappa, pr.cross_track, pr.lookahead_x,
                         pr.lookahead_y, pr.pp_curvature, pr.pivot, pr.done)

    def project(self, x: float, y: float, theta: float) -> Projection:
        """Advance progress from the robot pose and return the nearest point (`update` without
        the profile's speeds there). Path.geometry and Path.index are written out below
        (the same arithmetic): this runs every control tick."""
        self._advance(x, y, theta)
        p = self.path
        i, s = self._i, self._s
        sig, xs, ys = p.sigma, p.x, p.y
        # The nearest point: geometry(i, s).
        s0 = sig[i]
        f = (s - s0) / (sig[i + 1] - s0)
        xd = xs[i] + f * (xs[i + 1] - xs[i])
        yd = ys[i] + f * (ys[i + 1] - ys[i])
        th = p.theta
        thd = th[i] + f * (th[i + 1] - th[i])
        pivot = p.seg_pivot[i]
        ks = p.kappa
        k = 0.0 if pivot else ks[i] + f * (ks[i + 1] - ks[i])
        ct = -math.sin(thd) * (x - xd) + math.cos(thd) * (y - yd)
        # The look-ahead point, found from the last one's interval, and pure pursuit's
        # curvature towards it.
        ahead = s + self.lookahead_m
        end = p.piece_end[i]
        if ahead > end and end < p.length and p.direction[interval_index(sig, end, i)] != p.direction[i]:
            ahead = end  # not past a cusp: beyond it the path comes back
        g = self._goal_i = interval_index(sig, ahead, self._goal_i)
        if ahead > p.length:
            ahead = p.length
        s0 = sig[g]
        f = (ahead - s0) / (sig[g + 1] - s0)
        gx = xs[g] + f * (xs[g + 1] - xs[g])
        gy = ys[g] + f * (ys[g + 1] - ys[g])
        dx, dy = gx - x, gy - y
        d2 = dx * dx + dy * dy
        ppk = 0.0 if d2 < 1e-12 else 2.0 * (-math.sin(theta) * dx + math.cos(theta) * dy) / d2
        return Projection(s, i, xd, yd, thd, k, ct, gx, gy, ppk, pivot, p.length - s <= self.arrive_tol_m)
