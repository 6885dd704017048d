"""The pose's uncertainty (ddrt/core/uncertainty.py) against an independent Monte-Carlo of the
dead reckoning under the same error model, and pose fixes (ddrt/core/pose_fix.py) against
the truth they are meant to approach.

The Monte-Carlo does not linearise: each sample draws its own encoder and gyro scale errors,
bias, bias walk and gyro noise, integrates the true and the estimated pose with the same
midpoint rule the estimator uses, and the spread of their difference over the samples is
what the propagated covariance must match."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ddrt.core.pose_fix import FixError, MapFrame, PoseFix, parse_cov, parse_fix
from ddrt.core.uncertainty import ErrorModel, Tracker, std_of

DT = 0.005


def _model(**kw: float) -> ErrorModel:
    base = dict(encoder_scale_std=0.01, gyro_scale_std=0.02, bias0_std=math.radians(0.05),
                bias_walk=math.radians(0.01), heading_walk=math.radians(0.07) * math.sqrt(DT))
    base.update(kw)
    return ErrorModel(**base)  # type: ignore[arg-type]


def _increments(n: int) -> tuple[np.ndarray, np.ndarray]:
    """The estimate's own (measured) steps: 0.3 m/s with S-bends of up to 1.2 rad/s."""
    t = np.arange(n) * DT
    ds = np.full(n, 0.3 * DT)
    dth = 1.2 * np.sin(2 * np.pi * t / 6.0) * DT
    return ds, dth


def _integrate(ds: np.ndarray, dth: np.ndarray, th0: float = 0.3) -> tuple[np.ndarray, ...]:
    """Midpoint dead reckoning along the last axis; (x, y, th) after every step."""
    th_before = th0 + np.concatenate([np.zeros(ds.shape[:-1] + (1,)), np.cumsum(dth, axis=-1)[..., :-1]], axis=-1)
    mid = th_before + 0.5 * dth
    x = np.cumsum(ds * np.cos(mid), axis=-1)
    y = np.cumsum(ds * np.sin(mid), axis=-1)
    return x, y, th0 + np.cumsum(dth, axis=-1)


def _feed(track: Tracker, ds: np.ndarray, dth: np.ndarray, th0: float = 0.3, t0: float = 0.0, upto: int | None = None,
          start: int = 0, frame: MapFrame | None = None) -> None:
    """The odometry's steps into the tracker (through the map frame's dead reckoning, if given)."""
    x, y, th = _integrate(ds, dth, th0)
    for k in range(start, len(ds) if upto is None else upto):
        if frame is not None:
            frame.step(track, t0 + (k + 1) * DT, DT, float(ds[k]), float(dth[k]), x[k], y[k], th[k])
            continue
        xp = x[k - 1] if k else 0.0
        yp = y[k - 1] if k else 0.0
        track.step(t0 + (k + 1) * DT, x[k], y[k], th[k], DT, x[k] - xp, y[k] - yp, dth[k])


def _fed_map(history: int, steps: int, gate_chi2: float) -> tuple[Tracker, MapFrame]:
    """A tracker with `history` ticks of history and a map frame, both fed `steps` of the S-bend
    odometry from the origin."""
    track = Tracker(_model(), history, every=4, odom_every=20)
    track.reset(0.0, (0.0, 0.0, 0.0))
    frame = MapFrame(gate_chi2=gate_chi2)
    frame.reset((0.0, 0.0, 0.0))
    ds, dth = _increments(steps)
    _feed(track, ds, dth, th0=0.0, frame=frame)
    return track, frame


