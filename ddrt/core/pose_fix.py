"""Absolute pose fixes: checked, gated and fused with their latency into the `map` frame.

Two frames:
- `odom`: the estimator's dead reckoning, continuous; a fix never moves it.
- `map`: odom composed with a correction map -> odom (`MapFrame`: a rigid transform), which
  each accepted fix updates. Before the first fix the two are the same.

A fix (x, y, theta in `map`, a 3x3 covariance, and the time at which it was true, on the
loop's clock) is compared with the map pose of its own time: the odometry's history
(ddrt/core/uncertainty.py) gives the odometry's pose then, the covariance saved nearest
before it is carried to it, and the transition from then to now carries the correction to
the present (a delayed-measurement Kalman update). The update is a Schmidt ("consider")
one: it corrects the pose and the pose's correlations with the scale and bias errors, but
does not estimate those errors, so the odometry stays what it was. A fix whose Mahalanobis
distance exceeds the chi-square gate (3 degrees of freedom, estimator.fix_gate_chi2) is an
outlier: counted, and nothing changes. docs/estimation.md has the equations.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ddrt.core.uncertainty import N, Tracker, phi, propagate
from ddrt.core.wrap import wrap_angle

POSE_BOUND_M = 1e6  # |x|, |y| beyond this is no place on a floor
COV_BOUND = 1e6  # a variance beyond this (m^2, rad^2) says nothing
SYMMETRY_TOL = 1e-9  # relative: cov[i][j] and cov[j][i] may differ by this much of the largest entry
FIELDS = ("x", "y", "theta", "cov", "stamp")


class FixError(ValueError):
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
    last_d2: float = math.nan  # the last fix's squared Mahalanobis distance
    last_stamp: float = -math.inf  # the newest stamp fused


class MapFrame:
    """The correction map -> odom: map pose = (cx, cy, cth) composed with the odometry's."""

    def __init__(self, gate_chi2: float) -> None:
        self.gate_chi2 = gate_chi2
        self.cx = self.cy = self.cth = 0.0
        self.counters = FixCounters()

    def reset(self) -> None:
        """The map and odom frames are the same again (a pose set or a reset)."""
        self.cx = self.cy = self.cth = 0.0
        self.counters.last_stamp = -math.inf

    def to_map(self, x: float, y: float, th: float) -> tuple[float, float, float]:
        c, s = math.cos(self.cth), math.sin(self.cth)
        return self.cx + c * x - s * y, self.cy + s * x + c * y, th + self.cth

    def check_stamp(self, track: Tracker, stamp: float) -> None:
        """FixError unless `stamp` lies within the odometry's history and after the last fix."""
        h = track.hist
        if h.n == 0:
            raise FixError("stamp", "no odometry yet: the estimator has not started")
        now = h.t[h.head]
        oldest = h.t[h.slot(h.oldest)]
        if stamp > now + 1e-9:
            raise FixError("stamp", f"{stamp:.6f} s is in the future: the loop's clock is at {now:.6f} s")
        if stamp < oldest:
            raise FixError("stamp", f"{stamp:.6f} s is older than the history, which reaches back to {oldest:.6f} s "
                                    f"({now - oldest:.2f} s; estimator.fix_history_s)")
        if stamp < self.counters.last_stamp:
            raise FixError("stamp", f"{stamp:.6f} s is before the last fix fused ({self.counters.last_stamp:.6f} s): "
                                    "fixes are fused in time order")

    def fuse(self, track: Tracker, fix: PoseFix) -> dict[str, Any]:
        """Gate and fuse `fix` (its stamp checked first); returns what happened, for the reply."""
        self.check_stamp(track, fix.stamp)
        h = track.hist
        model = track.model
        a_f = h.at_time(fix.stamp)
        k_f = h.find(fix.stamp)
        saved = track.saved_before(k_f)
        if saved is None:  # not expected: a save is made at every reset and propagation
            raise FixError("stamp", "no covariance saved that far back: try a newer stamp")
        k_b, p_b = saved
        # The covariance at the fix's time: the saved one carried to it.
        p_f = list(p_b)
        g, dt = phi(h.state(k_b), a_f)
        propagate(p_f, g, math.cos(self.cth), math.sin(self.cth), dt, model)
        pf = np.array(p_f).reshape(N, N)
        xm, ym, thm = self.to_map(a_f[1], a_f[2], a_f[3])
        y = np.array([fix.x - xm, fix.y - ym, wrap_angle(fix.theta - thm)])
        s_mat = pf[:3, :3] + np.array(fix.cov).reshape(3, 3)
        s_inv = np.linalg.inv(s_mat)
        d2 = float(y @ s_inv @ y)
        c = self.counters
        c.last_d2 = d2
        if not d2 <= self.gate_chi2:
            c.outliers += 1
            return {"fused": False, "outlier": True, "d2": d2, "gate": self.gate_chi2,
                    "innovation": y.tolist()}
        # Bring the map covariance to now, then the delayed update of every covariance the
        # fix's time precedes: the present's and those saved after it.
        now_k = h.n - 1
        if track.k_map != now_k:
            track.advance_map(now_k)
        cs = (math.cos(self.cth), math.sin(self.cth))
        pf_cols = pf[:, :3]
        delta = None
        for i, ks in enumerate(track.saved_k):
            if ks < 0 or ks < h.oldest or h.t[h.slot(ks)] < fix.stamp:
                continue
            cmat = _phi_matrix(phi(a_f, h.state(ks))[0], *cs) @ pf_cols  # cov(error then, innovation)
            m = cmat @ s_inv @ cmat.T
            m[3:, 3:] = 0.0  # Schmidt: the scale and bias errors are considered, not estimated
            p = np.array(track.saved_p[i]).reshape(N, N) - m
            track.saved_p[i][:] = (0.5 * (p + p.T)).ravel().tolist()
            if ks == now_k:
                delta = cmat[:3] @ s_inv @ y
                track.p_map[:] = track.saved_p[i]
        if delta is None:  # not expected: advance_map saved the present
            raise FixError("stamp", "internal: the present's covariance was not saved")
        track._publish()
        # The present's map pose moves by delta; the correction is what maps odom onto it.
        xo, yo, tho = h.x[h.head], h.y[h.head], h.th[h.head]
        xm, ym, thm = self.to_map(xo, yo, tho)
        xm += float(delta[0])
        ym += float(delta[1])
        thm += float(delta[2])
        self.cth = thm - tho
        cc, ss = math.cos(self.cth), math.sin(self.cth)
        self.cx = xm - (cc * xo - ss * yo)
        self.cy = ym - (ss * xo + cc * yo)
        track.c, track.s = cc, ss
        c.fused += 1
        c.last_stamp = fix.stamp
        return {"fused": True, "outlier": False, "d2": d2, "gate": self.gate_chi2, "innovation": y.tolist(),
                "correction": [float(delta[0]), float(delta[1]), float(delta[2])]}


def _phi_matrix(g: tuple[float, ...], c: float, s: float) -> np.ndarray:
    """Phi = I + G as a 6x6 array (position rows turned into the map frame)."""
    a02, a03, a04, a05, a12, a13, a14, a15, g24, g25 = g
    m = np.eye(N)
    m[0, 2:] = (c * a02 - s * a12, c * a03 - s * a13, c * a04 - s * a14, c * a05 - s * a15)
    m[1, 2:] = (s * a02 + c * a12, s * a03 + c * a13, s * a04 + c * a14, s * a05 + c * a15)
    m[2, 4:] = (g24, g25)
    return m
