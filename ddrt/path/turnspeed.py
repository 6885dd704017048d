"""Speed caps that take a grid plan's turns gently: the yaw rate changes at a bounded rate.

Why. A grid planner's 90 degree turns (at an obstacle's corner, where the diagonal cell is
blocked) must be smoothed within a cell-sized corridor, so the reference's curvature rises
to about one per cell and falls again within a cell or two. At the asked speed the yaw rate
then jumps: d(omega)/dt = v^2 d(kappa)/ds + a kappa reached 17 rad/s^2 on a 5 cm plan at
0.4 m/s. No smoothing within the corridor can make such a turn gentle (a 90 degree turn
that stays within half a cell of the corner's centre has a radius below 1.2 cells), so the
reference slows down for it instead.

How. Each turn (a run of samples whose |kappa| exceeds `STRAIGHT_KAPPA`) gets one speed
cap, the largest v with v^2 |d(kappa)/ds| <= yaw_accel at every sample of the turn. The cap
is constant across the turn, so the profile brakes and speeds up on the straights either
side, where kappa is small and a kappa stays below accel * STRAIGHT_KAPPA; inside the turn
the only yaw acceleration is v^2 d(kappa)/ds. Between turns the per-sample cap applies as
it is. The caps are the conditioning's own point caps (`Geometry.cap_sigma/cap_value`),
so the speed profile (ddrt/path/profile.py) needs no new limit.

Blended turns. A turn of `BLENDED_TURN_DEG` or more (a grid's 45 degree step, which the fit
smooths to about 30 degrees within the cells, an obstacle's corner bent within them) gets no
cap here: taken gently it would last at least sqrt(4 |turn| / GRID_YAW_ACCEL) s (1.5 s for 45
degrees) whatever its radius, and a plan whose cells force a few such turns a metre could not
keep 1.3 x length / speed + 3 s. It is left to the profile's own limits instead, which every
other path drives with: the yaw rate, the lateral acceleration and v^2 |d(kappa)/ds| <=
alpha_max / 2, half the yaw acceleration of a turn in place, so a blended turn is no rougher
than stopping to turn in place, and faster. Of 600 fuzzed plans (python -m bench.grid_plans,
every 90 degree corner turned in place) 517 held that bound with every turn gentle, 531
blending from 40 degrees, 537 from 25 (538 from 15, with rougher gentle driving); tracking in
closed loop was unchanged.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ddrt.path.geometry import Piece

__all__ = ["BLENDED_TURN_DEG", "GRID_YAW_ACCEL", "STRAIGHT_KAPPA", "TurnCaps", "turn_caps"]

GRID_YAW_ACCEL = 1.4  # rad/s^2: RMS of d(omega)/dt over each of a grid plan's gentle turns
BLENDED_TURN_DEG = 25.0  # a turn this large is blended: left to the profile's own limits
STRAIGHT_KAPPA = 0.25  # 1/m: below this a sample is on a straight (a kappa <= 0.25 rad/s^2 at 1 m/s^2)
_NO_CAP = 1e3  # m/s: a sample whose curvature does not change


def _piece_caps(pc: Piece, yaw_accel: float, blended: list[tuple[float, float]], offset: float) -> np.ndarray:
    """Per-sample caps of one driving piece: per gentle turn one speed, none in a blended turn
    (its progress span, from `offset`, appended to `blended`), elsewhere each sample's own."""
    k = pc.kappa
    dk = np.gradient(k, pc.s)
    ds = np.gradient(pc.s)
    with np.errstate(divide="ignore"):
        cap = np.minimum(np.sqrt(yaw_accel / np.abs(dk)), _NO_CAP)
    turning = np.abs(k) > STRAIGHT_KAPPA
    edges = np.flatnonzero(np.diff(turning.astype(np.int8))) + 1
    starts = np.concatenate(([0], edges))
    ends = np.concatenate((edges, [len(k)]))
    for a, b in zip(starts.tolist(), ends.tolist()):
        if not turning[a]:
            continue
        # At one speed v through the turn, the mean square of d(omega)/dt = v^2 dkappa/ds over
        # the turn's time L / v is v^4 I / L with I the integral of dkappa/ds^2 over its length.
        lo, hi = max(a - 1, 0), min(b + 1, len(k))  # reached a sample before the turn begins
        if abs(float(np.sum(k[lo:hi] * ds[lo:hi]))) >= math.radians(BLENDED_TURN_DEG):
            cap[lo:hi] = _NO_CAP  # blended: the profile's own yaw limits
            blended.append((offset + float(pc.s[lo]), offset + float(pc.s[hi - 1])))
            continue
        length = float(np.sum(ds[lo:hi]))
        rough = float(np.sum(dk[lo:hi] ** 2 * ds[lo:hi]))
        v = (yaw_accel ** 2 * length / rough) ** 0.25 if rough > 0.0 else _NO_CAP
        cap[lo:hi] = min(v, _NO_CAP)
    return cap


def _end_ramp(s: np.ndarray, pieces: Sequence[Piece], total: float, yaw_accel: float) -> np.ndarray:
    """A plan that starts or ends in a turn starts or stops there: the speed ramps at most at
    yaw_accel / |kappa| (so a kappa stays within yaw_accel) over the first and last turn."""
    cap = np.full(len(s), _NO_CAP)
    for pc, dist, first in ((pieces[0], s, True), (pieces[-1], total - s, False)):
        if pc.pivot:
            continue
        k = np.abs(pc.kappa)
        end = k if first else k[::-1]
        if end[0] <= STRAIGHT_KAPPA:
            continue
        run = int(np.argmax(end <= STRAIGHT_KAPPA)) if np.any(end <= STRAIGHT_KAPPA) else len(end)
        accel = yaw_accel / float(end[:run + 1].max())
        cap = np.minimum(cap, np.sqrt(2.0 * accel * np.maximum(dist, 0.0)))
    return cap


@dataclass(frozen=True)
class TurnCaps:
    """A grid plan's turn speeds as point caps, and where its blended turns are."""

    sigma: np.ndarray  # progress of each cap, from the first piece's start
    cap: np.ndarray  # m/s
    blended: tuple[tuple[float, float], ...]  # (start, end) progress of each blended turn


def turn_caps(pieces: Sequence[Piece], yaw_accel: float = GRID_YAW_ACCEL) -> TurnCaps:
    """Caps at every sample of the driving pieces; pivots are left to the profile (it stops
    for them)."""
    sig: list[np.ndarray] = []
    val: list[np.ndarray] = []
    blended: list[tuple[float, float]] = []
    offset = 0.0
    for pc in pieces:
        if not pc.pivot and len(pc.s) >= 3:
            sig.append(pc.s + offset)
            val.append(_piece_caps(pc, yaw_accel, blended, offset))
        offset += pc.length
    if not sig:
        return TurnCaps(np.array([0.0, offset]), np.full(2, _NO_CAP), ())
    s, v = np.concatenate(sig), np.concatenate(val)
    v = np.minimum(v, _end_ramp(s, pieces, offset, yaw_accel))
    # Pieces meet at a shared progress: keep progress non-decreasing, the lower cap first.
    order = np.lexsort((v, s))
    return TurnCaps(s[order], v[order], tuple(blended))
