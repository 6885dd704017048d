"""The simulated robot: the truth the controller is tested against in CI.

One plant, specified once. The reduced model of ddrt/core/model.py (docs/model.md) plus pose
kinematics is integrated with RK4 at the plant's own fixed step, independent of the
controller's rate. Torques come from each wheel's DC motor model (ddrt/core/motor.py), with
the seed's random slip torque on top; duty commands and sensor readings are delayed like a
real driver and bus delay them; the sensors report raw integers (a wrapping 32-bit encoder
count, a saturating int16 gyro with bias, white noise and the MPU-6050's low-pass filter).

The plant's options (`PlantConfig.realism`, sim_hal/plant_config.py) add what real robots
have: a battery that sags under load, the gyro's die warm-up, drift and register timing, its
FIFO, the driver's deadband, gearbox backlash, encoder slip, payloads and floor patches. Each
is part of the same step below (`_step`), the readable reference integrator.

The compiled kernel (sim_hal/plant_kernel.c, plant_native.py) is the fast path: the same step,
every option included, bit for bit. Without a C compiler (or with DDRT_PLANT=python) the
Python step integrates.
"""

from __future__ import annotations

import ctypes
import math
import random
from collections import deque
from dataclasses import replace
from typing import Any, NamedTuple

from ddrt.config.sim_truth import LI_ION_CELL_OCV
from ddrt.core.model import Dynamics
from ddrt.params.robot import RobotParams
from ddrt.params.motor import MotorParams
from ddrt.params.gyro_scale import GYRO_LSB_PER_DPS

from sim_hal import plant_native, raw_readings
from sim_hal.plant_config import EnergyLedger, PlantConfig, Realism, SupplyLedger
from sim_hal.plant_effects import FIFO_SAMPLES, Wanderer, with_payload

__all__ = ["EnergyLedger", "PlantConfig", "Realism", "SimRobot", "SupplyLedger"]

_DEG_PER_RAD = 180.0 / math.pi
_TWO_PI = 2.0 * math.pi  # random.TWOPI: the kernel's gauss must match random.gauss bit for bit
_EPS_T = 1e-12  # times closer than this count as equal (float rounding of k * step)
_FIFO_CHUNK = 32  # with a FIFO, it is filled at least every this many steps (the rings hold them)


# Indices into the kernel's state buffer (plant_kernel.c's enum).
(_X, _Y, _TH, _V, _W, _PHL, _PHR, _PH3, _DL, _DR, _WEM, _WFR, _WSLIP, _GF, _TL, _TR,
 _SOC, _CHG, _SRC, _INT, _ARM, _FREE, _CUR, _VT, _C3, _CL, _CR, _OU3, _OUL, _OUR,
 _SDL, _SDR, _GPL, _GPR, _GRL, _GRR) = range(plant_native.NSTATE)


class _Consts(NamedTuple):
    """The step's constants, in plant_kernel.c's order (its c[] array)."""

    h: float
    h2: float
    h6: float
    a11: float  # the inverse of the mass matrix H
    a12: float
    a22: float
    mx: float
    big_l: float
    big_r: float
    irl: float  # 1 / r_L
    irr: float
    ir3: float
    cl: float  # left motor at the wheel: tau_em = cl * duty - el * w (its supply_v)
    el: float
    bl: float  # friction = bl * w + tcl * tanh(w * iwsl)
    tcl: float
    iwsl: float
    cr: float
    er: float
    br: float
    tcr: float
    iwsr: float
    slip_on: float
    slip_p: float
    slip_frac: float
    slip_sig: float
    g_a: float  # the gyro's low-pass coefficient per step
    g_sig: float
    g_scale: float
    g_bias: float
    two_pi: float
    deadband: float
    bias_varies: float  # the gyro's zero-rate bias follows g_bias + ... below
    g_per_c: float
    g_t0: float
    g_rise: float
    g_tau: float
    g_drift: float
    g_step: float
    g_step_at: float


