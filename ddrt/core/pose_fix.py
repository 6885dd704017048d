"""Absolute pose fixes: checked, gated and fused with their latency into the `map` frame.

Two frames:
- `odom`: the estimator's dead reckoning, continuous; a fix never moves it.
- `map`: a second dead reckoning of the same steps (`MapFrame`), corrected by each accepted
  fix, which also teaches it the encoder's and the gyro's scale errors and the bias error,
  so that between fixes it drifts less than odom. Before the first fix the two are the same.
  The correction map -> odom (a rigid transform) is what takes odom's pose onto map's.

A fix (x, y, theta in `map`, a 3x3 covariance, and the time at which it was true, on the
loop's clock) is compared with the map pose of its own time: the history
(ddrt/core/uncertainty.py) holds the map pose of every tick, the covariance saved nearest
before the fix is carried to it, and the transition from then to now carries the correction
to the present (a delayed-measurement Kalman update of the 6-state error: pose, scales,
bias). A fix whose Mahalanobis distance exceeds the chi-square gate (3 degrees of freedom,
estimator.fix_gate_chi2) is an outlier: counted, and nothing changes. docs/estimation.md
has the equations.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ddrt.errors import DdrtError
from ddrt.core.uncertainty import N, Tracker, phi, propagate
from ddrt.core.wrap import wrap_angle
from ddrt.params.numbers import POSE_BOUND_M

COV_BOUND = 1e6  # a variance beyond this (m^2, rad^2) says nothing
SYMMETRY_TOL = 1e-9  # relative: cov[i][j] and cov[j][i] may differ by this much of the largest entry
FIELDS = ("x", "y", "theta", "cov", "stamp")
# Outliers in a row after which the next fix is believed whole (re-anchors map), as the
# sensors' gate re-syncs after estimator.max_rejects: a map that is wrong (a kidnapped robot,
# a drift the error model does not allow for) must not reject every fix from then on.
MAX_OUTLIERS_IN_A_ROW = 5


class FixError(DdrtError, ValueError):
    """A pose fix or pose that cannot be used; `field` names the request's key."""

    def __init__(self, field: str, message: str) -> None:
        super().__init__(f"{field}: {message}")
        self.field = field


