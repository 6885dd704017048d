"""The simulated robot: the truth the controller is tested against in CI.

The reduced model of ddrt/core/model.py (docs/model.md) plus pose kinematics is integrated with RK4
at the plant's own fixed step, independent of the controller's rate. Torques come from each
wheel's DC motor model (ddrt/core/motor.py), with the seed's random slip torque on top; duty
commands and sensor readings are delayed like a real driver and bus delay them; the sensors
report raw integers (a wrapping 32-bit encoder count, a saturating int16 gyro with bias,
white noise and the MPU-6050's low-pass filter).

Speed matters (a closed-loop CI run must go >= 100x real time), so the inner step is plain
float arithmetic on locals: the motor and model formulas are inlined there with their
constants taken from `Motor`'s parameters and `Dynamics`; tests check the inlined torque
against `Motor.torque` and the motion against an independent derivation of the model.

A plant with anything but the default `PlantConfig.realism` (a battery, gyro warm-up and
register timing, encoder slip, deadband, backlash, events) integrates in Python,
in sim_hal/plant_real.py, never in the compiled kernel: the default plant keeps its fast,
bit-identical path and the realistic one is written once.
"""

from __future__ import annotations

import ctypes
import math
import random
from collections import deque
from dataclasses import replace
from typing import Any

from ddrt.core.model import Dynamics
from ddrt.params.robot import RobotParams
from ddrt.params.motor import MotorParams
from ddrt.params.gyro_scale import GYRO_LSB_PER_DPS

from sim_hal import plant_native, raw_readings
from sim_hal.plant_config import EnergyLedger, PlantConfig, Realism

__all__ = ["EnergyLedger", "PlantConfig", "Realism", "SimRobot"]

