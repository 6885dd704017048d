"""The simulated robot with what real robots have: SimRobot's integrator when its
`PlantConfig.realism` is not the default. Plain Python, written for clarity over speed: the
default plant keeps the compiled kernel, and a realistic run is a few times slower.

The same RK4 model as plant.py (docs/model.md), with:
- battery: one pack feeds both drivers; its terminal voltage V = OCV(soc) - R_int I, with
  I = sum(duty_i * I_i) the pack current (an ideal H-bridge) and I_i = (duty_i V - k_i w_i) / R_i
  each armature current, solved in closed form at every RK4 stage; the charge drawn lowers
  the state of charge. The motors see duty x V, so a sagging battery slows the robot.
- driver deadband: |duty| below `deadband` applies nothing.
- gearbox backlash: each motor turns freely across `backlash_deg` of play (its own inertia
  under its electromagnetic torque; the wheel gets no torque from it meanwhile) until it
  meets the other flank, where the impact is inelastic. Engaged, it drives the wheel as
  before and leaves the flank when its torque turns away from it. The friction stays with
  the wheel (gearbox and bearings), so a free wheel still feels it; the wheel's inertia in
  the model stays the configured one (the motor's is taken to be part of it when engaged).
- floor patches scale the motors' friction while A is inside one; payloads change the
  platform's mass, centre and inertia at their time.
- gyro: zero-rate bias with die warm-up and drift, scale error, noise, the DLPF, and (with
  `gyro_odr_hz`) the output register holding the filtered rate of the last sample instant
  of the MPU's own clock, so a read is 0 to one sample period old. With `gyro_fifo` every
  sample instant's reading (quantised) also goes into a FIFO of FIFO_SAMPLES, the oldest lost
  when it is full (flagged), which `read_fifo` drains: each sample is read exactly once.
- encoders: the omni wheel's count follows the ground with a wandering scale (roller slip);
  the drive wheels' counts turn more than the ground under traction (slip ratio
  slip_per_nm x torque) and with their own wandering scale. The dynamics keep rolling
  contact: slip is what the encoders see, its energy is not modelled.
"""

from __future__ import annotations

import math
import random
from dataclasses import replace
from typing import Any

from ddrt.core.model import Dynamics
from ddrt.params.robot import RobotParams
from sim_hal import raw_readings

_DEG_PER_RAD = 180.0 / math.pi
_EPS_T = 1e-12
FIFO_SAMPLES = 512  # the MPU-6050's 1024-byte FIFO holds this many 2-byte gyro z samples


def _with_payload(p: RobotParams, mass: float, inertia: float, x: float, y: float) -> RobotParams:
    """`p` with a payload merged into the platform (m_p, its centre and its inertia I_p)."""
    m = p.m_p + mass
    cx = (p.m_p * p.d_xc + mass * x) / m
    cy = (p.m_p * p.d_yc + mass * y) / m
    i_p = (p.I_p + p.m_p * ((p.d_xc - cx) ** 2 + (p.d_yc - cy) ** 2)
           + inertia + mass * ((x - cx) ** 2 + (y - cy) ** 2))
    return replace(p, m_p=m, d_xc=cx, d_yc=cy, I_p=i_p)


class _Wanderer:
    """An Ornstein-Uhlenbeck scale error, exact discretisation at the plant step."""

    def __init__(self, spec: Any, h: float) -> None:
        self.mean = spec.mean
        self.s = 0.0
        self.a = math.exp(-h / spec.tau_s)
        self.k = spec.sigma * math.sqrt(1.0 - self.a * self.a)

    def scale(self) -> float:
        return 1.0 + self.mean + self.s

    def step(self, gauss: Any) -> None:
        if self.k:
            self.s = self.a * self.s + self.k * gauss(0.0, 1.0)


