"""The speed profile under the motors' torque envelope, as TOPP-RA computes it
(ddrt/path/profile.py has the overview and the profile without an envelope).

The state is x = u^2 (u = d(sigma)/dt); on each interval i (between samples i and i + 1) the
wheel torques the dynamic model needs for the interval's constant acceleration are

    tau_j = G_j u_{i+1}^2 + M_j u_i u_{i+1} + N_j u_i^2

exactly. `Constraints` holds those coefficients for every interval of one path with the
checks on them; `envelope_passes` computes, per sample, the velocity limit curve (the largest
u_i for which some u_{i+1} meets every bound), the backward pass (the largest x_i from which
the robot can still brake onto the samples after it: the controllable set) and the forward
pass (sample by sample, the largest x_{i+1} reachable from x_i within it). Both passes are
vectorised where the profile rides its caps; only where it ramps do they step sample by
sample, each step in closed form (every bound is a quadratic in the unknown speed).
"""

from __future__ import annotations

import bisect
import math
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from ddrt.core.envelope import Envelope

__all__ = ["Constraints", "envelope_passes"]


# On interval i (x = u_i, y = u_{i+1}) wheel j needs the torque tau_j = g y^2 + m x y + n x^2
# and turns at w_j = c x. Its bounds: |tau_j| <= T_h (the torque limit at the headroom) and
# -V_h <= tau_j + kv w_j + tau_c tanh(w_j / w_s) <= V_h (the voltage at the headroom, in torque
# units). The acceleration caps: (y^2 - x^2) ia <= 1 and (x^2 - y^2) id <= 1 (ia = 1 / (2 ds A)).
_TOL = 1e-10  # a bound is met when it is exceeded by less than this fraction of itself
_CHUNK = 4096  # intervals per chunk of plain-float coefficients for the sample-by-sample steps