_DEG_PER_RAD = 180.0 / math.pi
_TWO_PI = 2.0 * math.pi  # random.TWOPI: the inlined gauss must match random.gauss bit for bit
_EPS_T = 1e-12  # times closer than this count as equal (float rounding of k * step)


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
        self.dynamics = Dynamics.from_params(params)
        self._consts: tuple | None = None  # _constants(), on first use
        self._h = 1.0 / cfg.step_hz
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

        # Gyro: state in deg/s after the low-pass, started where it would have settled.
        self._gyro_lsb_per_dps = GYRO_LSB_PER_DPS[cfg.gyro_range_dps]
        self._gyro_a = raw_readings.lowpass_coefficient(cfg.gyro_dlpf_hz, cfg.step_hz)
        self._gyro_sigma = cfg.gyro_noise_dps_rthz * math.sqrt(cfg.step_hz / 2.0)
        self._gyro_f = cfg.gyro_bias_dps

        # Sensor ring at plant-step resolution: the readings of the last `delay + 1` steps.
        self._sensor_delay = max(0, math.ceil(cfg.sensor_latency_s * cfg.step_hz - 1e-9))
        n = self._n_ring = self._sensor_delay + 1
        self._ring_phi3: Any = [0.0] * n
        self._ring_gyro: Any = [self._gyro_f] * n
        self._ring_phl: Any = [0.0] * n  # the drive wheels' angles, for their encoders
        self._ring_phr: Any = [0.0] * n

        # Issue 23's realism: the Python integrator of plant_real.py (imported only then).
        self._real: Any = None
        if cfg.realism.active:
            from sim_hal.plant_real import RealisticPlant

            self._real = RealisticPlant(self)

        # The compiled kernel (plant_native.py says why), else None: the Python below. With the
        # kernel, the state lives in its buffer `_st` (the properties read it), else in attributes.
        self._st: Any = None
        self._kernel = plant_native.kernel() if self._real is None else None
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
        if n > 0:
            kernel = self._kernel
            if kernel is not None:  # _run_native, inline: this runs every controller tick
                kernel(n, self._plant_addr)
                self._k = self._kbuf.value
            else:
                self._run(n)

    # --- sensors, delayed by the sensor latency ------------------------------------------

    def _ring_index(self) -> int:
        n = len(self._ring_phi3)
        return max(self._k - self._sensor_delay, 0) % n

    def read_encoder(self) -> int:
        """Front encoder count as the hardware counter holds it (signed 32-bit, wrapping)."""
        if self._real is not None:
            return self._real.read_encoder()
        phi3 = self._ring_phi3[self._ring_index()]
        return raw_readings.encoder_count(phi3, self.cfg.encoder_counts_per_rev, self.cfg.encoder_offset_counts)

    def read_sensors(self) -> tuple[int, int]:
        """(read_encoder(), read_gyro_raw()) from one look-up of the sensor ring (SimHal.read's,
        every controller tick)."""
        if self._real is not None:
            return self.read_encoder(), self.read_gyro_raw()
        k = self._k - self._sensor_delay
        i = (k if k > 0 else 0) % self._n_ring  # _ring_index()
        cfg = self.cfg
        return (raw_readings.encoder_count(self._ring_phi3[i], cfg.encoder_counts_per_rev, cfg.encoder_offset_counts),
                raw_readings.gyro_raw(self._ring_gyro[i], self._gyro_lsb_per_dps))

    def read_gyro_raw(self) -> int:
        """Gyro z as the int16 the MPU-6050 reports at its configured range (bias included)."""
        if self._real is not None:
            return raw_readings.gyro_raw(self._real.gyro_dps(), self._gyro_lsb_per_dps)
        return raw_readings.gyro_raw(self._ring_gyro[self._ring_index()], self._gyro_lsb_per_dps)

    @property
    def gyro_fifo(self) -> bool:
        """The gyro's FIFO is filled (`Realism.gyro_fifo`, from `sensors.gyro_fifo`)."""
        return self._real is not None and self._real.fifo_on

    def read_gyro_fifo(self) -> tuple[list[int], bool]:
        """Drain the gyro's FIFO: every raw sample (int16) produced since the last drain, oldest
        first, as old as `read_gyro_raw`'s reading; and True when some were lost to a full FIFO
        (512 samples). ValueError without a FIFO."""
        if not self.gyro_fifo:
            raise ValueError("read_gyro_fifo: this plant has no gyro FIFO (sensors.gyro_fifo is off)")
        return self._real.read_fifo()

    def read_wheel_counts(self) -> tuple[int, int]:
        """The drive wheels' encoder counters (left, right; signed 32-bit, wrapping), as old as
        the front encoder's reading; (0, 0) when `wheel_counts_per_rev` is 0 (not counted)."""
        cpr = self.cfg.wheel_counts_per_rev
        if cpr == 0:
            return 0, 0
        if self._real is not None:
            return self._real.read_wheel_counts(cpr)
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
        if self._real is not None and self._real.battery is not None:
            return self._real.terminal_v
        return 0.5 * (self.motor_l.supply_v + self.motor_r.supply_v)

    @property
    def gyro_die_temp_c(self) -> float:
        """The gyro's die temperature now (degC): what its TEMP_OUT register reports."""
        if self._real is not None:
            return self._real.die_temp_c(self.t)
        return self.cfg.realism.gyro_temp_start_c

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
        return self._real.odr_period if self._real is not None else 0.0

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
        """The duties the motors see now (commands after their latency)."""
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

    def _constants(self) -> tuple:
        """The integrator's constants, derived once (the parameters are fixed after __init__):
        deriving them on every `_run` call cost several microseconds a controller tick."""
        cfg = self.cfg
        h = self._h
        dyn = self.dynamics
        det = dyn.m_k * dyn.I - dyn.mbar * dyn.mbar
        p = self.params
        ml, mr = self.motor_l, self.motor_r
        # Motor at the wheel: tau_em = c*duty - e*w; friction = b*w + tc*tanh(w/ws).
        return (
            h, 0.5 * h, h / 6.0,
            dyn.I / det, -dyn.mbar / det, dyn.m_k / det,  # inverse mass matrix
            dyn.m_x, p.L, p.R, 1.0 / p.r_L, 1.0 / p.r_R, 1.0 / p.r_3,
            ml.k_nm_per_a * ml.supply_v / ml.resistance_ohm, ml.k_nm_per_a * ml.k_nm_per_a / ml.resistance_ohm,
            ml.viscous_nms, ml.coulomb_nm, 1.0 / ml.coulomb_smoothing_rad_s,
            mr.k_nm_per_a * mr.supply_v / mr.resistance_ohm, mr.k_nm_per_a * mr.k_nm_per_a / mr.resistance_ohm,
            mr.viscous_nms, mr.coulomb_nm, 1.0 / mr.coulomb_smoothing_rad_s,
            cfg.slip and cfg.slip_probability > 0.0, cfg.slip_probability, cfg.slip_fraction, cfg.slip_sigma_nm,
            self._gyro_a, self._gyro_sigma, (1.0 + cfg.gyro_scale_error) * _DEG_PER_RAD, cfg.gyro_bias_dps,
        )

    def _native_setup(self) -> None:
        """Move the state, constants, generators and sensor rings into the C kernel's buffers;
        from here on those buffers hold them (the state attributes are no longer updated)."""
        c_double = ctypes.c_double
        self._st = (c_double * plant_native.NSTATE)(
            self._x, self._y, self._th, self._v, self._w, self._phi_l, self._phi_r, self._phi_3,
            self._duty_l, self._duty_r, self._w_em, self._w_fr, self._w_slip, self._gyro_f, self._tau_l, self._tau_r)
        consts = self._constants()
        self._c = (c_double * (len(consts) + 1))(*(float(c) for c in consts), _TWO_PI)
        self._rngs = (plant_native.Rng.from_random(self._slip_rng), plant_native.Rng.from_random(self._gyro_rng))
        n = len(self._ring_phi3)
        self._ring_phi3 = (c_double * n)(*self._ring_phi3)
        self._ring_gyro = (c_double * n)(*self._ring_gyro)
        self._ring_phl = (c_double * n)(*self._ring_phl)
        self._ring_phr = (c_double * n)(*self._ring_phr)
        self._kbuf = ctypes.c_int64(self._k)
        self._q_last = 0  # step at which the last queued command applies
        self._queue_alloc(64)

    def _queue_alloc(self, cap: int) -> None:
        """(Re)allocate the kernel's command ring with room for `cap`, keeping what is queued."""
        old = None
        if hasattr(self, "_q"):
            head, tail, old_cap = self._q
            old = [(self._q_step[i % old_cap], self._q_duty[2 * (i % old_cap)], self._q_duty[2 * (i % old_cap) + 1])
                   for i in range(head, tail)]
        self._q = (ctypes.c_int64 * 3)(0, 0, cap)
        self._q_step = (ctypes.c_int64 * cap)()
        self._q_duty = (ctypes.c_double * (2 * cap))()
        for i, (j, dl, dr) in enumerate(old or ()):
            self._q_step[i], self._q_duty[2 * i], self._q_duty[2 * i + 1] = j, dl, dr
        self._q[1] = self._q_tail = len(old or ())  # tail and capacity mirrored: fewer ctypes reads
        self._q_cap = cap
        # command() queues at the first step whose start time k*h is (within _EPS_T) at or
        # after the command's time, and not before the command ahead of it: the step at which
        # the Python integrator would pop it from `_pending`.
        a = ctypes.addressof
        self._plant = plant_native.Plant(a(self._kbuf), a(self._st), a(self._c), a(self._rngs[0]), a(self._rngs[1]),
                                         a(self._ring_phi3), a(self._ring_gyro), len(self._ring_phi3),
                                         a(self._q), a(self._q_step), a(self._q_duty),
                                         a(self._ring_phl), a(self._ring_phr))
        self._plant_addr = a(self._plant)

    def _run_native(self, n_steps: int) -> None:
        """`_run` by the C kernel, in one call (it applies the queued commands on time)."""
        self._kernel(n_steps, self._plant_addr)
        self._k = self._kbuf.value

    def _run(self, n_steps: int) -> None:
        """Take `n_steps` RK4 steps. Hot path: locals only, formulas inlined.

        The four stages repeat the same few lines on purpose: a derivative function called
        four times per step (with its tuple) costs about a third of the plant's speed, and the
        closed loop must run hundreds of times faster than real time. For the same reason the
        constants come from one cached tuple, `c * duty` is formed once per duty change, and
        `random.gauss` is inlined (the same Box-Muller, draws and pair cache as CPython's,
        so the noise is the same bit for bit; the cache is written back to the generator).
        """
        if self._kernel is not None:
            self._run_native(n_steps)
            return
        if self._real is not None:
            self._real.run(n_steps)
            return
        consts = self._consts
        if consts is None:
            consts = self._consts = self._constants()
        (h, h2, h6, a11, a12, a22, mx, big_l, big_r, irl, irr, ir3,
         cl, el, bl, tcl, iwsl, cr, er, br, tcr, iwsr,
         slip_on, slip_p, slip_frac, slip_sig, g_a, g_sig, g_scale, g_bias) = consts
        tanh, sin, cos, log, sqrt = math.tanh, math.sin, math.cos, math.log, math.sqrt
        two_pi = _TWO_PI
        slip_rng, gyro_rng = self._slip_rng, self._gyro_rng
        srand, grand = slip_rng.random, gyro_rng.random
        s_next, g_next = slip_rng.gauss_next, gyro_rng.gauss_next
        ring_phi3, ring_gyro, ring_phl, ring_phr = self._ring_phi3, self._ring_gyro, self._ring_phl, self._ring_phr
        n_ring = len(ring_phi3)
        pending = self._pending

        x, y, th, v, w = self._x, self._y, self._th, self._v, self._w
        phi_l, phi_r, phi_3 = self._phi_l, self._phi_r, self._phi_3
        dl, dr = self._duty_l, self._duty_r
        cdl, cdr = cl * dl, cr * dr
        w_em, w_fr, w_slip = self._w_em, self._w_fr, self._w_slip
        gf = self._gyro_f
        k = self._k
        tl = tr = 0.0
        for _ in range(n_steps):
            if pending:
                t_now = k * h + _EPS_T
                while pending and pending[0][0] <= t_now:
                    _, dl, dr = pending.popleft()
                    cdl, cdr = cl * dl, cr * dr

            # Stage 1 (also fixes the slip torque for the whole step).
            wl = (v - big_l * w) * irl
            wr = (v + big_r * w) * irr
            eml = cdl - el * wl
            emr = cdr - er * wr
            frl = bl * wl + tcl * tanh(wl * iwsl)
            frr = br * wr + tcr * tanh(wr * iwsr)
            tl = eml - frl
            tr = emr - frr
            sl = sr = 0.0
            if slip_on:
                if srand() < slip_p:
                    z, s_next = s_next, None
                    if z is None:
                        x2pi = srand() * two_pi
                        g2rad = sqrt(-2.0 * log(1.0 - srand()))
                        z = cos(x2pi) * g2rad
                        s_next = sin(x2pi) * g2rad
                    sl = slip_frac * tl + z * slip_sig
                    if srand() < 0.5:
                        sl = -sl
                if srand() < slip_p:
                    z, s_next = s_next, None
                    if z is None:
                        x2pi = srand() * two_pi
                        g2rad = sqrt(-2.0 * log(1.0 - srand()))
                        z = cos(x2pi) * g2rad
                        s_next = sin(x2pi) * g2rad
                    sr = slip_frac * tr + z * slip_sig
                    if srand() < 0.5:
                        sr = -sr
                tl += sl
                tr += sr
            ul, ur = tl * irl, tr * irr
            fv = ul + ur + mx * w * w
            fw = big_r * ur - big_l * ul - mx * v * w
            dv1 = a11 * fv + a12 * fw
            dw1 = a12 * fv + a22 * fw
            pem = eml * wl + emr * wr
            pfr = frl * wl + frr * wr
            v1, w1, th1 = v, w, th

            # Stage 2.
            v2 = v + h2 * dv1
            w2 = w + h2 * dw1
            th2 = th + h2 * w1
            wl = (v2 - big_l * w2) * irl
            wr = (v2 + big_r * w2) * irr
            eml = cdl - el * wl
            emr = cdr - er * wr
            frl = bl * wl + tcl * tanh(wl * iwsl)
            frr = br * wr + tcr * tanh(wr * iwsr)
            ul = (eml - frl + sl) * irl
            ur = (emr - frr + sr) * irr
            fv = ul + ur + mx * w2 * w2
            fw = big_r * ur - big_l * ul - mx * v2 * w2
            dv2 = a11 * fv + a12 * fw
            dw2 = a12 * fv + a22 * fw
            pem += 2.0 * (eml * wl + emr * wr)
            pfr += 2.0 * (frl * wl + frr * wr)

            # Stage 3.
            v3 = v + h2 * dv2
            w3 = w + h2 * dw2
            th3 = th + h2 * w2
            wl = (v3 - big_l * w3) * irl
            wr = (v3 + big_r * w3) * irr
            eml = cdl - el * wl
            emr = cdr - er * wr
            frl = bl * wl + tcl * tanh(wl * iwsl)
            frr = br * wr + tcr * tanh(wr * iwsr)
            ul = (eml - frl + sl) * irl
            ur = (emr - frr + sr) * irr
            fv = ul + ur + mx * w3 * w3
            fw = big_r * ur - big_l * ul - mx * v3 * w3
            dv3 = a11 * fv + a12 * fw
            dw3 = a12 * fv + a22 * fw
            pem += 2.0 * (eml * wl + emr * wr)
            pfr += 2.0 * (frl * wl + frr * wr)

            # Stage 4.
            v4 = v + h * dv3
            w4 = w + h * dw3
            th4 = th + h * w3
            wl = (v4 - big_l * w4) * irl
            wr = (v4 + big_r * w4) * irr
            eml = cdl - el * wl
            emr = cdr - er * wr
            frl = bl * wl + tcl * tanh(wl * iwsl)
            frr = br * wr + tcr * tanh(wr * iwsr)
            ul = (eml - frl + sl) * irl
            ur = (emr - frr + sr) * irr
            fv = ul + ur + mx * w4 * w4
            fw = big_r * ur - big_l * ul - mx * v4 * w4
            dv4 = a11 * fv + a12 * fw
            dw4 = a12 * fv + a22 * fw
            pem += eml * wl + emr * wr
            pfr += frl * wl + frr * wr

            # Combine. Wheel angles are linear in (v, omega), so their RK4 increments follow
            # from the path length s and heading change of the step.
            ds = h6 * (v1 + 2.0 * (v2 + v3) + v4)
            dth = h6 * (w1 + 2.0 * (w2 + w3) + w4)
            x += h6 * (v1 * cos(th1) + 2.0 * (v2 * cos(th2) + v3 * cos(th3)) + v4 * cos(th4))
            y += h6 * (v1 * sin(th1) + 2.0 * (v2 * sin(th2) + v3 * sin(th3)) + v4 * sin(th4))
            th += dth
            v += h6 * (dv1 + 2.0 * (dv2 + dv3) + dv4)
            w += h6 * (dw1 + 2.0 * (dw2 + dw3) + dw4)
            dphi_l = (ds - big_l * dth) * irl
            dphi_r = (ds + big_r * dth) * irr
            phi_l += dphi_l
            phi_r += dphi_r
            phi_3 += ds * ir3
            w_em += h6 * pem
            w_fr += h6 * pfr
            w_slip += sl * dphi_l + sr * dphi_r
            k += 1

            # Sensors at the end of the step: the gyro's low-pass runs at the plant rate.
            z, g_next = g_next, None
            if z is None:
                x2pi = grand() * two_pi
                g2rad = sqrt(-2.0 * log(1.0 - grand()))
                z = cos(x2pi) * g2rad
                g_next = sin(x2pi) * g2rad
            gf += g_a * (g_scale * w + g_bias + (0.0 + z * g_sig) - gf)
            i = k % n_ring
            ring_phi3[i] = phi_3
            ring_gyro[i] = gf
            ring_phl[i] = phi_l
            ring_phr[i] = phi_r

        self._x, self._y, self._th, self._v, self._w = x, y, th, v, w
        self._phi_l, self._phi_r, self._phi_3 = phi_l, phi_r, phi_3
        self._duty_l, self._duty_r = dl, dr
        self._tau_l, self._tau_r = tl, tr
        self._w_em, self._w_fr, self._w_slip = w_em, w_fr, w_slip
        self._gyro_f = gf
        self._k = k
        slip_rng.gauss_next, gyro_rng.gauss_next = s_next, g_next
