"""Paths the robot follows, sampled densely along a progress coordinate, with a speed profile.

A path is a chain of *pieces*: driving pieces (lines, arcs, smooth curves) and turn-in-place
*pivots* at sharp corners. Everything is indexed by a generalised progress `sigma` (metres):
on driving pieces d(sigma) = ds (arc length); in a pivot the robot stands at the corner and
turns, and d(sigma) = b * |d(theta)| with b = `pivot_radius`, so progress keeps growing while
the robot turns and one monotone coordinate covers the whole path.

Geometry choices (documented because they shape the motion):
- Sharp corners (turn > `corner_pivot_deg`, 30 degrees by default) become pivots: the robot
  stops, turns in place, drives on.
- Gentle corners become a curvature-continuous blend: a "raised-cosine" curvature bump
  kappa(s) = (phi / L) (1 - cos(2 pi s / L)), symmetric about the corner's bisector and tangent
  to both straight segments. Its curvature is zero where it meets the lines, so omega = v kappa
  has no step and the angular acceleration stays finite (a circular fillet would step kappa).
  The blend's tangent length is at most `blend_max_m` and at most half of each adjacent segment.
- Analytic shapes (circle, ellipse, figure-eight, S-curve) are sampled exactly at uniform arc
  length; ellipse-like curves are re-parametrised by arc length numerically.
- Samples are `sample_step_m` apart (2 mm by default): linear interpolation between them then
  leaves less than 2 um of chord error on a 0.3 m radius circle.

Speed profile: the progress rate u = d(sigma)/dt is capped per sample (v_max, per-point caps,
lateral acceleration, omega_max, and v^2 |d(kappa)/ds| <= alpha_max / 2 on driving pieces;
b * omega_max in pivots), then limited by forward (accel) and backward (decel) passes, with
u = 0 at both ends and at both sides of every pivot. Between two samples the progress has a
constant acceleration (u^2 is linear in sigma), which makes t(sigma), v(t) and at_time exact for
the profile. On driving pieces the tangential acceleration is also capped at
alpha_max / (2 |kappa|), so |alpha| = |a kappa + v^2 dkappa/ds| <= alpha_max. In a pivot v = 0,
omega = turn * u / b (an angular trapezoid limited by omega_max and alpha_max).

Conventions: theta is continuous (unwrapped) along the path and starts in (-pi, pi]; consumers
should wrap their heading errors. kappa is 0 inside pivots (d theta / ds is undefined there).

Index arrays (read-only Python lists, for the pursuit's hot path; n samples, n - 1 intervals):
  sigma, x, y, theta, kappa, u, v, omega, t     per sample
  tx, ty                                        per sample: unit tangent (cos theta, sin theta)
  acc_u, a, alpha, seg_pivot, turn, piece_end   per interval i (between samples i and i + 1):
    acc_u      d(u)/dt, constant over the interval
    a, alpha   dv/dt and d(omega)/dt over the interval (a = 0 and alpha = turn * acc_u / b in pivots)
    seg_pivot  True if the interval lies in a pivot
    turn       +1 (left) / -1 (right) for pivot intervals, 0 otherwise
    piece_end  sigma at which the interval's piece ends
"""

from __future__ import annotations

import bisect
import csv
import io
import math
import os
from dataclasses import dataclass, fields, replace
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import yaml

YAML_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)  # libyaml when present

__all__ = ["PathError", "SpeedLimits", "PathPoint", "Path", "load_path"]

TWO_PI = 2.0 * math.pi


class PathError(ValueError):
    """A path file or spec is malformed; the message names the file, line or key, and the problem."""


@dataclass(frozen=True, slots=True)
class SpeedLimits:
    """Motion limits the speed profile respects (SI units). `decel` defaults to `accel`."""

    v_max: float = 1.0  # m/s
    accel: float = 1.0  # m/s^2
    lateral_accel: float = 1.5  # m/s^2
    omega_max: float = 4.0  # rad/s
    alpha_max: float = 20.0  # rad/s^2
    decel: float | None = None  # m/s^2

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if value is None and f.name == "decel":
                continue
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
                raise ValueError(f"SpeedLimits.{f.name}: expected a finite number, got {value!r}")
            if value <= 0.0:
                raise ValueError(f"SpeedLimits.{f.name}: must be > 0, got {value!r}")
            object.__setattr__(self, f.name, float(value))

    @property
    def decel_eff(self) -> float:
        return self.accel if self.decel is None else self.decel


@dataclass(frozen=True, slots=True)
class PathPoint:
    """The path and its profile at one progress value (see the module docstring for units)."""

    sigma: float
    x: float
    y: float
    theta: float
    kappa: float
    v: float
    omega: float
    a: float
    alpha: float
    t: float
    pivot: bool


# --------------------------------------------------------------------------------------------
# Geometry pieces


@dataclass(slots=True)
class _Piece:
    """Samples of one piece, both end points included; `s` is progress from the piece's start."""

    s: np.ndarray
    x: np.ndarray
    y: np.ndarray
    theta: np.ndarray
    kappa: np.ndarray
    pivot: bool = False
    turn: float = 0.0

    @property
    def length(self) -> float:
        return float(self.s[-1])


