"""telemetry.csv's rows formatted in C (ddrt/simrun/row_format.c) are the Python text, byte for byte.

The Python path of format_rows ("%.9g", correctly rounded) is the reference. The C is compared
with it on over a million doubles per run from a seeded generator: random bit patterns of every
exponent, subnormals, values around powers of ten, exact and near 9-digit half-way cases,
integers, signed zeros, infinities and NaNs of either sign with payloads.
"""

from __future__ import annotations

import ctypes
import math
import shutil

import numpy as np
import pytest

from ddrt.simrun import row_native
from ddrt.simrun.runner import SIM_COLUMNS, format_rows, format_rows_python

pytestmark = pytest.mark.skipif(shutil.which("cc") is None and shutil.which("gcc") is None,
                                reason="no C compiler: format_rows stays in Python")


@pytest.fixture
def lib(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.delenv(row_native.ENV, raising=False)
    loaded = row_native.library()
    assert loaded is not None, "a C compiler is here, so row_format.c must build and load"
    return loaded


def _bits(u: np.ndarray) -> np.ndarray:
    return u.astype(np.uint64).view(np.float64)


def mixed_values(seed: int, n_each: int = 55_000) -> np.ndarray:
    """Over a million doubles that stress "%.9g" (see the module's docstring)."""
    rng = np.random.default_rng(seed)
    u64 = lambda n: rng.integers(0, 2**64, size=n, dtype=np.uint64)  # noqa: E731
    sign = lambda n: np.where(rng.random(n) < 0.5, -1.0, 1.0)  # noqa: E731
    parts = []
    # random bit patterns: every exponent (NaNs and infinities among them, rarely)
    parts.append(_bits(u64(2 * n_each)))
    # subnormals and the smallest normals
    mant = u64(n_each // 2) & np.uint64((1 << 52) - 1)
    parts.append(_bits(mant | (u64(n_each // 2) & np.uint64(1 << 63))))
    parts.append(_bits(mant | np.uint64(1 << 52)))
    # the fast path's range and around it: mantissa * 10^k, k in -18..34
    parts.append(sign(2 * n_each) * rng.uniform(1.0, 10.0, 2 * n_each) * 10.0 ** rng.integers(-18, 35, 2 * n_each))
    # around powers of ten: 10^k and its neighbours up to 3 ulps away, and 9.999999995e(k) ones
    p10 = np.array([float(f"1e{k}") for k in range(-330, 309)])
    near = []
    for sc in (1.0, 9.999999995, 9.9999999949999, 9.9999999950001, 0.99999999949999):
        with np.errstate(over="ignore"):
            up = down = p10 * sc  # inf where 1e308 * sc overflows: fine
        near.append(up)
        for _ in range(3):
            up, down = np.nextafter(up, np.inf), np.nextafter(down, -np.inf)
            near += [up, down]
    near_arr = np.concatenate(near)
    parts.append(np.concatenate([near_arr, -near_arr]))
    # 9-digit half-way cases: (k + 0.5) (exact), scaled by 10^j, and their neighbours
    k = rng.integers(10**8, 10**9, size=n_each).astype(np.float64)
    half = k + 0.5
    scaled = half * 10.0 ** rng.integers(-25, 26, n_each)
    scaled2 = half / 10.0 ** rng.integers(0, 23, n_each)
    for x in (half, scaled, scaled2):
        parts += [x, np.nextafter(x, np.inf), np.nextafter(x, -np.inf)]
    # exact ties beyond 9 digits: integers ending in 5 after 9 digits (10..16 digits), exact in binary
    digits = rng.integers(10, 17, n_each)
    lead = rng.integers(10**8, 10**9, n_each)
    ties = np.array([float((int(a) * 10 + 5) * 10 ** int(d - 10)) for a, d in zip(lead, digits)])
    parts += [ties, np.nextafter(ties, np.inf), np.nextafter(ties, -np.inf)]
    # integers
    parts.append(sign(n_each) * rng.integers(0, 2**53, n_each).astype(np.float64))
    parts.append(sign(n_each) * rng.integers(0, 10**6, n_each).astype(np.float64))
    # zeros, infinities, NaNs of either sign with payloads
    nans = (u64(n_each // 10) & np.uint64(0x800FFFFFFFFFFFFF)) | np.uint64(0x7FF0000000000001)
    parts.append(_bits(nans))
    parts.append(np.array([0.0, -0.0, math.inf, -math.inf, math.nan, -math.nan, 5e-324, -5e-324,
                           2.2250738585072014e-308, 1.7976931348623157e308, -1.7976931348623157e308]))
    out = np.concatenate(parts)
    assert len(out) >= 1_000_000
    return rng.permutation(out)


def _first_differences(values: np.ndarray, got: str, want: str, limit: int = 10) -> list[str]:
    g, w = got.replace("\r\n", ",").split(","), want.replace("\r\n", ",").split(",")
    bad = [i for i, (a, b) in enumerate(zip(g, w)) if a != b][:limit]
    return [f"{values.ravel()[i]!r} (0x{values.ravel()[i:i + 1].view(np.uint64)[0]:016x}): C {g[i]!r}, "
            f"Python {w[i]!r}" for i in bad]


@pytest.mark.parametrize("seed", [1])
def test_c_prints_every_double_as_python(lib, seed: int) -> None:
    values = mixed_values(seed)
    arr = values[: len(values) // 8 * 8].reshape(-1, 8)
    got, want = format_rows(arr), format_rows_python(arr)
    assert got == want, "\n".join(_first_differences(arr, got, want))
    rest = values[len(values) // 8 * 8:].reshape(-1, 1)
    assert format_rows(rest) == format_rows_python(rest)


def test_the_fast_path_does_the_work_and_leaves_ties_to_snprintf(lib) -> None:
    # Without this, a fast path that always fell back would pass the comparison above.
    buf = ctypes.create_string_buffer(32)
    rng = np.random.default_rng(5)
    typical = rng.uniform(-1e4, 1e4, 20_000) * 10.0 ** rng.integers(-12, 8, 20_000)
    fast = sum(lib.g9_fast(float(v), buf) >= 0 for v in typical)
    assert fast >= 0.999 * len(typical)
    for tie in (123456788.5, 1234567885.0, 0.1234567885, 1.000000005):
        # exact ties (the first two), and decimal ties inexact in binary: near a tie either way
        assert lib.g9_fast(tie, buf) == -1, tie
        n = lib.g9(tie, buf)
        assert buf.raw[:n].decode() == "%.9g" % tie
    for out_of_range in (1e-15, 1e31, 5e-324, 1e300):
        assert lib.g9_fast(out_of_range, buf) == -1
    for v, text in ((-math.nan, "nan"), (-0.0, "-0"), (-math.inf, "-inf"), (1e-5, "1e-05"),
                    (123456789.0, "123456789"), (0.0001, "0.0001"), (999999999.6, "1e+09")):
        n = lib.g9_fast(v, buf)
        assert buf.raw[:n].decode() == text == "%.9g" % v


def test_rows_with_constant_columns_and_one_row(lib) -> None:
    rng = np.random.default_rng(3)
    ncols = len(SIM_COLUMNS)
    rows = rng.normal(size=(300, ncols)) * 10.0 ** rng.integers(-20, 20, size=(300, ncols))
    rows[:, 3] = 0.0
    rows[:, 4] = -0.0
    rows[:, 5] = 7.25
    rows[:, 6] = -np.nan
    rows[::7, 8] = -0.0  # 0.0 and -0.0 in one column: not constant, different text
    rows[:, 9] = 1e-300  # constant and outside the fast path
    rows[1, 10:14] = [np.nan, np.inf, -np.inf, 5e-324]
    for arr in (rows, rows[:1], rows[5:6], rows[:2], rows[:0], rows[:, :1], rows[::2], rows[:, ::3]):
        assert format_rows(arr) == format_rows_python(arr)
    nan_col = np.full((4, 1), np.nan)
    nan_col[1:].view(np.uint64)[:] |= np.uint64(1 << 63)  # -nan: not the same bits as nan
    assert format_rows(nan_col) == "nan\r\n" * 4


def test_the_python_path_when_asked(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(row_native.ENV, "python")
    assert row_native.library() is None and row_native.format_rows(np.ones((2, 2))) is None
    assert format_rows(np.array([[1.5, -0.0], [np.nan, 1e22]])) == "1.5,-0\r\nnan,1e+22\r\n"