def _monte_carlo(model: ErrorModel, ds: np.ndarray, dth: np.ndarray, samples: int, seed: int) -> np.ndarray:
    """(samples, n, 3) true minus estimated pose."""
    rng = np.random.default_rng(seed)
    n = len(ds)
    es = rng.normal(0.0, model.encoder_scale_std, (samples, 1))
    eg = rng.normal(0.0, model.gyro_scale_std, (samples, 1))
    eb = rng.normal(0.0, model.bias0_std, (samples, 1)) + np.cumsum(
        rng.normal(0.0, model.bias_walk * math.sqrt(DT), (samples, n)), axis=1)
    noise = rng.normal(0.0, model.heading_walk * math.sqrt(DT), (samples, n))
    true_ds = ds * (1.0 + es)
    true_dth = dth * (1.0 + eg) + eb * DT + noise
    xt, yt, tht = _integrate(true_ds, true_dth)
    xe, ye, the = _integrate(ds[None, :], dth[None, :])
    return np.stack([xt - xe, yt - ye, tht - the], axis=-1)


def test_the_propagated_covariance_matches_a_monte_carlo_of_the_dead_reckoning() -> None:
    n = 3000  # 15 s, 4.5 m
    ds, dth = _increments(n)
    model = _model()
    err = _monte_carlo(model, ds, dth, samples=4000, seed=7)
    track = Tracker(model, n + 10, every=4, odom_every=20)
    track.reset(0.0, (0.0, 0.0, 0.3))
    checked = 0
    x, y, th = _integrate(ds, dth)
    for k in range(n):
        xp = x[k - 1] if k else 0.0
        yp = y[k - 1] if k else 0.0
        track.step((k + 1) * DT, x[k], y[k], th[k], DT, x[k] - xp, y[k] - yp, dth[k])
        if track.k_map == k + 1 and (k + 1) % 600 == 0:
            e = err[:, k, :]
            mc = np.cov(e.T)
            p = np.array(track.p_map).reshape(6, 6)[:3, :3]
            for i in range(3):
                assert p[i, i] == pytest.approx(mc[i, i], rel=0.12), (k, i, p[i, i], mc[i, i])
            rho_mc = mc[0, 1] / math.sqrt(mc[0, 0] * mc[1, 1])
            rho = p[0, 1] / math.sqrt(p[0, 0] * p[1, 1])
            assert rho == pytest.approx(rho_mc, abs=0.06)
            checked += 1
    assert checked == 5
    sx, sy, sth = std_of(track.p_map)
    assert sx > 0.005 and sth > math.radians(0.5)  # it really grew: these are not zeros agreeing
    # The odometry's own covariance (propagated less often, same model) agrees with the map's
    # while there has been no fix.
    track.advance_map(n)
    track._advance(track.p_odom, track.k_odom, n, 1.0, 0.0)
    assert np.allclose(track.p_odom, track.p_map, rtol=1e-4, atol=1e-12)  # the noise batched differently


def test_the_batch_transition_equals_step_by_step_propagation() -> None:
    """Phi over many ticks from the history's running sums = the product of one-tick Phis."""
    n = 1200
    ds, dth = _increments(n)
    model = _model(bias_walk=0.0, heading_walk=0.0)  # the noise's batching is an approximation
    every1 = Tracker(model, n + 10, every=1, odom_every=1)
    every25 = Tracker(model, n + 10, every=25, odom_every=100)
    for tr in (every1, every25):
        tr.reset(0.0, (0.0, 0.0, 0.3))
        _feed(tr, ds, dth)
    every25.advance_map(n)
    assert np.allclose(every1.p_map, every25.p_map, rtol=1e-9, atol=1e-18)