def _count(length: float, step: float) -> int:
    """Number of intervals: at least 2 so every piece has an interior sample (u > 0 there)."""
    return max(2, int(math.ceil(length / step - 1e-9)))


def _line(x0: float, y0: float, heading: float, length: float, step: float) -> _Piece:
    n = _count(length, step)
    s = np.linspace(0.0, length, n + 1)
    c, sn = math.cos(heading), math.sin(heading)
    return _Piece(s, x0 + c * s, y0 + sn * s, np.full(n + 1, heading), np.zeros(n + 1))


def _arc(x0: float, y0: float, heading: float, radius: float, sweep: float, step: float) -> _Piece:
    """Arc of `radius` turning by `sweep` (rad, positive = left) from pose (x0, y0, heading)."""
    length = radius * abs(sweep)
    n = _count(length, step)
    s = np.linspace(0.0, length, n + 1)
    k = math.copysign(1.0 / radius, sweep)
    th = heading + k * s
    # Centre to the left for a left turn: c = p + (1/k) * normal.
    cx, cy = x0 - math.sin(heading) / k, y0 + math.cos(heading) / k
    x = cx + np.sin(th) / k
    y = cy - np.cos(th) / k
    x[0], y[0] = x0, y0
    return _Piece(s, x, y, th, np.full(n + 1, k))


def _pivot(x: float, y: float, theta0: float, dtheta: float, b: float, step: float) -> _Piece:
    length = b * abs(dtheta)
    n = _count(length, step)
    s = np.linspace(0.0, length, n + 1)
    th = theta0 + np.linspace(0.0, dtheta, n + 1)
    return _Piece(s, np.full(n + 1, x), np.full(n + 1, y), th, np.zeros(n + 1), True, math.copysign(1.0, dtheta))


_SUB = 16  # sub-steps per sample when integrating a blend's position


def _blend_unit_chord(phi: float) -> float:
    """Length of the chord of a unit-length raised-cosine blend turning by phi."""
    u = np.linspace(0.0, 1.0, 4001)
    th = phi * (u - np.sin(TWO_PI * u) / TWO_PI)
    cx, cy = np.trapezoid(np.cos(th), u), np.trapezoid(np.sin(th), u)
    return math.hypot(cx, cy)


def _blend(x0: float, y0: float, heading: float, phi: float, length: float, step: float) -> _Piece:
    """Curvature-continuous corner: kappa rises and falls as a raised cosine, total turn phi."""
    n = _count(length, step)
    m = n * _SUB
    sf = np.linspace(0.0, length, m + 1)
    w = sf / length
    th = heading + phi * (w - np.sin(TWO_PI * w) / TWO_PI)
    dx = np.concatenate(([0.0], np.cumsum(0.5 * (np.cos(th[1:]) + np.cos(th[:-1])) * np.diff(sf))))
    dy = np.concatenate(([0.0], np.cumsum(0.5 * (np.sin(th[1:]) + np.sin(th[:-1])) * np.diff(sf))))
    sel = slice(None, None, _SUB)
    kap = (phi / length) * (1.0 - np.cos(TWO_PI * w[sel]))
    return _Piece(sf[sel], x0 + dx[sel], y0 + dy[sel], th[sel], kap)


Curve = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]


def _parametric(r: Curve, dr: Curve, ddr: Curve, u0: float, u1: float, step: float) -> _Piece:
    """Smooth curve r(u), u in [u0, u1], resampled at uniform arc length."""
    fine = max(20001, int(50000 * (u1 - u0) / TWO_PI) + 1)
    uf = np.linspace(u0, u1, fine)
    dxf, dyf = dr(uf)
    speed = np.hypot(dxf, dyf)
    if np.any(speed <= 0.0):
        raise ValueError("curve has a cusp (zero speed)")
    sf = np.concatenate(([0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(uf))))
    length = float(sf[-1])
    n = _count(length, step)
    s = np.linspace(0.0, length, n + 1)
    u = np.interp(s, sf, uf)
    # One Newton step on s(u) = s_target using the exact speed refines the inverse.
    dxu, dyu = dr(u)
    u = u - (np.interp(u, uf, sf) - s) / np.hypot(dxu, dyu)
    u[0], u[-1] = u0, u1
    x, y = r(u)
    dx, dy = dr(u)
    ddx, ddy = ddr(u)
    th = np.unwrap(np.arctan2(dy, dx))
    kap = (dx * ddy - dy * ddx) / np.hypot(dx, dy) ** 3
    return _Piece(s, x, y, th, kap)


def _wrap(a: float) -> float:
    """Angle to (-pi, pi]."""
    a = math.fmod(a + math.pi, TWO_PI)
    if a <= 0.0:
        a += TWO_PI
    return a - math.pi


@dataclass(slots=True)
class _Geometry:
    pieces: list[_Piece]
    cap_sigma: np.ndarray | None = None  # progress of waypoints with a speed cap
    cap_value: np.ndarray | None = None


