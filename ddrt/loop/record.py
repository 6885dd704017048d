"""The telemetry row: its columns declared once, each with where its value comes from.

`COLUMNS` (the CSV header, the ring's and Foxglove's field names) and `fill_row` (what the tick
calls to write the row) are both derived from the declaration below, so a column cannot be
named in one place and filled from another. `fill_row` is generated from the declaration
once, at import, as plain assignments (`r[3] = est.theta`): the tick pays no loop, call or
allocation per column for it.
"""

from __future__ import annotations

import linecache
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

if TYPE_CHECKING:
    from ddrt.loop.tick import ControlLoop

__all__ = ["ADAPTER_COLUMNS", "COLUMNS", "Column", "LATER_COLUMNS", "PARTS", "TICK_COLUMNS", "fill_row",
           "fill_row_source"]


@dataclass(frozen=True)
class Column:
    """One telemetry column: its name, and its value as a Python expression over the tick's
    parts (PARTS), `loop` (the ControlLoop) and `t` (the sample's time)."""

    name: str
    source: str


# What the expressions may name, bound once per row.
PARTS = (
    ("est", "loop.estimator"),
    ("sp", "loop.setpoint"),
    ("cmd", "loop.cmd"),
    ("ref", "loop.reference"),
    ("sample", "loop.sample"),
)

TICK_COLUMNS = (
    Column("t", "t"),
    Column("x_est", "est.x"),
    Column("y_est", "est.y"),
    Column("theta_est", "est.theta"),
    Column("v_est", "est.v"),
    Column("omega_est", "est.yaw.w"),
    Column("gyro_bias", "est.yaw.b"),
    Column("x_ref", "sp.x_d"),
    Column("y_ref", "sp.y_d"),
    Column("theta_ref", "sp.theta_d"),
    Column("v_ref", "sp.v_d"),
    Column("omega_ref", "sp.omega_d"),
    Column("v_cmd", "cmd.v_c"),
    Column("omega_cmd", "cmd.omega_c"),
    Column("tau_l", "cmd.tau_l"),
    Column("tau_r", "cmd.tau_r"),
    Column("duty_l", "loop.duty_l"),
    Column("duty_r", "loop.duty_r"),
    Column("sigma", "ref.sigma if ref is not None else 0.0"),
    Column("cross_track_est", "ref.cross_track if ref is not None else 0.0"),
    Column("saturated", "1.0 if cmd.saturated else 0.0"),
    Column("state", "float(loop.state)"),  # the LoopState's value: its code
    Column("fresh", "1.0 if (sample is not None and sample.fresh) else 0.0"),
    Column("hal_fault_ticks", "float(loop.hal_fault_ticks)"),
)

# Written only while the loop has an adapter (they keep their zeros without one); `th` is its
# estimate of the dynamic coefficients (ddrt/core/adapt.py).
ADAPTER_COLUMNS = (
    Column("ad_m_k", "th[0]"),
    Column("ad_mbar", "th[1]"),
    Column("ad_I", "th[2]"),
    Column("ad_m_x", "th[3]"),
    Column("ad_fric_l", "th[4]"),
    Column("ad_fric_r", "th[5]"),
    Column("ad_active", "1.0 if loop.adapt_active else 0.0"),
)

# Written every tick, after the adapter's (a column is only ever added at the end of the
# header). `battery_v`: the supply voltage the motor model uses (V; measured and filtered, or
# robot.motor.supply_v when not measured: ddrt/loop/power.py); `hw_estop`: 1 while the
# hardware emergency-stop input is open.
LATER_COLUMNS = (
    Column("battery_v", "loop.power.v"),
    Column("hw_estop", "1.0 if loop.power.hw_estop else 0.0"),
    # The pose in `map` (odom until a fix; docs/estimation.md), its 1-sigma uncertainty
    # (ddrt/core/uncertainty.py, propagated every 20 ms) and the fixes fused so far.
    Column("x_map", "est.frame.x"),
    Column("y_map", "est.frame.y"),
    Column("theta_map", "est.frame.th"),
    Column("std_x", "est.track.std[0]"),
    Column("std_y", "est.track.std[1]"),
    Column("std_theta", "est.track.std[2]"),
    Column("cov_xy", "est.track.cov_xy"),
    Column("fixes", "float(est.frame.counters.fused)"),
    # 1 while the drive wheels slip (their turn or distance disagrees with the gyro's or the
    # omni wheel's beyond their noise: ddrt/core/wheel_odometry.py); 0 without wheel encoders.
    Column("wheel_slip", "1.0 if est.wheel_slip else 0.0"),
)

COLUMNS = tuple(c.name for c in TICK_COLUMNS + ADAPTER_COLUMNS + LATER_COLUMNS)


def fill_row_source(tick: tuple[Column, ...] = TICK_COLUMNS, adapter: tuple[Column, ...] = ADAPTER_COLUMNS,
                    later: tuple[Column, ...] = LATER_COLUMNS) -> str:
    """The source of `fill_row(r, loop, t)` for these columns, in this order."""
    lines = ["def fill_row(r, loop, t):"]
    lines += [f"    {name} = {expr}" for name, expr in PARTS]
    lines += [f"    r[{i}] = {c.source}  # {c.name}" for i, c in enumerate(tick)]
    lines += [f"    r[{i}] = {c.source}  # {c.name}" for i, c in enumerate(later, len(tick) + len(adapter))]
    lines += ["    ad = loop.adapter", "    if ad is not None:", "        th = ad.theta"]
    lines += [f"        r[{i}] = {c.source}  # {c.name}" for i, c in enumerate(adapter, len(tick))]
    return "\n".join(lines) + "\n"


def _compile(source: str) -> Callable[[list[float], "ControlLoop", float], None]:
    filename = "<ddrt.loop.record: fill_row>"
    linecache.cache[filename] = (len(source), None, source.splitlines(True), filename)  # readable tracebacks
    namespace: dict[str, object] = {}
    exec(compile(source, filename, "exec"), namespace)
    return namespace["fill_row"]  # type: ignore[return-value]


#: Write the loop's telemetry row for the sample at time `t` into `r` (a list of COLUMNS' length).
fill_row = _compile(fill_row_source())
