"""Step 3, at rest: the gyro's bias and noise with the motors held at zero, its die
temperature, and the supply voltage the driver measures against a multimeter when it measures one.

The bias is measured again at every start (it drifts with temperature), so it is reported,
not configured; the noise is reported beside `estimator.gyro_noise_dps`. The bias's
temperature slope (`estimator.gyro_bias_per_c_dps`) needs the bias at two temperatures: a
rest is a few seconds at one, so the slope is measured when this step runs again with the die
at least MIN_SPAN_C warmer or colder than at the rest before (the robot powered throughout:
the bias also shifts from one power-up to the next), and written; otherwise the report says
the estimator learns it at the stops (ddrt/core/gyro_bias.py), which it does from the first
stop on either way.
"""

from __future__ import annotations

import math
from typing import Any

from ddrt.commission.session import CommissionError, Session

REST_S = 3.0
DIVIDER_WARN = 0.03  # a supply reading this far from the multimeter's is worth fixing
MIN_SPAN_C = 2.0  # two rests this far apart in die temperature measure the bias's slope
TEMP_READS = 3  # TEMP_OUT readings averaged into the rest's temperature (0.01 degC apart on an MPU)
MAX_PAIRS = 8  # (temperature, bias) of the latest rests kept in the state
MAX_SLOPE_DPS_PER_C = 1.0  # beyond estimator.gyro_bias_per_c_dps's range: not a slope (the robot moved, a power-up between)


def run(session: Session) -> dict[str, Any]:
    from ddrt.calibrate import calibrate_gyro_at_rest

    cfg = session.config("rest", extra={"estimator": {"calibration_s": REST_S}})
    session.answers.confirm(f"rest: the robot stands still for {REST_S:g} s (gyro bias and noise). Do not touch it "
                            "or the table it stands on.")
    earlier = session.state.get("rest") or {}
    with session.robot(cfg) as hal:
        res = calibrate_gyro_at_rest(cfg, hal)
        temp_c = die_temperature(hal, 1.0 / cfg.controller.rate_hz)
    out: dict[str, Any] = {
        "seconds": res.seconds,
        "bias_dps": math.degrees(res.bias_rad_s),
        "noise_dps": math.degrees(res.std_rad_s),
        "configured_noise_dps": cfg.estimator.gyro_noise_dps,
        "temperature_c": temp_c,
    }
    pairs = [p for p in earlier.get("pairs") or [] if isinstance(p, list) and len(p) == 2 and None not in p]
    out.update(temperature_slope(pairs, out["bias_dps"], temp_c, cfg.sensors.gyro_temp_hz))
    if "config" not in out and earlier.get("config"):  # a slope measured at an earlier rest stands
        out.update(config=earlier["config"], bias_per_c_dps=earlier.get("bias_per_c_dps"))
        out["temperature"] += f"; the slope measured before ({earlier.get('bias_per_c_dps'):+.4f}) is kept"
    if temp_c == temp_c:
        pairs.append([temp_c, out["bias_dps"]])
    out["pairs"] = pairs[-MAX_PAIRS:]
    session.say(f"rest: gyro bias {out['bias_dps']:+.3f} deg/s, noise {out['noise_dps']:.4f} deg/s per sample "
                f"(estimator.gyro_noise_dps is {cfg.estimator.gyro_noise_dps:g}); temperature: {out['temperature']}")
    link = session.state.get("link") or {}
    robot_v = link.get("battery_v")
    if robot_v is None:
        out["battery"] = "not measured by this driver (HalInfo.battery_measured false): skipped"
        return out
    if session.opts.from_sim_truth:
        out.update(battery_v=robot_v, battery="simulation: the driver's reading is the plant's supply, no multimeter "
                                             "to hold against it: skipped")
        return out
    meter = session.answers.value(
        "battery.multimeter_v",
        f"  The driver reads the supply as {robot_v:.2f} V. Hold a multimeter's probes on the motor driver's supply "
        "terminals (V+ and GND): what does it read (V)? ")
    ratio = robot_v / meter
    if not 0.8 <= ratio <= 1.25:
        raise CommissionError(f"rest: the driver reads {robot_v:.2f} V and the multimeter {meter:.2f} V: more than "
                              "20% apart, check the reading (probes on the driver's supply terminals, DC volts range)")
    out.update(battery_v=robot_v, multimeter_v=meter, battery_ratio=ratio)
    if abs(ratio - 1.0) > DIVIDER_WARN:
        session.notes.append(f"rest: the supply reads {100 * (ratio - 1):+.1f}% off the multimeter: the firmware's "
                             "divider ratio needs correcting (docs/hardware.md)")
    return out


def die_temperature(hal: Any, period_s: float) -> float:
    """The gyro's die temperature (degC): the mean of TEMP_READS readings, the HAL read every
    loop period (`period_s`) as the loop does, the motors still at zero; NaN when it reads
    none (`sensors.gyro_temp_hz` 0, or TEMP_OUT failing)."""
    from ddrt.calibrate import clock_for

    hz = hal.info.gyro_temp_hz
    if not hz > 0.0:
        return math.nan
    clock = clock_for(hal)
    readings: list[float] = []
    t = clock.now()
    for _ in range(int((TEMP_READS + 1) / (hz * period_s)) + 1):
        t += period_s
        clock.sleep_until(t)
        c = hal.read().gyro_temp_c
        if c == c:
            readings.append(c)
            if len(readings) == TEMP_READS:
                break
    return sum(readings) / len(readings) if readings else math.nan


def temperature_slope(pairs: list[list[float]], bias_dps: float, temp_c: float, temp_hz: float) -> dict[str, Any]:
    """What this rest says of the bias's temperature slope, given the (temperature, bias) of
    the rests before: a slope (and its config key) against the one farthest in temperature when
    that is MIN_SPAN_C or more away, else why not and what learns it instead (module doc)."""
    if not temp_c == temp_c:
        why = ("not read (sensors.gyro_temp_hz is 0): the bias is not compensated for temperature"
               if temp_hz <= 0.0 else "TEMP_OUT gave no reading: check the gyro")
        return {"temperature": why}
    here = f"{temp_c:.2f} degC"
    if not pairs:
        return {"temperature": f"{here}; the bias's slope is left for the stops to learn (one temperature: run "
                               f"`ddrt commission --step rest` again when the die is {MIN_SPAN_C:g} degC warmer, "
                               "after driving, to measure it)"}
    t0, b0 = (float(v) for v in max(pairs, key=lambda p: abs(temp_c - float(p[0]))))
    span = temp_c - t0
    if abs(span) < MIN_SPAN_C:
        return {"temperature": f"{here}, at most {abs(span):.2f} degC from the rests before ({t0:.2f} degC): under "
                               f"{MIN_SPAN_C:g} degC apart, the bias's slope is left for the stops to learn"}
    slope = (bias_dps - b0) / span
    if abs(slope) > MAX_SLOPE_DPS_PER_C:
        return {"temperature": f"{here}; the rests' bias ({b0:+.3f} deg/s at {t0:.2f} degC, {bias_dps:+.3f} now) "
                               f"gives {slope:+.3f} deg/s per degC, beyond any MPU's: not written (was the robot "
                               "moved or powered off between them?); the stops learn it"}
    return {"temperature": f"{here}; slope {slope:+.4f} deg/s per degC from the rest at {t0:.2f} degC "
                           f"({span:+.2f} degC, bias {b0:+.3f} -> {bias_dps:+.3f} deg/s)",
            "bias_per_c_dps": slope,
            "config": {"estimator": {"gyro_bias_per_c_dps": round(slope, 5)}}}