@dataclass(frozen=True, slots=True)
class _Options:
    step: float = 0.002
    pivot_radius: float = 0.1
    corner_pivot_deg: float = 30.0
    blend_max: float = 0.15


def _polyline(pts: Sequence[tuple[float, float]], caps: Sequence[float] | None, opt: _Options) -> _Geometry:
    """Straight segments through the waypoints; pivots at sharp corners, blends at gentle ones."""
    p = [(float(a), float(b)) for a, b in pts]
    nseg = len(p) - 1
    seg_len = [math.hypot(p[i + 1][0] - p[i][0], p[i + 1][1] - p[i][1]) for i in range(nseg)]
    seg_dir = [math.atan2(p[i + 1][1] - p[i][1], p[i + 1][0] - p[i][0]) for i in range(nseg)]
    sharp = math.radians(opt.corner_pivot_deg)
    turn = [0.0] * len(p)
    tangent = [0.0] * len(p)  # tangent length consumed by a blend at each vertex
    for k in range(1, nseg):
        phi = _wrap(seg_dir[k] - seg_dir[k - 1])
        turn[k] = phi
        if 1e-9 < abs(phi) <= sharp:
            tangent[k] = min(opt.blend_max, 0.5 * seg_len[k - 1], 0.5 * seg_len[k])
    pieces: list[_Piece] = []
    enter = [0.0] * len(p)
    leave = [0.0] * len(p)
    sigma = 0.0
    heading = seg_dir[0]
    for k in range(nseg):
        (ax, ay), (bx, by) = p[k], p[k + 1]
        c, sn = math.cos(seg_dir[k]), math.sin(seg_dir[k])
        x0, y0 = ax + c * tangent[k], ay + sn * tangent[k]
        straight = seg_len[k] - tangent[k] - tangent[k + 1]
        heading = heading + _wrap(seg_dir[k] - heading)  # keep theta continuous
        if straight > 1e-9:
            pieces.append(_line(x0, y0, heading, straight, opt.step))
            sigma += straight
        if k + 1 == nseg:
            enter[k + 1] = leave[k + 1] = sigma
            break
        phi = turn[k + 1]
        if abs(phi) > sharp:
            enter[k + 1] = sigma
            pieces.append(_pivot(bx, by, heading, phi, opt.pivot_radius, opt.step))
            sigma += pieces[-1].length
            leave[k + 1] = sigma
        elif tangent[k + 1] > 0.0:
            d = tangent[k + 1]
            length = 2.0 * d * math.cos(0.5 * phi) / _blend_unit_chord(phi)
            pieces.append(_blend(bx - c * d, by - sn * d, heading, phi, length, opt.step))
            enter[k + 1] = leave[k + 1] = sigma + 0.5 * length
            sigma += length
        else:
            enter[k + 1] = leave[k + 1] = sigma
        heading += phi
    geo = _Geometry(pieces)
    if caps is not None:
        xs = np.array([v for pair in zip(enter, leave) for v in pair])
        geo.cap_sigma = xs
        geo.cap_value = np.repeat(np.asarray(caps, dtype=float), 2)
    return geo


# --------------------------------------------------------------------------------------------
# The path and its profile


