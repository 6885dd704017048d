"""The dead-reckoned pose's uncertainty: a 6-state error covariance, propagated from the
odometry's own increments, and the short history a late pose fix is fused against.

Error state e = (ex, ey, eth, es, eg, eb), true = estimate + error:
- ex, ey, eth: the pose's error (m, m, rad);
- es: the encoder's relative scale error (true distance = counted distance x (1 + es));
- eg: the gyro's relative scale error (true turn = integrated turn x (1 + eg));
- eb: the gyro bias's error (rad/s; the true turn gains eb per second).

es and eg are constants the odometry does not know (its configured r_3 and gyro_scale are
taken as exact; the map frame learns them from pose fixes); eb drifts as a random walk
(estimator.uncertainty_bias_walk, at least the bias filters' gyro_bias_walk) and is
re-learnt whenever the robot stands still (the estimator's at-rest update, which this
follows). A step of the dead reckoning (ds along
the midpoint heading th_m, dth, dt) moves the error by

    ex  += -ds sin(th_m) eth + ds cos(th_m) es
    ey  +=  ds cos(th_m) eth + ds sin(th_m) es
    eth += dth eg + dt eb            (+ the gyro's white noise, + the bias's walk)

so over an interval a..b the transition Phi is the identity plus sums of the increments,
which the history keeps as running sums (per tick: t, x, y, th of the map's dead reckoning
and the steps weighted by their midpoint heading and time): Phi for any interval of the
history is a few subtractions, exact for this linear error model whatever its length.
That is what lets the covariance be propagated only every few ticks (`Tracker`: every
20 ms, off the per-tick cost) and a fix stamped in the past be fused against the pose and
covariance of its own time (ddrt/core/pose_fix.py). docs/estimation.md derives the figures
and holds the model against a Monte-Carlo of the dead reckoning (tests/test_uncertainty.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

from ddrt.config import EstimatorConfig

N = 6
IX, IY, ITH, IS, IG, IB = range(N)
DEG = math.pi / 180.0


@dataclass(frozen=True, slots=True)
class ErrorModel:
    """The 1-sigma figures the covariance grows from, all derived from the estimator's config
    (docs/estimation.md): nothing here is tuned to a scenario."""

    encoder_scale_std: float  # relative, 1 sigma (estimator.encoder_scale_std)
    gyro_scale_std: float  # relative, 1 sigma (estimator.gyro_scale_std)
    bias0_std: float  # rad/s after the start-up calibration: gyro noise / sqrt(samples)
    bias_walk: float  # rad/s per sqrt(s) (estimator.uncertainty_bias_walk, at least gyro_bias_walk)
    heading_walk: float  # rad per sqrt(s): the gyro's white noise integrated (angle random walk)

    @classmethod
    def from_config(cls, cfg: EstimatorConfig, period_s: float) -> "ErrorModel":
        noise = cfg.gyro_noise_dps * DEG  # rad/s, one sample
        samples = max(10, int(round(cfg.calibration_s / period_s)))
        # The calibration averages `samples` readings of independent noise (the MPU's low-pass
        # at 98 Hz keeps readings 5 ms apart nearly independent); a sample's noise summed over
        # one period each gives an angle variance of noise^2 * period per second.
        # The bias filters' walk (gyro_bias_walk) is a tuning; what the bias error may really do
        # between two rests or fixes is the gyro's drift, which a warming part makes far larger.
        walk = max(cfg.gyro_bias_walk, cfg.uncertainty_bias_walk)
        return cls(cfg.encoder_scale_std, cfg.gyro_scale_std, noise / math.sqrt(samples),
                   walk, noise * math.sqrt(period_s))


def zero_cov() -> list[float]:
    return [0.0] * (N * N)


def initial_cov(model: ErrorModel, pose_cov: list[float] | None = None) -> list[float]:
    """The covariance at a reset: the pose's own (zero: exactly known) and the parameters'."""
    p = zero_cov()
    if pose_cov is not None:
        for i in range(3):
            for j in range(3):
                p[i * N + j] = pose_cov[i * 3 + j]
    p[IS * N + IS] = model.encoder_scale_std ** 2
    p[IG * N + IG] = model.gyro_scale_std ** 2
    p[IB * N + IB] = model.bias0_std ** 2
    return p


def propagate(p: list[float], g: tuple[float, ...], c: float, s: float, dt: float, model: ErrorModel) -> None:
    """P = Phi P Phi' + Q in place, for Phi = I + G with G's entries
    g = (g02, g03, g04, g05, g12, g13, g14, g15, g24, g25) in the odometry's frame, rotated
    into the covariance's frame by (c, s) = (cos, sin) of its angle (map -> odom), and the
    noise of `dt` seconds: the bias's walk and the heading's random walk."""
    a02, a03, a04, a05, a12, a13, a14, a15, g24, g25 = g
    if s != 0.0 or c != 1.0:  # the position rows turn with the frame
        a02, a12 = c * a02 - s * a12, s * a02 + c * a12
        a03, a13 = c * a03 - s * a13, s * a03 + c * a13
        a04, a14 = c * a04 - s * a14, s * a04 + c * a14
        a05, a15 = c * a05 - s * a15, s * a05 + c * a15
    # A = Phi P: rows 0, 1, 2 change (from the old rows 2..5).
    for j in range(N):
        p2, p3, p4, p5 = p[12 + j], p[18 + j], p[24 + j], p[30 + j]
        p[j] += a02 * p2 + a03 * p3 + a04 * p4 + a05 * p5
        p[6 + j] += a12 * p2 + a13 * p3 + a14 * p4 + a15 * p5
        p[12 + j] = p2 + g24 * p4 + g25 * p5
    # P' = A Phi': columns 0, 1, 2 likewise.
    for i in range(0, N * N, N):
        p2, p3, p4, p5 = p[i + 2], p[i + 3], p[i + 4], p[i + 5]
        p[i] += a02 * p2 + a03 * p3 + a04 * p4 + a05 * p5
        p[i + 1] += a12 * p2 + a13 * p3 + a14 * p4 + a15 * p5
        p[i + 2] = p2 + g24 * p4 + g25 * p5
    qb = model.bias_walk * model.bias_walk
    if dt > 0.0:
        q22 = qb * dt * dt * dt / 3.0 + model.heading_walk * model.heading_walk * dt
        q25 = qb * dt * dt * 0.5
        p[14] += q22
        p[17] += q25
        p[32] += q25
        p[35] += qb * dt


def condition_bias(p: list[float], var: float) -> float:
    """The estimator re-learnt the bias at rest, to `var` (rad/s)^2: its new estimate is the
    old one moved by a gain k towards readings whose noise is independent of everything
    before, so eb' = (1 - k) eb + k n with (1 - k) = var / P[eb, eb]. Its correlations shrink
    by that factor; what the old bias error did to the heading and position stays (the
    estimator corrects the bias, not the pose it already integrated). Returns 1 - k: the map's
    own learnt bias correction shrinks by it too (ddrt/core/pose_fix.py)."""
    pbb = p[35]
    if not var < pbb:
        return 1.0
    f = max(var, 0.0) / pbb
    for i in range(N - 1):
        p[i * N + IB] *= f
        p[IB * N + i] *= f
    p[35] = max(var, 0.0)
    return f


class History:
    """The last `capacity` ticks of the odometry as running sums, in preallocated lists.

    Per tick: the time, the odometry's pose (x, y, th; th unwrapped) and the running sums
    of the steps weighted by their midpoint heading and time, S(dx th), S(dy th), S(dx t),
    S(dy t), from which `phi` builds the transition between any two of them."""

    __slots__ = ("cap", "n", "head", "t", "x", "y", "th", "xth", "yth", "xt", "yt", "_sums")

    def __init__(self, capacity: int) -> None:
        self.cap = max(2, capacity)
        self.t = [0.0] * self.cap
        self.x = [0.0] * self.cap
        self.y = [0.0] * self.cap
        self.th = [0.0] * self.cap
        self.xth = [0.0] * self.cap
        self.yth = [0.0] * self.cap
        self.xt = [0.0] * self.cap
        self.yt = [0.0] * self.cap
        self.n = 0  # ticks recorded since the reset (the newest is n - 1)
        self.head = 0  # where the newest is
        self._sums = [0.0, 0.0, 0.0, 0.0]

    def reset(self, t: float, x: float, y: float, th: float) -> None:
        self.n = 0
        self._sums[:] = (0.0, 0.0, 0.0, 0.0)
        self.head = self.cap - 1
        self.record(t, x, y, th, 0.0, 0.0, 0.0, 0.0)

    def record(self, t: float, x: float, y: float, th: float, dt: float, dx: float, dy: float, dth: float) -> None:
        """The tick that ended at (t, x, y, th) after a step (dt, dx, dy, dth)."""
        sums = self._sums
        if dx != 0.0 or dy != 0.0:
            thm = th - 0.5 * dth
            tm = t - 0.5 * dt
            sums[0] += dx * thm
            sums[1] += dy * thm
            sums[2] += dx * tm
            sums[3] += dy * tm
        i = self.head + 1
        if i == self.cap:
            i = 0
        self.head = i
        self.t[i] = t
        self.x[i] = x
        self.y[i] = y
        self.th[i] = th
        self.xth[i], self.yth[i], self.xt[i], self.yt[i] = sums
        self.n += 1

    # ------------------------------------------------------------------ queries (not per tick)

    def slot(self, k: int) -> int:
        """The list index of tick k (0 <= n - cap <= k < n)."""
        return (self.head - (self.n - 1 - k)) % self.cap

    @property
    def oldest(self) -> int:
        return max(0, self.n - self.cap)

    def find(self, t: float) -> int:
        """The newest tick k at or before time t (oldest - 1 when t is before the history)."""
        lo, hi = self.oldest, self.n - 1
        tt = self.t
        if t < tt[self.slot(lo)]:
            return lo - 1
        while lo < hi:
            mid = (lo + hi + 1) // 2
            if tt[self.slot(mid)] <= t:
                lo = mid
            else:
                hi = mid - 1
        return lo

    def state(self, k: int) -> tuple[float, ...]:
        """(t, x, y, th, xth, yth, xt, yt) at tick k."""
        i = self.slot(k)
        return (self.t[i], self.x[i], self.y[i], self.th[i], self.xth[i], self.yth[i], self.xt[i], self.yt[i])

    def at_time(self, t: float) -> tuple[float, ...]:
        """The state at time t, interpolated linearly between the ticks either side."""
        k = self.find(t)
        if k < self.oldest:
            raise ValueError("before the history")
        a = self.state(k)
        if k == self.n - 1 or a[0] >= t:
            return a
        b = self.state(k + 1)
        span = b[0] - a[0]
        f = (t - a[0]) / span if span > 0.0 else 0.0
        return tuple(u + f * (v - u) for u, v in zip(a, b))


def phi(a: tuple[float, ...], b: tuple[float, ...]) -> tuple[tuple[float, ...], float]:
    """G of Phi = I + G from history state `a` to `b` (as `propagate` takes it), and the time
    between them."""
    ta, xa, ya, tha, xtha, ytha, xta, yta = a
    tb, xb, yb, thb, xthb, ythb, xtb, ytb = b
    dx, dy = xb - xa, yb - ya
    # S dx_k (th_k - th_a) and S dx_k (t_k - t_a), likewise for y
    sxth = (xthb - xtha) - tha * dx
    syth = (ythb - ytha) - tha * dy
    sxt = (xtb - xta) - ta * dx
    syt = (ytb - yta) - ta * dy
    return (-dy, dx, -syth, -syt, dx, dy, sxth, sxt, thb - tha, tb - ta), tb - ta


def std_of(p: list[float]) -> tuple[float, float, float]:
    """1 sigma of x, y, theta."""
    return (math.sqrt(max(p[0], 0.0)), math.sqrt(max(p[7], 0.0)), math.sqrt(max(p[14], 0.0)))


class Tracker:
    """The odometry's history and the two covariances: the map estimate's (what status,
    telemetry and fixes use; fixes shrink it) propagated every `every` ticks, and the
    odometry's own (which never shrinks) every `odom_every`. The map's is kept at each of
    its propagations (`saved`) for as long as the history reaches back, so a late fix finds
    the covariance of its own time."""

    def __init__(self, model: ErrorModel, history_ticks: int, every: int, odom_every: int) -> None:
        self.model = model
        self.hist = History(history_ticks)
        self.every = max(1, every)
        self.odom_every = max(1, odom_every)
        self.p_map = zero_cov()
        self.p_odom = zero_cov()
        self.k_map = 0  # the history tick each covariance was last propagated to
        self.k_odom = 0
        self.at_rest_var = math.inf  # the bias's variance learnt at rest since the last propagation
        n_saved = self.hist.cap // self.every + 2
        self.saved_k = [-1] * n_saved
        self.saved_p = [zero_cov() for _ in range(n_saved)]
        self._save_i = 0
        self.std = (0.0, 0.0, 0.0)  # the map estimate's 1 sigma of x, y, theta
        self.cov_xy = 0.0

    def reset(self, t: float, pose: tuple[float, float, float], pose_cov: list[float] | None = None) -> None:
        """A new pose (a reset or a pose set): history and covariances start again."""
        self.hist.reset(t, pose[0], pose[1], pose[2])
        self.p_map[:] = initial_cov(self.model, pose_cov)
        self.p_odom[:] = self.p_map
        self.k_map = self.k_odom = 0
        self.bias_shrink = 1.0
        self.at_rest_var = math.inf
        for i in range(len(self.saved_k)):
            self.saved_k[i] = -1
        self._save()
        self._publish()

    def step(self, t: float, x: float, y: float, th: float, dt: float, dx: float, dy: float, dth: float,
             odom_angle: float = 0.0) -> None:
        """One tick of the map's dead reckoning (per tick: a few sums and stores); the
        covariances follow on their schedule. `odom_angle`: odom's heading minus map's (the
        odometry's covariance is kept in its own frame)."""
        h = self.hist
        h.record(t, x, y, th, dt, dx, dy, dth)
        k = h.n - 1
        if k - self.k_map >= self.every:
            self.advance_map(k)
        elif k - self.k_odom >= self.odom_every:
            self._advance(self.p_odom, self.k_odom, k, math.cos(odom_angle), math.sin(odom_angle))
            self.k_odom = k

    def advance_map(self, k: int) -> None:
        """Propagate the map's covariance to history tick k (and keep it for late fixes)."""
        self._advance(self.p_map, self.k_map, k, 1.0, 0.0)
        self.k_map = k
        if self.at_rest_var < math.inf:
            self.bias_shrink *= condition_bias(self.p_map, self.at_rest_var)
            condition_bias(self.p_odom, self.at_rest_var)
            self.at_rest_var = math.inf
        self._save()
        self._publish()

    def rescale(self, new: ErrorModel) -> None:
        """A reload's error model: the scale errors' rows and columns of every covariance kept
        are rescaled to the new figures (so each stays positive); a figure that was 0 starts at
        its new variance."""
        old, self.model = self.model, new
        for i, (a, b) in ((3, (old.encoder_scale_std, new.encoder_scale_std)),
                          (4, (old.gyro_scale_std, new.gyro_scale_std))):
            if a != b:
                k = b / a if a > 0.0 else 0.0
                for p in [self.p_map, self.p_odom] + self.saved_p:
                    for j in range(6):
                        p[i * 6 + j] *= k
                        p[j * 6 + i] *= k
                    if a == 0.0:
                        p[i * 6 + i] = b * b

    def carry(self, old: "Tracker") -> None:
        """Take `old`'s covariances as this fresh tracker's present ones (a new history length
        keeps what is known of the pose, not its history)."""
        self.p_map[:], self.p_odom[:] = old.p_map, old.p_odom
        self.saved_p[0][:] = old.p_map
        self._publish()

    def take_bias_shrink(self) -> float:
        """How much the bias's variance shrank at rest since the last call (1.0: not at all),
        for the map frame's learnt bias (ddrt/core/pose_fix.py)."""
        shrink, self.bias_shrink = self.bias_shrink, 1.0
        return shrink

    def correct_saved(self, stamp: float, now_k: int, correct: Callable[[int, list[float]], list[float]]) -> None:
        """A fix at `stamp` corrected the map's estimate: each covariance saved at its time or
        later becomes `correct(tick, covariance)`, the map's own with the one saved now."""
        h = self.hist
        for i, ks in enumerate(self.saved_k):
            if ks < 0 or ks < h.oldest or h.t[h.slot(ks)] < stamp:
                continue
            self.saved_p[i][:] = correct(ks, self.saved_p[i])
            if ks == now_k:
                self.p_map[:] = self.saved_p[i]
        self._publish()

    def _advance(self, p: list[float], k0: int, k1: int, c: float, s: float) -> None:
        h = self.hist
        k0 = max(k0, h.oldest)  # a covariance left behind by more than the history (not expected)
        g, dt = phi(h.state(k0), h.state(k1))
        propagate(p, g, c, s, dt, self.model)

    def _save(self) -> None:
        i = self._save_i
        self.saved_k[i] = self.k_map
        self.saved_p[i][:] = self.p_map
        self._save_i = (i + 1) % len(self.saved_k)

    def _publish(self) -> None:
        self.std = std_of(self.p_map)
        self.cov_xy = self.p_map[1]

    def saved_before(self, k: int) -> tuple[int, list[float]] | None:
        """The newest saved (tick, covariance) at or before tick k, within the history."""
        best = -1
        best_i = -1
        oldest = self.hist.oldest
        for i, ks in enumerate(self.saved_k):
            if oldest <= ks <= k and ks > best:
                best, best_i = ks, i
        return (best, self.saved_p[best_i]) if best_i >= 0 else None