class SimRobot:
    """A differential-drive robot integrated at a fixed step; see the module docstring."""

    def __init__(self, params: RobotParams, motor_l: MotorParams, motor_r: MotorParams,
                 cfg: PlantConfig | None = None,
                 start: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> None:
        cfg = PlantConfig() if cfg is None else cfg
        if len(start) != 3 or not all(math.isfinite(float(s)) for s in start):
            raise ValueError(f"start: expected finite (x, y, theta), got {start!r}")
        if not cfg.friction:
            motor_l = replace(motor_l, viscous_nms=0.0, coulomb_nm=0.0)
            motor_r = replace(motor_r, viscous_nms=0.0, coulomb_nm=0.0)
        self.params = params
        self.motor_l = motor_l
        self.motor_r = motor_r
        self.cfg = cfg
        opt = self.options = cfg.realism
        self.dynamics = Dynamics.from_params(params)  # the body now (payloads change it)
        self._body = params
        self._h = h = 1.0 / cfg.step_hz
        self._k = 0  # steps taken; sim time is k * h, so it does not drift

        # Truth state.
        self._x, self._y, self._th = (float(s) for s in start)
        self._v = self._w = 0.0
        self._phi_l = self._phi_r = self._phi_3 = 0.0
        self._duty_l = self._duty_r = 0.0
        self._tau_l = self._tau_r = 0.0
        self._w_em = self._w_fr = self._w_slip = 0.0
        self._pending: deque[tuple[float, float, float]] = deque()

        seed = cfg.seed
        self._slip_rng = random.Random(None if seed is None else f"{seed}/slip")
        self._gyro_rng = random.Random(None if seed is None else f"{seed}/gyro")
        self._real_rng = random.Random(None if seed is None else f"{seed}/realism")

        # Options' state: the battery, the gearboxes' play, the counted angles, the events.
        bat = opt.battery
        self._soc = bat.start_soc if bat is not None else 1.0
        self._charge_c = self._source_j = self._internal_j = self._armature_j = self._free_motor_j = 0.0
        self._current_a = 0.0
        self._terminal_v = bat.ocv_v(self._soc) if bat is not None else 0.5 * (motor_l.supply_v + motor_r.supply_v)
        self._half_play = math.radians(opt.actuators.backlash_deg) / 2.0
        self._side = [1, 1] if self._half_play == 0.0 else [0, 0]  # +-1 on a flank, 0 free in the play
        self._gap = [0.0, 0.0]  # motor angle minus wheel angle (rad at the wheel)
        self._gap_rate = [0.0, 0.0]
        self._counts_slip = opt.encoder_slip.active or opt.wheels != Realism().wheels
        self._ou3 = Wanderer(opt.encoder_slip, h)
        self._ou_l = Wanderer(opt.wheels.scale, h)
        self._ou_r = Wanderer(opt.wheels.scale, h)
        self._c3 = self._cl = self._cr = 0.0  # counted angles (rad) of the omni and drive wheels
        self._payloads = sorted(opt.events.payloads, key=lambda p: p.at_s)

        # Gyro: state in deg/s after the low-pass, started where it would have settled.
        self._gyro_lsb_per_dps = GYRO_LSB_PER_DPS[cfg.gyro_range_dps]
        self._gyro_a = raw_readings.lowpass_coefficient(cfg.gyro_dlpf_hz, cfg.step_hz)
        self._gyro_sigma = cfg.gyro_noise_dps_rthz * math.sqrt(cfg.step_hz / 2.0)
        self._gyro_f = self.gyro_bias_dps_at(0.0)
        odr = opt.gyro_odr_hz
        self._odr_period = 0.0 if odr == 0.0 else 1.0 / (odr * (1.0 + opt.gyro_clock_ppm * 1e-6))
        self._fifo: list[int] = []
        self._fifo_overflow = False
        self._fifo_next = 1  # index of the next sample instant
        self.fifo_pushed = 0  # samples that went into the FIFO since the start

        # Sensor rings at plant-step resolution: the readings of the last steps (counted angles,
        # the filtered gyro), long enough for the sensor latency and the register's sample period.
        self._sensor_delay = max(0, math.ceil(cfg.sensor_latency_s * cfg.step_hz - 1e-9))
        n = self._sensor_delay + 1
        if self._odr_period:
            n += 2 + math.ceil(self._odr_period / h) + _FIFO_CHUNK
        self._n_ring = n
        self._ring_phi3: Any = [0.0] * n
        self._ring_gyro: Any = [self._gyro_f] * n
        self._ring_phl: Any = [0.0] * n
        self._ring_phr: Any = [0.0] * n

        self._pyc = self._constants()  # the step's constants (the kernel's copy: `_cbuf`)
        # The compiled kernel, else None (no C compiler, or DDRT_PLANT=python): the Python step.
        # With the kernel, the state lives in its buffer `_st` (the properties read it).
        self._st: Any = None
        self._q: Any = None
        self._kernel = plant_native.kernel()
        if self._kernel is not None:
            self._native_setup()

    # --- commands and time -------------------------------------------------------------

    @property
    def t(self) -> float:
        """Simulated time (s) since the start."""
        return self._k * self._h

    @property
    def step_s(self) -> float:
        return self._h

    @property
    def integrator(self) -> str:
        """"kernel" (compiled) or "python" (the reference step: no C compiler, or DDRT_PLANT=python)."""
        return "python" if self._kernel is None else "kernel"

    def command(self, duty_l: float, duty_r: float) -> None:
        """Queue a duty pair; it reaches the motors `command_latency_s` from now."""
        dl, dr = float(duty_l), float(duty_r)
        if not -1.0 <= dl <= 1.0:
            raise ValueError(f"duty_l={duty_l!r} is outside [-1, 1] or not finite")
        if not -1.0 <= dr <= 1.0:
            raise ValueError(f"duty_r={duty_r!r} is outside [-1, 1] or not finite")
        t_apply = self._k * self._h + self.cfg.command_latency_s
        if self._kernel is None:
            self._pending.append((t_apply, dl, dr))
            return
        # The kernel's queue (see _queue_alloc), inline: this runs every tick.
        tail, cap = self._q_tail, self._q_cap
        if tail - self._q[0] >= cap:
            self._queue_alloc(2 * cap)
            tail, cap = self._q_tail, self._q_cap
        h = self._h
        k = self._k
        j = k if k > self._q_last else self._q_last
        while t_apply > j * h + _EPS_T:
            j += 1
        self._q_last = j
        i = tail % cap
        self._q_step[i] = j
        duty = self._q_duty
        duty[2 * i] = dl
        duty[2 * i + 1] = dr
        self._q[1] = self._q_tail = tail + 1

    def advance_to(self, t: float) -> None:
        """Integrate whole plant steps until the sim time is >= t (within float rounding)."""
        if not math.isfinite(t):
            raise ValueError(f"advance_to: t={t!r} is not finite")
        fs = self.cfg.step_hz
        target = max(0, math.floor(t * fs))
        while target / fs < t - _EPS_T:
            target += 1
        while target > 0 and (target - 1) / fs >= t - _EPS_T:
            target -= 1
        n = target - self._k
        if n <= 0:
            return
        if self.options.gyro_fifo:  # the FIFO is filled from the rings, which hold a chunk
            while n > 0:
                m = min(n, _FIFO_CHUNK)
                self._run(m)
                self._fill_fifo()
                n -= m
            return
        kernel = self._kernel
        if kernel is not None and not self._payloads:  # _run, inline: this runs every controller tick
            kernel(n, self._plant_addr)
            self._k = self._kbuf.value
        else:
            self._run(n)

    # --- sensors, delayed by the sensor latency ------------------------------------------

    def _ring_index(self) -> int:
        return max(self._k - self._sensor_delay, 0) % self._n_ring

    def read_encoder(self) -> int:
        """Front encoder count as the hardware counter holds it (signed 32-bit, wrapping)."""
        phi3 = self._ring_phi3[self._ring_index()]
        return raw_readings.encoder_count(phi3, self.cfg.encoder_counts_per_rev, self.cfg.encoder_offset_counts)

    def read_sensors(self) -> tuple[int, int]:
        """(read_encoder(), read_gyro_raw()) from one look-up of the sensor ring (SimHal.read's,
        every controller tick)."""
        if self._odr_period:
            return self.read_encoder(), self.read_gyro_raw()
        k = self._k - self._sensor_delay
        i = (k if k > 0 else 0) % self._n_ring  # _ring_index()
        cfg = self.cfg
        return (raw_readings.encoder_count(self._ring_phi3[i], cfg.encoder_counts_per_rev, cfg.encoder_offset_counts),
                raw_readings.gyro_raw(self._ring_gyro[i], self._gyro_lsb_per_dps))

    def read_gyro_raw(self) -> int:
        """Gyro z as the int16 the MPU-6050 reports at its configured range (bias included)."""
        return raw_readings.gyro_raw(self._gyro_register_dps(), self._gyro_lsb_per_dps)

    def _gyro_register_dps(self) -> float:
        """The rate in the gyro's output register (deg/s, before quantisation): the filtered
        rate at the read time, or with a sample clock at its last sample instant."""
        k_read = self._k - self._sensor_delay
        if self._odr_period == 0.0:
            return self._ring_gyro[max(k_read, 0) % self._n_ring]
        t_read = max(k_read, 0) * self._h
        period = self._odr_period
        return self._sampled(math.floor(t_read / period + 1e-9) * period, k_read)

    def _sampled(self, t_s: float, k_read: int) -> float:
        """The filtered rate at sample instant t_s (deg/s), between the plant's steps linearly."""
        ring, n, h = self._ring_gyro, self._n_ring, self._h
        j = math.floor(t_s / h + 1e-9)
        frac = t_s / h - j
        g0 = ring[max(j, 0) % n]
        if frac <= 1e-9 or j + 1 > k_read:
            return g0
        return g0 + frac * (ring[(j + 1) % n] - g0)

    def _fill_fifo(self) -> None:
        """Push every sample instant up to the sensors' read time (as old as a register read)."""
        k_read = self._k - self._sensor_delay
        t_read = max(k_read, 0) * self._h
        period = self._odr_period
        lsb = self._gyro_lsb_per_dps
        while self._fifo_next * period <= t_read + 1e-9:
            self._fifo.append(raw_readings.gyro_raw(self._sampled(self._fifo_next * period, k_read), lsb))
            self._fifo_next += 1
            self.fifo_pushed += 1
            if len(self._fifo) > FIFO_SAMPLES:
                del self._fifo[0]
                self._fifo_overflow = True

    @property
    def gyro_fifo(self) -> bool:
        """The gyro's FIFO is filled (`Realism.gyro_fifo`, from `sensors.gyro_fifo`)."""
        return self.options.gyro_fifo

    def read_gyro_fifo(self) -> tuple[list[int], bool]:
        """Drain the gyro's FIFO: every raw sample (int16) produced since the last drain, oldest
        first, as old as `read_gyro_raw`'s reading; and True when some were lost to a full FIFO
        (512 samples). ValueError without a FIFO."""
        if not self.gyro_fifo:
            raise ValueError("read_gyro_fifo: this plant has no gyro FIFO (sensors.gyro_fifo is off)")
        out, lost = self._fifo, self._fifo_overflow
        self._fifo = []
        self._fifo_overflow = False
        return out, lost

    def read_wheel_counts(self) -> tuple[int, int]:
        """The drive wheels' encoder counters (left, right; signed 32-bit, wrapping), as old as
        the front encoder's reading; (0, 0) when `wheel_counts_per_rev` is 0 (not counted)."""
        cpr = self.cfg.wheel_counts_per_rev
        if cpr == 0:
            return 0, 0
        i = self._ring_index()
        return (raw_readings.encoder_count(self._ring_phl[i], cpr), raw_readings.encoder_count(self._ring_phr[i], cpr))

    @property
    def wheel_counts_per_rev(self) -> int:
        return self.cfg.wheel_counts_per_rev

    @property
    def battery_v(self) -> float:
        """Terminal voltage at the motor driver now (V): the battery's under load when
        `realism.battery` is set, else the motors' supply_v (their mean when per-wheel motors
        were given two), a source with no internal resistance."""
        st = self._st
        return self._terminal_v if st is None else st[_VT]

    @property
    def supply(self) -> SupplyLedger:
        """The battery's state and energy (see SupplyLedger)."""
        st = self._st
        if st is not None:
            soc = st[_SOC]
            bat = self.options.battery
            ocv = bat.ocv_v(soc) if bat is not None else st[_VT]
            return SupplyLedger(ocv, st[_VT], st[_CUR], soc, st[_CHG], st[_SRC], st[_INT], st[_ARM], st[_FREE])
        return SupplyLedger(self._ocv_v(), self._terminal_v, self._current_a, self._soc, self._charge_c,
                            self._source_j, self._internal_j, self._armature_j, self._free_motor_j)

    @property
    def backlash_side(self) -> tuple[int, int]:
        """Each gearbox's motor: on its front (1) or back (-1) flank, or free in the play (0)."""
        st = self._st
        if st is not None:
            return int(st[_SDL]), int(st[_SDR])
        return self._side[0], self._side[1]

    @property
    def gyro_die_temp_c(self) -> float:
        """The gyro's die temperature now (degC): what its TEMP_OUT register reports."""
        return self.die_temp_at(self.t)

    def die_temp_at(self, t: float) -> float:
        o = self.options
        return o.gyro_temp_start_c + o.gyro_warmup_rise_c * (1.0 - math.exp(-t / o.gyro_warmup_tau_s))

    def gyro_bias_dps_at(self, t: float) -> float:
        """The gyro's zero-rate output at sim time t (deg/s): PlantConfig.gyro_bias_dps plus the
        options' warm-up, drift and step."""
        o = self.options
        if not o.gyro_bias_varies:
            return self.cfg.gyro_bias_dps
        b = (self.cfg.gyro_bias_dps + o.gyro_bias_per_c_dps * (self.die_temp_at(t) - o.gyro_temp_start_c)
             + o.gyro_drift_dps_per_s * t)
        if o.gyro_bias_step_dps != 0.0 and t >= o.gyro_bias_step_at_s:
            b += o.gyro_bias_step_dps
        return b

    @property
    def encoder_counts_per_rev(self) -> int:
        return self.cfg.encoder_counts_per_rev

    @property
    def gyro_lsb_per_rad_s(self) -> float:
        return self._gyro_lsb_per_dps * _DEG_PER_RAD

    @property
    def gyro_delay_s(self) -> float:
        """Low-frequency group delay of the simulated low-pass: (1 - a) / a plant steps."""
        a = self._gyro_a
        return (1.0 - a) / a * self._h

    @property
    def gyro_hold_s(self) -> float:
        """How long the gyro's output register holds a sample (`sim.gyro.register_hold`: one
        sample period of its own clock); 0: read at the tick."""
        return self._odr_period

    @property
    def gyro_full_scale_rad_s(self) -> float:
        return raw_readings.INT16_MAX / self.gyro_lsb_per_rad_s

    # --- truth, for tests and logs -------------------------------------------------------

    @property
    def pose(self) -> tuple[float, float, float]:
        """(x, y, theta) of A, mid rear axle; theta is continuous (not wrapped)."""
        st = self._st
        if st is not None:
            return st[0], st[1], st[2]
        return self._x, self._y, self._th

    def truth(self) -> list[float]:
        """[x, y, theta, v, omega]: `pose` and `velocity` in one list (`ddrt sim`'s telemetry row)."""
        st = self._st
        if st is not None:
            return st[0:5]  # one ctypes read of the kernel's state buffer
        return [self._x, self._y, self._th, self._v, self._w]

    @property
    def velocity(self) -> tuple[float, float]:
        """(v, omega): forward speed of A (m/s) and yaw rate (rad/s)."""
        st = self._st
        if st is not None:
            return st[3], st[4]
        return self._v, self._w

    @property
    def wheel_angles(self) -> tuple[float, float, float]:
        """(phi_L, phi_R, phi_3) in rad since the start."""
        st = self._st
        if st is not None:
            return st[5], st[6], st[7]
        return self._phi_l, self._phi_r, self._phi_3

    @property
    def applied_duty(self) -> tuple[float, float]:
        """The duties the motors' driver gets now (commands after their latency, before its deadband)."""
        st = self._st
        if st is not None:
            return st[8], st[9]
        return self._duty_l, self._duty_r

    @property
    def wheel_torque(self) -> tuple[float, float]:
        """Net wheel torques (N m, friction and slip included) at the start of the last step."""
        st = self._st
        if st is not None:
            return st[14], st[15]
        return self._tau_l, self._tau_r

    @property
    def energy(self) -> EnergyLedger:
        st = self._st
        if st is not None:
            return EnergyLedger(st[10], st[11], st[12])
        return EnergyLedger(self._w_em, self._w_fr, self._w_slip)

    # --- the integrator -------------------------------------------------------------------

    def _constants(self) -> _Consts:
        """The step's constants, derived once (and again when a payload changes the body)."""
        cfg, o = self.cfg, self.options
        h = self._h
        dyn = self.dynamics
        det = dyn.m_k * dyn.I - dyn.mbar * dyn.mbar
        p = self._body
        ml, mr = self.motor_l, self.motor_r
        return _Consts(
            h, 0.5 * h, h / 6.0,
            dyn.I / det, -dyn.mbar / det, dyn.m_k / det,
            dyn.m_x, p.L, p.R, 1.0 / p.r_L, 1.0 / p.r_R, 1.0 / p.r_3,
            ml.k_nm_per_a * ml.supply_v / ml.resistance_ohm, ml.k_nm_per_a * ml.k_nm_per_a / ml.resistance_ohm,
            ml.viscous_nms, ml.coulomb_nm, 1.0 / ml.coulomb_smoothing_rad_s,
            mr.k_nm_per_a * mr.supply_v / mr.resistance_ohm, mr.k_nm_per_a * mr.k_nm_per_a / mr.resistance_ohm,
            mr.viscous_nms, mr.coulomb_nm, 1.0 / mr.coulomb_smoothing_rad_s,
            float(cfg.slip and cfg.slip_probability > 0.0), cfg.slip_probability, cfg.slip_fraction,
            cfg.slip_sigma_nm,
            self._gyro_a, self._gyro_sigma, (1.0 + cfg.gyro_scale_error) * _DEG_PER_RAD, cfg.gyro_bias_dps,
            _TWO_PI, o.actuators.deadband, float(o.gyro_bias_varies), o.gyro_bias_per_c_dps,
            o.gyro_temp_start_c, o.gyro_warmup_rise_c, o.gyro_warmup_tau_s, o.gyro_drift_dps_per_s,
            o.gyro_bias_step_dps, o.gyro_bias_step_at_s,
        )

    def _run(self, n_steps: int) -> None:
        """Take `n_steps` RK4 steps: the kernel's, or the Python step's. The kernel stops at
        each payload's step, where the body and its constants change as `_step` changes them."""
        if self._kernel is None:
            for _ in range(n_steps):
                self._step()
            return
        end = self._k + n_steps
        while self._k < end:
            stop = end
            if self._payloads:
                j = max(self._k, self._first_step_at(self._payloads[0].at_s))
                if j == self._k:
                    pl = self._payloads.pop(0)
                    self._set_body(with_payload(self._body, pl.mass_kg, pl.inertia_kgm2, pl.x_m, pl.y_m))
                    continue
                stop = min(end, j)
            self._kernel(stop - self._k, self._plant_addr)
            self._k = self._kbuf.value

    def _first_step_at(self, t: float) -> int:
        """The first step whose start time k * h is at or after t (within _EPS_T): where `_step`
        applies what happens at t."""
        h = self._h
        j = max(0, math.ceil((t - _EPS_T) / h))
        while j > 0 and (j - 1) * h + _EPS_T >= t:
            j -= 1
        while j * h + _EPS_T < t:
            j += 1
        return j

    def _ocv_v(self) -> float:
        bat = self.options.battery
        return bat.ocv_v(self._soc) if bat is not None else self._terminal_v

    def _pack_v(self, dl: float, dr: float, ml: float, mr: float) -> float:
        """The pack's terminal voltage with duties (dl, dr) on motors turning at (ml, mr) (rad/s
        at the wheel): V = E - R_int I, I = sum(d_i (d_i V - k_i m_i) / R_i), solved for V."""
        bat = self.options.battery
        if bat is None:
            return self._terminal_v
        ri = bat.resistance_ohm
        num, den = self._ocv_v(), 1.0
        for d, m, mot in ((dl, ml, self.motor_l), (dr, mr, self.motor_r)):
            num += ri * d * mot.k_nm_per_a * m / mot.resistance_ohm
            den += ri * d * d / mot.resistance_ohm
        return num / den

    def _wheel_torques(self, c: _Consts, v: float, w: float, dl: float, dr: float, fs: float) -> tuple:
        """At (v, w) with driver duties (dl, dr) and the floor's friction scale fs: the wheel
        torques without slip and the powers (electromagnetic into the wheels, friction, out of
        the battery's open-circuit source, into its resistance, into the armatures, into motors
        turning free in the play) and the pack current.

        Without a battery each motor sees its own supply_v (tau = c duty - e w); with one, the
        pack's terminal voltage. A motor free in the play turns at the wheel's speed plus the
        gap's rate and gives its wheel no torque."""
        wl = (v - c.big_l * w) * c.irl
        wr = (v + c.big_r * w) * c.irr
        fl = fs * (c.bl * wl + c.tcl * math.tanh(wl * c.iwsl))
        fr = fs * (c.br * wr + c.tcr * math.tanh(wr * c.iwsr))
        side = self._side
        if side[0] and side[1] and self.options.battery is None:  # the seed's motors, both driving
            eml = c.cl * dl - c.el * wl
            emr = c.cr * dr - c.er * wr
            return eml - fl, emr - fr, eml * wl + emr * wr, fl * wl + fr * wr, 0.0, 0.0, 0.0, 0.0, 0.0
        ml = wl if side[0] else wl + self._gap_rate[0]
        mr = wr if side[1] else wr + self._gap_rate[1]
        if self.options.battery is None:
            eml, emr = c.cl * dl - c.el * ml, c.cr * dr - c.er * mr
            cur_l = (dl * self.motor_l.supply_v - self.motor_l.k_nm_per_a * ml) / self.motor_l.resistance_ohm
            cur_r = (dr * self.motor_r.supply_v - self.motor_r.k_nm_per_a * mr) / self.motor_r.resistance_ohm
        else:
            volts = self._pack_v(dl, dr, ml, mr)
            cur_l = (dl * volts - self.motor_l.k_nm_per_a * ml) / self.motor_l.resistance_ohm
            cur_r = (dr * volts - self.motor_r.k_nm_per_a * mr) / self.motor_r.resistance_ohm
            eml, emr = self.motor_l.k_nm_per_a * cur_l, self.motor_r.k_nm_per_a * cur_r
        p_em = p_free = 0.0
        if side[0]:
            tl, p_em = eml - fl, eml * wl
        else:
            tl, p_free = -fl, eml * ml
        if side[1]:
            tr, p_em = emr - fr, p_em + emr * wr
        else:
            tr, p_free = -fr, p_free + emr * mr
        ib = dl * cur_l + dr * cur_r
        bat = self.options.battery
        ri = bat.resistance_ohm if bat is not None else 0.0
        p_arm = self.motor_l.resistance_ohm * cur_l * cur_l + self.motor_r.resistance_ohm * cur_r * cur_r
        return tl, tr, p_em, fl * wl + fr * wr, self._ocv_v() * ib, ri * ib * ib, p_arm, p_free, ib

    @staticmethod
    def _accel(c: _Consts, v: float, w: float, tl: float, tr: float) -> tuple[float, float]:
        """d(v, w)/dt under wheel torques (tl, tr): H^-1 (Bbar tau - h(eta))."""
        ul, ur = tl * c.irl, tr * c.irr
        fv = ul + ur + c.mx * w * w
        fw = c.big_r * ur - c.big_l * ul - c.mx * v * w
        return c.a11 * fv + c.a12 * fw, c.a12 * fv + c.a22 * fw

    def _slip_torque(self, c: _Consts, tau: float) -> float:
        """The seed's random slip on one wheel's torque (drawn from the slip generator)."""
        rng = self._slip_rng
        if rng.random() >= c.slip_p:
            return 0.0
        s = c.slip_frac * tau + rng.gauss(0.0, 1.0) * c.slip_sig
        return -s if rng.random() < 0.5 else s

    def _floor_scale(self) -> float:
        for f in self.options.events.floor:
            if f.x_min <= self._x <= f.x_max and f.y_min <= self._y <= f.y_max:
                return f.friction_scale
        return 1.0

    def _step(self) -> None:
        """One RK4 step of the plant with its options: the reference the kernel follows."""
        c = self._pyc
        h, h2, h6 = c.h, c.h2, c.h6
        k = self._k
        t = k * h
        pending = self._pending
        while pending and pending[0][0] <= t + _EPS_T:
            _, self._duty_l, self._duty_r = pending.popleft()
        while self._payloads and self._payloads[0].at_s <= t + _EPS_T:
            pl = self._payloads.pop(0)
            self._set_body(with_payload(self._body, pl.mass_kg, pl.inertia_kgm2, pl.x_m, pl.y_m))
            c = self._pyc
        db = c.deadband
        dl = 0.0 if abs(self._duty_l) < db else self._duty_l
        dr = 0.0 if abs(self._duty_r) < db else self._duty_r
        fs = self._floor_scale() if self.options.events.floor else 1.0
        if self._half_play:
            self._release(c, dl, dr)
        v, w, th = self._v, self._w, self._th

        # Stage 1 (also fixes the slip torque for the whole step).
        s1 = self._wheel_torques(c, v, w, dl, dr, fs)
        sl = sr = 0.0
        if c.slip_on:
            sl = self._slip_torque(c, s1[0])
            sr = self._slip_torque(c, s1[1])
        tl, tr = s1[0] + sl, s1[1] + sr
        dv1, dw1 = self._accel(c, v, w, tl, tr)
        v2, w2, th2 = v + h2 * dv1, w + h2 * dw1, th + h2 * w
        s2 = self._wheel_torques(c, v2, w2, dl, dr, fs)
        dv2, dw2 = self._accel(c, v2, w2, s2[0] + sl, s2[1] + sr)
        v3, w3, th3 = v + h2 * dv2, w + h2 * dw2, th + h2 * w2
        s3 = self._wheel_torques(c, v3, w3, dl, dr, fs)
        dv3, dw3 = self._accel(c, v3, w3, s3[0] + sl, s3[1] + sr)
        v4, w4, th4 = v + h * dv3, w + h * dw3, th + h * w3
        s4 = self._wheel_torques(c, v4, w4, dl, dr, fs)
        dv4, dw4 = self._accel(c, v4, w4, s4[0] + sl, s4[1] + sr)

        def rk(j: int) -> float:
            return h6 * (s1[j] + 2.0 * (s2[j] + s3[j]) + s4[j])

        # Combine. Wheel angles are linear in (v, omega), so their RK4 increments follow from
        # the path length s and heading change of the step.
        cos, sin = math.cos, math.sin
        ds = h6 * (v + 2.0 * (v2 + v3) + v4)
        dth = h6 * (w + 2.0 * (w2 + w3) + w4)
        self._x += h6 * (v * cos(th) + 2.0 * (v2 * cos(th2) + v3 * cos(th3)) + v4 * cos(th4))
        self._y += h6 * (v * sin(th) + 2.0 * (v2 * sin(th2) + v3 * sin(th3)) + v4 * sin(th4))
        self._th = th + dth
        v_new = v + h6 * (dv1 + 2.0 * (dv2 + dv3) + dv4)
        w_new = w + h6 * (dw1 + 2.0 * (dw2 + dw3) + dw4)
        if self._half_play:
            self._free_motors(c, dl, dr, v_new, w_new)
        self._v, self._w = v_new, w_new
        dphi_l = (ds - c.big_l * dth) * c.irl
        dphi_r = (ds + c.big_r * dth) * c.irr
        dphi_3 = ds * c.ir3
        self._phi_l += dphi_l
        self._phi_r += dphi_r
        self._phi_3 += dphi_3
        self._w_em += rk(2)
        self._w_fr += rk(3)
        self._w_slip += sl * dphi_l + sr * dphi_r
        self._tau_l, self._tau_r = tl, tr
        bat = self.options.battery
        if bat is not None or self._half_play:
            self._source_j += rk(4)
            self._internal_j += rk(5)
            self._armature_j += rk(6)
            self._free_motor_j += rk(7)
            self._charge_c += rk(8)
        if bat is not None:
            self._soc = min(1.0, max(0.0, bat.start_soc - self._charge_c / (3600.0 * bat.capacity_ah)))
            wl = (v_new - c.big_l * w_new) * c.irl + (0.0 if self._side[0] else self._gap_rate[0])
            wr = (v_new + c.big_r * w_new) * c.irr + (0.0 if self._side[1] else self._gap_rate[1])
            volts = self._pack_v(dl, dr, wl, wr)
            self._terminal_v = volts
            self._current_a = sum(d * (d * volts - m.k_nm_per_a * x) / m.resistance_ohm
                                  for d, x, m in ((dl, wl, self.motor_l), (dr, wr, self.motor_r)))
        self._k = k = k + 1
        self._sense(c, k, dphi_l, dphi_r, dphi_3, tl, tr)

    def _sense(self, c: _Consts, k: int, dphi_l: float, dphi_r: float, dphi_3: float, tl: float, tr: float) -> None:
        """The sensors at the end of step k: the counted angles (with the encoders' slip when
        that option is on) and the gyro, whose low-pass runs at the plant rate."""
        if self._counts_slip:
            spn = self.options.wheels.slip_per_nm
            self._c3 += dphi_3 * self._ou3.scale()
            self._cl += dphi_l * self._ou_l.scale() + spn * tl * abs(dphi_l)
            self._cr += dphi_r * self._ou_r.scale() + spn * tr * abs(dphi_r)
            gauss = self._real_rng.gauss
            for ou in (self._ou3, self._ou_l, self._ou_r):
                ou.step(gauss)
            c3, cl, cr = self._c3, self._cl, self._cr
        else:
            c3, cl, cr = self._phi_3, self._phi_l, self._phi_r
        bias = self.gyro_bias_dps_at(k * c.h) if c.bias_varies else c.g_bias
        noise = self._gyro_rng.gauss(0.0, c.g_sig)
        self._gyro_f += c.g_a * (c.g_scale * self._w + bias + noise - self._gyro_f)
        i = k % self._n_ring
        self._ring_phi3[i] = c3
        self._ring_gyro[i] = self._gyro_f
        self._ring_phl[i] = cl
        self._ring_phr[i] = cr

    def _set_body(self, p: RobotParams) -> None:
        """A payload merged: the dynamics and the step's constants (the kernel's copy too)
        follow the new body."""
        self._body = p
        self.dynamics = Dynamics.from_params(p)
        self._pyc = self._constants()
        if self._st is not None:
            self._cbuf[:len(self._pyc)] = [float(x) for x in self._pyc]

    # --- gearbox backlash -----------------------------------------------------------------

    def _release(self, c: _Consts, dl: float, dr: float) -> None:
        """At the start of a step: a motor whose torque turns away from its flank leaves it."""
        wl = (self._v - c.big_l * self._w) * c.irl
        wr = (self._v + c.big_r * self._w) * c.irr
        volts = self._pack_v(dl, dr, wl, wr)
        for i, (d, ww, m) in enumerate(((dl, wl, self.motor_l), (dr, wr, self.motor_r))):
            side = self._side[i]
            if side:
                supply = volts if self.options.battery is not None else m.supply_v
                em = m.k_nm_per_a * (d * supply - m.k_nm_per_a * ww) / m.resistance_ohm
                if side * em <= 0.0:
                    self._side[i] = 0
                    self._gap_rate[i] = 0.0

    def _free_motors(self, c: _Consts, dl: float, dr: float, v_new: float, w_new: float) -> None:
        """Advance the motors turning in the play by one step, exactly for the step's voltage: a
        free motor relaxes to duty V / k at the rate of its back-EMF's damping, k^2 / (R J). An
        explicit step diverges once that rate times the step passes 2 (a strong gearmotor's
        k at the wheel on the default 2e-4 kg m^2: the motor then chatters across the play and
        never drives its wheel)."""
        h, jm, half = c.h, self.options.actuators.motor_inertia_kgm2, self._half_play
        wl_old = (self._v - c.big_l * self._w) * c.irl
        wr_old = (self._v + c.big_r * self._w) * c.irr
        ww_new = ((v_new - c.big_l * w_new) * c.irl, (v_new + c.big_r * w_new) * c.irr)
        wm = (wl_old + self._gap_rate[0], wr_old + self._gap_rate[1])
        volts = self._pack_v(dl, dr, wm[0], wm[1])
        for i, (d, m) in enumerate(((dl, self.motor_l), (dr, self.motor_r))):
            if self._side[i]:
                continue
            supply = volts if self.options.battery is not None else m.supply_v
            rate = m.k_nm_per_a ** 2 / (m.resistance_ohm * jm)
            settled = d * supply / m.k_nm_per_a
            new = settled + (wm[i] - settled) * math.exp(-rate * h)
            self._gap_rate[i] = new - ww_new[i]
            self._gap[i] += h * self._gap_rate[i]
            if abs(self._gap[i]) >= half:
                self._side[i] = 1 if self._gap[i] > 0 else -1
                self._gap[i] = math.copysign(half, self._gap[i])
                self._gap_rate[i] = 0.0  # inelastic: the motor takes the wheel's speed

    # --- the compiled kernel ----------------------------------------------------------------

    def _kernel_constants(self) -> list[float]:
        """The kernel's c[]: _Consts, the options' constants, the battery's OCV table and the
        floor patches (plant_kernel.c's layout after NC)."""
        o, ml, mr = self.options, self.motor_l, self.motor_r
        bat = o.battery
        table: tuple[tuple[float, float], ...] = ()
        ocv_mul = 1.0
        if bat is not None:
            table = bat.ocv_table or LI_ION_CELL_OCV
            ocv_mul = 1.0 if bat.ocv_table else float(bat.cells)
        extra = [
            float(bat is not None), bat.resistance_ohm if bat is not None else 0.0,
            ml.k_nm_per_a, ml.resistance_ohm, mr.k_nm_per_a, mr.resistance_ohm,
            bat.start_soc if bat is not None else 1.0, bat.capacity_ah if bat is not None else 1.0, ocv_mul,
            float(self._counts_slip), o.wheels.slip_per_nm,
            *(x for ou in (self._ou3, self._ou_l, self._ou_r) for x in (ou.mean, ou.a, ou.k)),
            self._half_play, o.actuators.motor_inertia_kgm2, ml.supply_v, mr.supply_v,
            float(len(table)), float(len(o.events.floor)),
        ]
        tables = [float(x) for pair in table for x in pair]
        tables += [float(x) for f in o.events.floor for x in (f.x_min, f.y_min, f.x_max, f.y_max, f.friction_scale)]
        return [float(x) for x in self._pyc] + extra + tables

    def _native_setup(self) -> None:
        """Move the state, constants, generators and sensor rings into the C kernel's buffers;
        from here on those buffers hold them (the state attributes are no longer updated)."""
        c_double = ctypes.c_double
        self._st = (c_double * plant_native.NSTATE)(
            self._x, self._y, self._th, self._v, self._w, self._phi_l, self._phi_r, self._phi_3,
            self._duty_l, self._duty_r, self._w_em, self._w_fr, self._w_slip, self._gyro_f, self._tau_l, self._tau_r,
            self._soc, self._charge_c, self._source_j, self._internal_j, self._armature_j, self._free_motor_j,
            self._current_a, self._terminal_v, self._c3, self._cl, self._cr, self._ou3.s, self._ou_l.s, self._ou_r.s,
            *self._side, *self._gap, *self._gap_rate)
        consts = self._kernel_constants()
        self._cbuf = (c_double * len(consts))(*consts)
        self._rngs = (plant_native.Rng.from_random(self._slip_rng), plant_native.Rng.from_random(self._gyro_rng),
                      plant_native.Rng.from_random(self._real_rng))
        n = self._n_ring
        self._ring_phi3 = (c_double * n)(*self._ring_phi3)
        self._ring_gyro = (c_double * n)(*self._ring_gyro)
        self._ring_phl = (c_double * n)(*self._ring_phl)
        self._ring_phr = (c_double * n)(*self._ring_phr)
        self._kbuf = ctypes.c_int64(self._k)
        self._q_last = 0  # step at which the last queued command applies
        self._queue_alloc(64)

    def _queue_alloc(self, cap: int) -> None:
        """(Re)allocate the kernel's command ring with room for `cap`, keeping what is queued."""
        old: list[tuple[int, float, float]] = []
        if self._q is not None:
            head, tail, old_cap = self._q
            old = [(self._q_step[i % old_cap], self._q_duty[2 * (i % old_cap)], self._q_duty[2 * (i % old_cap) + 1])
                   for i in range(head, tail)]
        self._q = (ctypes.c_int64 * 3)(0, 0, cap)
        self._q_step = (ctypes.c_int64 * cap)()
        self._q_duty = (ctypes.c_double * (2 * cap))()
        for i, (j, dl, dr) in enumerate(old):
            self._q_step[i], self._q_duty[2 * i], self._q_duty[2 * i + 1] = j, dl, dr
        self._q[1] = self._q_tail = len(old)  # tail and capacity mirrored: fewer ctypes reads
        self._q_cap = cap
        # command() queues at the first step whose start time k*h is (within _EPS_T) at or
        # after the command's time, and not before the command ahead of it: the step at which
        # the Python step would pop it from `_pending`.
        a = ctypes.addressof
        self._plant = plant_native.Plant(a(self._kbuf), a(self._st), a(self._cbuf), a(self._rngs[0]), a(self._rngs[1]),
                                         a(self._ring_phi3), a(self._ring_gyro), self._n_ring,
                                         a(self._q), a(self._q_step), a(self._q_duty),
                                         a(self._ring_phl), a(self._ring_phr), a(self._rngs[2]))
        self._plant_addr = a(self._plant)
