"""Each sensor's fusion step of the estimator (ddrt/core/fusion.py), driven alone against an
expectation computed without it: the step sees only its channel of the Sample and a stand-in
for the estimator's public calls (`Sink`), which does the filter algebra or records the call."""

from __future__ import annotations

import dataclasses
import math
import random

import numpy as np
import pytest
from filterpy.kalman import KalmanFilter

from ddrt.config import load_config
from ddrt.core.front_encoder import FrontEncoder, NoFront
from ddrt.core.gyro_bias import DEG, StopsOnly, TemperatureBias
from ddrt.core.gyro_fifo import FifoRate
from ddrt.core.gyro_register import GyroRegister
from ddrt.core.kalman import TravelFilter, YawFilter
from ddrt.core.model import Dynamics
from ddrt.core.types import Sample
from ddrt.core.wheel_odometry import BIAS_WINDOW_S, NoWheels, WheelOdometry
from tests.support.repo import REPO

PERIOD = 0.005
LSB = 131.0 / DEG  # raw per rad/s at +-250 deg/s
CFG = load_config(REPO / "configs" / "sim.yaml")


class _Health:
    def __init__(self) -> None:
        self.slips = self.resyncs = 0

    def count_slip(self) -> None:
        self.slips += 1

    def count_resync(self) -> None:
        self.resyncs += 1


class Sink:
    """The estimator's side of a step, in the open: its public calls, each recorded, the
    travel and yaw calls also run on one plain filter each."""

    def __init__(self) -> None:
        self.cfg = CFG.estimator
        self.dyn = Dynamics.from_params(CFG.robot)
        self.period = PERIOD
        self.rad_s_per_lsb = 1.0 / LSB
        self.gyro_full_scale = 250.0 * DEG
        self.gyro_var = (self.cfg.gyro_noise_dps * DEG) ** 2
        self.gate2 = 25.0
        self.metres_per_count = 0.0
        self.travel = TravelFilter(0.0, 0.0)
        self.heading = YawFilter(0.0, 0.0, 0.0)
        self.yaw = YawFilter(0.0, 0.0, 0.0)
        self.health = _Health()
        self.faults: list[str] = []
        self.travels: list[tuple[bool, float, float]] = []
        self.rates: list[tuple[float, float, bool]] = []
        self.no_rates = 0
        self.biases: list[tuple[float, float]] = []
        self.widened = 0.0
        self.shifts: list[float] = []
        self.at_rest, self.rest_rate, self.t_est = False, math.nan, 0.0

    def set_fault(self, text: str) -> None:
        self.faults.append(text)

    def fuse_travel(self, moved: bool, z: float, dt: float) -> None:
        self.travels.append((moved, z, dt))
        self.travel.update(z)

    def fuse_rate(self, z: float, lead_dt: float, commanded_still: bool) -> None:
        self.rates.append((z, lead_dt, commanded_still))

    def fuse_no_rate(self) -> None:
        self.no_rates += 1

    def fuse_bias(self, z: float, var: float) -> None:
        self.biases.append((z, var))
        self.heading.update_bias(z, var)
        self.yaw.update_bias(z, var)

    def widen_bias(self, var: float) -> None:
        self.widened += var
        self.heading.widen_bias(var)
        self.yaw.widen_bias(var)

    def shift_bias(self, db: float) -> None:
        self.shifts.append(db)
        self.heading.shift_bias(db)


# ---------------------------------------------------------------------- the front encoder


