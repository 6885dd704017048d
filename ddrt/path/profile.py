"""The speed profile along a sampled path: the fastest progress rate the motion limits allow.

The progress rate u = d(sigma)/dt is capped per sample (v_max, per-point caps, lateral
acceleration, omega_max, and v^2 |d(kappa)/ds| <= alpha_max / 2 on driving pieces;
b * omega_max in pivots), then limited by forward (accel) and backward (decel) passes, with
u = 0 at both ends and at both sides of every pivot. Between two samples the progress has a
constant acceleration (u^2 is linear in sigma), which makes t(sigma), v(t) and at_time exact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Sequence

import numpy as np


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


def speed_profile(sigma: Sequence[float], kappa: Sequence[float], seg_pivot: Sequence[bool],
                  turn: Sequence[float], v_cap: np.ndarray, limits: SpeedLimits, pivot_radius: float) -> Profile:
    """The time-optimal profile under `limits` for samples at progress `sigma` (see the module doc)."""
    lim, b = limits, pivot_radius
    s = np.asarray(sigma)
    kap = np.asarray(kappa)
    piv = np.asarray(seg_pivot)
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
    # Forward (accel) then backward (decel) pass, on w = u^2: w[i+1] = min(cap^2, w[i] + 2 acc ds).
    w = _limited_rise(cap * cap, 2.0 * acc_lim * ds)
    w = _limited_rise(w[::-1], (2.0 * dec_lim * ds)[::-1])[::-1]
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
    v_arr = np.where(in_piv, 0.0, u_arr)
    turn_arr = np.asarray(turn, dtype=float)
    # In a pivot, a sample takes the turn of its own interval, the last sample its left one's.
    j = np.arange(n)
    own = np.zeros(n, dtype=bool)
    own[:-1] = piv
    j = np.where(own, j, j - 1).clip(0, max(n - 2, 0))
    omega_arr = np.where(in_piv, turn_arr[j] * u_arr / b, u_arr * kap)
    a_arr = np.where(piv, 0.0, acc_arr)
    alpha_arr = (omega_arr[1:] - omega_arr[:-1]) / (t_arr[1:] - t_arr[:-1])
    u, v, omega, t = u_arr.tolist(), v_arr.tolist(), omega_arr.tolist(), t_arr.tolist()
    acc_u, a, alpha = acc_arr.tolist(), a_arr.tolist(), alpha_arr.tolist()
    in_pivl = in_piv.tolist()
    arrays = {"u": u_arr, "v": v_arr, "omega": omega_arr, "t": t_arr, "acc_u": acc_arr, "a": a_arr,
              "alpha": alpha_arr, "pivot_sample": in_piv}
    return Profile(u, v, omega, t, acc_u, a, alpha, in_pivl, arrays)
