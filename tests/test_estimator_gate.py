"""The estimator's outlier gate on a pair of filters (Estimator._fuse_pair): outliers are rejected
and counted, and after max_rejects of them in a row the sensor is trusted again (a re-sync)
with both filters' variances widened. `_fuse_pair` was one method calling another
(_gated_update) before it was written as one for speed; `reference_fuse_pair` is that earlier
form, and the merged one must do exactly (bit for bit) what it did."""

from __future__ import annotations

import random

from ddrt.config import load_config
from ddrt.core.kalman import TravelFilter, YawFilter
from ddrt.loop import ControlLoop
from hal.registry import open_hal
from tests.support.repo import SIM_YAML


def make_estimator():
    cfg = load_config(str(SIM_YAML))
    return ControlLoop(cfg, open_hal(cfg)).estimator


def reference_fuse_pair(est, sharp, smooth, z: float, row: int) -> int:
    """The two-method form: gate and fuse the odometry filter, then (accepted) the smooth one."""
    def gated(filt, row):
        y, s = filt.innovation(z)
        if y * y / s > est.gate2 and row < est.cfg.max_rejects:
            return row + 1
        if row >= est.cfg.max_rejects:
            est.health.resyncs += 1
            filt.p00 += y * y
        filt.update(z)
        return 0
    resyncs = est.health.resyncs
    row = gated(sharp, row)
    if row == 0:
        if est.health.resyncs > resyncs:
            y, _ = smooth.innovation(z)
            smooth.p00 += y * y
        smooth.update(z)
    return row


def state(f) -> tuple[float, ...]:
    return tuple(getattr(f, k) for k in f.__slots__)


def clone(f):
    g = object.__new__(type(f))
    for k in f.__slots__:
        setattr(g, k, getattr(f, k))
    return g


def test_fuse_pair_is_the_two_method_form_bit_for_bit() -> None:
    est = make_estimator()
    rng = random.Random(11)
    max_rejects = est.cfg.max_rejects
    for make in (lambda: TravelFilter(0.5, 1e-4), lambda: YawFilter(2.0, 1e-4, 2e-3)):
        a_sharp, a_smooth = make(), make()
        b_sharp, b_smooth = clone(a_sharp), clone(a_smooth)
        row_a = row_b = 0
        z = 0.0
        resyncs_seen = rejects_seen = 0
        for i in range(3000):
            for f in (a_sharp, a_smooth, b_sharp, b_smooth):
                if isinstance(f, TravelFilter):
                    f.predict(0.005, 0.1)
                else:
                    f.predict(0.005, 0.0)
            # Mostly consistent readings; now and then a jump (an outlier), runs of them, and
            # runs longer than max_rejects (the sensor really moved: a re-sync).
            z += rng.gauss(0.0, 1e-4)
            if rng.random() < 0.01:
                z += rng.choice((-1.0, 1.0)) * rng.uniform(0.05, 0.5)
            zz = z + (rng.uniform(0.1, 1.0) if rng.random() < 0.02 else 0.0)
            r0 = est.health.resyncs
            row_a = est._fuse_pair(a_sharp, a_smooth, zz, row_a)
            r1 = est.health.resyncs
            row_b = reference_fuse_pair(est, b_sharp, b_smooth, zz, row_b)
            assert est.health.resyncs - r1 == r1 - r0  # the same re-sync decision
            assert row_a == row_b, i
            assert state(a_sharp) == state(b_sharp) and state(a_smooth) == state(b_smooth), i
            resyncs_seen += r1 - r0
            rejects_seen += row_a > 0
            assert row_a <= max_rejects
        assert resyncs_seen > 0 and rejects_seen > max_rejects  # both branches were exercised


def test_after_max_rejects_outliers_the_sensor_is_trusted_again() -> None:
    est = make_estimator()
    sharp, smooth = TravelFilter(0.5, 1e-4), TravelFilter(0.5, 1e-4)
    max_rejects = est.cfg.max_rejects
    row = 0
    for k in range(max_rejects):  # a step of 1 m: far outside the gate, rejected every time
        before = (state(sharp), state(smooth))
        row = est._fuse_pair(sharp, smooth, 1.0, row)
        assert row == k + 1
        assert (state(sharp), state(smooth)) == before  # nothing fused
    resyncs = est.health.resyncs
    row = est._fuse_pair(sharp, smooth, 1.0, row)
    assert row == 0 and est.health.resyncs == resyncs + 1
    # Widened by the innovation, the filters take most of the measurement at once.
    assert sharp.p > 0.9 and smooth.p > 0.9