class Path:
    """Dense samples of a path and its speed profile; O(log n) lookups by progress or time."""

    def __init__(self, geo: _Geometry, limits: SpeedLimits, *, v_cap: float, pivot_radius: float,
                 start_pose: tuple[float, float, float] | None = None) -> None:
        self.limits = limits
        self.pivot_radius = pivot_radius
        self._assemble(geo.pieces)
        sig = np.asarray(self.sigma)
        cap = np.full(len(sig), min(v_cap, limits.v_max))
        if geo.cap_sigma is not None and geo.cap_value is not None:
            cap = np.minimum(cap, np.interp(sig, geo.cap_sigma, geo.cap_value))
        self._profile(cap)
        self.length: float = self.sigma[-1]
        self.duration: float = self.t[-1]
        if start_pose is None:
            start_pose = (self.x[0], self.y[0], self.theta[0])
        self.start_pose: tuple[float, float, float] = tuple(float(v) for v in start_pose)  # type: ignore[assignment]
        self._np: dict[str, np.ndarray] | None = None

    # -- construction -------------------------------------------------------------------------
    def _assemble(self, pieces: list[_Piece]) -> None:
        cols: dict[str, list[np.ndarray]] = {k: [] for k in ("s", "x", "y", "theta", "kappa")}
        seg_pivot: list[bool] = []
        turn: list[float] = []
        piece_end: list[float] = []
        base = 0.0
        for j, pc in enumerate(pieces):
            sl = slice(0 if j == 0 else 1, None)
            if j:
                gap = math.hypot(pc.x[0] - cols["x"][-1][-1], pc.y[0] - cols["y"][-1][-1])
                if gap > 1e-6:
                    raise AssertionError(f"pieces do not join ({gap:.3g} m)")
            cols["s"].append(base + pc.s[sl])
            for k in ("x", "y", "theta", "kappa"):
                cols[k].append(getattr(pc, k)[sl])
            n = len(pc.s) - 1
            seg_pivot += [pc.pivot] * n
            turn += [pc.turn] * n
            base += pc.length
            piece_end += [base] * n
        arr = {k: np.concatenate(v) for k, v in cols.items()}
        # Theta continuous across pieces (each piece is continuous inside).
        arr["theta"] = np.unwrap(arr["theta"])
        shift = arr["theta"][0] - _wrap(float(arr["theta"][0]))
        arr["theta"] -= shift
        self.sigma: list[float] = arr["s"].tolist()
        self.x: list[float] = arr["x"].tolist()
        self.y: list[float] = arr["y"].tolist()
        self.theta: list[float] = arr["theta"].tolist()
        self.kappa: list[float] = arr["kappa"].tolist()
        self.tx: list[float] = np.cos(arr["theta"]).tolist()
        self.ty: list[float] = np.sin(arr["theta"]).tolist()
        self.seg_pivot: list[bool] = seg_pivot
        self.turn: list[float] = turn
        self.piece_end: list[float] = piece_end

    def _profile(self, v_cap: np.ndarray) -> None:
        lim, b = self.limits, self.pivot_radius
        s = np.asarray(self.sigma)
        kap = np.asarray(self.kappa)
        piv = np.asarray(self.seg_pivot)
        ds = np.diff(s)
        n = len(s)
        absk = np.abs(kap)
        with np.errstate(divide="ignore"):
            cap = np.minimum(v_cap, np.sqrt(lim.lateral_accel / absk))
            cap = np.minimum(cap, lim.omega_max / absk)
            dk = np.abs(np.diff(kap)) / ds
            dk[piv] = 0.0
            kcap = np.sqrt(0.5 * lim.alpha_max / dk)
            kmax = np.maximum(absk[1:], absk[:-1])
            acc_lim = np.minimum(lim.accel, 0.5 * lim.alpha_max / kmax)
            dec_lim = np.minimum(lim.decel_eff, 0.5 * lim.alpha_max / kmax)
        cap[:-1] = np.minimum(cap[:-1], kcap)
        cap[1:] = np.minimum(cap[1:], kcap)
        # Pivot samples: angular speed cap; rest points on both sides of each pivot.
        in_piv = np.zeros(n, dtype=bool)
        in_piv[:-1] |= piv
        in_piv[1:] |= piv
        cap[in_piv] = b * lim.omega_max
        edge = np.zeros(n, dtype=bool)
        edge[:-1] |= piv & ~np.concatenate(([False], piv[:-1]))  # first sample of a pivot
        edge[1:] |= piv & ~np.concatenate((piv[1:], [False]))  # last sample of a pivot
        cap[edge] = 0.0
        cap[0] = cap[-1] = 0.0
        acc_lim[piv] = b * lim.alpha_max
        dec_lim[piv] = b * lim.alpha_max
        capl, dsl, accl, decl = cap.tolist(), ds.tolist(), acc_lim.tolist(), dec_lim.tolist()
        u = [0.0] * n
        for i in range(n - 1):
            u[i + 1] = min(capl[i + 1], math.sqrt(u[i] * u[i] + 2.0 * accl[i] * dsl[i]))
        for i in range(n - 2, -1, -1):
            u[i] = min(u[i], math.sqrt(u[i + 1] * u[i + 1] + 2.0 * decl[i] * dsl[i]))
        kl, pl, tl = self.kappa, self.seg_pivot, self.turn
        t = [0.0] * n
        acc_u = [0.0] * (n - 1)
        for i in range(n - 1):
            us = u[i] + u[i + 1]
            if us <= 0.0:  # cannot happen: every piece has an interior sample with u > 0
                raise AssertionError("profile has two consecutive rest samples")
            t[i + 1] = t[i] + 2.0 * dsl[i] / us
            acc_u[i] = (u[i + 1] * u[i + 1] - u[i] * u[i]) / (2.0 * dsl[i])
        # Per-sample v and omega. A pivot's edge samples are rest points (v = omega = 0).
        in_pivl = in_piv.tolist()
        v = [0.0 if in_pivl[i] else u[i] for i in range(n)]
        omega = [0.0] * n
        for i in range(n):
            if in_pivl[i]:
                j = i if i < n - 1 and pl[i] else i - 1
                omega[i] = tl[j] * u[i] / b
            else:
                omega[i] = u[i] * kl[i]
        a = [0.0 if pl[i] else acc_u[i] for i in range(n - 1)]
        alpha = [(omega[i + 1] - omega[i]) / (t[i + 1] - t[i]) for i in range(n - 1)]
        self.u, self.v, self.omega, self.t = u, v, omega, t
        self.acc_u, self.a, self.alpha = acc_u, a, alpha
        self.pivot_sample: list[bool] = in_pivl

    # -- lookups ------------------------------------------------------------------------------
    def index(self, sigma: float) -> int:
        """Interval i with sigma[i] <= sigma < sigma[i + 1] (clamped to the valid range)."""
        i = bisect.bisect_right(self.sigma, sigma) - 1
        last = len(self.sigma) - 2
        return 0 if i < 0 else (last if i > last else i)

    def geometry(self, i: int, s: float) -> tuple[float, float, float, float]:
        """(x, y, theta, kappa) at progress s inside interval i, linearly interpolated."""
        s0 = self.sigma[i]
        f = (s - s0) / (self.sigma[i + 1] - s0)
        x, y, th, k = self.x, self.y, self.theta, self.kappa
        return (x[i] + f * (x[i + 1] - x[i]), y[i] + f * (y[i + 1] - y[i]),
                th[i] + f * (th[i + 1] - th[i]), k[i] + f * (k[i + 1] - k[i]))

    def dynamics(self, i: int, s: float) -> tuple[float, float, float, float, float]:
        """(v, omega, a, alpha, t) at progress s inside interval i, exact for the profile."""
        u0 = self.u[i]
        acc = self.acc_u[i]
        ds = s - self.sigma[i]
        uu = u0 * u0 + 2.0 * acc * ds
        u = math.sqrt(uu) if uu > 0.0 else 0.0
        den = u0 + u
        tau = 2.0 * ds / den if den > 0.0 else 0.0
        return self._dyn(i, u, tau)

    def _dyn(self, i: int, u: float, tau: float) -> tuple[float, float, float, float, float]:
        if self.seg_pivot[i]:
            w = self.turn[i] * u / self.pivot_radius
            return 0.0, w, 0.0, self.alpha[i], self.t[i] + tau
        return u, self.omega[i] + self.alpha[i] * tau, self.a[i], self.alpha[i], self.t[i] + tau

    def _point(self, i: int, s: float, dyn: tuple[float, float, float, float, float]) -> PathPoint:
        x, y, th, k = self.geometry(i, s)
        v, w, a, al, t = dyn
        return PathPoint(s, x, y, th, 0.0 if self.seg_pivot[i] else k, v, w, a, al, t, self.seg_pivot[i])

    def at(self, sigma: float) -> PathPoint:
        """The path at progress sigma (clamped to [0, length])."""
        s = 0.0 if sigma <= 0.0 else (self.length if sigma >= self.length else float(sigma))
        i = self.index(s)
        return self._point(i, s, self.dynamics(i, s))

    def at_time(self, t: float) -> PathPoint:
        """The path where the profile is at time t (clamped to [0, duration])."""
        tc = 0.0 if t <= 0.0 else (self.duration if t >= self.duration else float(t))
        i = bisect.bisect_right(self.t, tc) - 1
        i = min(max(i, 0), len(self.t) - 2)
        tau = tc - self.t[i]
        u0, acc = self.u[i], self.acc_u[i]
        s = self.sigma[i] + u0 * tau + 0.5 * acc * tau * tau
        s = min(max(s, self.sigma[i]), self.sigma[i + 1])
        u = max(u0 + acc * tau, 0.0)
        return self._point(i, s, self._dyn(i, u, tau))

    # -- offline helpers ----------------------------------------------------------------------
    def arrays(self) -> dict[str, np.ndarray]:
        """Numpy copies of the sample arrays (for plots, metrics and tests)."""
        if self._np is None:
            names = ("sigma", "x", "y", "theta", "kappa", "u", "v", "omega", "t", "a", "alpha",
                     "acc_u", "seg_pivot", "turn", "pivot_sample")
            self._np = {k: np.asarray(getattr(self, k)) for k in names}
        return self._np

    def distance_to(self, x: float, y: float) -> float:
        """Geometric distance from (x, y) to the path's polyline (vectorised; not for the hot path)."""
        arr = self.arrays()
        ax, ay = arr["x"][:-1], arr["y"][:-1]
        dx, dy = arr["x"][1:] - ax, arr["y"][1:] - ay
        l2 = dx * dx + dy * dy
        with np.errstate(invalid="ignore", divide="ignore"):
            f = np.where(l2 > 0.0, ((x - ax) * dx + (y - ay) * dy) / l2, 0.0)
        f = np.clip(f, 0.0, 1.0)
        return float(np.sqrt(np.min((ax + f * dx - x) ** 2 + (ay + f * dy - y) ** 2)))


