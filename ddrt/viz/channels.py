"""The Foxglove channels, defined once for the live server and the MCAP recordings.

One `Channels` is bound to a foxglove Context; every sink of that context (the WebSocket
server, an MCAP writer) gets the same topics, schemas and messages. A tick becomes:

| topic | schema | what |
|---|---|---|
| `/tf` | foxglove.FrameTransform | odom -> base_link, the estimated pose |
| `/tf_true` | foxglove.FrameTransform | odom -> base_link_true, the simulated robot's true pose |
| `/reference` | foxglove.SceneUpdate | a sphere at the reference point |
| `/uncertainty` | foxglove.SceneUpdate | the 2-sigma ellipse of the estimated position, at it (docs/estimation.md) |
| `/state` | ddrt.State (JSON) | the telemetry row by column name (the supply voltage `battery_v`, `hw_estop` among them), errors, the true state |
| `/timing` | ddrt.Timing (JSON) | the daemon's lateness and tick cost (not in `ddrt sim`) |
| `/path` | foxglove.SceneUpdate | the path as a line strip, once when it starts |
| `/log` | foxglove.Log | state changes, faults, the daemon's log records |

Channels with no sink (no client subscribed, no recording) cost one `has_sinks()` call.
"""

from __future__ import annotations

import json
import math
from types import ModuleType
from typing import Callable, Sequence

from ddrt.core.wrap import wrap_angle
from ddrt.loop import COLUMNS, LoopState, state_label

ODOM, BASE, BASE_TRUE = "odom", "base_link", "base_link_true"
TOPICS = ("/tf", "/tf_true", "/reference", "/state", "/timing", "/path", "/log", "/uncertainty")
TICK_TOPICS = ("/tf", "/reference", "/state")  # one message per tick, always
TRUTH = ("true_x", "true_y", "true_theta", "true_v", "true_omega")
ERRORS = ("err_v", "err_omega", "err_heading", "err_position")
STATE_FIELDS = COLUMNS + ERRORS + TRUTH
PATH_POINTS_MAX = 5000  # the line strip is decimated to at most this many points
_C = {name: i for i, name in enumerate(COLUMNS)}


def _json_schema(title: str, numbers: Sequence[str], strings: Sequence[str] = ()) -> bytes:
    props: dict[str, object] = {n: {"type": ["number", "null"]} for n in numbers}
    props.update({n: {"type": "string"} for n in strings})
    return json.dumps({"title": title, "type": "object", "properties": props}).encode()


STATE_SCHEMA = _json_schema("ddrt.State", STATE_FIELDS, ("state_name",))
TIMING_FIELDS = ("tick", "late_us", "tick_us")
TIMING_SCHEMA = _json_schema("ddrt.Timing", TIMING_FIELDS)


def _finite(v: float) -> float | None:
    return v if v - v == 0.0 else None  # NaN and +-inf are not JSON


