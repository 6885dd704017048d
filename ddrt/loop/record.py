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
    """One telemetry column: its name, its value as a Python expression over the tick's parts
    (PARTS), `loop` (the ControlLoop) and `t` (the sample's time), and, for the generated
    reference (docs/reference/telemetry.md, `python -m ddrt.docgen`), its unit and meaning."""

    name: str
    source: str
    unit: str
    about: str


# What the expressions may name, bound once per row.
PARTS = (
    ("est", "loop.estimator"),
    ("sp", "loop.setpoint"),
    ("cmd", "loop.cmd"),
    ("ref", "loop.reference"),
    ("sample", "loop.sample"),
)

TICK_COLUMNS = (
    Column("t", "t", "s", "the sample's time on the loop's clock"),
    Column("x_est", "est.x", "m", "estimated position of the rear axle's midpoint, odom frame"),
    Column("y_est", "est.y", "m", "estimated position, odom frame"),
    Column("theta_est", "est.theta", "rad", "estimated heading, odom frame"),
    Column("v_est", "est.v", "m/s", "estimated forward speed (the speed filter the controller feeds back)"),
    Column("omega_est", "est.yaw.w", "rad/s", "estimated yaw rate (the yaw filter)"),
    Column("gyro_bias", "est.yaw.b", "rad/s", "the gyro's bias as the yaw filter tracks it"),
    Column("x_ref", "sp.x_d", "m", "reference position: the setpoint the controller tracks"),
    Column("y_ref", "sp.y_d", "m", "reference position"),
    Column("theta_ref", "sp.theta_d", "rad", "reference heading"),
    Column("v_ref", "sp.v_d", "m/s", "reference forward speed"),
    Column("omega_ref", "sp.omega_d", "rad/s", "reference yaw rate"),
    Column("v_cmd", "cmd.v_c", "m/s", "forward speed asked of the inner loop by the outer law"),
    Column("omega_cmd", "cmd.omega_c", "rad/s", "yaw rate asked of the inner loop"),
    Column("tau_l", "cmd.tau_l", "N m", "left wheel torque commanded"),
    Column("tau_r", "cmd.tau_r", "N m", "right wheel torque commanded"),
    Column("duty_l", "loop.duty_l", "-1..1", "left motor duty written"),
    Column("duty_r", "loop.duty_r", "-1..1", "right motor duty written"),
    Column("sigma", "ref.sigma if ref is not None else 0.0", "m",
           "progress along the path (grows in turns in place too); 0 without a path"),
    Column("cross_track_est", "ref.cross_track if ref is not None else 0.0", "m",
           "signed cross-track error of the estimated pose, left positive"),
    Column("saturated", "1.0 if cmd.saturated else 0.0", "0/1", "1 when a duty was limited this tick"),
    Column("state", "float(loop.state)", "code", "the loop's state, as its LoopState code"),
    Column("fresh", "1.0 if (sample is not None and sample.fresh) else 0.0", "0/1",
           "1 when the tick's sample carried new sensor data"),
    Column("hal_fault_ticks", "float(loop.hal_fault_ticks)", "count",
           "ticks so far whose sample reported a fault (retries, holds, lost packets)"),
)

# Written only while the loop has an adapter (they keep their zeros without one); `th` is its
# estimate of the dynamic coefficients (ddrt/core/adapt.py).
ADAPTER_COLUMNS = (
    Column("ad_m_k", "th[0]", "kg", "adaptation: m + k, the translational mass"),
    Column("ad_mbar", "th[1]", "kg m", "adaptation: mbar, the coupling of speed and yaw"),
    Column("ad_I", "th[2]", "kg m^2", "adaptation: I, the yaw inertia"),
    Column("ad_m_x", "th[3]", "kg m", "adaptation: m_x, the centre of mass's offset times mass"),
    Column("ad_fric_l", "th[4]", "N m", "adaptation: the extra Coulomb friction learnt at the left wheel"),
    Column("ad_fric_r", "th[5]", "N m", "adaptation: the extra Coulomb friction learnt at the right wheel"),
    Column("ad_active", "1.0 if loop.adapt_active else 0.0", "0/1", "1 while the learnt model is in use"),
)

# Written every tick, after the adapter's (a column is only ever added at the end of the
# header; the supply's, ddrt/loop/power.py).
LATER_COLUMNS = (
    Column("battery_v", "loop.power.v", "V",
           "the supply voltage the motor model uses (measured and filtered, or robot.motor.supply_v)"),
    Column("hw_estop", "1.0 if loop.power.hw_estop else 0.0", "0/1",
           "1 while the hardware emergency-stop input is open"),
    # The pose in `map` (odom until a fix; docs/estimation.md), its 1-sigma uncertainty
    # (ddrt/core/uncertainty.py, propagated every 20 ms) and the fixes fused so far.
    Column("x_map", "est.frame.x", "m", "estimated position in the map frame (odom until a pose fix)"),
    Column("y_map", "est.frame.y", "m", "estimated position in the map frame"),
    Column("theta_map", "est.frame.th", "rad", "estimated heading in the map frame"),
    Column("std_x", "est.track.std[0]", "m", "1-sigma uncertainty of x"),
    Column("std_y", "est.track.std[1]", "m", "1-sigma uncertainty of y"),
    Column("std_theta", "est.track.std[2]", "rad", "1-sigma uncertainty of the heading"),
    Column("cov_xy", "est.track.cov_xy", "m^2", "covariance of x and y"),
    Column("fixes", "float(est.frame.counters.fused)", "count", "pose fixes fused so far"),
    # 1 while the drive wheels slip (their turn or distance disagrees with the gyro's or the
    # omni wheel's beyond their noise: ddrt/core/wheel_odometry.py); 0 without wheel encoders.
    Column("wheel_slip", "1.0 if est.wheel_slip else 0.0", "0/1",
           "1 while the drive wheels slip (0 without wheel encoders)"),
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
