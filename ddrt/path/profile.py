"""The speed profile along a sampled path: the fastest progress rate the robot's motors allow.

The progress rate u = d(sigma)/dt is capped per sample (v_max, per-point caps, lateral
acceleration, omega_max, and v^2 |d(kappa)/ds| <= alpha_max / 2 on driving pieces;
b * omega_max in pivots), with u = 0 at both ends and at both sides of every pivot. Between
two samples the progress has a constant acceleration (u^2 is linear in sigma), which makes
t(sigma), v(t) and at_time exact.

With a motor envelope (`SpeedLimits.envelope`, ddrt/core/envelope.py) the profile is
time-optimal under the motors, as TOPP-RA computes it: the state is x = u^2, and on each
interval i (between samples i and i + 1) the wheel torques the dynamic model needs for the
interval's constant acceleration are

    tau_j = G_j u_{i+1}^2 + M_j u_i u_{i+1} + N_j u_i^2

exactly (the u_i u_{i+1} term is the yaw acceleration the Path reports over a piece whose
curvature changes: alpha = (omega_{i+1} - omega_i) / dt). At sample i each wheel's torque must
lie within what its motor gives at that wheel's speed, with `headroom` of the voltage kept
for feedback, and within the torque limit; the config's accelerations stay caps too. Per
sample, the velocity limit curve is the largest u_i for which some u_{i+1} satisfies all of
that; a backward pass then gives the largest x_i from which the robot can still brake onto
the samples after it (the controllable set), and a forward pass takes, sample by sample, the
largest x_{i+1} reachable from x_i within the controllable set. Both passes are vectorised
where the profile rides its caps; only where it ramps (accelerating out of a rest point,
braking into one) do they step sample by sample, each step in closed form (every bound is
a quadratic in the unknown speed). That part is ddrt/path/envelope_profile.py.

Without an envelope (a path built with no robot in mind), the accelerations are constant caps
(accel, decel, and alpha_max / (2 |kappa|) on driving pieces, b * alpha_max in pivots) and
the passes are the closed-form running minima of `_limited_rise`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Sequence

import numpy as np

from ddrt.params.decl import field_items
from ddrt.path.envelope_profile import Constraints, envelope_passes

if TYPE_CHECKING:
    from ddrt.core.envelope import Envelope


@dataclass(frozen=True, slots=True)
class SpeedLimits:
    """Motion limits the speed profile respects (SI units). `decel` defaults to `accel`.

    `accel` and `decel` may be inf (no cap beyond the motors'). `envelope`, when given, adds
    the motors' torque envelope through the dynamic model; `notes` are what resolving the
    config's limits against the motors found (a cap above what they give), for the path's
    warnings.
    """

    v_max: float = 1.0  # m/s
    accel: float = 1.0  # m/s^2
    lateral_accel: float = 1.5  # m/s^2
    omega_max: float = 4.0  # rad/s
    alpha_max: float = 20.0  # rad/s^2
    decel: float | None = None  # m/s^2
    envelope: "Envelope | None" = None
    notes: tuple[str, ...] = field(default=(), compare=False)

    def __post_init__(self) -> None:
        for f, value in field_items(self):
            if f.name in ("envelope", "notes") or (value is None and f.name == "decel"):
                continue
            unbounded = f.name in ("accel", "decel") and value == math.inf
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) or unbounded):
                raise ValueError(f"SpeedLimits.{f.name}: expected a finite number, got {value!r}")
            if value <= 0.0:
                raise ValueError(f"SpeedLimits.{f.name}: must be > 0, got {value!r}")
            object.__setattr__(self, f.name, float(value))

    @property
    def decel_eff(self) -> float:
        return self.accel if self.decel is None else self.decel

    # Never less than this (m/s^2): a schedule that speeds up never stalls on a rounding zero.
    _MIN_ACCEL = 1e-3

    def accel_at(self, v: float, kappa: float = 0.0, direction: float = 1.0) -> float:
        """The hardest speeding-up (m/s^2 of |v|, finite) allowed at speed v along the robot's
        curvature kappa (`direction` -1: reversing, for v = 0): the accel cap, alpha_max /
        (2 |kappa|) as the profile has it, and the motors' envelope. For schedules that leave
        the profile (a resume ramp, the start stage's release)."""
        k = abs(kappa)
        a = min(self.accel, 0.5 * self.alpha_max / k) if k > 0.0 else self.accel
        if self.envelope is not None:
            a = min(a, max(self.envelope.accel_at(v, kappa, direction), self._MIN_ACCEL))
        return a if math.isfinite(a) else self._MIN_ACCEL

    def turn_accel_at(self, omega: float) -> float:
        """The hardest yaw speeding-up (rad/s^2) in a turn in place at yaw rate omega."""
        a = self.alpha_max
        if self.envelope is not None:
            a = min(a, max(self.envelope.turn_accel_at(omega), self._MIN_ACCEL))
        return a


_BLOCK = 4096  # samples per block of the vectorised passes (bounds their rounding, see below)


def _limited_rise(cap2: np.ndarray, inc: np.ndarray) -> np.ndarray:
    """w[0] = cap2[0], w[i+1] = min(cap2[i+1], w[i] + inc[i]): the profile's forward pass on u^2.

    Unrolled, w[i] = min over j <= i of cap2[j] + (D[i] - D[j]) with D the running sum of
    inc, which numpy evaluates without a Python loop per sample: the minimising j comes from
    a running minimum, and w is then taken as cap2[j] + (D[i] - D[j]) so a small cap is
    not lost against a large D. D restarts at each block of _BLOCK samples (the block's first
    w carries over), so its rounding stays within ~_BLOCK ulps of the increments.
    """
    n = len(cap2)
    w = np.empty(n)
    w[0] = cap2[0]
    for s0 in range(0, n - 1, _BLOCK):
        s1 = min(s0 + _BLOCK, n - 1)
        c = cap2[s0:s1 + 1].copy()
        c[0] = w[s0]
        d = np.concatenate(([0.0], np.cumsum(inc[s0:s1])))
        key = c - d
        run = np.minimum.accumulate(key)
        idx = np.arange(len(c))
        best = np.maximum.accumulate(np.where(key <= run, idx, 0))
        w[s0:s1 + 1] = np.minimum(c[best] + (d - d[best]), c)
    return w


@dataclass(slots=True)
class Profile:
    """Per-sample u, v, omega, t; per-interval acc_u, a, alpha; which samples lie in pivots."""

    u: list[float]
    v: list[float]
    omega: list[float]
    t: list[float]
    acc_u: list[float]
    a: list[float]
    alpha: list[float]
    pivot_sample: list[bool]
    arrays: dict[str, np.ndarray] = field(default_factory=dict)  # the same as numpy arrays
    constraints: "Constraints | None" = None  # the motor envelope's bounds, when there was one



@dataclass(frozen=True)
class CapTerms:
    """The profile's limits from the geometry, one array per limit so that `ddrt path` can name
    the one that binds (ddrt/path/report.py) from the same numbers the profile used. Per
    sample: lateral acceleration, yaw rate, yaw acceleration from the change of curvature (the
    smaller of a sample's two intervals); per interval: the acceleration and braking caps."""

    lateral: np.ndarray  # sqrt(lateral_accel / |kappa|)
    omega: np.ndarray  # omega_max / |kappa|
    curv_rate: np.ndarray  # sqrt(alpha_max / (2 |dkappa/ds|)), pivots excluded
    acc_lim: np.ndarray  # min(accel, alpha_max / (2 |kappa|)); b alpha_max in a pivot
    dec_lim: np.ndarray  # the same with the braking limit
    in_piv: np.ndarray  # samples that are part of a turn in place


def cap_terms(s: np.ndarray, kap: np.ndarray, piv: np.ndarray, lim: SpeedLimits, b: float) -> CapTerms:
    ds = np.diff(s)
    n = len(s)
    absk = np.abs(kap)
    with np.errstate(divide="ignore", invalid="ignore"):
        lateral = np.sqrt(lim.lateral_accel / absk)
        omega = lim.omega_max / absk
        dk = np.abs(np.diff(kap)) / ds
        dk[piv] = 0.0
        kcap = np.sqrt(0.5 * lim.alpha_max / dk)
        kmax = np.maximum(absk[1:], absk[:-1])
        acc_lim = np.minimum(lim.accel, 0.5 * lim.alpha_max / kmax)
        dec_lim = np.minimum(lim.decel_eff, 0.5 * lim.alpha_max / kmax)
    rate = np.full(n, np.inf)
    rate[:-1] = np.minimum(rate[:-1], kcap)
    rate[1:] = np.minimum(rate[1:], kcap)
    in_piv = np.zeros(n, dtype=bool)
    in_piv[:-1] |= piv
    in_piv[1:] |= piv
    acc_lim[piv] = b * lim.alpha_max
    dec_lim[piv] = b * lim.alpha_max
    return CapTerms(lateral, omega, rate, acc_lim, dec_lim, in_piv)


def _caps(s: np.ndarray, kap: np.ndarray, piv: np.ndarray, v_cap: np.ndarray, lim: SpeedLimits,
          b: float, direction: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-sample speed caps, per-interval acceleration caps, and which samples lie in pivots."""
    n = len(s)
    t = cap_terms(s, kap, piv, lim, b)
    # A cap that is not a finite number (a waypoint speed of 1e308 interpolated overflows)
    # is no cap beyond v_max.
    v_cap = np.where(np.isfinite(v_cap), np.maximum(v_cap, 0.0), np.inf)
    cap = np.minimum(np.minimum(v_cap, lim.v_max), t.lateral)
    cap = np.minimum(np.minimum(cap, t.omega), t.curv_rate)
    # Pivot samples: angular speed cap; rest points on both sides of each pivot.
    cap[t.in_piv] = b * lim.omega_max
    edge = np.zeros(n, dtype=bool)
    edge[:-1] |= piv & ~np.concatenate(([False], piv[:-1]))  # first sample of a pivot
    edge[1:] |= piv & ~np.concatenate((piv[1:], [False]))  # last sample of a pivot
    cap[edge] = 0.0
    if direction is not None and len(direction) > 1:
        cap[1:-1][direction[1:] != direction[:-1]] = 0.0  # a cusp: at rest where the direction flips
    cap[0] = cap[-1] = 0.0
    return cap, t.acc_lim, t.dec_lim, t.in_piv


def speed_profile(sigma: Sequence[float], kappa: Sequence[float], seg_pivot: Sequence[bool],
                  turn: Sequence[float], v_cap: np.ndarray, limits: SpeedLimits, pivot_radius: float,
                  envelope: "Envelope | None" = None, keep: "tuple[int, np.ndarray] | None" = None,
                  direction: "np.ndarray | None" = None) -> Profile:
    """The time-optimal profile under `limits` for samples at progress `sigma` (see the module doc).

    `envelope` (default `limits.envelope`) adds the motors' torque envelope. `keep` = (first,
    u): samples up to `first` keep the progress rates u (a profile being followed), and the
    profile from there on starts at u[first] (braking as hard as the passes ask when the
    robot is already faster than the limits can brake from). `direction` (per interval, -1 where
    the path is driven backwards, default all +1): the profile rests at every cusp and v, a and
    omega take the sign (ddrt/path/sampled.py's docstring)."""
    lim, b = limits, pivot_radius
    env = lim.envelope if envelope is None else envelope
    s = np.asarray(sigma, dtype=float)
    kap = np.asarray(kappa, dtype=float)
    piv = np.asarray(seg_pivot, dtype=bool)
    turn_arr = np.asarray(turn, dtype=float)
    ds = np.diff(s)
    dirs = np.ones(len(ds)) if direction is None else np.asarray(direction, dtype=float)
    cap, acc_lim, dec_lim, in_piv = _caps(s, kap, piv, np.asarray(v_cap, dtype=float), lim, b, dirs)
    first, u_start = 0, None
    if keep is not None:
        first = int(keep[0])
        u_old = np.asarray(keep[1], dtype=float)
        if not 0 <= first < len(s) - 1:
            raise ValueError(f"speed_profile: keep from sample {first} of {len(s)}")
        u_start = float(u_old[first])
    constraints = None
    if env is None:
        tail = cap[first:].copy()
        if u_start is not None:
            tail[0] = u_start
        # Forward (accel) then backward (decel) pass, on w = u^2: w[i+1] = min(cap^2, w[i] + 2 acc ds).
        w = _limited_rise(tail * tail, 2.0 * acc_lim[first:] * ds[first:])
        w = _limited_rise(w[::-1], (2.0 * dec_lim[first:] * ds[first:])[::-1])[::-1]
        if u_start is not None:
            w[0] = u_start * u_start
    else:
        constraints = Constraints(env, s, kap, piv, turn_arr, b, acc_lim, dec_lim, dirs)
        if first == 0 and u_start is None:
            w, _ = envelope_passes(constraints, cap)
        else:
            tail_con = Constraints(env, s[first:], kap[first:], piv[first:], turn_arr[first:], b,
                                   acc_lim[first:], dec_lim[first:], dirs[first:])
            tail = cap[first:].copy()
            tail[0] = u_start
            w, _ = envelope_passes(tail_con, tail, start=u_start)
    if first:
        w = np.concatenate((u_old[:first] ** 2, w))
    return _finish(s, kap, piv, turn_arr, b, w, in_piv, constraints, dirs)


def envelope_excess(sigma: Sequence[float], kappa: Sequence[float], seg_pivot: Sequence[bool],
                    turn: Sequence[float], u: np.ndarray, limits: SpeedLimits, pivot_radius: float,
                    envelope: "Envelope", first: int = 0, direction: "np.ndarray | None" = None) -> float:
    """How far the profile u goes beyond `envelope` (and the acceleration caps of `limits`) on the
    intervals from `first` on, as a fraction of the bound exceeded (<= 0: within)."""
    s = np.asarray(sigma, dtype=float)
    kap = np.asarray(kappa, dtype=float)
    piv = np.asarray(seg_pivot, dtype=bool)
    dirs = np.ones(len(s) - 1) if direction is None else np.asarray(direction, dtype=float)
    _, acc_lim, dec_lim, _ = _caps(s, kap, piv, np.full(len(s), np.inf), limits, pivot_radius)
    con = Constraints(envelope, s[first:], kap[first:], piv[first:], np.asarray(turn, dtype=float)[first:],
                      pivot_radius, acc_lim[first:], dec_lim[first:], dirs[first:])
    uu = np.asarray(u, dtype=float)[first:]
    if len(uu) < 2:
        return -math.inf
    worst = -math.inf
    for b0 in range(0, len(uu) - 1, 1 << 16):
        b1 = min(b0 + (1 << 16), len(uu) - 1)
        worst = max(worst, float(con.violation(uu[b0:b1], uu[b0 + 1:b1 + 1], b0).max()))
    return worst


def _finish(s: np.ndarray, kap: np.ndarray, piv: np.ndarray, turn_arr: np.ndarray, b: float, w: np.ndarray,
            in_piv: np.ndarray, constraints: "Constraints | None", dirs: np.ndarray | None = None) -> Profile:
    """Times, speeds and accelerations of the profile u^2 = w."""
    ds = np.diff(s)
    n = len(s)
    u_arr = np.sqrt(w)
    us = u_arr[:-1] + u_arr[1:]
    if not np.all(us > 0.0):
        # Every piece has an interior sample with u > 0 unless the limits leave u^2 below
        # the smallest float (a radius of 1e-300 m, a speed of 1e-200 m/s).
        i = int(np.argmin(us > 0.0))
        raise ValueError(f"the speed profile cannot move at progress {float(s[i]):.6g} m: the limits allow "
                         "no speed there (a radius or speed too small to represent)")
    t_arr = np.concatenate(([0.0], np.cumsum(2.0 * ds / us)))
    acc_arr = (u_arr[1:] * u_arr[1:] - u_arr[:-1] * u_arr[:-1]) / (2.0 * ds)
    # Per-sample v and omega. A pivot's edge samples are rest points (v = omega = 0).
    if dirs is None:
        dirs = np.ones(n - 1)
    sgn = np.concatenate((dirs, dirs[-1:]))  # a sample takes its own interval's direction (u = 0 at cusps)
    v_arr = np.where(in_piv, 0.0, sgn * u_arr)
    # In a pivot, a sample takes the turn of its own interval, the last sample its left one's.
    j = np.arange(n)
    own = np.zeros(n, dtype=bool)
    own[:-1] = piv
    j = np.where(own, j, j - 1).clip(0, max(n - 2, 0))
    omega_arr = np.where(in_piv, turn_arr[j] * u_arr / b, v_arr * kap)
    a_arr = np.where(piv, 0.0, dirs * acc_arr)
    alpha_arr = (omega_arr[1:] - omega_arr[:-1]) / (t_arr[1:] - t_arr[:-1])
    u, v, omega, t = u_arr.tolist(), v_arr.tolist(), omega_arr.tolist(), t_arr.tolist()
    acc_u, a, alpha = acc_arr.tolist(), a_arr.tolist(), alpha_arr.tolist()
    in_pivl = in_piv.tolist()
    arrays = {"u": u_arr, "v": v_arr, "omega": omega_arr, "t": t_arr, "acc_u": acc_arr, "a": a_arr,
              "alpha": alpha_arr, "pivot_sample": in_piv}
    return Profile(u, v, omega, t, acc_u, a, alpha, in_pivl, arrays, constraints)