class Constraints:
    """The envelope's bounds on every interval of one path: coefficients and their checks.

    `W[i]` = (g_l, m_l, n_l, c_l, g_r, m_r, n_r, c_r, ia, id) for interval i, from the path's
    geometry (progress, curvature, pivots) and the envelope's model and motor.
    """

    def __init__(self, env: "Envelope", s: np.ndarray, kap: np.ndarray, piv: np.ndarray, turn: np.ndarray,
                 b: float, acc_lim: np.ndarray, dec_lim: np.ndarray, direction: np.ndarray | None = None) -> None:
        self.env = env
        self.th = env.torque_bound_nm
        self.vh = env.voltage_bound_nm
        self.kv = env.emf_damping
        self.tc = env.motor.coulomb_nm
        self.ws = env.motor.coulomb_smoothing_rad_s
        d = np.ones(len(s) - 1) if direction is None else np.asarray(direction, dtype=float)
        self.W = self._coefficients(env, np.diff(s), kap, piv.astype(float), np.asarray(turn, dtype=float), b,
                                    acc_lim, dec_lim, d)
        self._chunks: dict[int, list[list[float]]] = {}

    @staticmethod
    def _coefficients(env: "Envelope", ds: np.ndarray, kap: np.ndarray, p: np.ndarray, turn: np.ndarray, b: float,
                      acc_lim: np.ndarray, dec_lim: np.ndarray, sgn: np.ndarray) -> np.ndarray:
        d = env.dyn
        q = 1.0 - p
        sgn = np.where(p > 0.0, 1.0, sgn)
        # kappa is the robot's curvature; on a reversing interval (sgn = -1) v = -u and
        # omega = kappa v = (sgn kappa) u: with k = sgn kappa (the travel curvature) omega and
        # alpha are as forward, and the terms in v and a (m_k a, mbar a, m_x v omega, the wheels'
        # v) take the sign.
        k0, k1 = sgn * kap[:-1], sgn * kap[1:]
        dk = q * (k1 - k0) / ds
        inv2 = 0.5 / ds
        tb = p * turn / b
        # Generalised forces per unit of y^2, x y and x^2 (docs/model.md: H eta' + h). Driving:
        # v = x, omega = kappa_i x, a = (y^2 - x^2) / (2 ds), alpha = kappa_{i+1} a + dk (x^2 + x y) / 2
        # (what the Path reports: (omega_{i+1} - omega_i) / dt); a pivot: v = 0, omega = turn x / b.
        fv_a = q * (d.m_k * sgn + d.mbar * k1) + d.mbar * tb
        fw_a = q * (d.mbar * sgn + d.I * k1) + d.I * tb
        fv = (fv_a * inv2, 0.5 * d.mbar * dk, q * (0.5 * d.mbar * dk - d.m_x * k0 * k0) - p * d.m_x / (b * b) - fv_a * inv2)
        fw = (fw_a * inv2, 0.5 * d.I * dk, q * (0.5 * d.I * dk + d.m_x * sgn * k0) - fw_a * inv2)
        track = d.L + d.R
        W = np.empty((len(ds), 10))
        for j in range(3):
            W[:, j] = d.r_L / track * (d.R * fv[j] - fw[j])
            W[:, 4 + j] = d.r_R / track * (d.L * fv[j] + fw[j])
        W[:, 3] = q * (sgn - d.L * k0) / d.r_L - tb * d.L / d.r_L
        W[:, 7] = q * (sgn + d.R * k0) / d.r_R + tb * d.R / d.r_R
        with np.errstate(divide="ignore"):
            W[:, 8] = np.where(np.isfinite(acc_lim), inv2 / acc_lim, 0.0)
            W[:, 9] = np.where(np.isfinite(dec_lim), inv2 / dec_lim, 0.0)
        return W

    def row(self, i: int) -> list[float]:
        """Interval i's coefficients as plain floats (chunks are converted once, as the passes reach them)."""
        c = i // _CHUNK
        chunk = self._chunks.get(c)
        if chunk is None:
            chunk = self._chunks[c] = self.W[c * _CHUNK:(c + 1) * _CHUNK].tolist()
        return chunk[i - c * _CHUNK]

    def release(self) -> None:
        """Drop the plain-float chunks (a pass's working copy; 1.3 MB per 4096 intervals)."""
        self._chunks.clear()

    # -- vectorised checks ----------------------------------------------------------------
    def violation(self, x: np.ndarray, y: np.ndarray, i0: int = 0, decel_only: bool = False) -> np.ndarray:
        """Per interval i0.., the largest bound's excess as a fraction of the bound (<= 0: within).

        `decel_only`: only the bounds that limit braking (those a lower u_{i+1} makes worse)."""
        W = self.W[i0:i0 + len(x)]
        th, vh, kv, tc, ws = self.th, self.vh, self.kv, self.tc, self.ws
        out = np.full(len(x), -np.inf)
        for j in (0, 4):
            g, m, n, c = W[:, j], W[:, j + 1], W[:, j + 2], W[:, j + 3]
            tau = g * y * y + m * x * y + n * x * x
            w = c * x
            drive = kv * w + tc * np.tanh(w / ws)
            up = np.maximum((tau - th) / th, (tau + drive - vh) / vh)
            lo = np.maximum((-tau - th) / th, (-tau - drive - vh) / vh)
            if decel_only:
                brakes_low = (g > 0.0) | ((g == 0.0) & (m > 0.0))
                brakes_high = (g < 0.0) | ((g == 0.0) & (m < 0.0))
                up = np.where(brakes_high, up, -np.inf)
                lo = np.where(brakes_low, lo, -np.inf)
            out = np.maximum(out, np.maximum(up, lo))
        dx = y * y - x * x
        if not decel_only:
            out = np.maximum(out, dx * W[:, 8] - 1.0)
        out = np.maximum(out, -dx * W[:, 9] - 1.0)
        return out

    def within(self, x: np.ndarray, y: np.ndarray, i0: int = 0, decel_only: bool = False) -> np.ndarray:
        out = np.empty(len(x), dtype=bool)
        for b0 in range(0, len(x), 1 << 16):
            b1 = min(b0 + (1 << 16), len(x))
            out[b0:b1] = self.violation(x[b0:b1], y[b0:b1], i0 + b0, decel_only) <= _TOL
        return out

    def quadratics(self, idx: np.ndarray, x: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """The bounds of intervals idx at u_i = x as quadratics a2 y^2 + a1 y + a0 <= 0 in y = u_{i+1}."""
        W = self.W[idx]
        th, vh, kv, tc, ws = self.th, self.vh, self.kv, self.tc, self.ws
        out = []
        for j in (0, 4):
            g, m, n, c = W[:, j], W[:, j + 1], W[:, j + 2], W[:, j + 3]
            w = c * x
            drive = kv * w + tc * np.tanh(w / ws)
            up = np.minimum(th, vh - drive)
            lo = np.maximum(-th, -vh - drive)
            out.append((g, m * x, n * x * x - up))
            out.append((-g, -m * x, lo - n * x * x))
        ia, id_ = W[:, 8], W[:, 9]
        out.append((ia, 0.0 * x, -ia * x * x - 1.0))
        out.append((-id_, 0.0 * x, id_ * x * x - 1.0))
        return out

    # -- sample-by-sample steps -------------------------------------------------------------
    def forward_step(self, i: int, x: float, ymax: float) -> float | None:
        """The largest u_{i+1} <= ymax within every bound of interval i from u_i = x, or None."""
        gl, ml, nl, cl, gr, mr, nr, cr, ia, id_ = self.row(i)
        th, vh, kv, tc, ws = self.th, self.vh, self.kv, self.tc, self.ws
        x2 = x * x
        wl = cl * x
        dl = kv * wl + tc * math.tanh(wl / ws)
        wr = cr * x
        dr = kv * wr + tc * math.tanh(wr / ws)
        tol = _TOL * min(th, vh)
        quads = [(gl, ml * x, nl * x2 - min(th, vh - dl), tol), (-gl, -ml * x, max(-th, -vh - dl) - nl * x2, tol),
                 (gr, mr * x, nr * x2 - min(th, vh - dr), tol), (-gr, -mr * x, max(-th, -vh - dr) - nr * x2, tol)]
        if ia > 0.0:
            quads.append((ia, 0.0, -ia * x2 - 1.0, _TOL))
        if id_ > 0.0:
            quads.append((-id_, 0.0, id_ * x2 - 1.0, _TOL))
        return _sup(quads, ymax)

    def backward_step(self, i: int, y: float, zmax: float) -> float:
        """The largest u_i <= zmax from which interval i can brake to u_{i+1} = y within its bounds."""
        gl, ml, nl, cl, gr, mr, nr, cr, ia, id_ = self.row(i)
        th, vh, kv, tc = self.th, self.vh, self.kv, self.tc
        y2 = y * y
        quads = []
        wheels = ((gl, ml, nl, cl), (gr, mr, nr, cr))
        for g, m, n, c in wheels:
            sgn = 1.0 if c > 0.0 else (-1.0 if c < 0.0 else 0.0)
            if g > 0.0 or (g == 0.0 and m > 0.0):  # braking drives tau down: tau >= max(-T_h, -V_h - drive)
                quads.append((-n, -m * y, -g * y2 - th, _TOL * th))
                quads.append((-n, -m * y - kv * c, -g * y2 - vh - tc * sgn, _TOL * vh))
            elif g < 0.0 or m < 0.0:  # braking drives tau up
                quads.append((n, m * y, g * y2 - th, _TOL * th))
                quads.append((n, m * y + kv * c, g * y2 + tc * sgn - vh, _TOL * vh))
        if id_ > 0.0:
            quads.append((id_, 0.0, -id_ * y2 - 1.0, _TOL))
        z = _sup(quads, zmax)
        z = 0.0 if z is None else z
        if self._brakes(i, z, y):
            return z
        # Only at a crawl (a wheel slower than ~20 w_s, where Coulomb friction still builds up):
        # bisect on the exact bounds.
        lo, hi = 0.0, z
        for _ in range(80):
            mid = 0.5 * (lo + hi)
            if self._brakes(i, mid, y):
                lo = mid
            else:
                hi = mid
            if hi - lo <= 1e-15 * hi:
                break
        return lo

    def _brakes(self, i: int, x: float, y: float) -> bool:
        """Whether interval i's braking bounds hold exactly at u_i = x, u_{i+1} = y."""
        gl, ml, nl, cl, gr, mr, nr, cr, ia, id_ = self.row(i)
        th, vh, kv, tc, ws = self.th, self.vh, self.kv, self.tc, self.ws
        for g, m, n, c in ((gl, ml, nl, cl), (gr, mr, nr, cr)):
            tau = g * y * y + m * x * y + n * x * x
            w = c * x
            drive = kv * w + tc * math.tanh(w / ws)
            if g > 0.0 or (g == 0.0 and m > 0.0):
                if -tau - th > _TOL * th or -tau - drive - vh > _TOL * vh:
                    return False
            elif g < 0.0 or m < 0.0:
                if tau - th > _TOL * th or tau + drive - vh > _TOL * vh:
                    return False
        return (x * x - y * y) * id_ - 1.0 <= _TOL


def _y_interval(a2: np.ndarray, a1: np.ndarray, a0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per element, an interval [lo, hi] of y >= 0 within {a2 y^2 + a1 y + a0 <= 0} (lo > hi: none).

    Where the set has two pieces on y >= 0 (a2 < 0, both roots positive) the upper piece is
    taken: a subset, so a velocity limit found with it is never above the true one."""
    lo = np.zeros_like(a0)
    hi = np.full_like(a0, np.inf)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        disc = a1 * a1 - 4.0 * a2 * a0
        sq = np.sqrt(np.maximum(disc, 0.0))
        qq = -0.5 * (a1 + np.copysign(sq, a1))
        ra = qq / a2
        rb = np.where(qq != 0.0, a0 / qq, 0.0)
        r1 = np.minimum(ra, rb)
        r2 = np.maximum(ra, rb)
        lin = -a0 / a1
    pos = a2 > 0.0
    neg = a2 < 0.0
    zer = a2 == 0.0
    real = disc >= 0.0
    m = pos & real
    lo = np.where(m, np.maximum(r1, 0.0), lo)
    hi = np.where(m, r2, hi)
    m = pos & ~real
    lo = np.where(m, np.inf, lo)
    hi = np.where(m, -np.inf, hi)
    m = neg & real & (r2 > 0.0)
    lo = np.where(m, r2, lo)
    m = zer & (a1 > 0.0)
    hi = np.where(m, lin, hi)
    m = zer & (a1 < 0.0)
    lo = np.where(m, np.maximum(lin, 0.0), lo)
    m = zer & (a1 == 0.0) & (a0 > 0.0)
    lo = np.where(m, np.inf, lo)
    hi = np.where(m, -np.inf, hi)
    return lo, hi


def _nonempty(con: Constraints, idx: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Whether interval idx[k] has some u_{i+1} >= 0 within every bound from u_i = x[k]."""
    top = np.zeros(len(idx))
    bottom = np.full(len(idx), np.inf)
    for a2, a1, a0 in con.quadratics(idx, x):
        lo, hi = _y_interval(a2, a1, a0)
        top = np.maximum(top, lo)
        bottom = np.minimum(bottom, hi)
    return top <= bottom * (1.0 + 1e-12)


def _velocity_limit(con: Constraints, ucap: np.ndarray) -> np.ndarray:
    """min(ucap, the largest u_i from which some u_{i+1} meets every bound of interval i)."""
    out = ucap.copy()
    idx = np.arange(len(ucap) - 1)
    fine = np.ones(len(idx), dtype=bool)
    for b0 in range(0, len(idx), 1 << 16):
        b1 = min(b0 + (1 << 16), len(idx))
        fine[b0:b1] = _nonempty(con, idx[b0:b1], ucap[b0:b1])
    bad = idx[~fine]
    if len(bad):
        lo = np.zeros(len(bad))
        hi = ucap[bad].copy()
        for _ in range(64):
            mid = 0.5 * (lo + hi)
            ok = _nonempty(con, bad, mid)
            lo = np.where(ok, mid, lo)
            hi = np.where(ok, hi, mid)
            if np.all(hi - lo <= 1e-13 * hi):
                break
        out[bad] = lo
    return out


def _below(a2: float, a1: float, a0: float, y: float) -> float | None:
    """The largest y' <= y with a2 y'^2 + a1 y' + a0 <= 0 (the quadratic is above 0 at y), or None."""
    if a2 == 0.0:
        if a1 > 0.0:
            r = -a0 / a1
            return min(r, y) if r >= 0.0 else None
        return None
    disc = a1 * a1 - 4.0 * a2 * a0
    if disc < 0.0:
        return None if a2 > 0.0 else y
    sq = math.sqrt(disc)
    qq = -0.5 * (a1 + (sq if a1 >= 0.0 else -sq))
    ra = qq / a2
    rb = a0 / qq if qq != 0.0 else 0.0
    r1, r2 = (ra, rb) if ra <= rb else (rb, ra)
    if a2 > 0.0:
        r = r2 if y > r2 else None
    else:
        r = r1 if r1 < y else None
    if r is None or r < 0.0:
        return None
    return min(r, y)


def _sup(quads: list[tuple[float, float, float, float]], ymax: float) -> float | None:
    """The largest y in [0, ymax] where every a2 y^2 + a1 y + a0 <= tol holds, or None."""
    y = ymax
    for _ in range(2 * len(quads) + 4):
        moved = False
        for a2, a1, a0, tol in quads:
            if (a2 * y + a1) * y + a0 <= tol:
                continue
            yn = _below(a2, a1, a0, y)
            if yn is None:
                return None
            if yn < y:
                y = yn
                moved = True
        if not moved:
            return y
    return y


def envelope_passes(con: Constraints, cap: np.ndarray, start: float | None = None) -> tuple[np.ndarray, int]:
    """u^2 per sample: the velocity limit, then the backward (controllable set) and forward passes.

    `start`: the first sample's speed, kept even where it lies above what the robot can brake from."""
    n = len(cap)
    capv = _velocity_limit(con, cap)
    capv[-1] = cap[-1]
    # ---- backward: the largest u_i <= capv[i] that can still brake onto the samples after it.
    ub = capv.copy()
    bad = np.flatnonzero(~con.within(capv[:-1], capv[1:], decel_only=True)).tolist()
    i = n - 2
    while i >= 0:
        k = bisect.bisect_right(bad, i) - 1
        if k < 0:
            break
        i = bad[k]
        while i >= 0:  # off the curve: step until a step lands on it
            z = con.backward_step(i, float(ub[i + 1]), float(capv[i]))
            if z >= capv[i]:
                i -= 1
                break
            ub[i] = z
            i -= 1
    # ---- forward: the largest u_{i+1} <= ub[i + 1] reachable from u_i.
    u = ub.copy()
    bad = np.flatnonzero(~con.within(ub[:-1], ub[1:])).tolist()
    if start is not None and start != ub[0]:
        u[0] = start
        bad = [0] + [j for j in bad if j > 0]
    fallbacks = 0
    i = 0
    while i < n - 1:
        k = bisect.bisect_left(bad, i)
        if k == len(bad):
            break
        i = bad[k]
        while i < n - 1:
            ymax = float(ub[i + 1])
            y = con.forward_step(i, float(u[i]), ymax)
            if y is None:  # outside the controllable set (a rebuilt profile's start): brake as told
                y = ymax
                fallbacks += 1
            i += 1
            if y >= ymax:
                break
            u[i] = y
    con.release()
    return u * u, fallbacks
