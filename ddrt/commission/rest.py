"""Step 3, at rest: the gyro's bias and noise with the motors held at zero, and the supply
voltage the driver measures against a multimeter when it measures one.

The bias is measured again at every start (it drifts with temperature), so it is reported,
not configured; the noise is reported beside `estimator.gyro_noise_dps`. The gyro's
temperature is not read by any backend yet, so its bias-versus-temperature slope is not
measured (said in the report).
"""

from __future__ import annotations

import math
from typing import Any

from ddrt.commission.session import CommissionError, Session

REST_S = 3.0
DIVIDER_WARN = 0.03  # a supply reading this far from the multimeter's is worth fixing


def run(session: Session) -> dict[str, Any]:
    from ddrt.calibrate import calibrate_gyro_at_rest

    cfg = session.config("rest", extra={"estimator": {"calibration_s": REST_S}})
    session.answers.confirm(f"rest: the robot stands still for {REST_S:g} s (gyro bias and noise). Do not touch it "
                            "or the table it stands on.")
    with session.robot(cfg) as hal:
        res = calibrate_gyro_at_rest(cfg, hal)
    out: dict[str, Any] = {
        "seconds": res.seconds,
        "bias_dps": math.degrees(res.bias_rad_s),
        "noise_dps": math.degrees(res.std_rad_s),
        "configured_noise_dps": cfg.estimator.gyro_noise_dps,
        "temperature": "not measured: no backend reads the MPU-6050's temperature yet",
    }
    session.say(f"rest: gyro bias {out['bias_dps']:+.3f} deg/s, noise {out['noise_dps']:.4f} deg/s per sample "
                f"(estimator.gyro_noise_dps is {cfg.estimator.gyro_noise_dps:g})")
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