@pytest.mark.parametrize("start", [0, 2**31 - 700, -(2**31) + 5])
def test_front_encoder_fuses_the_unwrapped_distance_as_filterpy_would(start: int) -> None:
    # A robot that speeds up and brakes over a counter that wraps (start near +-2^31): the
    # step's position is the true distance quantised, whatever the wrap, and the travel
    # filter fed by it steps with filterpy's on the count computed here, not by the step.
    mpc = 2.0 * math.pi * 0.025 / 2048
    sink = Sink()
    sink.travel.meas_var = mpc * mpc / 12.0
    sink.travel.accel_var = 4.0
    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.x = np.zeros((2, 1))
    kf.P = np.diag([sink.travel.p00, sink.travel.p11])
    kf.R = np.array([[mpc * mpc / 12.0]])
    kf.H = np.array([[1.0, 0.0]])
    step = FrontEncoder()
    step.configure(mpc)
    assert step.position_var == pytest.approx(mpc * mpc / 12.0)
    wrap = lambda c: (c + 2**31) % 2**32 - 2**31  # noqa: E731 - the MCU's signed 32-bit counter
    step.reset(Sample(0.0, wrap(start), 0))
    x = v = 0.0
    for i in range(1, 1500):
        a = 2.0 if i < 400 else (-1.5 if i > 1000 else 0.0)
        v += a * PERIOD
        x += v * PERIOD
        count = math.floor(x / mpc)
        sink.travel.predict(PERIOD, 0.0)
        step.fuse(sink, Sample(i * PERIOD, wrap(start + count), 0), PERIOD)
        F = np.array([[1.0, PERIOD], [0.0, 1.0]])
        q = sink.travel.accel_var
        G = np.array([[0.5 * PERIOD * PERIOD], [PERIOD]])
        kf.predict(F=F, Q=q * (G @ G.T))
        kf.update(np.array([[count * mpc]]))
        moved, z, dt = sink.travels[-1]
        assert z == pytest.approx(count * mpc, abs=1e-12) and dt == PERIOD
        assert moved == (count != math.floor((x - v * PERIOD) / mpc))
        assert abs(step.z - x) <= mpc
    assert sink.travel.p == pytest.approx(float(kf.x[0, 0]), abs=1e-9)
    assert sink.travel.v == pytest.approx(float(kf.x[1, 0]), abs=1e-6)
    assert abs(sink.travel.v - v) < 0.05


def test_front_encoder_catches_up_a_gap_and_rebases() -> None:
    step = FrontEncoder()
    step.configure(0.001)
    step.reset(Sample(0.0, 100, 0))
    step.catch_up(Sample(0.5, 350, 0))
    assert (step.ds, step.moved, step.z) == (pytest.approx(0.25), True, pytest.approx(0.25))
    step.rebase()
    step.catch_up(Sample(0.6, 350, 0))
    assert (step.ds, step.moved, step.z) == (0.0, False, 0.0)
    none = NoFront()
    sink = Sink()
    none.fuse(sink, Sample(0.1, 99, 0), PERIOD)
    assert sink.travels == [] and (none.ds, none.moved, none.position_var) == (0.0, False, 0.0)


# ---------------------------------------------------------------------- the gyro register


def test_gyro_register_fuses_each_reading_at_its_interval_and_watches_its_word() -> None:
    rng = random.Random(3)
    sink = Sink()
    step = GyroRegister()
    step.reset(Sample(0.0, 0, 5))
    t = 0.0
    for _ in range(200):
        dt = PERIOD * rng.uniform(0.8, 1.2)
        t += dt
        raw = rng.randint(-3000, 3000)
        step.fuse(sink, Sample(t, 0, raw), commanded_still=False)
        z, lead_dt, still = sink.rates[-1]
        assert z == pytest.approx(raw / LSB, rel=1e-12) and lead_dt == pytest.approx(dt) and not still
    assert sink.faults == []
    assert step.turn(0.7, 0.004, True) == pytest.approx(0.0028)
    # A word repeated stuck_gyro_ticks times after its first reading is a stuck gyro; full
    # scale a saturated one.
    n = CFG.estimator.stuck_gyro_ticks
    for i in range(n + 1):
        t += PERIOD
        step.fuse(sink, Sample(t, 0, 17), commanded_still=True)
        assert sink.faults == ([] if i < n else [f"gyro stuck at raw 17 for {n} samples"])
    sink.faults.clear()
    step.fuse(sink, Sample(t + PERIOD, 0, -32768), commanded_still=False)
    assert sink.faults == ["gyro saturated"]