def test_learning_the_bias_at_rest_stops_the_heading_growth_but_keeps_what_grew() -> None:
    model = _model(gyro_scale_std=0.0, encoder_scale_std=0.0, heading_walk=0.0, bias0_std=math.radians(0.5))
    tr = Tracker(model, 5000, every=4, odom_every=20)
    tr.reset(0.0, (0.0, 0.0, 0.0))
    ds = np.zeros(2000)
    dth = np.zeros(2000)
    _feed(tr, ds, dth, th0=0.0, upto=1000)
    grown = tr.p_map[14]
    assert math.sqrt(grown) == pytest.approx(math.radians(0.5) * 5.0, rel=0.01)  # bias x 5 s
    tr.at_rest_var = 1e-12
    _feed(tr, ds, dth, th0=0.0, start=1000, upto=1004)
    tr.advance_map(1004)
    after = tr.p_map[14]
    _feed(tr, ds, dth, th0=0.0, start=1004, upto=2000)
    tr.advance_map(2000)
    assert after == pytest.approx(grown, rel=0.01)
    assert tr.p_map[14] < after * 1.01  # no more growth from a bias known to 1e-6 rad/s
    assert np.all(np.linalg.eigvalsh(np.array(tr.p_map).reshape(6, 6)) > -1e-15)


# --------------------------------------------------------------------------- pose fixes


def _run_with_fix(seed: int, latency_ticks: int, fix_std: tuple[float, float, float], n: int = 1600,
                  fix_at: int = 1000) -> tuple[np.ndarray, np.ndarray, dict]:
    """One Monte-Carlo sample: a true run, its estimate, a fix of the truth at tick `fix_at`
    arriving `latency_ticks` later; returns (map error now, its covariance, the fuse result)."""
    rng = np.random.default_rng(seed)
    model = _model()
    ds, dth = _increments(n)
    es = rng.normal(0.0, model.encoder_scale_std)
    eg = rng.normal(0.0, model.gyro_scale_std)
    eb = rng.normal(0.0, model.bias0_std) + np.cumsum(rng.normal(0.0, model.bias_walk * math.sqrt(DT), n))
    true_dth = dth * (1.0 + eg) + eb * DT + rng.normal(0.0, model.heading_walk * math.sqrt(DT), n)
    xt, yt, tht = _integrate(ds * (1.0 + es), true_dth)
    track = Tracker(model, 400, every=4, odom_every=20)
    track.reset(0.0, (0.0, 0.0, 0.3))
    frame = MapFrame(gate_chi2=1e9)
    frame.reset((0.0, 0.0, 0.3))
    arrive = fix_at + latency_ticks
    _feed(track, ds, dth, upto=arrive + 1, frame=frame)
    k = fix_at
    sx, sy, sth = fix_std
    fix = PoseFix(xt[k] + rng.normal(0, sx), yt[k] + rng.normal(0, sy), tht[k] + rng.normal(0, sth),
                  (sx * sx, 0.0, 0.0, 0.0, sy * sy, 0.0, 0.0, 0.0, sth * sth), (k + 1) * DT)
    result = frame.fuse(track, fix)
    _feed(track, ds, dth, start=arrive + 1, frame=frame)
    track.advance_map(n)
    err = np.array([xt[-1] - frame.x, yt[-1] - frame.y, tht[-1] - frame.th])
    return err, np.array(track.p_map).reshape(6, 6)[:3, :3], result


@pytest.mark.parametrize("latency_ticks", [0, 120], ids=["on-time", "0.6s-late"])
def test_a_late_fix_leaves_an_error_its_covariance_describes(latency_ticks: int) -> None:
    """Over many runs, the map pose's error after a fix (late or not) has zero mean and the
    spread the updated covariance reports, and is much smaller than without the fix."""
    fix_std = (0.005, 0.005, math.radians(1.0))
    errs, covs = [], []
    for seed in range(300):
        e, p, result = _run_with_fix(seed, latency_ticks, fix_std)
        assert result["fused"]
        errs.append(e)
        covs.append(p)
    e = np.array(errs)
    p = covs[0]
    mc = np.cov(e.T)
    for i in range(3):
        assert mc[i, i] == pytest.approx(p[i, i], rel=0.3), (i, mc[i, i], p[i, i])
        # Unbiased but for the second-order terms the linear filter leaves out (heading errors
        # of a few degrees bend the position by their square): within a fifth of a sigma.
        assert abs(e[:, i].mean()) < 3.0 * math.sqrt(p[i, i] / len(e)) + 0.2 * math.sqrt(p[i, i])
    # Without the fix the same runs spread far wider (the fix did something).
    n = 1600
    ds, dth = _increments(n)
    free = _monte_carlo(_model(), ds, dth, samples=300, seed=1)[:, -1, :]
    assert np.var(free[:, 0]) + np.var(free[:, 1]) > 4.0 * (mc[0, 0] + mc[1, 1])


