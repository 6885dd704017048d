"""The speed profile along a sampled path: the fastest progress rate the motion limits allow.

The progress rate u = d(sigma)/dt is capped per sample (v_max, per-point caps, lateral
acceleration, omega_max, and v^2 |d(kappa)/ds| <= alpha_max / 2 on driving pieces;
b * omega_max in pivots), then limited by forward (accel) and backward (decel) passes, with
u = 0 at both ends and at both sides of every pivot. Between two samples the progress has a
constant acceleration (u^2 is linear in sigma), which makes t(sigma), v(t) and at_time exact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
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
    capl, dsl, accl, decl = cap.tolist(), ds.tolist(), acc_lim.tolist(), dec_lim.tolist()
    u = [0.0] * n
    for i in range(n - 1):
        u[i + 1] = min(capl[i + 1], math.sqrt(u[i] * u[i] + 2.0 * accl[i] * dsl[i]))
    for i in range(n - 2, -1, -1):
        u[i] = min(u[i], math.sqrt(u[i + 1] * u[i + 1] + 2.0 * decl[i] * dsl[i]))
    kl, pl, tl = list(kappa), list(seg_pivot), list(turn)
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
    return Profile(u, v, omega, t, acc_u, a, alpha, in_pivl)