# ---------------------------------------------------------------------- the gyro FIFO


def test_fifo_rate_fuses_each_batch_mean_and_turns_every_sample_once() -> None:
    # The gyro's clock runs 1 % slow against the loop's and the loop jitters: the heading the
    # step turns at the true rate is the rate times the time its samples really cover.
    rng = random.Random(11)
    w = 0.8  # rad/s, true and constant
    raw = round(w * LSB)
    true_period = PERIOD * 1.01
    sink = Sink()
    step = FifoRate(PERIOD)
    step.reset(Sample(0.0, 0, raw))
    produced = 0  # gyro samples produced since the reset
    t = heading = 0.0
    delivered = 0
    for i in range(4000):
        t += PERIOD * rng.uniform(0.7, 1.3)
        n = int(t / true_period) - produced
        produced += n
        fresh = i % 97 != 5  # now and then a stale tick: its samples come with the next
        if not fresh:
            carried = n
            heading += step.turn(w, PERIOD, False)
            continue
        if i % 97 == 6:
            n += carried
        s = Sample(t, 0, raw, gyro_n=n, gyro_sum_raw=n * raw)
        before = len(sink.rates)
        step.fuse(sink, s, commanded_still=False)
        if n > 0:
            delivered += n
            z, span, _ = sink.rates[-1]
            assert len(sink.rates) == before + 1 and z == pytest.approx(raw / LSB)
        heading += step.turn(w, PERIOD, True)
    assert delivered == produced and sink.no_rates > 0  # some ticks brought no sample
    assert step.fifo.learnt and step.fifo.period == pytest.approx(true_period, rel=2e-3)
    assert heading == pytest.approx(w * produced * true_period, abs=w * 2 * true_period)


def test_fifo_rate_fuses_no_junk_batch() -> None:
    sink = Sink()
    step = FifoRate(PERIOD)
    step.reset(Sample(0.0, 0, 0))
    step.fuse(sink, Sample(0.01, 0, 9, gyro_n=2, gyro_sum_raw=18), False)
    step.fuse(sink, Sample(0.02, 0, 9, gyro_n=40, gyro_sum_raw=360), False)  # 40 samples in 10 ms: junk
    assert len(sink.rates) == 1 and sink.no_rates == 1 and step.fifo.rejects == 1


# ---------------------------------------------------------------------- the temperature's bias


def test_temperature_bias_recovers_the_slope_of_a_warming_die() -> None:
    # The die warms 8 degC with a time constant of 60 s; the zero-rate output follows it at
    # 0.1 deg/s per degC. The robot drives 12 s, stands 2 s, again. The step sees the
    # temperature at 5 Hz and, at each stop, the raw rate; what it shifts the filter's bias by
    # between stops must follow the truth, and the slope it learns must be the truth's.
    rng = random.Random(5)
    k_true = 0.1 * DEG
    b0 = 0.4 * DEG
    temp = lambda t: 25.0 + 8.0 * (1.0 - math.exp(-t / 60.0))  # noqa: E731
    bias = lambda t: b0 + k_true * (temp(t) - 25.0)  # noqa: E731
    sink = Sink()
    sink.heading.b = b0  # the start-up calibration
    cfg = dataclasses.replace(CFG.estimator, gyro_bias_per_c_dps=None)  # the slope is to be learnt
    step = TemperatureBias(PERIOD, cfg)
    step.configure(cfg)
    assert step.line.fixed_k is None and step.line.k == 0.0
    t = 0.0
    worst_late = 0.0
    for i in range(int(150.0 / PERIOD)):
        t += PERIOD
        sink.t_est = t
        rest = (t % 14.0) > 12.0
        sink.at_rest = rest
        sink.rest_rate = bias(t) + rng.gauss(0.0, 0.05 * DEG)
        s = Sample(t, 0, 0, gyro_temp_c=temp(t) if i % 40 == 0 else math.nan)
        step.fuse(sink, s, True, PERIOD)
        if t > 60.0:
            worst_late = max(worst_late, abs(sink.heading.b - bias(t)))
    assert step.line.pairs >= 9
    assert step.line.k == pytest.approx(k_true, rel=0.1)
    assert worst_late < 0.02 * DEG  # the bias between stops follows the warming to a fiftieth of a deg/s
    assert sum(sink.shifts) == pytest.approx(bias(t) - b0, abs=0.02 * DEG)