def test_a_fix_far_outside_its_covariance_is_an_outlier_counted_and_ignored() -> None:
    track, frame = _fed_map(400, 400, 16.27)
    before = (list(track.p_map), frame.correction(), list(track.hist.x))
    r = frame.fuse(track, PoseFix(5.0, 5.0, 0.0, (1e-4, 0, 0, 0, 1e-4, 0, 0, 0, 1e-3), 1.0))
    assert not r["fused"] and r["outlier"] and r["d2"] > 16.27
    assert frame.counters.outliers == 1 and frame.counters.fused == 0
    assert (list(track.p_map), frame.correction(), list(track.hist.x)) == before


def test_fix_input_is_checked_field_by_field() -> None:
    good = {"x": 1.0, "y": 2.0, "theta": 0.1, "cov": [[1e-4, 0, 0], [0, 1e-4, 0], [0, 0, 1e-3]], "stamp": 1.0}
    assert parse_fix(good, 2.0).stamp == 1.0
    assert parse_fix({k: v for k, v in good.items() if k != "stamp"}, 2.0).stamp == 2.0
    assert parse_cov([1, 0, 0, 0, 2, 0, 0, 0, 3]) == [1.0, 0, 0, 0, 2.0, 0, 0, 0, 3.0]
    cases = {
        "x": [{**good, "x": math.nan}, {**good, "x": "1"}, {**good, "x": True}, {**good, "x": 1e7}],
        "theta": [{**good, "theta": math.inf}],
        "y": [{k: v for k, v in good.items() if k != "y"}],
        "cov": [{**good, "cov": [[1, 0], [0, 1]]}, {**good, "cov": [1, 2, 3]},
                {**good, "cov": [[1, 0.5, 0], [0, 1, 0], [0, 0, 1]]},  # not symmetric
                {**good, "cov": [[1, 2, 0], [2, 1, 0], [0, 0, 1]]},  # not positive definite
                {**good, "cov": [[0, 0, 0], [0, 1, 0], [0, 0, 1]]}, {**good, "cov": None},
                {k: v for k, v in good.items() if k != "cov"}],
        "cov[1][1]": [{**good, "cov": [[1, 0, 0], [0, math.nan, 0], [0, 0, 1]]}],
        "stamp": [{**good, "stamp": "now"}, {**good, "stamp": math.nan}],
        "colour": [{**good, "colour": "red"}],
    }
    for field, reqs in cases.items():
        for req in reqs:
            with pytest.raises(FixError) as info:
                parse_fix(req, 2.0)
            assert info.value.field == field, (req, str(info.value))
            assert str(info.value).startswith(f"{field}: ")


def test_stamps_outside_the_history_or_out_of_order_change_nothing() -> None:
    track, frame = _fed_map(200, 600, 1e9)  # 1 s of history at 5 ms
    cov = (1e-4, 0, 0, 0, 1e-4, 0, 0, 0, 1e-3)
    now = 600 * DT

    def state() -> tuple:
        return (list(track.p_map), [list(p) for p in track.saved_p], list(track.hist.x), frame.correction(),
                frame.s, frame.g, frame.b, frame.counters.fused)

    before = state()
    for stamp, words in ((now + 0.01, "in the future"), (now - 1.5, "older than the history")):
        with pytest.raises(FixError, match=words) as info:
            frame.fuse(track, PoseFix(0.0, 0.0, 0.0, cov, stamp))
        assert info.value.field == "stamp"
        assert state() == before
    x, y, th = track.hist.x[track.hist.head], track.hist.y[track.hist.head], track.hist.th[track.hist.head]
    assert frame.fuse(track, PoseFix(x + 0.01, y, th, cov, now - 0.2))["fused"]
    assert frame.correction()[0] != 0.0
    after = state()
    with pytest.raises(FixError, match="before the last fix"):
        frame.fuse(track, PoseFix(x, y, th, cov, now - 0.3))
    assert state() == after


