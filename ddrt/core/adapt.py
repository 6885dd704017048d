"""Online estimation of the lumped dynamic parameters the compensator and the estimator use.

The reduced model (docs/model.md) with an extra Coulomb friction c_L, c_R at each wheel (what the
motor model's friction misses) is linear in theta = (m_k, mbar, I, m_x, c_L, c_R):

    m_k v' + mbar w' - m_x w^2     + c_L s_L / r_L + c_R s_R / r_R =  tau_L/r_L + tau_R/r_R
    mbar v' + I w'   + m_x v w     - L c_L s_L/r_L + R c_R s_R/r_R = -L tau_L/r_L + R tau_R/r_R

with s = tanh(wheel speed / w_s) a smoothed sign. Torques come from the motor model at the
applied duty and the estimated wheel speeds (as the estimator predicts with them). Both sides
pass through the same second-order low-pass F(s) = a^2 / (s + a)^2, two first-order stages:
the derivative of the filtered speed is then a (v_1 - v_f), exact, where v_1 is the first
stage's output, so no noise is differentiated. (With one stage the derivative a (v - v_f)
passes the speed estimate's noise straight through; noise on a regressor biases least squares
towards zero, and the masses drifted down by half in 12 s.) The second row is divided by
the half track so both rows are forces (N) and weigh alike.

Recursive least squares with forgetting, updated only when the filtered accelerations excite
the regressor (driving straight at constant speed carries no information about the masses,
and forgetting without information would wind the covariance up) and while both wheels turn
faster than `min_wheel_speed` (near zero speed friction flips sign and sticks, and the
torque the motor model reports is not the torque the wheel gets). Every estimate is clamped
to bounds around the configured values. The configured values are the prior, weighed per
robot and per rate (`noise_n`), so data outweighs them only where it carries information.
The adapted model is handed out only once enough excited samples have been seen and while it
predicts the torques clearly better than the configured model does (a running comparison of
both residuals, `min_improvement`), else the configured model is the fallback; the model in use then follows the target with a first-order blend, so the
compensator's torque never jumps. Plain floats: one update costs two scalar RLS steps on a 6x6
covariance (about 25 us on the development machine).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ddrt.config import AdaptationConfig
from ddrt.core.model import Dynamics
from ddrt.core.motor import Motor

NAMES = ("m_k", "mbar", "I", "m_x", "fric_l", "fric_r")
N = 6
FRICTION_SIGN_SPEED = 0.2  # rad/s: w_s of the smoothed sign in the friction regressors
RESIDUAL_TAU_S = 2.0  # s: time constant of the running residual comparison


@dataclass(frozen=True, slots=True)
class AdaptedDynamics(Dynamics):
    """`Dynamics` plus the extra wheel friction the adapter found (N m, Coulomb-like).

    `inverse` adds the torque that overcomes it, `forward` subtracts it, so the compensator
    and the estimator's prediction use the same identified robot.
    """

    fric_l: float = 0.0
    fric_r: float = 0.0
    fric_full_speed: float = 0.0  # rad/s: below this wheel speed the friction fades out linearly

    def _friction(self, v: float, w: float) -> tuple[float, float]:
        return (self._wheel((v - self.L * w) / self.r_L, self.fric_l),
                self._wheel((v + self.R * w) / self.r_R, self.fric_r))

    def _wheel(self, ws: float, c: float) -> float:
        """The friction torque at wheel speed ws: the adapter learns it only from ticks where
        both wheels turn faster than `min_wheel_speed`, so below that it fades to zero rather
        than switch sign as a wheel reverses (a pivot), where nothing was learnt."""
        full = self.fric_full_speed
        fade = 1.0 if abs(ws) >= full else abs(ws) / full
        return c * fade * math.tanh(ws / FRICTION_SIGN_SPEED)

    def forward(self, v: float, w: float, tau_l: float, tau_r: float) -> tuple[float, float]:
        fl, fr = self._friction(v, w)
        return Dynamics.forward(self, v, w, tau_l - fl, tau_r - fr)

    def inverse(self, v: float, w: float, v_dot: float, w_dot: float) -> tuple[float, float]:
        tl, tr = Dynamics.inverse(self, v, w, v_dot, w_dot)
        fl, fr = self._friction(v, w)
        return tl + fl, tr + fr


def theta_of(dyn: Dynamics) -> list[float]:
    """The parameter vector of a model (friction 0 unless it is an AdaptedDynamics)."""
    fric_l, fric_r = (dyn.fric_l, dyn.fric_r) if isinstance(dyn, AdaptedDynamics) else (0.0, 0.0)
    return [dyn.m_k, dyn.mbar, dyn.I, dyn.m_x, fric_l, fric_r]


def regressor(dyn: Dynamics, v: float, w: float, ww: float, vw: float, sl: float, sr: float,
              dv: float, dw: float) -> tuple[list[float], list[float]]:
    """The two regressor rows (row 2 already divided by the half track)."""
    half = 0.5 * (dyn.L + dyn.R)
    phi1 = [dv, dw, 0.0, -ww, sl / dyn.r_L, sr / dyn.r_R]
    phi2 = [0.0, dv / half, dw / half, vw / half, -dyn.L * sl / (dyn.r_L * half), dyn.R * sr / (dyn.r_R * half)]
    return phi1, phi2


class DynamicsAdapter:
    """RLS estimate of (m_k, mbar, I, m_x, c_L, c_R) from the loop's own signals."""

    def __init__(self, nominal: Dynamics, motor: Motor, cfg: AdaptationConfig, period_s: float) -> None:
        self.nominal = nominal
        self.motor = motor
        self.cfg = cfg
        self.period = period_s
        self.beta = 1.0 - math.exp(-2.0 * math.pi * cfg.filter_hz * period_s)
        self.rate = self.beta / period_s  # d(x_f)/dt = rate * (x - x_f)
        self.lam = cfg.forgetting
        self.theta0 = theta_of(nominal)
        m_k0 = nominal.m_k
        shift = cfg.max_com_shift_m * m_k0 * cfg.bound_ratio
        r = cfg.bound_ratio
        self.lo = [m_k0 / r, nominal.mbar - shift, nominal.I / r, nominal.m_x - shift,
                   -cfg.max_friction_nm, -cfg.max_friction_nm]
        self.hi = [m_k0 * r, nominal.mbar + shift, nominal.I * r, nominal.m_x + shift,
                   cfg.max_friction_nm, cfg.max_friction_nm]
        # Prior std of each parameter: half the nominal for the masses, a centre-of-mass shift
        # of the whole mass by 2 cm sideways and 5 cm forward for the moments, 0.03 N m friction.
        prior = [0.5 * m_k0, 0.02 * m_k0, 0.5 * nominal.I, 0.05 * m_k0, 0.03, 0.03]
        self.p0 = [(s / self.noise_n(nominal, cfg, period_s)) ** 2 for s in prior]
        self.k_res = 1.0 - math.exp(-period_s / RESIDUAL_TAU_S)
        # Batch identification (ddrt calibrate identify) collects the gated-in rows here.
        self.recorder: list[tuple[list[float], float]] | None = None
        self.fallbacks = 0  # resets to the configured values after a non-finite number
        self.reset()

    @staticmethod
    def noise_n(nominal: Dynamics, cfg: AdaptationConfig, period_s: float) -> float:
        """The std (N) RLS assumes for one row's residual: what sets the prior's weight.

        `noise_accel` times the configured m + k, so the prior weighs the same on a light
        robot and a heavy one, times the square root of the ticks within the filter's time
        constant: the filtered rows of successive ticks are nearly the same sample, and counted
        as independent they would outweigh the configured values within a fraction of a
        second, whatever the rate."""
        ticks = max(1.0, 1.0 / (2.0 * math.pi * cfg.filter_hz * period_s))
        return cfg.noise_accel * nominal.m_k * math.sqrt(ticks)

    def reset(self) -> None:
        """Back to the configured values and the prior covariance; filters emptied."""
        self.theta = list(self.theta0)
        self.used = list(self.theta0)  # the parameters of the model in use (see blend)
        self.p = [0.0] * (N * N)
        for i in range(N):
            self.p[i * N + i] = self.p0[i]
        self.g = [0.0] * 8  # first stage of the filter: v, w, w^2, v w, s_L, s_R, force, moment/half
        self.f = [0.0] * 8  # second stage: what the regression uses
        self.primed = False
        self.updates = 0
        self.ticks = 0
        self.res_adapt = 0.0
        self.res_nominal = 0.0

    # ------------------------------------------------------------------ per tick

    def update(self, v: float, w: float, duty_l: float, duty_r: float) -> None:
        """Feed one tick: estimated (v, omega) and the duties applied since the last tick."""
        if not (math.isfinite(v) and math.isfinite(w) and math.isfinite(duty_l) and math.isfinite(duty_r)):
            self.fallbacks += 1
            self.reset()
            return
        nom = self.nominal
        L, R, rl, rr = nom.L, nom.R, nom.r_L, nom.r_R
        half = 0.5 * (L + R)
        wl = (v - L * w) / rl
        wr = (v + R * w) / rr
        motor = self.motor
        tau_l, tau_r = motor.net_torques(duty_l, wl, duty_r, wr)
        ul = tau_l / rl
        ur = tau_r / rr
        raw = (v, w, w * w, v * w, math.tanh(wl / FRICTION_SIGN_SPEED), math.tanh(wr / FRICTION_SIGN_SPEED),
               ul + ur, (-L * ul + R * ur) / half)
        f = self.f
        g = self.g
        self.ticks += 1
        if not self.primed:
            f[:] = raw
            g[:] = raw
            self.primed = True
            return
        b = self.beta
        for i in range(8):
            g[i] += b * (raw[i] - g[i])
        dv = self.rate * (g[0] - f[0])
        dw = self.rate * (g[1] - f[1])
        mid = [0.0] * 8
        for i in range(8):
            old = f[i]
            new = old + b * (g[i] - old)
            f[i] = new
            mid[i] = 0.5 * (old + new)
        phi1, phi2 = regressor(nom, mid[0], mid[1], mid[2], mid[3], mid[4], mid[5], dv, dw)
        y1, y2 = mid[6], mid[7]
        th = self.theta
        t0 = self.theta0
        e1 = y1 - sum(phi1[i] * th[i] for i in range(N))
        e2 = y2 - sum(phi2[i] * th[i] for i in range(N))
        n1 = y1 - sum(phi1[i] * t0[i] for i in range(N))
        n2 = y2 - sum(phi2[i] * t0[i] for i in range(N))
        k = self.k_res
        self.res_adapt += k * (e1 * e1 + e2 * e2 - self.res_adapt)
        self.res_nominal += k * (n1 * n1 + n2 * n2 - self.res_nominal)
        # Gates: enough acceleration, and both wheels well away from zero speed, where the
        # friction's sign flips and stiction makes the torque unknown.
        ws_min = self.cfg.min_wheel_speed
        if (max(abs(dv), half * abs(dw)) < self.cfg.min_excitation or abs(wl) < ws_min or abs(wr) < ws_min):
            return
        if self.recorder is not None:
            self.recorder.append((phi1, y1))
            self.recorder.append((phi2, y2))
        self._rls(phi1, e1, self.lam)
        e2 = y2 - sum(phi2[i] * th[i] for i in range(N))
        self._rls(phi2, e2, 1.0)
        for i in range(N):
            x = th[i]
            if not math.isfinite(x):
                self.fallbacks += 1
                self.reset()
                return
            th[i] = self.lo[i] if x < self.lo[i] else (self.hi[i] if x > self.hi[i] else x)
        # Keep H positive definite with a margin (|mbar| < 0.9 sqrt(m_k I)).
        lim = 0.9 * math.sqrt(th[0] * th[2])
        th[1] = -lim if th[1] < -lim else (lim if th[1] > lim else th[1])
        self.updates += 1

    def _rls(self, phi: list[float], err: float, lam: float) -> None:
        """One scalar RLS step; forgetting stops once the covariance is back at the prior."""
        p = self.p
        pphi = [0.0] * N
        for i in range(N):
            row = i * N
            s = 0.0
            for j in range(N):
                s += p[row + j] * phi[j]
            pphi[i] = s
        denom = lam + sum(phi[i] * pphi[i] for i in range(N))
        if denom <= 0.0:
            return
        gain = [x / denom for x in pphi]
        th = self.theta
        for i in range(N):
            th[i] += gain[i] * err
        wind = lam < 1.0 and all(p[i * N + i] < self.p0[i] for i in range(N))
        inv = 1.0 / lam if wind else 1.0
        for i in range(N):
            row = i * N
            gi = gain[i]
            for j in range(N):
                p[row + j] = (p[row + j] - gi * pphi[j]) * inv

    # ------------------------------------------------------------------ results

    @property
    def trusted(self) -> bool:
        """Enough excited samples, and the estimate explains the torques clearly better: its
        running RMS residual at least `min_improvement` below the configured model's (a
        model that is only as good changes the loop for nothing)."""
        keep = (1.0 - self.cfg.min_improvement) ** 2
        return self.updates >= self.cfg.min_updates and self.res_adapt <= keep * self.res_nominal

    def estimate(self) -> AdaptedDynamics:
        """The current estimate as a model (whether or not it is trusted)."""
        th = self.theta
        n = self.nominal
        return AdaptedDynamics(m_k=th[0], mbar=th[1], I=th[2], m_x=th[3], L=n.L, R=n.R, r_L=n.r_L,
                               r_R=n.r_R, fric_l=th[4], fric_r=th[5], fric_full_speed=self.cfg.min_wheel_speed)

    def target(self) -> list[float]:
        """The parameters the controller should converge to: the estimate if trusted, else
        the configured values."""
        return self.theta if self.trusted else self.theta0

    def blend(self, dt: float) -> AdaptedDynamics:
        """Move the model in use towards `target()` by a first-order step of `dt` seconds.

        A model that jumps makes the compensator's torque jump while the PID's integrator still
        holds the old model's error: the blend lets the integrator unwind as the model moves.
        """
        k = 1.0 - math.exp(-dt / self.cfg.blend_s) if self.cfg.blend_s > 0.0 else 1.0
        used = self.used
        tgt = self.target()
        for i in range(N):
            used[i] += k * (tgt[i] - used[i])
        n = self.nominal
        return AdaptedDynamics(m_k=used[0], mbar=used[1], I=used[2], m_x=used[3], L=n.L, R=n.R, r_L=n.r_L,
                               r_R=n.r_R, fric_l=used[4], fric_r=used[5], fric_full_speed=self.cfg.min_wheel_speed)

    def status(self) -> dict[str, object]:
        """What the daemon's status shows."""
        return {"active": self.trusted, "updates": self.updates, "fallbacks": self.fallbacks,
                "estimate": dict(zip(NAMES, self.theta)), "in_use": dict(zip(NAMES, self.used)),
                "configured": dict(zip(NAMES, self.theta0)),
                "residual_n": math.sqrt(self.res_adapt), "residual_configured_n": math.sqrt(self.res_nominal)}