# --------------------------------------------------------------------------------------------
# Loading

_LIMIT_KEYS = ("accel", "decel", "lateral_accel", "omega_max", "alpha_max")
_COMMON = {"shape", "speed", "start", "start_pose", "pivot_radius", "corner_pivot_deg", "blend_max",
           "name", "description", *_LIMIT_KEYS}
_SHAPE_KEYS = {
    "line": {"heading_deg", "length", "origin"},
    "circle": {"radius", "direction", "center", "laps"},
    "rectangle": {"width", "height", "direction", "laps"},
    "ellipse": {"a", "b", "direction", "center", "laps"},
    "figure_eight": {"width", "height", "size", "center", "laps"},
    "s_curve": {"length", "offset"},
}
_MISSING = object()


class _Spec:
    """A YAML mapping with typed getters whose errors name the file and key."""

    def __init__(self, mapping: Mapping[str, Any], where: str) -> None:
        self.m = mapping
        self.where = where

    def fail(self, key: str, problem: str) -> PathError:
        return PathError(f"{self.where}: key '{key}': {problem}")

    def num(self, key: str, default: Any = _MISSING, *, positive: bool = False, nonneg: bool = False) -> float:
        if key not in self.m:
            if default is _MISSING:
                raise self.fail(key, "missing")
            return default
        return _number(self.m[key], lambda p: self.fail(key, p), positive=positive, nonneg=nonneg)

    def vec(self, key: str, size: int | tuple[int, ...], default: Any = _MISSING) -> tuple[float, ...]:
        if key not in self.m:
            if default is _MISSING:
                raise self.fail(key, "missing")
            return default
        raw = self.m[key]
        sizes = (size,) if isinstance(size, int) else size
        if not isinstance(raw, (list, tuple)) or len(raw) not in sizes:
            raise self.fail(key, f"expected a list of {' or '.join(map(str, sizes))} numbers, got {raw!r}")
        return tuple(_number(v, lambda p: self.fail(key, p)) for v in raw)

    def choice(self, key: str, options: tuple[str, ...], default: str) -> str:
        raw = self.m.get(key, default)
        if not isinstance(raw, str) or raw.lower() not in options:
            raise self.fail(key, f"expected one of {', '.join(options)}, got {raw!r}")
        return raw.lower()