def test_fuzzed_fix_requests_never_raise_anything_but_a_named_field_error() -> None:
    rng = np.random.default_rng(11)
    track, frame = _fed_map(200, 300, 16.27)
    junk = [None, True, "x", [], {}, [1], [[1, 2, 3]] * 3, math.nan, -math.inf, 1e308, -1e-300, 10 ** 400, 0, -1.0,
            [[1e-4, 0, 0], [0, 1e-4, 0], [0, 0, 1e-3]], [[-1, 0, 0], [0, 1, 0], [0, 0, 1]], 1.4, 1.0]
    fields = ("x", "y", "theta", "cov", "stamp")
    for _ in range(3000):
        req = {f: junk[rng.integers(len(junk))] for f in fields if rng.random() < 0.9}
        if rng.random() < 0.05:
            req["extra"] = 1
        p_before = list(track.p_map)
        c_before = (frame.x, frame.y, frame.th, frame.s, frame.g, frame.b)
        try:
            frame.fuse(track, parse_fix(req, 1.5))
        except FixError as exc:
            assert exc.field in fields + ("extra",) or exc.field.startswith("cov["), str(exc)
            assert track.p_map == p_before and (frame.x, frame.y, frame.th, frame.s, frame.g, frame.b) == c_before


def test_after_five_outliers_in_a_row_the_next_fix_reanchors_map() -> None:
    """A map that is wrong (the robot was carried away) must not refuse every fix from then on."""
    from ddrt.core.pose_fix import MAX_OUTLIERS_IN_A_ROW

    track, frame = _fed_map(400, 400, 16.27)
    cov = (1e-4, 0, 0, 0, 1e-4, 0, 0, 0, 1e-3)
    for i in range(MAX_OUTLIERS_IN_A_ROW):
        assert frame.fuse(track, PoseFix(5.0, 5.0, 1.0, cov, 2.0))["outlier"]
    r = frame.fuse(track, PoseFix(5.0, 5.0, 1.0, cov, 2.0))
    assert r["fused"] and r["anchored"] and frame.counters.reanchors == 1
    assert (frame.x, frame.y, frame.th) == pytest.approx((5.0, 5.0, 1.0))
    assert std_of(track.p_map)[0] == pytest.approx(0.01)


def test_the_error_models_bias_walk_is_the_larger_of_the_drift_allowed_for_and_the_filters_walk() -> None:
    """estimator.uncertainty_bias_walk (what a drifting gyro may do between rests and fixes) is
    the walk the covariance grows by; a bias filter told of a faster walk raises it, never
    lowers it. A negative value is refused, naming the key."""
    from ddrt.config import ConfigError, load_config
    from tests.support.repo import SIM_YAML

    def walk(**est: float) -> float:
        return ErrorModel.from_config(load_config(SIM_YAML, {"estimator": est}).estimator, DT).bias_walk

    assert walk() == pytest.approx(3e-4)
    assert walk(uncertainty_bias_walk=0.0) == pytest.approx(1e-5)  # the bias filters' own walk
    assert walk(gyro_bias_walk=1e-3) == pytest.approx(1e-3)
    with pytest.raises(ConfigError, match="estimator.uncertainty_bias_walk"):
        load_config(SIM_YAML, {"estimator": {"uncertainty_bias_walk": -1e-4}})
