"""Two 2-state Kalman filters in plain floats: the estimator's hot path.

filterpy's KalmanFilter does the same algebra with numpy arrays; for 2x2 matrices the
array overhead costs more than the arithmetic (tens of microseconds per step on a Pi-class
CPU), so the filters are written out by hand here and tests/test_estimator.py checks them
step for step against filterpy.kalman.KalmanFilter on the same inputs.

`TravelFilter`: state (p, v): distance travelled along body x (what the front encoder
measures) and forward speed. `YawFilter`: state (w, b): yaw rate and the gyro's zero-rate
bias (the gyro measures w + b).
"""

from __future__ import annotations


class TravelFilter:
    """Constant-acceleration-input filter on (p, v) with a position measurement."""

    __slots__ = ("p", "v", "p00", "p01", "p11", "accel_var", "meas_var")

    def __init__(self, accel_noise: float, meas_std: float, p0_var: float = 1e-8, v0_var: float = 1e-4) -> None:
        self.p = 0.0
        self.v = 0.0
        self.p00 = p0_var
        self.p01 = 0.0
        self.p11 = v0_var
        self.accel_var = accel_noise * accel_noise
        self.meas_var = meas_std * meas_std

    def predict(self, dt: float, accel: float) -> None:
        """x = F x + B a with F = [[1, dt], [0, 1]], B = [dt^2/2, dt]; P = F P F' + Q."""
        dt2 = dt * dt
        self.p += self.v * dt + 0.5 * accel * dt2
        self.v += accel * dt
        q = self.accel_var
        p00, p01, p11 = self.p00, self.p01, self.p11
        self.p00 = p00 + 2.0 * dt * p01 + dt2 * p11 + q * dt2 * dt2 * 0.25
        self.p01 = p01 + dt * p11 + q * dt2 * dt * 0.5
        self.p11 = p11 + q * dt2

    def innovation(self, z: float) -> tuple[float, float]:
        """(residual, its variance) for a position measurement z."""
        return z - self.p, self.p00 + self.meas_var

    def widen(self, var: float) -> None:
        """Add `var` to the first state's variance: a re-sync trusts the sensor again."""
        self.p00 += var

    def update(self, z: float) -> float:
        """Fuse a position measurement; returns the normalised innovation squared."""
        y = z - self.p  # innovation(z), written out: four updates a tick
        s = self.p00 + self.meas_var
        k0 = self.p00 / s
        k1 = self.p01 / s
        self.p += k0 * y
        self.v += k1 * y
        p00, p01, p11 = self.p00, self.p01, self.p11
        self.p00 = p00 - k0 * p00
        self.p01 = p01 - k0 * p01
        self.p11 = p11 - k1 * p01
        return y * y / s


class YawFilter:
    """Random-walk filter on (w, b): yaw rate driven by the model, bias drifting slowly."""

    __slots__ = ("w", "b", "p00", "p01", "p11", "yaw_accel_var", "bias_walk_var", "meas_var")

    def __init__(self, yaw_accel_noise: float, bias_walk: float, meas_std: float,
                 w0_var: float = 1e-4, b0_var: float = 1e-6) -> None:
        self.w = 0.0
        self.b = 0.0
        self.p00 = w0_var
        self.p01 = 0.0
        self.p11 = b0_var
        self.yaw_accel_var = yaw_accel_noise * yaw_accel_noise
        self.bias_walk_var = bias_walk * bias_walk
        self.meas_var = meas_std * meas_std

    def predict(self, dt: float, yaw_accel: float) -> None:
        """w += alpha dt; b stays; P += diag(q_w dt^2, q_b dt)."""
        self.w += yaw_accel * dt
        self.p00 += self.yaw_accel_var * dt * dt
        self.p11 += self.bias_walk_var * dt

    def innovation(self, z: float) -> tuple[float, float]:
        """(residual, variance) for a gyro reading z = w + b."""
        return z - self.w - self.b, self.p00 + 2.0 * self.p01 + self.p11 + self.meas_var

    def widen(self, var: float) -> None:
        """Add `var` to the rate's variance: a re-sync trusts the gyro again."""
        self.p00 += var

    def update(self, z: float) -> float:
        """Fuse a gyro reading (H = [1, 1]); returns the normalised innovation squared."""
        y = z - self.w - self.b  # innovation(z), written out: four updates a tick
        s = self.p00 + 2.0 * self.p01 + self.p11 + self.meas_var
        h0 = self.p00 + self.p01  # P H'
        h1 = self.p01 + self.p11
        k0 = h0 / s
        k1 = h1 / s
        self.w += k0 * y
        self.b += k1 * y
        self.p00 -= k0 * h0
        self.p01 -= k0 * h1
        self.p11 -= k1 * h1
        return y * y / s

    def update_at_rest(self, var: float) -> None:
        """Fuse the fact that the robot is not turning (w = 0, H = [1, 0], R = var)."""
        s = self.p00 + var
        k0 = self.p00 / s
        k1 = self.p01 / s
        y = -self.w
        self.w += k0 * y
        self.b += k1 * y
        p00, p01, p11 = self.p00, self.p01, self.p11
        self.p00 = p00 - k0 * p00
        self.p01 = p01 - k0 * p01
        self.p11 = p11 - k1 * p01

    def shift_bias(self, db: float) -> None:
        """Move the bias by db (rad/s), its variance kept: a model of the bias said it moved
        (the die temperature's line, ddrt/core/gyro_bias.py)."""
        self.b += db

    def widen_bias(self, var: float) -> None:
        """Add var ((rad/s)^2) to the bias's variance: its random walk over a window, or a
        re-sync's innovation."""
        self.p11 += var

    def update_bias(self, z: float, var: float) -> None:
        """Fuse a measurement of the bias itself (H = [0, 1], R = var): the gyro's turn less the
        drive wheels' over a window (ddrt/core/wheel_odometry.py)."""
        s = self.p11 + var
        k0 = self.p01 / s
        k1 = self.p11 / s
        y = z - self.b
        self.w += k0 * y
        self.b += k1 * y
        p01, p11 = self.p01, self.p11
        self.p00 -= k0 * p01
        self.p01 = p01 - k0 * p11
        self.p11 = p11 - k1 * p11