def _number(raw: Any, fail: Callable[[str], PathError], *, positive: bool = False, nonneg: bool = False) -> float:
    if isinstance(raw, bool) or not isinstance(raw, (int, float, str)):
        raise fail(f"expected a number, got {raw!r}")
    try:
        value = float(raw)
    except ValueError:
        raise fail(f"not a number: {raw!r}") from None
    if not math.isfinite(value):
        raise fail(f"must be finite, got {raw!r}")
    if positive and value <= 0.0:
        raise fail(f"must be > 0, got {raw!r}")
    if nonneg and value < 0.0:
        raise fail(f"must be >= 0, got {raw!r}")
    return value


def _merge_points(rows: list[tuple[float, float, float]]) -> list[tuple[float, float, float]]:
    """Drop consecutive duplicates (keeping the lower speed cap)."""
    out: list[tuple[float, float, float]] = []
    for x, y, v in rows:
        if out and math.hypot(x - out[-1][0], y - out[-1][1]) < 1e-9:
            out[-1] = (out[-1][0], out[-1][1], min(out[-1][2], v))
        else:
            out.append((x, y, v))
    return out


def _read_csv(filename: str) -> tuple[list[tuple[float, float, float]], bool]:
    """Waypoints (x, y, v cap or inf) from a CSV with header x,y or x,y,v; second item: has v."""
    try:
        with open(filename, newline="", encoding="utf-8") as fh:
            text = fh.read()
    except OSError as exc:
        raise PathError(f"{filename}: cannot read: {exc.strerror or exc}") from None
    rows: list[tuple[float, float, float]] = []
    header: list[str] | None = None
    for lineno, fields_ in enumerate(csv.reader(io.StringIO(text)), start=1):
        cells = [c.strip() for c in fields_]
        if not cells or all(c == "" for c in cells) or cells[0].startswith("#"):
            continue
        if header is None:
            header = [c.lower() for c in cells]
            if header not in (["x", "y"], ["x", "y", "v"]):
                raise PathError(f"{filename}: line {lineno}: header must be 'x,y' or 'x,y,v', got {','.join(cells)!r}")
            continue
        if len(cells) != len(header):
            raise PathError(f"{filename}: line {lineno}: expected {len(header)} columns, got {len(cells)}")
        vals = []
        for name, cell in zip(header, cells):
            vals.append(_number(cell, lambda p, n=name: PathError(f"{filename}: line {lineno}: column '{n}': {p}")))
        v = math.inf
        if len(vals) == 3:
            v = vals[2]
            if v <= 0.0:
                raise PathError(f"{filename}: line {lineno}: column 'v': speed must be > 0, got {cells[2]!r}")
        rows.append((vals[0], vals[1], v))
    if header is None:
        raise PathError(f"{filename}: line 1: missing header 'x,y' or 'x,y,v' (file is empty)")
    return rows, len(header) == 3


def _waypoint_geometry(rows: list[tuple[float, float, float]], has_v: bool, where: str, opt: _Options) -> _Geometry:
    pts = _merge_points(rows)
    if len(pts) < 2:
        raise PathError(f"{where}: fewer than 2 distinct points ({len(pts)})")
    caps = [p[2] for p in pts] if has_v else None
    return _polyline([(p[0], p[1]) for p in pts], caps, opt)


def _closed_param(spec: _Spec, r: Curve, dr: Curve, ddr: Curve, laps: float, opt: _Options) -> _Geometry:
    try:
        return _Geometry([_parametric(r, dr, ddr, 0.0, TWO_PI * laps, opt.step)])
    except ValueError as exc:
        raise PathError(f"{spec.where}: {exc}") from None