def _number(field: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise FixError(field, f"expected a number, got {value!r:.40}")
    try:
        v = float(value)
    except OverflowError:
        raise FixError(field, "expected a finite number, got an integer beyond any float") from None
    if not math.isfinite(v):
        raise FixError(field, f"expected a finite number, got {v!r}")
    return v


def parse_cov(value: object, field: str = "cov") -> list[float]:
    """A 3x3 covariance of (x, y, theta) in m^2, m rad, rad^2 as 9 floats row by row, from a
    3x3 nested list or 9 numbers; FixError unless finite, symmetric and positive definite."""
    if isinstance(value, (list, tuple)) and len(value) == 3 and all(isinstance(r, (list, tuple)) for r in value):
        if any(len(r) != 3 for r in value):  # type: ignore[arg-type]
            raise FixError(field, "expected 3 rows of 3 numbers (or 9 numbers, row by row)")
        flat = [v for r in value for v in r]  # type: ignore[union-attr]
    elif isinstance(value, (list, tuple)) and len(value) == 9:
        flat = list(value)
    else:
        raise FixError(field, f"expected a 3x3 matrix (3 rows of 3 numbers, or 9 numbers), got {value!r:.60}")
    c = [_number(f"{field}[{i // 3}][{i % 3}]", v) for i, v in enumerate(flat)]
    big = max(abs(v) for v in c)
    for i in range(3):
        for j in range(i + 1, 3):
            if abs(c[i * 3 + j] - c[j * 3 + i]) > SYMMETRY_TOL * big:
                raise FixError(field, f"not symmetric: [{i}][{j}] = {c[i * 3 + j]:g} but [{j}][{i}] = {c[j * 3 + i]:g}")
    for i in range(3):
        if c[i * 4] > COV_BOUND:
            raise FixError(field, f"variance [{i}][{i}] = {c[i * 4]:g} is beyond {COV_BOUND:g}")
    if not _positive_definite(c):
        raise FixError(field, "not positive definite (every variance > 0, and no correlation of 1 or more)")
    for i in range(3):  # exactly symmetric from here on
        for j in range(i + 1, 3):
            c[j * 3 + i] = c[i * 3 + j]
    return c


def _positive_definite(c: list[float]) -> bool:
    """Cholesky of a symmetric 3x3 (row-major), with a margin against rounding."""
    a00 = c[0]
    if not a00 > 0.0:
        return False
    l00 = math.sqrt(a00)
    l10 = c[3] / l00
    l20 = c[6] / l00
    d1 = c[4] - l10 * l10
    if not d1 > 1e-12 * c[4]:
        return False
    l11 = math.sqrt(d1)
    l21 = (c[7] - l20 * l10) / l11
    d2 = c[8] - l20 * l20 - l21 * l21
    return d2 > 1e-12 * c[8]


def parse_pose(req: dict[str, Any]) -> tuple[float, float, float]:
    """x, y, theta of a request (m, m, rad; theta wrapped); FixError naming the field."""
    x, y, theta = (_number(k, req.get(k)) if k in req else _missing(k) for k in ("x", "y", "theta"))
    for name, v in (("x", x), ("y", y)):
        if abs(v) > POSE_BOUND_M:
            raise FixError(name, f"{v:g} is beyond +-{POSE_BOUND_M:g} m")
    if abs(theta) > 1e3:
        raise FixError("theta", f"{theta:g} rad is not an angle a fix would give")
    return x, y, wrap_angle(theta)


def _missing(field: str) -> float:
    raise FixError(field, "missing")


@dataclass(frozen=True, slots=True)
class PoseFix:
    """A pose in `map` (m, m, rad), its covariance (9 floats, row by row), and when it was true."""

    x: float
    y: float
    theta: float
    cov: tuple[float, ...]
    stamp: float


def parse_fix(req: dict[str, Any], now: float) -> PoseFix:
    """The fix in a `pose_fix` request ({x, y, theta, cov, stamp}; stamp defaults to `now`);
    FixError naming the field. Whether the stamp lies within the history is the estimator's
    check (MapFrame.check_stamp)."""
    extra = sorted(k for k in req if k not in FIELDS + ("cmd", "id"))
    if extra:
        raise FixError(extra[0], f"unknown key (a fix takes {', '.join(FIELDS)})")
    x, y, theta = parse_pose(req)
    if "cov" not in req:
        raise FixError("cov", "missing: a fix needs its 3x3 covariance (m^2, m rad, rad^2)")
    cov = parse_cov(req["cov"])
    stamp = _number("stamp", req["stamp"]) if req.get("stamp") is not None else now
    return PoseFix(x, y, theta, tuple(cov), stamp)


@dataclass(slots=True)
class FixCounters:
    fused: int = 0
    outliers: int = 0  # beyond the gate: counted, not fused
    outliers_in_a_row: int = 0
    reanchors: int = 0  # fixes believed whole after MAX_OUTLIERS_IN_A_ROW outliers in a row
    last_d2: float = math.nan  # the last fix's squared Mahalanobis distance
    last_stamp: float = -math.inf  # the newest stamp fused


class MapFrame:
    """The pose in `map`: its own dead reckoning of the odometry's steps, with the scale and
    bias errors the fixes have taught it taken out, corrected by each fix.

    Per tick (`step`): th_m += dth (1 + g) + b dt, and the distance ds (1 + s) along the
    midpoint heading, where (s, g, b) are the learnt corrections of the encoder's scale, the
    gyro's scale and its bias (zero until a fix). The correction map -> odom (`correction`)
    is what takes the odometry's pose onto this one: it moves at a fix (a jump, counted by
    `jumps`) and slowly as the learnt corrections act."""

    def __init__(self, gate_chi2: float) -> None:
        self.gate_chi2 = gate_chi2
        self.x = self.y = self.th = 0.0  # the map pose now
        self.xo = self.yo = self.tho = 0.0  # the odometry's pose now
        self.s = self.g = self.b = 0.0  # learnt corrections: encoder scale, gyro scale, bias (rad/s)
        self.jumps = 0
        self.anchored = False  # does anything say where map is (a pose set, or a first fix)?
        self.counters = FixCounters()

    def regate(self, gate_chi2: float) -> None:
        """A reload's outlier gate (estimator.fix_gate_chi2)."""
        self.gate_chi2 = gate_chi2

    def history_restarted(self, t: float) -> None:
        """The pose history starts again at `t`: a fix stamped before it cannot be placed."""
        self.counters.last_stamp = t

    def reset(self, pose: tuple[float, float, float], anchored: bool = True) -> None:
        """The map and odom frames are the same again, at `pose` (a pose set or a reset).
        `anchored`: the pose is where the robot is in map (a pose set); otherwise (a start
        or a reset) nothing has said where map is, and the first fix will (`fuse`)."""
        self.anchored = anchored
        self.x, self.y, self.th = pose
        self.xo, self.yo, self.tho = pose
        self.s = self.g = self.b = 0.0
        self.jumps += 1
        self.counters.last_stamp = -math.inf

    def step(self, track: Tracker, t: float, dt: float, ds: float, dth: float,
             xo: float, yo: float, tho: float) -> None:
        """One tick of the odometry (distance ds, turn dth over dt, ending at (xo, yo, tho))."""
        shrink = track.take_bias_shrink()
        if shrink != 1.0:  # the estimator re-learnt the bias at rest
            self.b *= shrink
        dthm = dth * (1.0 + self.g) + self.b * dt
        dsm = ds * (1.0 + self.s)
        half = self.th + 0.5 * dthm
        dx = dsm * math.cos(half)
        dy = dsm * math.sin(half)
        self.x += dx
        self.y += dy
        self.th += dthm
        self.xo, self.yo, self.tho = xo, yo, tho
        track.step(t, self.x, self.y, self.th, dt, dx, dy, dthm, tho - self.th)

    def correction(self) -> tuple[float, float, float]:
        """map -> odom as a transform (x, y, theta): map pose = it composed with odom's."""
        cth = self.th - self.tho
        c, s = math.cos(cth), math.sin(cth)
        return self.x - (c * self.xo - s * self.yo), self.y - (s * self.xo + c * self.yo), cth

    def check_stamp(self, track: Tracker, stamp: float) -> None:
        """FixError unless `stamp` lies within the odometry's history and after the last fix."""
        h = track.hist
        if h.n == 0:
            raise FixError("stamp", "no odometry yet: the estimator has not started")
        now = h.t[h.head]
        oldest = h.t[h.slot(h.oldest)]
        if stamp > now + 1e-9:
            raise FixError("stamp", f"{stamp:.6f} s is in the future: the loop's clock is at {now:.6f} s")
        if stamp < self.counters.last_stamp:
            raise FixError("stamp", f"{stamp:.6f} s is before the last fix fused ({self.counters.last_stamp:.6f} s): "
                                    "fixes are fused in time order")
        if stamp < oldest:
            raise FixError("stamp", f"{stamp:.6f} s is older than the history, which reaches back to {oldest:.6f} s "
                                    f"({now - oldest:.2f} s; estimator.fix_history_s)")

    def fuse(self, track: Tracker, fix: PoseFix) -> dict[str, Any]:
        """Gate and fuse `fix` (its stamp checked first); returns what happened, for the reply.

        The Kalman update of the error state at the fix's time (pose, scale and bias errors),
        carried to every later moment the history holds: the covariances saved since, the
        map poses recorded since (so a later fix compares with corrected ones), and the
        present, whose learnt corrections take the scale and bias parts."""
        self.check_stamp(track, fix.stamp)
        h = track.hist
        a_f = h.at_time(fix.stamp)
        if not self.anchored:
            return self._anchor(track, fix, a_f)
        if self.counters.outliers_in_a_row >= MAX_OUTLIERS_IN_A_ROW:
            self.counters.reanchors += 1
            return self._anchor(track, fix, a_f)
        k_f = h.find(fix.stamp)
        saved = track.saved_before(k_f)
        if saved is None:  # not expected: a save is made at every reset and propagation
            raise FixError("stamp", "no covariance saved that far back: try a newer stamp")
        k_b, p_b = saved
        p_f = list(p_b)  # the covariance at the fix's time: the saved one carried to it
        g, dt = phi(h.state(k_b), a_f)
        propagate(p_f, g, 1.0, 0.0, dt, track.model)
        pf = np.array(p_f).reshape(N, N)
        y = np.array([fix.x - a_f[1], fix.y - a_f[2], wrap_angle(fix.theta - a_f[3])])
        s_inv = np.linalg.inv(pf[:3, :3] + np.array(fix.cov).reshape(3, 3))
        d2 = float(y @ s_inv @ y)
        c = self.counters
        c.last_d2 = d2
        if not d2 <= self.gate_chi2:
            c.outliers += 1
            c.outliers_in_a_row += 1
            return {"fused": False, "outlier": True, "d2": d2, "gate": self.gate_chi2, "innovation": y.tolist()}
        c.outliers_in_a_row = 0
        now_k = h.n - 1
        if track.k_map != now_k:
            track.advance_map(now_k)
        gain = pf[:, :3] @ s_inv  # K at the fix's time
        delta_f = gain @ y  # the error state's correction then
        m_f = gain @ pf[:3, :]  # and what it takes off the covariance: K H P

        def corrected(ks: int, saved_p: list[float]) -> list[float]:
            ph = _phi_matrix(phi(a_f, h.state(ks))[0])
            p = np.array(saved_p).reshape(N, N) - ph @ m_f @ ph.T
            return (0.5 * (p + p.T)).ravel().tolist()

        track.correct_saved(fix.stamp, now_k, corrected)
        delta = self._shift_history(h, a_f, k_f, delta_f)
        self.x, self.y, self.th = h.x[h.head], h.y[h.head], h.th[h.head]
        self.s += float(delta_f[3])
        self.g += float(delta_f[4])
        self.b += float(delta_f[5])
        self.jumps += 1
        c.fused += 1
        c.last_stamp = fix.stamp
        return {"fused": True, "outlier": False, "anchored": False, "d2": d2, "gate": self.gate_chi2,
                "innovation": y.tolist(),
                "correction": delta, "learnt": {"encoder_scale": self.s, "gyro_scale": self.g, "gyro_bias": self.b}}

    def _anchor(self, track: Tracker, fix: PoseFix, a_f: tuple[float, ...]) -> dict[str, Any]:
        """The first fix of an unanchored map: it says where map is. The map pose becomes the
        fix carried to now by the motion since its time, known to the fix's covariance; the
        history starts again there (a later fix must be newer than this moment)."""
        h = track.hist
        now = (h.x[h.head], h.y[h.head], h.th[h.head])
        c, s = math.cos(a_f[3]), math.sin(a_f[3])
        ex, ey = now[0] - a_f[1], now[1] - a_f[2]
        rel = (c * ex + s * ey, -s * ex + c * ey, now[2] - a_f[3])  # the motion since, in the body frame then
        c, s = math.cos(fix.theta), math.sin(fix.theta)
        pose = (fix.x + c * rel[0] - s * rel[1], fix.y + s * rel[0] + c * rel[1], fix.theta + rel[2])
        jump = [pose[0] - now[0], pose[1] - now[1], wrap_angle(pose[2] - now[2])]
        t_now = h.t[h.head]
        track.reset(t_now, pose, list(fix.cov))
        self.x, self.y, self.th = pose
        self.anchored = True
        self.jumps += 1
        self.counters.fused += 1
        self.counters.outliers_in_a_row = 0
        self.counters.last_d2 = math.nan
        self.counters.last_stamp = t_now
        return {"fused": True, "outlier": False, "anchored": True, "d2": None, "gate": self.gate_chi2,
                "correction": jump, "learnt": {"encoder_scale": self.s, "gyro_scale": self.g, "gyro_bias": self.b}}

    @staticmethod
    def _shift_history(h: Any, a_f: tuple[float, ...], k_f: int, delta_f: np.ndarray) -> list[float]:
        """Every map pose recorded after the fix's time moves by the correction carried to
        it (Phi from then, applied to delta_f); returns the present's."""
        dxf, dyf, dthf, dsf, dgf, dbf = (float(v) for v in delta_f)
        out = [0.0, 0.0, 0.0]
        first = k_f if h.t[h.slot(k_f)] >= a_f[0] else k_f + 1  # a fix as new as a tick moves that tick
        for k in range(first, h.n):
            g02, g03, g04, g05, g12, g13, g14, g15, g24, g25 = phi(a_f, h.state(k))[0]
            i = h.slot(k)
            out = [dxf + g02 * dthf + g03 * dsf + g04 * dgf + g05 * dbf,
                   dyf + g12 * dthf + g13 * dsf + g14 * dgf + g15 * dbf,
                   dthf + g24 * dgf + g25 * dbf]
            h.x[i] += out[0]
            h.y[i] += out[1]
            h.th[i] += out[2]
        return out


def _phi_matrix(g: tuple[float, ...]) -> np.ndarray:
    """Phi = I + G as a 6x6 array."""
    a02, a03, a04, a05, a12, a13, a14, a15, g24, g25 = g
    m = np.eye(N)
    m[0, 2:] = (a02, a03, a04, a05)
    m[1, 2:] = (a12, a13, a14, a15)
    m[2, 4:] = (g24, g25)
    return m
