"""How noisy a polyline's points are, and what follows from it: the tolerance `auto` sets, the
least smoothing a fit may fall to without following the noise, and a parameter along the
points that noise does not stretch.

The noise. Residuals of local polynomial fits: in each window of `m` consecutive points x(t)
and y(t) are fitted by cubics in the distance t along the points, and the centre point's
residual across the fitted tangent, divided by sqrt(1 - its leverage), is one draw of the
lateral noise; sigma is their RMS without the largest 10 % (a corner's or a tight turn's few
windows), scaled to a Gaussian's. A cubic takes the curve's own bending out of the residual,
so a planner's path at 10 cm spacing does not read its curvature as noise (a light spline
fit read 29 mm of "noise" on +-4 mm of jitter), and a parametric one follows a window that
turns through a large angle (sparse points on a tight curve). The window is scale-aware: it
starts at 7 points and grows until it spans SPAN_SIGMAS noise sigmas (sized on graph cubics
y(x) in each window's principal frame, which need no parameter), so points closer together
than their noise (5 mm spacing, 8 mm of noise) are judged over a stretch where the curve
shows through the noise, not point to point.

The parameter. Chord length along noisy points grows with the noise, not with the curve (at
5 mm spacing and 8 mm of noise about three times faster, back and forth): where the noise is
larger than a fraction of the spacing, the chord length is taken along the points averaged
over a window that spans a few sigmas (`arc_parameter`), which is the distance along the
curve the points stand for.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["TOLERANCE_FLOOR_M", "arc_parameter", "auto_tolerance", "chase_floor", "estimate_noise",
           "presmooth"]

TOLERANCE_FLOOR_M = 0.01  # `auto` never sets a tolerance below this (m): no robot notices less
AUTO_MARGIN_SIGMAS = 1.0  # the fit's own error on top of the largest noise excursion, in sigmas
SPAN_SIGMAS = 8.0  # a noise window spans at least this many sigmas along the points
MIN_WINDOW = 7  # points in the shortest noise window (a cubic leaves 3 degrees of freedom)
MAX_WINDOW = 201  # and the longest
MAX_WINDOWS = 5000  # windows measured (evenly spread over a longer polyline)
TRIM = 0.1  # share of the largest residuals left out of the noise
TRIMMED_SHARE = 0.7893  # RMS of a unit Gaussian's |z| below its 90 % quantile
PRESMOOTH_SIGMAS = 3.0  # the parameter's averaging window spans this many sigmas
# Curvature noise (RMS, 1/m) a fit may keep from white noise at the least smoothing the
# tolerance may force (`chase_floor`).
CURVATURE_NOISE_BUDGET = 0.25


def _starts(n: int, m: int) -> np.ndarray:
    """First points of the windows of m among n points: every one, or MAX_WINDOWS spread evenly."""
    starts = np.arange(n - m + 1)
    return starts if len(starts) <= MAX_WINDOWS else np.linspace(0, n - m, MAX_WINDOWS).astype(np.intp)


def _windows(p: np.ndarray, m: int) -> np.ndarray:
    """(k, m, ...) windows of m consecutive points (`_starts`)."""
    return p[_starts(len(p), m)[:, None] + np.arange(m)[None, :]]


def _cubic(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per window (rows of x, scaled to [-1, 1]): the cubic design matrix and its (X^T X)^-1,
    for the windows whose points spread enough to fit one (`ok`, a mask of the rows kept)."""
    design = np.stack([np.ones_like(x), x, x * x, x * x * x], axis=2)  # (k, m, 4)
    gram = np.einsum("kmi,kmj->kij", design, design)
    ok = np.linalg.det(gram) > 1e-9 * x.shape[1] ** 4
    return design[ok], np.linalg.inv(gram[ok]) if ok.any() else np.zeros((0, 4, 4)), ok


