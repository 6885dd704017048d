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
- Dense polylines (recordings, exported curves, grid plans) are not corners at every point:
  they are fitted by a smoothing spline within `paths.tolerance_m` of every point, with
  pivots only at genuine corners (ddrt/path/condition.py); `Path.conditioning` says how a
  polyline was read and `Path.deviation_m` how far the reference lies from its points.
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

Reversing: a piece marked `reverse` is driven backwards. theta is the robot's heading (the
direction of travel + pi) and kappa the robot's curvature d(theta)/d(forward distance), the
negative of the travel curvature, so v = -u < 0, omega = v kappa and a = dv/dt hold as for a
forward piece; u and progress still grow. The profile comes to rest at every cusp (where the
direction flips), `cusps` lists them, `direction[i]` is -1.0 on reversing intervals (+1.0
elsewhere, pivots included). tx, ty stay (cos theta, sin theta): the robot's heading, not the
direction of travel (pure pursuit multiplies by `direction`).

Index arrays (read-only Python lists, for the pursuit's hot path; n samples, n - 1 intervals):
  sigma, x, y, theta, kappa, u, v, omega, t     per sample
  tx, ty                                        per sample: unit tangent (cos theta, sin theta)
  acc_u, a, alpha, seg_pivot, turn, piece_end   per interval i (between samples i and i + 1):
    acc_u      d(u)/dt, constant over the interval
    a, alpha   dv/dt and d(omega)/dt over the interval (a = 0 and alpha = turn * acc_u / b in pivots)
    seg_pivot  True if the interval lies in a pivot
    turn       +1 (left) / -1 (right) for pivot intervals, 0 otherwise
    piece_end  sigma at which the interval's piece ends
  arrays()["v_cap"]                             per sample: the speed cap the profile started from
                                                (the path's speed, or a lower waypoint v)
"""

from __future__ import annotations

import bisect
import copy
import math
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from ddrt.core.wrap import wrap_angle
from ddrt.path.geometry import Geometry, Piece
from ddrt.path.profile import SpeedLimits, envelope_excess, speed_profile

if TYPE_CHECKING:
    from ddrt.core.envelope import Envelope

__all__ = ["PathPoint", "Path", "distances_to_polyline", "interval_index"]


class PathPoint(NamedTuple):
    """The path and its profile at one progress value (see the module docstring for units).

    A NamedTuple, not a frozen dataclass: the reference builds one every control tick, and a
    frozen dataclass's __init__ (one object.__setattr__ a field) cost 1.5 us against 0.4."""

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



class Path:
    """Dense samples of a path and its speed profile; O(log n) lookups by progress or time."""

    def __init__(self, geo: Geometry, limits: SpeedLimits, *, v_cap: float, pivot_radius: float,
                 start_pose: tuple[float, float, float] | None = None) -> None:
        self.limits = limits
        self.pivot_radius = pivot_radius
        self._np: dict[str, np.ndarray] = {}  # numpy copies of the sample lists, kept from construction
        self._assemble(geo.pieces)
        sig = self._np["sigma"]
        cap = np.full(len(sig), min(v_cap, limits.v_max))
        if geo.cap_sigma is not None and geo.cap_value is not None:
            cap = np.minimum(cap, np.interp(sig, geo.cap_sigma, geo.cap_value))
        self.v_cap: float = min(v_cap, limits.v_max)  # the path's speed (its own or limits.v_max)
        self._np["v_cap"] = cap  # per sample: that speed or a lower waypoint cap
        self._profile(cap)
        self.length: float = self.sigma[-1]
        self.duration: float = self.t[-1]
        if start_pose is None:
            start_pose = (self.x[0], self.y[0], self.theta[0])
        self.start_pose: tuple[float, float, float] = tuple(float(v) for v in start_pose)  # type: ignore[assignment]
        # What the loader changed on the way, for the user (e.g. a path limit clamped to the config's).
        self.warnings: list[str] = []
        # What the loader did that is no cause for concern (how a polyline's points were read).
        self.notes: list[str] = []
        # How a polyline's points were read (ddrt.path.condition.Conditioning); None for shapes.
        self.conditioning: Any = None

    @property
    def deviation_m(self) -> float:
        """Largest distance from a point of the input polyline to this path (0 for shapes and
        waypoints, whose segments are the path; a grid plan's points as its cells' centres,
        within one quantum of their coordinates' rounding: gridplan.read_grid)."""
        c = self.conditioning
        return 0.0 if c is None or c.mode == "waypoints" else float(c.deviation_m)

    # -- construction -------------------------------------------------------------------------
    def _assemble(self, pieces: list[Piece]) -> None:
        cols: dict[str, list[np.ndarray]] = {k: [] for k in ("s", "x", "y", "theta", "kappa")}
        seg_pivot: list[bool] = []
        turn: list[float] = []
        direction: list[float] = []
        piece_end: list[float] = []
        base = 0.0
        for j, pc in enumerate(pieces):
            sl = slice(0 if j == 0 else 1, None)
            if j:
                gap = math.hypot(pc.x[0] - cols["x"][-1][-1], pc.y[0] - cols["y"][-1][-1])
                if gap > 1e-6:
                    raise AssertionError(f"pieces do not join ({gap:.3g} m)")
            cols["s"].append(base + pc.s[sl])
            for k, col in (("x", pc.x), ("y", pc.y), ("theta", pc.theta), ("kappa", pc.kappa)):
                cols[k].append(col[sl])
            n = len(pc.s) - 1
            seg_pivot += [pc.pivot] * n
            direction += [-1.0 if pc.reverse and not pc.pivot else 1.0] * n
            turn += [pc.turn] * n
            base += pc.length
            piece_end += [base] * n
        arr = {k: np.concatenate(v) for k, v in cols.items()}
        # Theta continuous across pieces (each piece is continuous inside).
        arr["theta"] = np.unwrap(arr["theta"])
        shift = arr["theta"][0] - wrap_angle(float(arr["theta"][0]))
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
        self.direction: list[float] = direction
        self.cusps: list[float] = _cusps(self.sigma, seg_pivot, direction)
        self._np.update(sigma=arr["s"], x=arr["x"], y=arr["y"], theta=arr["theta"], kappa=arr["kappa"],
                        seg_pivot=np.asarray(seg_pivot, dtype=bool), turn=np.asarray(turn, dtype=float),
                        direction=np.asarray(direction, dtype=float))

    def _profile(self, v_cap: np.ndarray, keep: tuple[int, np.ndarray] | None = None) -> None:
        a = self._np
        p = speed_profile(a["sigma"], a["kappa"], a["seg_pivot"], a["turn"], v_cap, self.limits, self.pivot_radius,
                          keep=keep, direction=a["direction"])
        self._np.update(p.arrays)
        for array in self._np.values():
            array.flags.writeable = False  # shared by every caller of arrays()
        self.u, self.v, self.omega, self.t = p.u, p.v, p.omega, p.t
        self.acc_u, self.a, self.alpha = p.acc_u, p.a, p.alpha
        self.pivot_sample: list[bool] = p.pivot_sample
        # The envelope's per-interval coefficients (p.constraints, 80 bytes a sample) are not
        # kept: they were for building, and the path worker ships a Path's scalars in a header
        # of at most 16 MiB. envelope_excess and reprofiled rebuild what they need.

    def reprofiled(self, limits: SpeedLimits, first: int) -> "Path":
        """The same path with its profile from sample `first` on rebuilt under `limits` (a new
        robot model while the path is followed): samples up to `first` and the speed there are
        kept, so a schedule before `first` reads the same times and speeds."""
        new = copy.copy(self)
        new._np = {k: v for k, v in self._np.items() if k in ("sigma", "x", "y", "theta", "kappa", "seg_pivot", "turn", "direction", "v_cap")}
        new.limits = limits
        new._profile(self._np["v_cap"], keep=(first, self._np["u"]))
        new.duration = new.t[-1]
        new.warnings = list(self.warnings)
        new.notes = list(self.notes)
        return new

    def moved(self, pose: tuple[float, float, float]) -> "Path":
        """The same path moved rigidly so that its start pose is `pose` (x, y, heading): every
        sample rotated about the start and translated; speeds, times and curvature unchanged."""
        x0, y0, th0 = self.start_pose
        x1, y1, th1 = (float(v) for v in pose)
        dth = wrap_angle(th1 - th0)
        c, s = math.cos(dth), math.sin(dth)
        a = self._np
        dx, dy = a["x"] - x0, a["y"] - y0
        x = x1 + c * dx - s * dy
        y = y1 + s * dx + c * dy
        theta = a["theta"] + dth
        new = copy.copy(self)
        new._np = dict(a, x=x, y=y, theta=theta)
        for arr in (x, y, theta):
            arr.flags.writeable = False
        new.x, new.y, new.theta = x.tolist(), y.tolist(), theta.tolist()
        new.tx, new.ty = np.cos(theta).tolist(), np.sin(theta).tolist()
        new.start_pose = (x1, y1, th0 + dth)
        new.warnings = list(self.warnings)
        new.notes = list(self.notes)
        return new

    def envelope_excess(self, envelope: "Envelope", first: int = 0) -> float:
        """How far this path's profile from sample `first` on goes beyond `envelope`, as a fraction
        of the bound exceeded (<= 0: within): is it still what that robot can drive?"""
        a = self._np
        return envelope_excess(a["sigma"], a["kappa"], a["seg_pivot"], a["turn"], a["u"], self.limits,
                               self.pivot_radius, envelope, first, direction=a["direction"])

    # -- lookups ------------------------------------------------------------------------------
    def index(self, sigma: float, near: int = -1) -> int:
        """Interval i with sigma[i] <= sigma < sigma[i + 1] (clamped to the valid range).

        `near` (optional) is an interval the answer is likely at or a few after (the last one
        a caller found): the same answer, found in a few comparisons (see interval_index)."""
        return interval_index(self.sigma, sigma, near)

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
        return self.direction[i] * u, self.omega[i] + self.alpha[i] * tau, self.a[i], self.alpha[i], self.t[i] + tau

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
        return self.at_time_near(t)[0]

    def at_time_near(self, t: float, near: int = -1) -> tuple[PathPoint, int]:
        """(at_time(t), index(its sigma)). `near` as in `index`: the schedule, read every
        control tick, finds its interval from the last one's. Written out (the interval's
        dynamics and geometry, the clamps), as this runs every tick; the same arithmetic as
        `_dyn` and `geometry`."""
        ts = self.t
        tc = 0.0 if t <= 0.0 else (self.duration if t >= self.duration else float(t))
        i = interval_index(ts, tc, near)
        tau = tc - ts[i]
        u0, acc = self.u[i], self.acc_u[i]
        sig = self.sigma
        s0, s1 = sig[i], sig[i + 1]
        s = s0 + u0 * tau + 0.5 * acc * tau * tau
        s = s0 if s0 > s else s  # min(max(s, s0), s1), without the builtins' calls
        s = s1 if s1 < s else s
        u = u0 + acc * tau
        u = 0.0 if 0.0 > u else u  # max(u, 0.0)
        al = self.alpha[i]
        pivot = self.seg_pivot[i]
        if pivot:
            v, w, a = 0.0, self.turn[i] * u / self.pivot_radius, 0.0
        else:
            v, w, a = self.direction[i] * u, self.omega[i] + al * tau, self.a[i]
        f = (s - s0) / (s1 - s0)
        x, y, th = self.x, self.y, self.theta
        k = 0.0 if pivot else self.kappa[i] + f * (self.kappa[i + 1] - self.kappa[i])
        point = PathPoint(s, x[i] + f * (x[i + 1] - x[i]), y[i] + f * (y[i + 1] - y[i]),
                          th[i] + f * (th[i + 1] - th[i]), k, v, w, a, al, ts[i] + tau, pivot)
        # s lies in [s0, s1]: interval i holds it unless it is s1 (then index() says which).
        return point, (i if s < s1 else interval_index(sig, s, i))

    # -- offline helpers ----------------------------------------------------------------------
    def arrays(self) -> dict[str, np.ndarray]:
        """The sample arrays as numpy arrays (read-only; for plots, metrics and tests)."""
        return self._np

    def distance_to(self, x: float, y: float) -> float:
        """Geometric distance from (x, y) to the path's polyline (vectorised; not for the hot path)."""
        arr = self.arrays()
        return float(distances_to_polyline(np.c_[arr["x"], arr["y"]], np.array([[x, y]], dtype=float))[0])


_WALK = 8  # intervals interval_index walks on from its hint before it searches instead


def interval_index(a: list[float], x: float, near: int = -1) -> int:
    """bisect.bisect_right(a, x) - 1 clamped to [0, len(a) - 2]: the interval of sorted
    samples `a` that holds x. From an interval `near` at or before the answer (a[near] <= x)
    it walks on at most _WALK intervals (a control tick moves a few); otherwise, or when
    the walk ends short of x, it searches all of a."""
    last = len(a) - 2
    if 0 <= near <= last and a[near] <= x:
        i = near
        stop = near + _WALK if near + _WALK < last else last
        while i < stop and a[i + 1] <= x:
            i += 1
        if i < stop or i == last or x < a[i + 1]:
            return i
    i = bisect.bisect_right(a, x) - 1
    return 0 if i < 0 else (last if i > last else i)


def _cusps(sigma: list[float], seg_pivot: list[bool], direction: list[float]) -> list[float]:
    """Progress of every cusp: where the driving direction reverses (at a sample, or across a
    turn in place; the robot is at rest there either way)."""
    out: list[float] = []
    last = 0.0  # direction of the last driving interval
    for i, (piv, d) in enumerate(zip(seg_pivot, direction)):
        if piv:
            continue
        if last and d != last:
            out.append(sigma[i])
        last = d
    return out


def distances_to_polyline(poly: np.ndarray, xy: np.ndarray, near_index: np.ndarray | None = None,
                          window: int = 400, chunk: int = 1024) -> np.ndarray:
    """Euclidean distance of each point in `xy` (M, 2) to the polyline `poly` (N, 2).

    With `near_index` (a polyline index near each point's closest point, e.g. from the
    run's progress), only `window` segments either side are searched: the same answer for a
    robot within that many samples of its progress, and linear instead of quadratic time.
    """
    a = poly[:-1]
    ab = poly[1:] - a
    len2 = np.einsum("ij,ij->i", ab, ab)
    len2 = np.where(len2 > 0.0, len2, 1.0)
    nseg = len(a)
    out = np.empty(len(xy))
    if near_index is None:
        offsets = None
    else:
        w = min(window, nseg)
        offsets = np.arange(-w, w + 1)
    for start in range(0, len(xy), chunk):
        p = xy[start:start + chunk]
        if offsets is None:
            idx = np.broadcast_to(np.arange(nseg), (len(p), nseg))
        else:
            idx = np.clip(near_index[start:start + chunk, None] + offsets[None, :], 0, nseg - 1)
        sa = a[idx]
        sab = ab[idx]
        ap = p[:, None, :] - sa
        t = np.clip(np.einsum("mij,mij->mi", ap, sab) / len2[idx], 0.0, 1.0)
        diff = ap - t[:, :, None] * sab
        d2 = np.einsum("mij,mij->mi", diff, diff)
        out[start:start + chunk] = np.sqrt(d2.min(axis=1))
    return out
