"""The platform's parameters from an identified lumped model, kept physical.

Identification fits the lumped model (m_k, mbar, I, m_x) and each wheel's extra Coulomb
friction. The config holds the platform's m_p, d_xc, d_yc, I_p instead (the wheels' own
masses and inertias stay as configured), so the fit is split: m_p = m_k less the wheels, and
so on (`unconstrained`). When the configured wheels are far off, or the run excited a
parameter too little, that split is impossible: no platform mass or yaw inertia left, the
platform's centre of mass beyond the wheels, a wheel's total friction below zero.

Then `physical_split` finds the physical parameters that fit the run best: least squares in
the fit's own metric (the regression's normal matrix, or its standard errors) over the
platform's parameters held within `bounds`, by projected Newton steps. A parameter that ends
on its bound is one the run could not separate from the configured wheels; the result names
each one, with its unconstrained value and the bound it was held at, so the user knows which
configured values to check. A feasible split is returned exactly as it is.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

from ddrt.core.adapt import NAMES as LUMPED  # the regression's parameters, in its order
from ddrt.params.robot import RobotParams

PLATFORM = ("m_p", "d_xc", "d_yc", "I_p")
FRICTION = ("fric_l", "fric_r")
# A platform keeps at least this fraction of its configured mass and yaw inertia: strictly
# positive (a physical body), small enough to bias the fitted model as little as the data allow.
MIN_FRACTION = 0.05

UNITS = {"m_p": "kg", "d_xc": "m", "d_yc": "m", "I_p": "kg m^2", "fric_l": "N m", "fric_r": "N m"}
# What a parameter held on its bound says about the input: what to check.
HINTS = {
    "m_p": "the configured wheels' masses (robot.m_L, m_R, m_3) and spin inertias leave no platform mass",
    "I_p": "the configured wheels' yaw inertias (robot.I_L, I_R, I_3), masses and spin inertias leave no "
           "platform inertia",
    "d_xc": "the robot's moment needs more platform mass than the configured wheels leave",
    "d_yc": "the robot's moment needs more platform mass than the configured wheels leave",
    "fric_l": "the run did not separate the left wheel's friction from the model's other terms",
    "fric_r": "the run did not separate the right wheel's friction from the model's other terms",
}


@dataclass(frozen=True)
class Bounds:
    """Where each parameter may lie (lower, upper; math.inf for none), and why, in words."""

    lower: dict[str, float]
    upper: dict[str, float]
    why: dict[str, str]


@dataclass(frozen=True)
class Held:
    """A parameter the run could not separate: its unconstrained value (None when undefined,
    e.g. a centre of mass without a platform mass), the value written, and the bound it sits on."""

    name: str
    unconstrained: float | None
    value: float
    bound: str

    def describe(self) -> str:
        unit = UNITS[self.name]
        was = "undefined" if self.unconstrained is None else f"{self.unconstrained:.6g} {unit}"
        return f"{self.name} {was} -> {self.value:.6g} {unit} (held at {self.bound}; {HINTS[self.name]})"


@dataclass(frozen=True)
class Split:
    """The platform's parameters and each wheel's extra friction, the lumped model they give,
    and the parameters held on a bound (empty when the unconstrained split was physical)."""

    platform: dict[str, float]
    friction: dict[str, float]
    lumped: dict[str, float]
    held: list[Held] = field(default_factory=list)


def _constants(p: RobotParams) -> tuple[float, float, float, float]:
    """What the configured wheels add to m_k, mbar, I and m_x (Dynamics.from_params' terms)."""
    spin = p.I_wL / p.r_L**2 + p.I_wR / p.r_R**2 + p.I_w3 / p.r_3**2
    mass = spin + p.m_L + p.m_R + p.m_3
    mbar = -p.m_L * p.L + p.m_R * p.R - p.L * p.I_wL / p.r_L**2 + p.R * p.I_wR / p.r_R**2
    inertia = (p.I_L + p.I_R + p.I_3 + p.m_3 * p.H**2 + p.L**2 * p.I_wL / p.r_L**2 + p.R**2 * p.I_wR / p.r_R**2
               + p.m_L * p.L**2 + p.m_R * p.R**2)
    return mass, mbar, inertia, p.m_3 * p.H


def bounds(p: RobotParams, coulomb_nm: float) -> Bounds:
    """The physical region: a platform with mass and yaw inertia (at least MIN_FRACTION of the
    configured ones), its centre of mass between the drive wheels and from half a track behind
    the axle to the front wheel, each wheel's total Coulomb friction (the motor's plus the
    extra) not negative."""
    rear = -max(p.L, p.R)
    lower = {"m_p": MIN_FRACTION * p.m_p, "d_xc": rear, "d_yc": -p.R, "I_p": MIN_FRACTION * p.I_p,
             "fric_l": -coulomb_nm, "fric_r": -coulomb_nm}
    upper = {"m_p": math.inf, "d_xc": p.H, "d_yc": p.L, "I_p": math.inf, "fric_l": math.inf, "fric_r": math.inf}
    why = {"m_p": f"{MIN_FRACTION:.0%} of the configured {p.m_p:.4g} kg",
           "I_p": f"{MIN_FRACTION:.0%} of the configured {p.I_p:.4g} kg m^2",
           "d_xc": f"the body, {rear:.4g} .. {p.H:.4g} m (half a track behind the axle .. the front wheel)",
           "d_yc": f"the body, {-p.R:.4g} .. {p.L:.4g} m (between the drive wheels)",
           "fric_l": f"no negative friction: the motor's coulomb_nm {coulomb_nm:.4g} N m less",
           "fric_r": f"no negative friction: the motor's coulomb_nm {coulomb_nm:.4g} N m less"}
    return Bounds(lower, upper, why)


def lumped_of(p: RobotParams, q: Sequence[float]) -> np.ndarray:
    """The lumped values (LUMPED order) of platform-and-friction q (PLATFORM + FRICTION order)."""
    m_p, d_xc, d_yc, i_p, f_l, f_r = q
    mass, mbar, inertia, m_x = _constants(p)
    return np.array([m_p + mass, -m_p * d_yc + mbar, i_p + m_p * (d_xc**2 + d_yc**2) + inertia,
                     m_p * d_xc + m_x, f_l, f_r])


def _jacobian(q: Sequence[float]) -> np.ndarray:
    m_p, d_xc, d_yc = q[0], q[1], q[2]
    jac = np.zeros((6, 6))
    jac[0, 0] = 1.0
    jac[1, 0], jac[1, 2] = -d_yc, -m_p
    jac[2, 0], jac[2, 1], jac[2, 2], jac[2, 3] = d_xc**2 + d_yc**2, 2 * m_p * d_xc, 2 * m_p * d_yc, 1.0
    jac[3, 0], jac[3, 1] = d_xc, m_p
    jac[4, 4] = jac[5, 5] = 1.0
    return jac


def unconstrained(p: RobotParams, values: Mapping[str, float]) -> dict[str, float | None]:
    """The exact split of `values` (None where it is undefined: no platform mass to divide by)."""
    mass, mbar, inertia, m_x = _constants(p)
    m_p = values["m_k"] - mass
    out: dict[str, float | None] = {"m_p": m_p, "d_xc": None, "d_yc": None, "I_p": None,
                                    "fric_l": values["fric_l"], "fric_r": values["fric_r"]}
    if m_p > 0.0:
        d_xc = (values["m_x"] - m_x) / m_p
        d_yc = -(values["mbar"] - mbar) / m_p
        out.update(d_xc=d_xc, d_yc=d_yc, I_p=values["I"] - m_p * (d_xc**2 + d_yc**2) - inertia)
    return out


def _feasible(q: dict[str, float | None], b: Bounds) -> bool:
    return all(v is not None and b.lower[k] <= v <= b.upper[k] and (k in ("d_xc", "d_yc", *FRICTION) or v > 0.0)
               for k, v in q.items())


def physical_split(p: RobotParams, coulomb_nm: float, values: Mapping[str, float],
                   weight: np.ndarray | None = None, std_err: Mapping[str, float] | None = None) -> Split:
    """The physical split that fits best (module doc). `weight` is the regression's normal matrix
    (phi^T phi, LUMPED order); without it the metric is 1 / std_err^2 per parameter."""
    theta = np.array([float(values[k]) for k in LUMPED])
    if not np.all(np.isfinite(theta)):
        raise ValueError(f"identified values are not finite: {dict(zip(LUMPED, theta.tolist()))}")
    b = bounds(p, coulomb_nm)
    raw = unconstrained(p, values)
    names = PLATFORM + FRICTION
    if _feasible(raw, b):
        q = [float(raw[k]) for k in names]  # type: ignore[arg-type]
        return Split(dict(zip(PLATFORM, q[:4])), dict(zip(FRICTION, q[4:])), dict(zip(LUMPED, theta.tolist())))
    w = _metric(weight, std_err)
    lo = np.array([b.lower[k] for k in names])
    hi = np.array([b.upper[k] for k in names])
    configured = {"m_p": p.m_p, "d_xc": p.d_xc, "d_yc": p.d_yc, "I_p": p.I_p, "fric_l": 0.0, "fric_r": 0.0}
    start = np.clip([raw[k] if raw[k] is not None else configured[k] for k in names], lo, hi)
    q = _projected_newton(p, theta, w, start, lo, hi)
    held = [Held(k, raw[k], float(q[i]), f"{'its lower bound' if q[i] <= lo[i] else 'its upper bound'}, "
                 f"{b.why[k]}")
            for i, k in enumerate(names) if q[i] <= lo[i] or q[i] >= hi[i]]
    return Split(dict(zip(PLATFORM, q[:4].tolist())), dict(zip(FRICTION, q[4:].tolist())),
                 dict(zip(LUMPED, lumped_of(p, q).tolist())), held)


def _metric(weight: np.ndarray | None, std_err: Mapping[str, float] | None) -> np.ndarray:
    if weight is not None:
        w = np.asarray(weight, dtype=float)
        if w.shape == (6, 6) and np.all(np.isfinite(w)):
            return 0.5 * (w + w.T)
    if std_err is not None:
        se = np.array([float(std_err[k]) for k in LUMPED])
        if np.all(np.isfinite(se)) and np.all(se > 0.0):
            return np.diag(1.0 / se**2)
    raise ValueError("a constrained split needs the fit's normal matrix or its standard errors")


def _curvature(q: Sequence[float], r: np.ndarray) -> np.ndarray:
    """sum_k r_k times the Hessian of lumped model k in q: the term Gauss-Newton leaves out,
    which matters when the best physical model is far from the fit (a large residual)."""
    m_p, d_xc, d_yc = q[0], q[1], q[2]
    out = np.zeros((6, 6))
    out[0, 2] = out[2, 0] = -r[1] + 2.0 * d_yc * r[2]
    out[0, 1] = out[1, 0] = 2.0 * d_xc * r[2] + r[3]
    out[1, 1] = out[2, 2] = 2.0 * m_p * r[2]
    return out


def _solve_free(hess: np.ndarray, grad: np.ndarray, free: np.ndarray, diag: np.ndarray) -> np.ndarray:
    """The Newton step on the free parameters (the others 0), solved diagonally scaled."""
    step = np.zeros_like(grad)
    scale = np.sqrt(diag[free])
    scaled = hess[np.ix_(free, free)] / np.outer(scale, scale) + 1e-12 * np.eye(int(free.sum()))
    try:
        step[free] = -np.linalg.solve(scaled, grad[free] / scale) / scale
    except np.linalg.LinAlgError:
        step[:] = np.nan
    return step


def _projected_newton(p: RobotParams, theta: np.ndarray, w: np.ndarray, q0: np.ndarray, lo: np.ndarray,
                            hi: np.ndarray, iterations: int = 300) -> np.ndarray:
    """min (lumped(q) - theta)^T w (lumped(q) - theta) over lo <= q <= hi.

    Each step solves Newton's system (or, where that does not descend, Gauss-Newton's, or a
    scaled gradient step) on the parameters not pinned at a bound by their gradient, clips the
    step to the box and halves it until the cost falls. The lumped model is
    a one-to-one map of the box (m_p > 0) onto a convex set of models, and the cost is convex in
    the model, so the minimum found is the one.
    """

    def cost(q: np.ndarray) -> float:
        e = lumped_of(p, q) - theta
        return float(e @ w @ e)

    q = q0.astype(float)
    c = cost(q)
    for _ in range(iterations):
        jac = _jacobian(q)
        e = lumped_of(p, q) - theta
        grad = 2.0 * jac.T @ w @ e
        hess = 2.0 * jac.T @ w @ jac
        diag = np.maximum(np.diag(hess), 1e-300)
        # pinned: on (or within a hair of) a bound, the gradient pushing outward
        near = 1e-9 * (np.abs(q) + 1e-6)
        pinned = ((q - lo <= near) & (grad > 0.0)) | ((hi - q <= near) & (grad < 0.0))
        free = ~pinned
        if not free.any():
            break
        steps = [_solve_free(h, grad, free, diag) for h in (hess + _curvature(q, 2.0 * w @ e), hess)]
        steps.append(np.where(free, -grad / diag, 0.0))  # a diagonally scaled gradient step
        moved = False
        for step in (s for s in steps if np.all(np.isfinite(s)) and grad @ s < 0.0):
            t = 1.0
            while t > 1e-12:
                trial = np.clip(q + t * step, lo, hi)
                ct = cost(trial)
                if ct < c:
                    moved = True
                    break
                t *= 0.5
            if moved:
                break
        if not moved:
            break
        done = c - ct <= 1e-15 * max(1.0, c)
        q, c = trial, ct
        if done:
            break
    return q
