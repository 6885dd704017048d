"""A path given in the `map` frame, followed by a loop that steers in `odom`.

The estimator's odometry (`odom`) never jumps; the map pose (ddrt/core/pose_fix.py) does at
each fix, and the correction map -> odom with it. The path was built in odom as the
correction stood when the follow was asked (`built`: the worker moved it there,
ddrt/service/pathjob.py). A fix's jump enters this stage as an offset that decays over
`blend_s` (estimator.map_blend_s), so the reference the controller sees moves smoothly and
the motor command does not step; between fixes the correction's slow drift (the learnt scale
and bias corrections at work) passes straight through. The offset decays critically damped
(x'' + 2w x' + w^2 x = 0, w = 2 / blend_s; 59 % gone after blend_s, 91 % after twice that),
not exponentially: its rate starts from the rate it had, so a fix does not step the speed at
which the reference moves either (an exponential's rate jumps to jump / blend_s, and the
controller's damping turned that into a duty step as large as the steadiest run's largest). The robot's pose is taken into the
path's coordinates through D = built^-1 . J . correction, the inner stage (a PathReference
or StartReference) works there, and its setpoint comes back through D^-1. Speeds, curvature
and progress are the same in every frame.
"""

from __future__ import annotations

import math
from typing import Protocol

from ddrt.core.types import Setpoint
from ddrt.core.wrap import wrap_angle
from ddrt.path.reference import PathReference
from ddrt.path.sampled import Path
from ddrt.path.start import StartReference

Transform = tuple[float, float, float]  # (x, y, theta): p_map = (x, y) + R(theta) p_odom


def compose(a: Transform, b: Transform) -> Transform:
    """a . b: first b, then a."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], a[2] + b[2]


def inverse(a: Transform) -> Transform:
    c, s = math.cos(a[2]), math.sin(a[2])
    return -(c * a[0] + s * a[1]), s * a[0] - c * a[1], -a[2]


class _Frame(Protocol):
    jumps: int

    def correction(self) -> Transform: ...


class MapReference:
    """A reference stage in `map` coordinates seen from `odom` (a ddrt.core.reference.Reference)."""

    def __init__(self, inner: PathReference | StartReference, built: Transform, frame: _Frame, blend_s: float,
                 period_s: float) -> None:
        self.inner = inner
        self.built_inv = inverse(built)
        self.frame = frame
        self.blend_s = blend_s
        self.period = period_s
        # The part of the fixes' jumps not yet applied (a map-frame transform that decays to
        # identity), and the correction as last seen: the correction in use is J . correction.
        self.jump: Transform = compose(built, inverse(frame.correction()))
        self.rate: Transform = (0.0, 0.0, 0.0)  # d(jump)/dt, per component (the blend's second state)
        self._jumps = frame.jumps
        self._last = frame.correction()

    # ------------------------------------------------------------------ the protocol

    @property
    def sigma(self) -> float:
        return self.inner.sigma

    @property
    def cross_track(self) -> float:
        return self.inner.cross_track

    @property
    def done(self) -> bool:
        return self.inner.done

    @property
    def stopping(self) -> bool:
        return self.inner.stopping

    @property
    def phase(self) -> str:
        return self.inner.phase

    @property
    def resumable(self) -> bool:
        return self.inner.resumable

    @property
    def path(self) -> Path:
        return self.inner.path

    def request_stop(self, decel: float) -> None:
        self.inner.request_stop(decel)

    def resume(self, x: float, y: float, theta: float) -> None:
        self.inner.resume(*compose(self._blend(0.0), (x, y, theta)))

    def update(self, x: float, y: float, theta: float, sp: Setpoint, dt: float | None = None) -> None:
        d = self._blend(self.period if dt is None else dt)
        px, py, pth = compose(d, (x, y, theta))
        self.inner.update(px, py, pth, sp, dt)
        # The setpoint back into odom: D^-1 applied to the reference pose.
        c, s = math.cos(d[2]), math.sin(d[2])
        ux, uy = sp.x_d - d[0], sp.y_d - d[1]
        sp.x_d = c * ux + s * uy
        sp.y_d = -s * ux + c * uy
        sp.theta_d -= d[2]

    def _blend(self, dt: float) -> Transform:
        """D = built^-1 . J . correction: a fix's jump enters J (so D does not move at it) and
        J decays to identity over blend_s; the correction's slow drift (the learnt scale and
        bias corrections acting) passes straight through."""
        frame = self.frame
        target = frame.correction()
        if frame.jumps != self._jumps:
            self._jumps = frame.jumps
            self.jump = compose(compose(self.jump, self._last), inverse(target))
        self._last = target
        j = self.jump
        if j != (0.0, 0.0, 0.0) or self.rate != (0.0, 0.0, 0.0):
            j = self._decay((j[0], j[1], wrap_angle(j[2])), dt)
        return compose(self.built_inv, compose(j, target))

    def _decay(self, j: Transform, dt: float) -> Transform:
        """The offset and its rate `dt` later: the exact solution of the critically damped
        blend, component by component (zero at once without a blend)."""
        if self.blend_s <= 0.0:
            self.jump = self.rate = (0.0, 0.0, 0.0)
            return self.jump
        w = 2.0 / self.blend_s
        e = math.exp(-w * dt)
        a, b, c = w * dt, w * w * dt, self.rate
        jump = (e * (j[0] * (1.0 + a) + c[0] * dt), e * (j[1] * (1.0 + a) + c[1] * dt), e * (j[2] * (1.0 + a) + c[2] * dt))
        rate = (e * (c[0] * (1.0 - a) - b * j[0]), e * (c[1] * (1.0 - a) - b * j[1]), e * (c[2] * (1.0 - a) - b * j[2]))
        if sum(abs(v) for v in jump) + self.blend_s * sum(abs(v) for v in rate) < 1e-12:
            jump = rate = (0.0, 0.0, 0.0)
        self.jump, self.rate = jump, rate
        return jump


def in_map(reference: PathReference | StartReference, frame: _Frame, built: Transform, blend_s: float,
           period_s: float) -> MapReference:
    """`reference` (built in odom at the correction `built`) followed in map as `frame` (the
    estimator's MapFrame) moves: what a follow with frame: map puts in the loop."""
    return MapReference(reference, built, frame, blend_s, period_s)