def _centre_residuals(w: np.ndarray) -> np.ndarray:
    """Each window's centre residual from a cubic in its own frame, divided by sqrt(1 - leverage):
    a draw of the lateral noise, whatever the curve does within the window."""
    m = w.shape[1]
    c = w.mean(axis=1, keepdims=True)
    d = w - c
    sxx = np.mean(d[:, :, 0] ** 2, axis=1)
    syy = np.mean(d[:, :, 1] ** 2, axis=1)
    sxy = np.mean(d[:, :, 0] * d[:, :, 1], axis=1)
    ang = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)
    ca, sa = np.cos(ang)[:, None], np.sin(ang)[:, None]
    x = ca * d[:, :, 0] + sa * d[:, :, 1]
    y = -sa * d[:, :, 0] + ca * d[:, :, 1]
    half = np.max(np.abs(x), axis=1, keepdims=True)
    x = x / np.where(half > 0.0, half, 1.0)
    design, inv, ok = _cubic(x)
    y = y[ok]
    coef = np.einsum("kij,kmj,km->ki", inv, design, y)
    i = m // 2
    xc = design[:, i, :]
    r = y[:, i] - np.einsum("ki,ki->k", xc, coef)
    lev = np.einsum("ki,kij,kj->k", xc, inv, xc)
    return r / np.sqrt(np.clip(1.0 - lev, 1e-6, None))