def test_without_a_temperature_nothing_moves() -> None:
    sink = Sink()
    step = StopsOnly()
    assert step.line is None
    assert step.fuse(sink, Sample(1.0, 0, 0, gyro_temp_c=40.0), True, PERIOD) == 0.0 and sink.shifts == []


# ---------------------------------------------------------------------- the drive wheels


def _wheels(gives_distance: bool) -> tuple[WheelOdometry, Sink]:
    sink = Sink()
    sink.metres_per_count = 0.0 if gives_distance else 2.0 * math.pi * 0.025 / 2048
    step = WheelOdometry(1440, PERIOD, gives_distance)
    step.configure(sink)
    step.reset(Sample(0.0, 0, 0))
    return step, sink


def _drive(step: WheelOdometry, sink: Sink, seconds: float, v: float, gyro_rate: float, right_gain: float = 1.0,
           t0: float = 0.0, counts: list[float] | None = None) -> float:
    """Straight at v (m/s) with the gyro reading gyro_rate (its bias: the robot does not turn);
    the right wheel turns right_gain times the left's (it slips when not 1)."""
    dyn = sink.dyn
    per_l = 1440 / (2.0 * math.pi * dyn.r_L)
    per_r = 1440 / (2.0 * math.pi * dyn.r_R)
    c = counts if counts is not None else [0.0, 0.0]
    t = t0
    for _ in range(int(round(seconds / PERIOD))):
        t += PERIOD
        c[0] += v * PERIOD * per_l
        c[1] += v * PERIOD * per_r * right_gain
        s = Sample(t, 0, round(gyro_rate * LSB), count_left=int(c[0]), count_right=int(c[1]))
        step.take(s)
        sink.travel.predict(PERIOD, 0.0)
        step.fuse(sink, s, PERIOD, False, v * PERIOD)
    return t


def test_wheels_measure_the_gyros_bias_on_a_straight() -> None:
    # The gyro reads 0.3 deg/s while the wheels say straight: the first window measures that
    # itself, and what the step learns after (the bias, and the wheels' radius difference times
    # u, which at one speed cannot be told apart: stops do that) adds up to the gyro's turn less
    # the wheels', per second.
    step, sink = _wheels(gives_distance=False)
    for f in (sink.heading, sink.yaw):
        f.p11 = (0.5 * DEG) ** 2  # not calibrated yet
    bias = 0.3 * DEG
    read = round(bias * LSB) / LSB  # what the raw word says
    _drive(step, sink, 10.0, 0.3, bias)
    assert len(sink.biases) >= int(10.0 / BIAS_WINDOW_S) - 2
    assert sink.biases[0][0] == pytest.approx(read, rel=1e-9)  # nothing learnt yet: the window's own
    u = 0.3 / step.track_w
    assert sink.heading.b + step.delta * u == pytest.approx(read, abs=0.002 * DEG)
    assert abs(sink.heading.b) > 0.01 * DEG and abs(step.delta) > 0.0  # both took their share
    assert sink.widened > 0.0  # the bias's walk over each window
    assert sink.travels == []  # the front encoder gives the distance
    assert sink.health.slips == 0