class RealisticPlant:
    """Integrates a SimRobot (its state attributes) with its realism; see the module doc."""

    def __init__(self, robot: Any) -> None:
        self.robot = robot
        cfg = robot.cfg
        r = cfg.realism
        self.r = r
        self.h = h = robot._h
        self.battery = r.battery
        self.soc = r.battery.start_soc if r.battery is not None else 1.0
        self.charge_c = 0.0  # drawn from the pack since the start (C)
        self.source_j = 0.0  # energy out of the open-circuit source: integral of OCV * I
        self.internal_j = 0.0  # ... into its internal resistance
        self.armature_j = 0.0  # ... into the motors' armature resistance
        self.free_motor_j = 0.0  # work of motor torque on motors turning free in the play
        self.current_a = 0.0
        ml, mr = robot.motor_l, robot.motor_r
        self.motors = (ml, mr)
        self.terminal_v = r.battery.ocv_v(self.soc) if r.battery is not None else ml.supply_v
        self.deadband = r.actuators.deadband
        self.half_play = math.radians(r.actuators.backlash_deg) / 2.0
        self.j_motor = r.actuators.motor_inertia_kgm2
        self.side = [1, 1] if self.half_play == 0.0 else [0, 0]  # +-1 on a flank, 0 free in the play
        self.gap = [0.0, 0.0]  # motor angle minus wheel angle (rad at the wheel)
        self.gap_rate = [0.0, 0.0]
        self.tau = (0.0, 0.0)  # wheel torques at the start of the last step (slip included)
        self.payloads = sorted(r.events.payloads, key=lambda p: p.at_s)
        self.floor = r.events.floor
        self._set_params(robot.params)
        seed = cfg.seed
        self.rng = random.Random(None if seed is None else f"{seed}/realism")
        self.ou3 = _Wanderer(r.encoder_slip, h)
        self.ou_l = _Wanderer(r.wheels.scale, h)
        self.ou_r = _Wanderer(r.wheels.scale, h)
        self.c3 = self.cl = self.cr = 0.0  # counted angles (rad) of the omni and drive wheels
        # Gyro: settled at the start (the default plant's convention).
        self.g_a = robot._gyro_a
        self.g_sig = robot._gyro_sigma
        self.g_scale = (1.0 + cfg.gyro_scale_error) * _DEG_PER_RAD
        self.gf = self.bias_dps(0.0)
        self.odr_period = 0.0 if r.gyro_odr_hz == 0.0 else 1.0 / (r.gyro_odr_hz * (1.0 + r.gyro_clock_ppm * 1e-6))
        self.delay = robot._sensor_delay
        self.n = self.delay + 3 + math.ceil(self.odr_period / h)
        self.hist = [(0.0, 0.0, 0.0, self.gf)] * self.n  # (c3, cl, cr, gf) at the end of step k
        # The FIFO (r.gyro_fifo): raw samples not yet read, whether one was lost, the next instant's index.
        self.fifo_on = r.gyro_fifo and self.odr_period > 0.0
        self.fifo: list[int] = []
        self.fifo_overflow = False
        self.fifo_next = 1
        self.fifo_pushed = 0  # samples that went into the FIFO since the start (tests)

    # --- truth the tests and the emulators read ------------------------------------------

    def die_temp_c(self, t: float) -> float:
        r = self.r
        return r.gyro_temp_start_c + r.gyro_warmup_rise_c * (1.0 - math.exp(-t / r.gyro_warmup_tau_s))

    def bias_dps(self, t: float) -> float:
        r = self.r
        b = (self.robot.cfg.gyro_bias_dps + r.gyro_bias_per_c_dps * (self.die_temp_c(t) - r.gyro_temp_start_c)
             + r.gyro_drift_dps_per_s * t)
        if r.gyro_bias_step_dps != 0.0 and t >= r.gyro_bias_step_at_s:  # sim.gyro.bias_step_dps
            b += r.gyro_bias_step_dps
        return b

    def ocv_v(self) -> float:
        return self.battery.ocv_v(self.soc) if self.battery is not None else self.motors[0].supply_v

    # --- readings (sensor latency as the default plant) ----------------------------------

    def _at(self, k: int) -> tuple[float, float, float, float]:
        return self.hist[max(k, 0) % self.n]

    def read_encoder(self) -> int:
        cfg = self.robot.cfg
        c3 = self._at(self.robot._k - self.delay)[0]
        return raw_readings.encoder_count(c3, cfg.encoder_counts_per_rev, cfg.encoder_offset_counts)

    def read_wheel_counts(self, cpr: int) -> tuple[int, int]:
        _, cl, cr, _ = self._at(self.robot._k - self.delay)
        return raw_readings.encoder_count(cl, cpr), raw_readings.encoder_count(cr, cpr)

    def gyro_dps(self) -> float:
        """The rate in the gyro's output register (deg/s, before quantisation)."""
        k_read = self.robot._k - self.delay
        if self.odr_period == 0.0:
            return self._at(k_read)[3]
        t_read = max(k_read, 0) * self.h
        return self._sampled(math.floor(t_read / self.odr_period + 1e-9) * self.odr_period, k_read)

    def read_fifo(self) -> tuple[list[int], bool]:
        """Drain the FIFO: the raw samples since the last read, oldest first, and whether any
        were lost to a full FIFO meanwhile."""
        out, lost = self.fifo, self.fifo_overflow
        self.fifo = []
        self.fifo_overflow = False
        return out, lost

    def _fill_fifo(self, k: int) -> None:
        """Push every sample instant up to the sensors' read time at step k (as old as a register
        read then)."""
        k_read = k - self.delay
        t_read = max(k_read, 0) * self.h
        period = self.odr_period
        lsb = self.robot._gyro_lsb_per_dps
        while self.fifo_next * period <= t_read + 1e-9:
            self.fifo.append(raw_readings.gyro_raw(self._sampled(self.fifo_next * period, k_read), lsb))
            self.fifo_next += 1
            self.fifo_pushed += 1
            if len(self.fifo) > FIFO_SAMPLES:
                del self.fifo[0]
                self.fifo_overflow = True

    def _sampled(self, t_s: float, k_read: int) -> float:
        """The filtered rate at sample instant t_s (deg/s), between the plant's steps linearly."""
        j = math.floor(t_s / self.h + 1e-9)
        frac = t_s / self.h - j
        g0 = self._at(j)[3]
        if frac <= 1e-9 or j + 1 > k_read:
            return g0
        return g0 + frac * (self._at(j + 1)[3] - g0)

    # --- the integrator -------------------------------------------------------------------

    def _set_params(self, p: RobotParams) -> None:
        dyn = Dynamics.from_params(p)
        self.robot.dynamics = dyn
        det = dyn.m_k * dyn.I - dyn.mbar * dyn.mbar
        self.a11, self.a12, self.a22, self.mx = dyn.I / det, -dyn.mbar / det, dyn.m_k / det, dyn.m_x
        self.params = p

    def _floor_scale(self, x: float, y: float) -> float:
        for f in self.floor:
            if f.x_min <= x <= f.x_max and f.y_min <= y <= f.y_max:
                return f.friction_scale
        return 1.0

    def _volts(self, d: tuple[float, float], wm: tuple[float, float]) -> tuple[float, float]:
        """Voltage at each motor: the pack's terminal voltage (both), or each motor's supply."""
        if self.battery is None:
            return self.motors[0].supply_v, self.motors[1].supply_v
        e = self.ocv_v()
        ri = self.battery.resistance_ohm
        num, den = e, 1.0
        for di, wi, m in zip(d, wm, self.motors):
            num += ri * di * m.k_nm_per_a * wi / m.resistance_ohm
            den += ri * di * di / m.resistance_ohm
        v = num / den
        return v, v

    def _motor(self, i: int, duty: float, volts: float, wm: float) -> tuple[float, float]:
        """(armature current, electromagnetic torque) of motor i turning at wm (at the wheel)."""
        m = self.motors[i]
        cur = (duty * volts - m.k_nm_per_a * wm) / m.resistance_ohm
        return cur, m.k_nm_per_a * cur

    def _friction(self, i: int, ww: float, fs: float) -> float:
        """Viscous and Coulomb friction at wheel i turning at ww, scaled by the floor's `fs`."""
        m = self.motors[i]
        return fs * (m.viscous_nms * ww + m.coulomb_nm * math.tanh(ww / m.coulomb_smoothing_rad_s))

    def _stage(self, v: float, w: float, d: tuple[float, float], fs: float, slip: tuple[float, float]) -> tuple:
        """One RK4 stage: (dv, dw, then the powers: electromagnetic at engaged wheels, friction,
        out of the open-circuit source, into the pack's resistance, into the armatures, on free
        motors; the pack current, the wheel torques). The source's terms mean something only
        with a battery."""
        p = self.params
        ww = ((v - p.L * w) / p.r_L, (v + p.R * w) / p.r_R)
        wm = tuple(ww[i] + (0.0 if self.side[i] else self.gap_rate[i]) for i in (0, 1))
        volts = self._volts(d, wm)
        tau = [0.0, 0.0]
        p_em = p_fr = p_arm = p_free = ib = 0.0
        for i in (0, 1):
            cur, em = self._motor(i, d[i], volts[i], wm[i])
            fr = self._friction(i, ww[i], fs)
            p_arm += self.motors[i].resistance_ohm * cur * cur
            ib += d[i] * cur
            p_fr += fr * ww[i]
            if self.side[i]:
                tau[i] = em - fr + slip[i]
                p_em += em * ww[i]
            else:
                tau[i] = slip[i] - fr
                p_free += em * wm[i]
        ul, ur = tau[0] / p.r_L, tau[1] / p.r_R
        fv = ul + ur + self.mx * w * w
        fw = p.R * ur - p.L * ul - self.mx * v * w
        e = self.ocv_v()
        ri = self.battery.resistance_ohm if self.battery is not None else 0.0
        return (self.a11 * fv + self.a12 * fw, self.a12 * fv + self.a22 * fw, p_em, p_fr,
                e * ib, ri * ib * ib, p_arm, p_free, ib, tau)

    def _engage(self, d: tuple[float, float]) -> None:
        """At the start of a step: does each motor press on a flank, or turn free in the play?"""
        if self.half_play == 0.0:
            return
        rb = self.robot
        p = self.params
        ww = ((rb._v - p.L * rb._w) / p.r_L, (rb._v + p.R * rb._w) / p.r_R)
        volts = self._volts(d, ww)
        for i in (0, 1):
            side = self.side[i]
            if side:
                em = self._motor(i, d[i], volts[i], ww[i])[1]
                if side * em <= 0.0:
                    self.side[i] = 0  # the torque turns away from the flank: free in the play
                    self.gap_rate[i] = 0.0

    def _free_motors(self, d: tuple[float, float], ww_new: tuple[float, float]) -> None:
        """Advance the motors turning in the play by one step, exactly for the step's voltage: a
        free motor relaxes to duty V / k at the rate of its back-EMF's damping, k^2 / (R J). An
        explicit step diverges once that rate times the step passes 2 (a strong gearmotor's
        k at the wheel on the default 2e-4 kg m^2: the motor then chatters across the play and
        never drives its wheel)."""
        if self.half_play == 0.0:
            return
        h, jm = self.h, self.j_motor
        rb = self.robot
        p = self.params
        ww_old = ((rb._v - p.L * rb._w) / p.r_L, (rb._v + p.R * rb._w) / p.r_R)
        wm = tuple(ww_old[i] + self.gap_rate[i] for i in (0, 1))
        volts = self._volts(d, wm)
        for i in (0, 1):
            if self.side[i]:
                continue
            m = self.motors[i]
            rate = m.k_nm_per_a**2 / (m.resistance_ohm * jm)
            settled = d[i] * volts[i] / m.k_nm_per_a
            new = settled + (wm[i] - settled) * math.exp(-rate * h)
            self.gap_rate[i] = new - ww_new[i]
            self.gap[i] += h * self.gap_rate[i]
            if abs(self.gap[i]) >= self.half_play:
                self.side[i] = 1 if self.gap[i] > 0 else -1
                self.gap[i] = math.copysign(self.half_play, self.gap[i])
                self.gap_rate[i] = 0.0  # inelastic: the motor takes the wheel's speed

    def _slip_torques(self, tau: list[float]) -> tuple[float, float]:
        """The seed's random slip torque (as the default plant draws it) on the engaged torques."""
        cfg = self.robot.cfg
        if not (cfg.slip and cfg.slip_probability > 0.0):
            return 0.0, 0.0
        rng = self.robot._slip_rng
        out = []
        for t in tau:
            s = 0.0
            if rng.random() < cfg.slip_probability:
                s = cfg.slip_fraction * t + rng.gauss(0.0, 1.0) * cfg.slip_sigma_nm
                if rng.random() < 0.5:
                    s = -s
            out.append(s)
        return out[0], out[1]

    def run(self, n_steps: int) -> None:
        rb = self.robot
        h, h2, h6 = self.h, 0.5 * self.h, self.h / 6.0
        for _ in range(n_steps):
            k = rb._k
            t = k * h
            pending = rb._pending
            while pending and pending[0][0] <= t + _EPS_T:
                _, rb._duty_l, rb._duty_r = pending.popleft()
            while self.payloads and self.payloads[0].at_s <= t + _EPS_T:
                pl = self.payloads.pop(0)
                self._set_params(_with_payload(self.params, pl.mass_kg, pl.inertia_kgm2, pl.x_m, pl.y_m))
            db = self.deadband
            d = tuple(0.0 if abs(x) < db else x for x in (rb._duty_l, rb._duty_r))
            fs = self._floor_scale(rb._x, rb._y)
            self._engage(d)
            v, w, th = rb._v, rb._w, rb._th

            s1 = self._stage(v, w, d, fs, (0.0, 0.0))
            slip = self._slip_torques(s1[9])
            if slip != (0.0, 0.0):
                s1 = self._stage(v, w, d, fs, slip)
            self.tau = tuple(s1[9])
            v2, w2 = v + h2 * s1[0], w + h2 * s1[1]
            s2 = self._stage(v2, w2, d, fs, slip)
            v3, w3 = v + h2 * s2[0], w + h2 * s2[1]
            s3 = self._stage(v3, w3, d, fs, slip)
            v4, w4 = v + h * s3[0], w + h * s3[1]
            s4 = self._stage(v4, w4, d, fs, slip)
            th2, th3, th4 = th + h2 * w, th + h2 * w2, th + h * w3

            def rk(j: int) -> float:
                return h6 * (s1[j] + 2.0 * (s2[j] + s3[j]) + s4[j])

            ds = h6 * (v + 2.0 * (v2 + v3) + v4)
            dth = h6 * (w + 2.0 * (w2 + w3) + w4)
            rb._x += h6 * (v * math.cos(th) + 2.0 * (v2 * math.cos(th2) + v3 * math.cos(th3)) + v4 * math.cos(th4))
            rb._y += h6 * (v * math.sin(th) + 2.0 * (v2 * math.sin(th2) + v3 * math.sin(th3)) + v4 * math.sin(th4))
            rb._th = th + dth
            v_new, w_new = v + rk(0), w + rk(1)
            p = self.params
            self._free_motors(d, ((v_new - p.L * w_new) / p.r_L, (v_new + p.R * w_new) / p.r_R))
            rb._v, rb._w = v_new, w_new
            dphi_l, dphi_r = (ds - p.L * dth) / p.r_L, (ds + p.R * dth) / p.r_R
            dphi_3 = ds / p.r_3
            rb._phi_l += dphi_l
            rb._phi_r += dphi_r
            rb._phi_3 += dphi_3
            rb._w_em += rk(2)
            rb._w_fr += rk(3)
            rb._w_slip += slip[0] * dphi_l + slip[1] * dphi_r
            rb._tau_l, rb._tau_r = self.tau
            self.source_j += rk(4)
            self.internal_j += rk(5)
            self.armature_j += rk(6)
            self.free_motor_j += rk(7)
            self.charge_c += rk(8)
            if self.battery is not None:
                self.soc = min(1.0, max(0.0, self.battery.start_soc - self.charge_c / (3600.0 * self.battery.capacity_ah)))
            rb._k = k = k + 1
            t = k * h

            # Sensors at the end of the step.
            gauss = self.rng.gauss
            slip_per_nm = self.r.wheels.slip_per_nm
            self.c3 += dphi_3 * self.ou3.scale()
            self.cl += dphi_l * self.ou_l.scale() + slip_per_nm * self.tau[0] * abs(dphi_l)
            self.cr += dphi_r * self.ou_r.scale() + slip_per_nm * self.tau[1] * abs(dphi_r)
            for ou in (self.ou3, self.ou_l, self.ou_r):
                ou.step(gauss)
            z = rb._gyro_rng.gauss(0.0, 1.0)
            self.gf += self.g_a * (self.g_scale * w_new + self.bias_dps(t) + z * self.g_sig - self.gf)
            self.hist[k % self.n] = (self.c3, self.cl, self.cr, self.gf)
            if self.fifo_on:
                self._fill_fifo(k)
            # The pack's state now, for battery_v.
            wm = tuple(ww + (0.0 if self.side[i] else self.gap_rate[i])
                       for i, ww in enumerate(((v_new - p.L * w_new) / p.r_L, (v_new + p.R * w_new) / p.r_R)))
            volts = self._volts(d, wm)
            self.terminal_v = volts[0]
            self.current_a = sum(d[i] * self._motor(i, d[i], volts[i], wm[i])[0] for i in (0, 1))
        rb._gyro_f = self.gf