def _shape_geometry(spec: _Spec, shape: str, opt: _Options) -> _Geometry:
    if shape == "line":
        origin = spec.vec("origin", 2, default=None)
        if origin is None:
            start = spec.m.get("start")
            origin = spec.vec("start", 2) if isinstance(start, (list, tuple)) and len(start) == 2 else (0.0, 0.0)
        heading = math.radians(spec.num("heading_deg", 0.0))
        return _Geometry([_line(origin[0], origin[1], heading, spec.num("length", positive=True), opt.step)])
    if shape == "circle":
        radius = spec.num("radius", positive=True)
        sign = 1.0 if spec.choice("direction", ("cw", "ccw"), "ccw") == "ccw" else -1.0
        laps = spec.num("laps", 1.0, positive=True)
        cx, cy = spec.vec("center", 2, default=(0.0, sign * radius))
        # Start where the heading is +x: bottom of a ccw circle, top of a cw one.
        return _Geometry([_arc(cx, cy - sign * radius, 0.0, radius, sign * TWO_PI * laps, opt.step)])
    if shape == "rectangle":
        w, h = spec.num("width", positive=True), spec.num("height", positive=True)
        sign = 1.0 if spec.choice("direction", ("cw", "ccw"), "ccw") == "ccw" else -1.0
        laps = spec.num("laps", 1.0, positive=True)
        if laps != int(laps):
            raise spec.fail("laps", f"a rectangle needs a whole number of laps, got {laps!r}")
        corners = [(w, 0.0), (w, sign * h), (0.0, sign * h), (0.0, 0.0)]
        return _polyline([(0.0, 0.0)] + corners * int(laps), None, opt)
    if shape == "ellipse":
        a, b = spec.num("a", positive=True), spec.num("b", positive=True)
        sign = 1.0 if spec.choice("direction", ("cw", "ccw"), "ccw") == "ccw" else -1.0
        laps = spec.num("laps", 1.0, positive=True)
        cx, cy = spec.vec("center", 2, default=(0.0, sign * b))
        # Starts at the end of the y semi-axis heading +x: (cx, cy - sign b).
        return _closed_param(
            spec,
            lambda u: (cx + a * np.sin(u), cy - sign * b * np.cos(u)),
            lambda u: (a * np.cos(u), sign * b * np.sin(u)),
            lambda u: (-a * np.sin(u), sign * b * np.cos(u)),
            laps, opt)
    if shape == "figure_eight":
        if "size" in spec.m and ("width" in spec.m or "height" in spec.m):
            raise spec.fail("size", "give either size or width/height, not both")
        if "size" in spec.m:
            w = spec.num("size", positive=True)
            h = 0.5 * w
        else:
            w, h = spec.num("width", positive=True), spec.num("height", positive=True)
        laps = spec.num("laps", 1.0, positive=True)
        cx, cy = spec.vec("center", 2, default=(0.0, 0.0))
        # Gerono's lemniscate: x = (w/2) sin u, y = (h/2) sin 2u; crosses itself at the centre.
        hw, hh = 0.5 * w, 0.5 * h
        return _closed_param(
            spec,
            lambda u: (cx + hw * np.sin(u), cy + hh * np.sin(2.0 * u)),
            lambda u: (hw * np.cos(u), 2.0 * hh * np.cos(2.0 * u)),
            lambda u: (-hw * np.sin(u), -4.0 * hh * np.sin(2.0 * u)),
            laps, opt)
    if shape == "s_curve":
        length, offset = spec.num("length", positive=True), spec.num("offset")
        k = math.pi / length
        # y = (offset/2)(1 - cos(pi x / length)): heading 0 at both ends, lateral shift `offset`.
        piece = _parametric(
            lambda u: (u, 0.5 * offset * (1.0 - np.cos(k * u))),
            lambda u: (np.ones_like(u), 0.5 * offset * k * np.sin(k * u)),
            lambda u: (np.zeros_like(u), 0.5 * offset * k * k * np.cos(k * u)),
            0.0, length, opt.step)
        return _Geometry([piece])
    raise spec.fail("shape", f"unknown shape {shape!r} (known: {', '.join(sorted(_SHAPE_KEYS))})")


