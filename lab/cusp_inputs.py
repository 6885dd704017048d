"""Manoeuvres with cusps, as a person records or writes them: the underlying curve, noisy samples
of it with signed speeds, and its exact form as a Path.

A manoeuvre is a list of legs, each driven one way (+1 forward, -1 in reverse), each a yaw
rate per driven distance c(s) (so the robot's heading is continuous across every cusp, as it
is for a real three-point turn: the robot is at rest there and only its direction flips).
Curvature inside a leg is a smooth bump (zero at both ends), so the exact curve has no turn
in place: any turn in place the loader makes of the samples is the loader's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ddrt.path.geometry import Geometry, Piece, reversed_piece

__all__ = ["Leg", "Manoeuvre", "three_point_turn", "parallel_park", "zig_zag", "random_manoeuvre"]


@dataclass(frozen=True)
class Leg:
    """One run of the manoeuvre: driven `direction` for `length` m, turning the robot's heading by
    `turn` rad as a raised-cosine bump of yaw per distance (`sshape`: a full sine instead, which
    turns and turns back, ending on the start heading and offset sideways)."""

    direction: float
    length: float
    turn: float = 0.0
    sshape: float = 0.0  # peak yaw per distance (1/m) of an S: heading out and back


@dataclass
class Manoeuvre:
    """Dense samples of the underlying curve (every ~1 mm) and which leg each sample is on."""

    s: np.ndarray  # driven distance
    x: np.ndarray
    y: np.ndarray
    theta: np.ndarray  # the robot's heading
    c: np.ndarray  # d(theta)/d(driven distance)
    leg: np.ndarray  # leg index per sample (a cusp sample belongs to the leg that ends there)
    directions: tuple[float, ...]

    @property
    def length(self) -> float:
        return float(self.s[-1])

    @property
    def cusps(self) -> int:
        d = self.directions
        return sum(1 for a, b in zip(d, d[1:]) if a != b)

    def xy(self) -> np.ndarray:
        return np.column_stack((self.x, self.y))

    def exact_path_geometry(self) -> Geometry:
        """The curve as pieces of the loader's convention (reversed legs: heading + pi of travel)."""
        pieces = []
        for k, d in enumerate(self.directions):
            sel = np.flatnonzero(self.leg == k)
            if k:
                sel = np.concatenate(([sel[0] - 1], sel))  # share the cusp sample
            s = self.s[sel] - self.s[sel[0]]
            travel = self.theta[sel] + (0.0 if d > 0 else math.pi)
            pc = Piece(s, self.x[sel], self.y[sel], travel, self.c[sel])
            pieces.append(reversed_piece(pc) if d < 0 else pc)
        return Geometry(pieces)

    def recording(self, rng: np.random.Generator, speed: float, spacing: tuple[float, float] = (0.01, 0.01),
                  noise: float = 0.0015) -> tuple[np.ndarray, np.ndarray]:
        """Samples every `spacing` (uniform random between the two) with Gaussian `noise` per axis,
        and each sample's signed v (the sign of the leg that reaches it), every cusp sampled."""
        at: list[float] = [0.0]
        ends = [float(self.s[self.leg == k][-1]) for k in range(len(self.directions))]
        for end in ends:
            while at[-1] + spacing[1] < end:
                at.append(at[-1] + float(rng.uniform(*spacing)))
            at.append(end)  # the cusp (or the end) itself is recorded: the robot stood there
        at_ = np.array(at)
        xy = np.column_stack((np.interp(at_, self.s, self.x), np.interp(at_, self.s, self.y)))
        leg = np.searchsorted(ends, at_ - 1e-12)
        v = np.array([speed * self.directions[min(k, len(ends) - 1)] for k in leg])
        return xy + rng.normal(0.0, noise, xy.shape), v


def _build(legs: list[Leg], x0: float = 0.0, y0: float = 0.0, th0: float = 0.0, step: float = 0.001) -> Manoeuvre:
    s_all, c_all, leg_all, d_all = [np.zeros(1)], [np.zeros(1)], [np.zeros(1, dtype=int)], []
    base = 0.0
    for k, leg in enumerate(legs):
        n = max(2, int(math.ceil(leg.length / step)))
        u = np.linspace(0.0, leg.length, n + 1)[1:]
        f = u / leg.length
        c = leg.turn / leg.length * (1.0 - np.cos(2.0 * math.pi * f)) + leg.sshape * np.sin(2.0 * math.pi * f)
        s_all.append(base + u)
        c_all.append(c)
        leg_all.append(np.full(n, k))
        d_all.append(np.full(n, leg.direction))
        base += leg.length
    s = np.concatenate(s_all)
    c = np.concatenate(c_all)
    d = np.concatenate([np.array([legs[0].direction])] + d_all)
    ds = np.diff(s)
    th = th0 + np.concatenate(([0.0], np.cumsum(0.5 * (c[1:] + c[:-1]) * ds)))
    # Travel: forward along the heading on forward legs, against it on reversed ones.
    cx, sy = d * np.cos(th), d * np.sin(th)
    x = x0 + np.concatenate(([0.0], np.cumsum(0.5 * (cx[1:] + cx[:-1]) * ds)))
    y = y0 + np.concatenate(([0.0], np.cumsum(0.5 * (sy[1:] + sy[:-1]) * ds)))
    leg_idx = np.concatenate(leg_all)
    leg_idx[0] = 0
    return Manoeuvre(s, x, y, th, c, leg_idx, tuple(leg.direction for leg in legs))


def three_point_turn(width: float = 1.2) -> Manoeuvre:
    """Turn round in a street `width` wide: forward turning left, back turning on, forward out
    (60 degrees each, heading 0 to pi)."""
    third = math.pi / 3.0
    return _build([Leg(1.0, 0.45 * width, third), Leg(-1.0, 0.35 * width, third), Leg(1.0, 0.6 * width, third)])


def parallel_park(offset: float = 0.3, back: float = 0.8) -> Manoeuvre:
    """Drive past the slot, back into it along an S (heading out and back to 0) `offset` to the
    right, then forward a little to centre."""
    # An S of length L with peak yaw-per-distance A: lateral offset about A L^2 / (2 pi).
    peak = 2.0 * math.pi * offset / back ** 2
    return _build([Leg(1.0, 1.0), Leg(-1.0, back, sshape=peak), Leg(1.0, 0.15)])


def zig_zag(rng: np.random.Generator, legs: int) -> Manoeuvre:
    """Alternating forward and reverse legs, each turning by a random angle."""
    out = []
    for k in range(legs):
        out.append(Leg(1.0 if k % 2 == 0 else -1.0, float(rng.uniform(0.3, 0.7)),
                       float(rng.uniform(-1.0, 1.0))))
    return _build(out)


def random_manoeuvre(rng: np.random.Generator) -> Manoeuvre:
    """One of the three kinds with random sizes (for the fuzz test)."""
    kind = int(rng.integers(0, 3))
    if kind == 0:
        m = three_point_turn(float(rng.uniform(0.9, 1.6)))
    elif kind == 1:
        m = parallel_park(float(rng.uniform(0.15, 0.35)), float(rng.uniform(0.7, 1.1)))
    else:
        m = zig_zag(rng, int(rng.integers(2, 5)))
    return m