class Channels:
    """The topics on one Context, and how a tick, a path and a log record become messages."""

    def __init__(self, fg: ModuleType, context: object, *, truth: bool, timing: bool) -> None:
        from foxglove import channels as ch
        from foxglove import messages as m

        self._m = m
        self.tf = ch.FrameTransformChannel("/tf", context=context)
        self.tf_true = ch.FrameTransformChannel("/tf_true", context=context) if truth else None
        self.reference = ch.SceneUpdateChannel("/reference", context=context)
        self.uncertainty = ch.SceneUpdateChannel("/uncertainty", context=context)
        self._ellipse_color = m.Color(r=0.6, g=0.2, b=0.9, a=0.35)
        self.path = ch.SceneUpdateChannel("/path", context=context)
        self.log = ch.LogChannel("/log", context=context)
        self.state = fg.Channel("/state", context=context, message_encoding="json",
                                schema=fg.Schema(name="ddrt.State", encoding="jsonschema", data=STATE_SCHEMA))
        self.timing = (fg.Channel("/timing", context=context, message_encoding="json",
                                  schema=fg.Schema(name="ddrt.Timing", encoding="jsonschema", data=TIMING_SCHEMA))
                       if timing else None)
        self._last_state = -1
        self.ticks = 0
        self._ref_color = m.Color(r=1.0, g=0.4, b=0.0, a=1.0)
        self._ref_size = m.Vector3(x=0.03, y=0.03, z=0.03)
        self._path_color = m.Color(r=0.2, g=0.6, b=1.0, a=1.0)
        self._levels = (m.LogLevel.Unknown, m.LogLevel.Debug, m.LogLevel.Info, m.LogLevel.Warning,
                        m.LogLevel.Error, m.LogLevel.Fatal)

    # ------------------------------------------------------------------ messages

    def _stamp(self, ns: int) -> object:
        sec, nsec = divmod(ns, 1_000_000_000)
        return self._m.Timestamp(sec, nsec)

    def _quat(self, theta: float) -> object:
        return self._m.Quaternion(x=0.0, y=0.0, z=math.sin(0.5 * theta), w=math.cos(0.5 * theta))

    def _transform(self, ts: object, child: str, x: float, y: float, theta: float) -> object:
        m = self._m
        return m.FrameTransform(timestamp=ts, parent_frame_id=ODOM, child_frame_id=child,
                                translation=m.Vector3(x=x, y=y, z=0.0), rotation=self._quat(theta))

    def publish_tick(self, row: Sequence[float], log_ns: int, truth: Sequence[float] | None = None,
                     timing: tuple[float, float] | None = None,
                     fault: Callable[[], str] | None = None) -> None:
        """One tick: `row` in ddrt.loop.COLUMNS order, `truth` (x, y, theta, v, omega),
        `timing` (lateness, tick cost) in s; `fault` gives the reason when the state becomes
        fault or estop. `log_ns` stamps every message (the tick's time)."""
        self.ticks += 1
        m = self._m
        ts = self._stamp(log_ns)
        c = _C
        x, y, th = row[c["x_est"]], row[c["y_est"]], row[c["theta_est"]]
        if self.tf.has_sinks():
            self.tf.log(self._transform(ts, BASE, x, y, th), log_time=log_ns)
        if truth is not None and self.tf_true is not None and self.tf_true.has_sinks():
            self.tf_true.log(self._transform(ts, BASE_TRUE, truth[0], truth[1], truth[2]), log_time=log_ns)
        xr, yr, thr = row[c["x_ref"]], row[c["y_ref"]], row[c["theta_ref"]]
        if self.reference.has_sinks():
            sphere = m.SpherePrimitive(pose=m.Pose(position=m.Vector3(x=xr, y=yr, z=0.0), orientation=self._quat(thr)),
                                       size=self._ref_size, color=self._ref_color)
            self.reference.log(m.SceneUpdate(entities=[m.SceneEntity(timestamp=ts, frame_id=ODOM, id="reference",
                                                                     frame_locked=True, spheres=[sphere])]),
                               log_time=log_ns)
        if self.uncertainty.has_sinks():
            self._publish_ellipse(ts, log_ns, x, y, row[c["std_x"]], row[c["std_y"]], row[c["cov_xy"]])
        code = int(row[c["state"]])
        if self.state.has_sinks():
            values = [_finite(v) for v in row]
            values += [_finite(row[c["v_ref"]] - row[c["v_est"]]), _finite(row[c["omega_ref"]] - row[c["omega_est"]]),
                       _finite(wrap_angle(thr - th)) if math.isfinite(thr - th) else None,
                       _finite(math.hypot(xr - x, yr - y))]
            values += [_finite(v) for v in truth] if truth is not None else [None] * len(TRUTH)
            doc = dict(zip(STATE_FIELDS, values))
            doc["state_name"] = state_label(code)
            self.state.log(json.dumps(doc).encode(), log_time=log_ns)
        if timing is not None and self.timing is not None and self.timing.has_sinks():
            self.timing.log(json.dumps({"tick": self.ticks, "late_us": _finite(timing[0] * 1e6),
                                        "tick_us": _finite(timing[1] * 1e6)}).encode(), log_time=log_ns)
        if code != self._last_state:
            if self._last_state >= 0:
                old, new = state_label(self._last_state), state_label(code)
                why = fault() if fault is not None and code in (LoopState.FAULT, LoopState.ESTOP) else ""
                level = 4 if code == LoopState.FAULT else 3 if code in (LoopState.ESTOP, LoopState.HOLDING) else 2
                self.publish_log(level, f"state {old} -> {new}" + (f": {why}" if why else ""), "ddrt.loop", log_ns)
            self._last_state = code

    def _publish_ellipse(self, ts: object, log_ns: int, x: float, y: float, sx: float, sy: float, cxy: float) -> None:
        """The position's 2-sigma ellipse: a flat elliptic cylinder along the covariance's axes."""
        m = self._m
        a, b, half = sx * sx, sy * sy, 0.5 * (sx * sx - sy * sy)
        r = math.sqrt(half * half + cxy * cxy)
        l1, l2 = 0.5 * (a + b) + r, max(0.5 * (a + b) - r, 0.0)
        angle = 0.5 * math.atan2(2.0 * cxy, a - b)
        if not all(math.isfinite(v) for v in (x, y, l1, l2, angle)):
            return
        cyl = m.CylinderPrimitive(pose=m.Pose(position=m.Vector3(x=x, y=y, z=0.0), orientation=self._quat(angle)),
                                  size=m.Vector3(x=4.0 * math.sqrt(l1), y=4.0 * math.sqrt(l2), z=0.002),
                                  bottom_scale=1.0, top_scale=1.0, color=self._ellipse_color)
        self.uncertainty.log(m.SceneUpdate(entities=[m.SceneEntity(timestamp=ts, frame_id=ODOM, id="uncertainty",
                                                                   frame_locked=True, cylinders=[cyl])]), log_time=log_ns)

    def publish_path(self, xs: Sequence[float], ys: Sequence[float], log_ns: int) -> None:
        """The path as one line strip in the odom frame (replaces the previous one)."""
        m = self._m
        step = max(1, -(-len(xs) // PATH_POINTS_MAX))
        idx = list(range(0, len(xs), step))
        if idx and idx[-1] != len(xs) - 1:
            idx.append(len(xs) - 1)
        points = [m.Point3(x=float(xs[i]), y=float(ys[i]), z=0.0) for i in idx]
        line = m.LinePrimitive(type=m.LinePrimitiveLineType.LineStrip, thickness=2.0, scale_invariant=True,
                               points=points, color=self._path_color)
        self.path.log(m.SceneUpdate(entities=[m.SceneEntity(timestamp=self._stamp(log_ns), frame_id=ODOM, id="path",
                                                            frame_locked=True, lines=[line])]), log_time=log_ns)

    def publish_log(self, level: int, message: str, name: str, log_ns: int) -> None:
        """A foxglove.Log: level 1 debug .. 5 fatal (foxglove.messages.LogLevel)."""
        m = self._m
        self.log.log(m.Log(timestamp=self._stamp(log_ns), level=self._levels[min(max(level, 0), 5)], message=message, name=name),
                     log_time=log_ns)