def _from_mapping(m: Any, limits: SpeedLimits, where: str, base_dir: str | None, opt: _Options) -> Path:
    if not isinstance(m, Mapping):
        raise PathError(f"{where}: expected a mapping at the top level, got {type(m).__name__}")
    spec = _Spec(m, where)
    kinds = [k for k in ("shape", "points", "file") if k in m]
    if len(kinds) != 1:
        raise PathError(f"{where}: exactly one of keys 'shape', 'points', 'file' is required, got {kinds or 'none'}")
    kind = kinds[0]
    if kind == "shape":
        shape = m["shape"]
        if not isinstance(shape, str) or shape not in _SHAPE_KEYS:
            raise spec.fail("shape", f"unknown shape {shape!r} (known: {', '.join(sorted(_SHAPE_KEYS))})")
        allowed = _COMMON | _SHAPE_KEYS[shape]
    else:
        allowed = _COMMON | {kind}
    unknown = sorted(str(k) for k in m if k not in allowed)
    if unknown:
        raise spec.fail(unknown[0], f"unknown key (allowed here: {', '.join(sorted(allowed))})")
    overrides = {k: spec.num(k, positive=True) for k in _LIMIT_KEYS if k in m}
    try:
        lim = replace(limits, **overrides)
    except ValueError as exc:
        raise PathError(f"{where}: {exc}") from None
    opt = replace(
        opt,
        pivot_radius=spec.num("pivot_radius", opt.pivot_radius, positive=True),
        corner_pivot_deg=spec.num("corner_pivot_deg", opt.corner_pivot_deg, nonneg=True),
        blend_max=spec.num("blend_max", opt.blend_max, positive=True),
    )
    v_cap = spec.num("speed", lim.v_max, positive=True)
    if kind == "shape":
        geo = _shape_geometry(spec, m["shape"], opt)
    elif kind == "points":
        raw = m["points"]
        if not isinstance(raw, (list, tuple)):
            raise spec.fail("points", f"expected a list of [x, y] or [x, y, v], got {raw!r}")
        rows = []
        has_v = False
        for j, item in enumerate(raw):
            key = f"points[{j}]"
            if not isinstance(item, (list, tuple)) or len(item) not in (2, 3):
                raise spec.fail(key, f"expected [x, y] or [x, y, v], got {item!r}")
            vals = [_number(c, lambda p, k=key: spec.fail(k, p)) for c in item]
            v = math.inf
            if len(vals) == 3:
                has_v = True
                v = vals[2]
                if v <= 0.0:
                    raise spec.fail(key, f"speed must be > 0, got {item[2]!r}")
            rows.append((vals[0], vals[1], v))
        geo = _waypoint_geometry(rows, has_v, f"{where}: key 'points'", opt)
        if has_v and geo.cap_value is not None:
            geo.cap_value = np.minimum(geo.cap_value, v_cap)
    else:
        fname = m["file"]
        if not isinstance(fname, str) or not fname.lower().endswith(".csv"):
            raise spec.fail("file", f"expected a .csv file name, got {fname!r}")
        if base_dir is not None and not os.path.isabs(fname):
            fname = os.path.join(base_dir, fname)
        try:
            rows, has_v = _read_csv(fname)
        except PathError as exc:
            raise spec.fail("file", str(exc)) from None
        geo = _waypoint_geometry(rows, has_v, fname, opt)
        if geo.cap_value is not None:
            geo.cap_value = np.minimum(geo.cap_value, v_cap)
    start = None
    for key in ("start_pose", "start"):
        raw = m.get(key)
        if isinstance(raw, (list, tuple)) and len(raw) == 3:
            start = spec.vec(key, 3)
        elif raw is not None and not (key == "start" and m.get("shape") == "line"):
            raise spec.fail(key, f"expected [x, y, theta] (theta in rad), got {raw!r}")
    return Path(geo, lim, v_cap=v_cap, pivot_radius=opt.pivot_radius, start_pose=start)


def load_path(source: str | os.PathLike[str] | Mapping[str, Any], limits: SpeedLimits | None = None, *,
              base_dir: str | None = None, sample_step_m: float = 0.002, pivot_radius: float = 0.1,
              corner_pivot_deg: float = 30.0, blend_max_m: float = 0.15) -> Path:
    """Load a path from a .csv / .yaml / .yml file or a mapping (see the module docstring).

    Relative `file:` entries resolve against `base_dir`, which defaults to the YAML file's folder.
    """
    limits = SpeedLimits() if limits is None else limits
    if not (sample_step_m > 0.0 and pivot_radius > 0.0 and blend_max_m > 0.0 and corner_pivot_deg >= 0.0):
        raise ValueError("load_path: sample_step_m, pivot_radius, blend_max_m must be > 0, corner_pivot_deg >= 0")
    opt = _Options(sample_step_m, pivot_radius, corner_pivot_deg, blend_max_m)
    if isinstance(source, Mapping):
        return _from_mapping(source, limits, "<mapping>", base_dir, opt)
    fname = os.fspath(source)
    low = fname.lower()
    if low.endswith(".csv"):
        rows, has_v = _read_csv(fname)
        return Path(_waypoint_geometry(rows, has_v, fname, opt), limits, v_cap=limits.v_max, pivot_radius=pivot_radius)
    if low.endswith((".yaml", ".yml")):
        try:
            with open(fname, encoding="utf-8") as fh:
                data = yaml.load(fh, Loader=YAML_LOADER)
        except OSError as exc:
            raise PathError(f"{fname}: cannot read: {exc.strerror or exc}") from None
        except yaml.YAMLError as exc:
            mark = getattr(exc, "problem_mark", None)
            line = f"line {mark.line + 1}: " if mark is not None else ""
            raise PathError(f"{fname}: {line}invalid YAML: {getattr(exc, 'problem', exc)}") from None
        return _from_mapping(data, limits, fname, base_dir if base_dir is not None else os.path.dirname(fname), opt)
    raise PathError(f"{fname}: unknown path file type (expected .csv, .yaml or .yml)")