def test_wheels_that_slip_are_flagged_once_and_give_no_bias() -> None:
    step, sink = _wheels(gives_distance=False)
    t = _drive(step, sink, 2.0, 0.3, 0.0)
    n = len(sink.biases)
    counts = [0.0, 0.0]
    _drive(step, sink, 0.3, 0.3, 0.0, right_gain=1.3, t0=t, counts=counts)  # the right wheel spins
    assert sink.health.slips == 1 and len(sink.biases) == n


def test_wheels_without_a_front_encoder_fuse_their_distance() -> None:
    step, sink = _wheels(gives_distance=True)
    assert step.position_var > 0.0
    sink.travel.meas_var = step.position_var
    sink.travel.accel_var = 1.0
    _drive(step, sink, 3.0, 0.4, 0.0)
    moved, z, _ = sink.travels[-1]
    assert moved and z == pytest.approx(0.4 * 3.0, abs=2e-3)  # within the counts' quantisation
    assert NoWheels().fuse(sink, Sample(0.0, 0, 0), PERIOD, False, 0.0) is False


# ---------------------------------------------------------------------- the composition


@pytest.mark.parametrize("front", [0, 2048])
@pytest.mark.parametrize("wheels", [0, 1440])
@pytest.mark.parametrize("fifo", [0.0, 0.005])
@pytest.mark.parametrize("temp_hz", [0.0, 5.0])
def test_the_estimator_takes_the_steps_the_hal_declares(front: int, wheels: int, fifo: float, temp_hz: float) -> None:
    from ddrt.core.estimator import Estimator
    from ddrt.core.motor import Motor
    from ddrt.core.types import HalInfo

    if not front and not wheels:
        return  # the HAL refuses a robot with neither (hal/real.py)
    info = HalInfo(encoder_counts_per_rev=front, gyro_lsb_per_rad_s=LSB, gyro_full_scale_rad_s=250 * DEG,
                   wheel_counts_per_rev=wheels, gyro_temp_hz=temp_hz, gyro_fifo_period_s=fifo)
    est = Estimator(Dynamics.from_params(CFG.robot), Motor(CFG.robot_motor), CFG.estimator, info, CFG.robot.r_3, PERIOD)
    assert (est.fifo is not None) == (fifo > 0.0)
    assert (est.wheels is not None) == (wheels > 0)
    assert (est.gyro_bias is not None) == (temp_hz > 0.0)
    assert (est.wheels is not None and est.wheels.gives_distance) == (front == 0)
    # Standing still at rest for a second: every combination runs the same tick and learns the bias.
    raw = 40  # the gyro's zero-rate output, in LSB
    est.reset(Sample(0.0, 0, raw), (0.0, 0.0, 0.0), raw / LSB)
    for i in range(1, 201):
        r = raw + i % 5 - 2  # a live gyro's noise: its mean is the bias
        est.update(Sample(i * PERIOD, 0, r, gyro_n=1 if fifo else 0, gyro_sum_raw=r if fifo else 0,
                          gyro_temp_c=30.0 if i % 40 == 0 else math.nan), 0.0, 0.0, True)
    assert est.health.fault == ""
    assert est.bias == pytest.approx(raw / LSB, abs=1.0 / LSB) and abs(est.theta) < 1e-5


def test_the_estimators_tick_asks_no_sensor_whether_it_is_there() -> None:
    # The tick runs the composed steps; the only None it looks at is "reset yet?".
    import ast
    import inspect
    import textwrap

    from ddrt.core.estimator import Estimator

    tree = ast.parse(textwrap.dedent(inspect.getsource(Estimator.update)))
    nones = [ast.unparse(n) for n in ast.walk(tree) if isinstance(n, ast.Compare)
             and any(isinstance(c, ast.Constant) and c.value is None for c in n.comparators)]
    assert nones == ["last_t is None"]
    names = {n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute)}
    assert not names & {"fifo", "wheels", "gyro_bias"}
