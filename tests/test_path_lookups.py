"""The per-tick path look-ups that start from a hint (Path.index(s, near), interval_index,
Path.at_time_near) and the projection that hands on its interval: the same answers as the
plain searches, for any hint, on paths with pivots, reversing pieces and cusps."""

from __future__ import annotations

import bisect
from pathlib import Path as FsPath

import numpy as np
import pytest

from ddrt.path import Path, SpeedLimits, load_path
from ddrt.path.pursuit import PurePursuit
from ddrt.path.sampled import interval_index
from tests.support.repo import REPO

PATHS = ("figure8_slow.yaml", "rectangle.yaml", "seed_square.yaml", "out_and_back")


def _out_and_back(tmp: FsPath) -> FsPath:
    """Half a metre out, marked back (negative v): a cusp where the direction flips."""
    rows = [f"{0.01 * k:.3f},0,0.3" for k in range(0, 51)] + [f"{0.5 - 0.01 * k:.3f},0.001,-0.3" for k in range(1, 40)]
    f = tmp / "out_and_back.csv"
    f.write_text("x,y,v\n" + "\n".join(rows) + "\n")
    return f


def _load(name: str, tmp: FsPath) -> Path:
    f = _out_and_back(tmp) if name == "out_and_back" else REPO / "configs" / "paths" / name
    return load_path(f, SpeedLimits())


def test_the_paths_have_what_the_look_ups_must_cope_with(tmp_path) -> None:
    paths = {name: _load(name, tmp_path) for name in PATHS}
    assert any(paths["rectangle.yaml"].seg_pivot)  # turns in place: many samples at one point
    assert paths["out_and_back"].cusps and min(paths["out_and_back"].v) < 0.0


def _plain(a: list[float], x: float) -> int:
    """The definition: bisect, clamped to the intervals."""
    i = bisect.bisect_right(a, x) - 1
    return min(max(i, 0), len(a) - 2)


def test_interval_index_is_bisect_for_every_hint() -> None:
    rng = np.random.default_rng(3)
    a = sorted(rng.uniform(0.0, 10.0, 300).tolist())
    a[50:53] = [a[50]] * 3  # repeated samples (a pivot's corner holds several)
    a.sort()
    xs = np.concatenate([rng.uniform(-1.0, 11.0, 400), np.asarray(a), [a[0], a[-1], -5.0, 50.0]])
    hints = [-1, 0, 1, 49, 50, 51, 52, 150, len(a) - 3, len(a) - 2, len(a) - 1, len(a), 10_000]
    for x in xs.tolist():
        want = _plain(a, x)
        for h in hints + [max(want - 3, 0), want, min(want + 1, len(a) - 2)]:
            assert interval_index(a, x, h) == want, (x, h)


@pytest.mark.parametrize("name", PATHS)
def test_path_index_and_at_time_near_agree_with_the_plain_look_ups(name: str, tmp_path) -> None:
    rng = np.random.default_rng(5)
    for path in [_load(name, tmp_path)]:
        sig = path.sigma
        hint = -1
        for s in np.sort(rng.uniform(-0.1, path.length + 0.1, 500)).tolist() + sig[::7]:
            want = _plain(sig, s)
            assert path.index(s) == want
            assert path.index(s, hint) == want
            hint = want
        near = -1
        for t in np.sort(rng.uniform(-0.5, path.duration + 0.5, 500)).tolist() + path.t[::5]:
            point, i = path.at_time_near(t, near)
            assert point == path.at_time(t)  # the same floats, field by field
            assert i == path.index(point.sigma)
            near = i
        # A hint from another part of the path (a reload, a resume) changes nothing either.
        for t in rng.uniform(0.0, path.duration, 50).tolist():
            assert path.at_time_near(t, int(rng.integers(0, len(sig) - 1)))[0] == path.at_time(t)


@pytest.mark.parametrize("name", PATHS)
def test_projection_hands_on_the_interval_of_its_progress(name: str, tmp_path) -> None:
    path = _load(name, tmp_path)
    pp = PurePursuit(path)
    rng = np.random.default_rng(11)
    n = 1500
    for k in range(n + 1):
        q = path.at(path.length * k / n)
        x, y, th = q.x + rng.normal(0.0, 0.002), q.y + rng.normal(0.0, 0.002), q.theta + rng.normal(0.0, 0.02)
        near = pp.project(x, y, th)
        assert near.index == path.index(near.sigma)
        ref = pp.update(x, y, th) if k % 97 == 0 else None  # update is project plus the speeds
        if ref is not None:
            assert ref.sigma >= near.sigma