def _parametric_residuals(w: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Each window's centre residual across the curve from cubics x(t), y(t) in the parameter t
    (k, m), divided by sqrt(1 - leverage): unlike a graph y(x), a parametric cubic follows a
    window that turns through a large angle (sparse points on a tight curve)."""
    m = w.shape[1]
    i = m // 2
    tc = t - t[:, i:i + 1]
    half = np.max(np.abs(tc), axis=1, keepdims=True)
    tc = tc / np.where(half > 0.0, half, 1.0)
    design, inv, ok = _cubic(tc)
    w = w[ok]
    coef = np.einsum("kij,kmj,kmc->kic", inv, design, w)  # (k, 4, 2)
    res = w[:, i, :] - coef[:, 0, :]  # the centre is at t = 0
    tang = coef[:, 1, :]
    norm = np.hypot(tang[:, 0], tang[:, 1])
    good = norm > 0.0
    lateral = (tang[good, 0] * res[good, 1] - tang[good, 1] * res[good, 0]) / norm[good]
    lev = inv[good, 0, 0]
    return lateral / np.sqrt(np.clip(1.0 - lev, 1e-6, None))


def _robust_sigma(r: np.ndarray) -> float:
    """1.4826 x the median |r|: a rough sigma that a corner's windows do not move."""
    return float(1.4826 * np.median(np.abs(r))) if len(r) else 0.0


def _trimmed_sigma(r: np.ndarray) -> float:
    """The RMS of r without its largest TRIM share, scaled to a Gaussian's sigma: as robust to
    the few windows that hold a corner, and twice as efficient as the median (the smoothing's
    choice leans on this number: 10 % low, and the fit follows the noise)."""
    if not len(r):
        return 0.0
    a = np.sort(np.abs(r))[:max(1, int(math.ceil((1.0 - TRIM) * len(r))))]
    return float(np.sqrt(np.mean(a * a))) / TRIMMED_SHARE


def _graph_sigma(p: np.ndarray) -> tuple[float, int]:
    """(sigma, window) from graph cubics, the window grown until it spans SPAN_SIGMAS sigmas of
    the distance along the points (measured end to end over the window, which the noise does
    not inflate once the window is long)."""
    n = len(p)
    m = MIN_WINDOW
    sigma = _robust_sigma(_centre_residuals(_windows(p, m)))
    for _ in range(10):
        w = _windows(p, m)
        spacing = float(np.median(np.hypot(*(w[:, -1] - w[:, 0]).T))) / (m - 1)
        need = int(math.ceil(SPAN_SIGMAS * sigma / max(spacing, 1e-12))) + 1
        need = min(need + (1 - need % 2), MAX_WINDOW, n - (1 - n % 2))
        if need <= m:
            break
        m = need
        sigma = _robust_sigma(_centre_residuals(_windows(p, m)))
    return sigma, m


def estimate_noise(p: np.ndarray) -> float:
    """Lateral noise of the points (1 sigma; module docstring); 0 for too few points. The
    window is sized on graph cubics, the noise read from parametric ones along the averaged
    chord length (which follow a window turning through a large angle as well)."""
    p = np.asarray(p, dtype=float)
    if len(p) < MIN_WINDOW + 1:
        return 0.0
    rough, m = _graph_sigma(p)
    t = arc_parameter(p, rough)
    r = _parametric_residuals(_windows(p, m), _windows(t, m))
    return _trimmed_sigma(r) if len(r) else rough


def presmooth(p: np.ndarray, noise: float) -> np.ndarray:
    """The points averaged over a window spanning PRESMOOTH_SIGMAS noise sigmas (shrinking to
    each end, which stays put); the points themselves where the noise is below the spacing's
    scale."""
    p = np.asarray(p, dtype=float)
    n = len(p)
    if n < 3:
        return p
    half = int(round(0.5 * PRESMOOTH_SIGMAS * noise / max(along_spacing(p, noise), 1e-12)))
    if half < 1:
        return p
    i = np.arange(n)
    h = np.minimum(np.minimum(i, n - 1 - i), half)
    cs = np.vstack((np.zeros((1, 2)), np.cumsum(p, axis=0)))
    return (cs[i + h + 1] - cs[i - h]) / (2 * h + 1)[:, None]


def along_spacing(p: np.ndarray, noise: float) -> float:
    """The points' spacing along the curve: the median chord over windows spanning SPAN_SIGMAS
    noise sigmas, per step (point to point, noise larger than the spacing inflates it)."""
    p = np.asarray(p, dtype=float)
    n = len(p)
    spacing = float(np.median(np.hypot(*np.diff(p, axis=0).T))) if n > 1 else 0.0
    for _ in range(3):
        m = min(n, int(math.ceil(SPAN_SIGMAS * noise / max(spacing, 1e-12))) + 1)
        if m <= 2:
            break
        w = _windows(p, m)
        spacing = float(np.median(np.hypot(*(w[:, -1] - w[:, 0]).T))) / (m - 1)
    return spacing


def arc_parameter(p: np.ndarray, noise: float) -> np.ndarray:
    """Distance along the curve the points stand for, at each point: the chord length of the
    points averaged over a few noise sigmas (`presmooth`); plain chord length when the noise
    is small against the spacing. Strictly increasing."""
    q = presmooth(p, noise)
    step = np.hypot(*np.diff(q, axis=0).T)
    raw = np.hypot(*np.diff(np.asarray(p, dtype=float), axis=0).T)
    # A floor keeps it increasing where averaging stalls (a point where the curve turns back).
    step = np.maximum(step, 1e-3 * raw + 1e-12)
    return np.concatenate(([0.0], np.cumsum(step)))


def auto_tolerance(noise: float, n: int) -> float:
    """The tolerance `auto` sets for n points with this noise: the largest lateral excursion n
    Gaussian draws make (about sqrt(2 ln 2n) sigma) plus AUTO_MARGIN_SIGMAS for the fit's own
    error, so a curve that removes the noise keeps every point without bending towards any;
    never below TOLERANCE_FLOOR_M."""
    reach = math.sqrt(2.0 * math.log(2.0 * max(n, 1))) + AUTO_MARGIN_SIGMAS
    return max(TOLERANCE_FLOOR_M, reach * noise)


def chase_floor(noise: float, spacing: float) -> float:
    """The least smoothing length (m) a fit may fall to where a point is out of tolerance: a
    smoothing spline of length l leaves sigma sqrt(h / (18 l^5)) of curvature (RMS) from white
    noise sigma at spacing h, and below this length that exceeds CURVATURE_NOISE_BUDGET (the fit
    would be following the noise, not the curve)."""
    if noise <= 0.0 or spacing <= 0.0:
        return 0.0
    return (noise * noise * spacing / (18.0 * CURVATURE_NOISE_BUDGET ** 2)) ** 0.2
