"""A path given in the `map` frame, followed by a loop that steers in `odom`.

The estimator's odometry (`odom`) never jumps; pose fixes move the correction map -> odom
(ddrt/core/pose_fix.py: map pose = correction composed with the odometry's). The path was
built in odom as the correction stood when the follow was asked (`built`: the worker moved
it there, ddrt/service/pathjob.py). As fixes move the correction, the correction this stage
applies follows it as a first-order lag of time constant `blend_s` (estimator.map_blend_s),
so the reference the controller sees moves smoothly and the motor command does not step:
the robot's pose is taken into the path's coordinates through D = built^-1 . applied, the
inner stage (a PathReference or StartReference) works there, and its setpoint comes back
through D^-1. Speeds, curvature and progress are the same in every frame.
"""

from __future__ import annotations

import math
from typing import Callable

from ddrt.core.reference import Reference
from ddrt.core.types import Setpoint
from ddrt.core.wrap import wrap_angle

Transform = tuple[float, float, float]  # (x, y, theta): p_map = (x, y) + R(theta) p_odom


def compose(a: Transform, b: Transform) -> Transform:
    """a . b: first b, then a."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], a[2] + b[2]


def inverse(a: Transform) -> Transform:
    c, s = math.cos(a[2]), math.sin(a[2])
    return -(c * a[0] + s * a[1]), s * a[0] - c * a[1], -a[2]


class MapReference:
    """A reference stage in `map` coordinates seen from `odom` (a ddrt.core.reference.Reference)."""

    def __init__(self, inner: Reference, built: Transform, correction: Callable[[], Transform],
                 blend_s: float, period_s: float) -> None:
        self.inner = inner
        self.built_inv = inverse(built)
        self.applied = built  # the correction in use, lagging `correction()`
        self.correction = correction
        self.blend_s = blend_s
        self.period = period_s
        self._d: Transform = (0.0, 0.0, 0.0)

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
    def path(self) -> object:
        return getattr(self.inner, "path", None)

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
        """Move the applied correction towards the estimator's; D = built^-1 . applied."""
        target = self.correction()
        a = self.applied
        if target != a:
            k = 1.0 if self.blend_s <= 0.0 else 1.0 - math.exp(-dt / self.blend_s)
            a = (a[0] + k * (target[0] - a[0]), a[1] + k * (target[1] - a[1]),
                 a[2] + k * wrap_angle(target[2] - a[2]))
            self.applied = a
            self._d = compose(self.built_inv, a)
        return self._d
