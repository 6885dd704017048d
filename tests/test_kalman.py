"""The hand-written filters must equal filterpy's KalmanFilter step for step."""

import random

import numpy as np
from filterpy.kalman import KalmanFilter

from ddrt.core.kalman import TravelFilter, YawFilter


def _travel_reference(accel_noise, meas_std, p0, v0):
    kf = KalmanFilter(dim_x=2, dim_z=1, dim_u=1)
    kf.x = np.zeros((2, 1))
    kf.P = np.diag([p0, v0])
    kf.H = np.array([[1.0, 0.0]])
    kf.R = np.array([[meas_std ** 2]])
    return kf


def test_travel_filter_matches_filterpy():
    rng = random.Random(3)
    ours = TravelFilter(accel_noise=0.7, meas_std=1e-5, p0_var=1e-6, v0_var=1e-3)
    ref = _travel_reference(0.7, 1e-5, 1e-6, 1e-3)
    for _ in range(400):
        dt = rng.uniform(0.003, 0.007)
        a = rng.uniform(-1, 1)
        ref.F = np.array([[1.0, dt], [0.0, 1.0]])
        ref.B = np.array([[0.5 * dt * dt], [dt]])
        q = 0.7 ** 2
        ref.Q = q * np.array([[dt ** 4 / 4, dt ** 3 / 2], [dt ** 3 / 2, dt ** 2]])
        ref.predict(u=np.array([[a]]))
        ours.predict(dt, a)
        z = ref.x[0, 0] + rng.gauss(0, 2e-5)
        ref.update(np.array([[z]]))
        ours.update(z)
        assert abs(ours.p - ref.x[0, 0]) < 1e-12
        assert abs(ours.v - ref.x[1, 0]) < 1e-9
        assert np.allclose([[ours.p00, ours.p01], [ours.p01, ours.p11]], ref.P, rtol=1e-7, atol=1e-18)


def test_yaw_filter_matches_filterpy_and_learns_bias():
    rng = random.Random(5)
    ours = YawFilter(yaw_accel_noise=4.0, bias_walk=1e-4, meas_std=1e-3, w0_var=1e-4, b0_var=1e-4)
    kf = KalmanFilter(dim_x=2, dim_z=1, dim_u=1)
    kf.x = np.zeros((2, 1))
    kf.P = np.diag([1e-4, 1e-4])
    kf.F = np.eye(2)
    kf.H = np.array([[1.0, 1.0]])
    kf.R = np.array([[1e-6]])
    for i in range(300):
        dt = 0.005
        alpha = rng.uniform(-2, 2)
        kf.B = np.array([[dt], [0.0]])
        kf.Q = np.diag([16.0 * dt * dt, 1e-8 * dt])
        kf.predict(u=np.array([[alpha]]))
        ours.predict(dt, alpha)
        z = rng.gauss(0.02, 1e-3)  # at rest with a 0.02 rad/s bias
        if i % 2 == 0:
            # the rest pseudo-measurement w = 0, checked against filterpy with H = [1, 0]
            kf.update(np.array([[0.0]]), R=np.array([[1e-10]]), H=np.array([[1.0, 0.0]]))
            ours.update_at_rest(1e-10)
        kf.update(np.array([[z]]))
        ours.update(z)
        assert abs(ours.w - kf.x[0, 0]) < 1e-9
        assert abs(ours.b - kf.x[1, 0]) < 1e-9
        assert np.allclose([[ours.p00, ours.p01], [ours.p01, ours.p11]], kf.P, rtol=1e-6, atol=1e-15)
    assert abs(ours.b - 0.02) < 5e-4  # at rest the bias is observable and learnt
