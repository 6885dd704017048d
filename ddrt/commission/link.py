"""Step 1, link: the robot's devices answer, at the rate the loop needs.

Opening the backend is the check itself: the serial bridge says HELLO and checks the
protocol version and the STATE rate, the gyro driver reads WHO_AM_I and says which part of the
MPU-6050 family it found (hal/bridge.py, hal/mpu6050.py, ddrt/params/mpu_parts.py). What fails
is turned into what to do next (port, permissions, udev rule, wiring). Then one second of
readings: how many were fresh, whether the gyro is alive, the supply voltage if the driver
measures it.
"""

from __future__ import annotations

import math
from typing import Any

from ddrt.commission.session import CommissionError, Session
from hal.base import HalError

HINTS = (  # (text in the error, what to do next): the gyro's first (a missing I2C bus is "no such file" too)
    ("who_am_i", "the gyro answers with an identity ddrt does not know: check hal.imu.address (0x68, or 0x69 with "
                 "AD0 high) and the wiring SDA, SCL, VCC, GND; a part outside the list above is not supported "
                 "(docs/hardware.md, 'Which gyro boards work')"),
    ("no answer during set-up", "the gyro does not answer: check its wiring SDA, SCL, VCC, GND and hal.imu.address "
                                "(`i2cdetect -y 1` should show 0x68)"),
    ("i2c bus", "the gyro's I2C bus cannot be used: check hal.imu.bus (1 is /dev/i2c-1), that I2C is enabled "
            "(raspi-config), and permissions on /dev/i2c-* (the i2c group)"),
    ("permission denied", "the port is not yours: add yourself to the dialout group (sudo usermod -aG dialout "
                          "$USER, then log in again) or install the udev rule of docs/deploy.md"),
    ("no such file", "no such port: plug the microcontroller in, look at `ls /dev/ttyACM* /dev/ttyUSB*` and set "
                     "hal.bridge.url (docs/hardware.md); a udev rule gives it a stable name (docs/deploy.md)"),
    ("could not open port", "the port cannot be opened: check hal.bridge.url and that no other program holds it"),
    ("hello_reply", "the microcontroller does not answer: is it powered, flashed with the ddrt bridge firmware "
                    "(firmware/, docs/hardware.md), and is hal.bridge.url its port (not another USB serial device)?"),
    ("protocol version", "the firmware speaks another protocol version: flash firmware/ from this ddrt (docs/hardware.md)"),
    ("streams state", "the firmware streams STATE too slowly: flash firmware/ from this ddrt"),
)


def next_step(message: str) -> str:
    low = message.lower()
    for key, hint in HINTS:
        if key in low:
            return hint
    return "check the hal: section of the config against docs/hardware.md and docs/deploy.md"


def run(session: Session) -> dict[str, Any]:
    cfg = session.config("link")
    session.say("link: opening the robot's devices (the microcontroller's HELLO, the gyro's WHO_AM_I)")
    from ddrt.calibrate import clock_for

    period = 1.0 / cfg.controller.rate_hz
    n = int(round(1.0 / period))
    fresh = 0
    raws: list[int] = []
    volts: list[float] = []
    try:
        with session.robot(cfg) as hal:
            info = hal.info
            clock = clock_for(hal)
            t0 = clock.now()
            for i in range(n):
                clock.sleep_until(t0 + (i + 1) * period)
                s = hal.read()
                hal.write(0.0, 0.0)
                fresh += bool(s.fresh)
                raws.append(s.gyro_z_raw)
                if info.battery_measured and math.isfinite(s.battery_v):
                    volts.append(s.battery_v)
    except (HalError, OSError) as exc:
        raise CommissionError(f"link: {' '.join(str(exc).split())}. Next: {next_step(str(exc))}") from None
    from hal.registry import backend_name
    from hal.wire import PROTOCOL_VERSION

    name = backend_name(cfg)
    result: dict[str, Any] = {
        "backend": name,
        # The bridge refuses any other version at HELLO, so an open bridge speaks this one.
        "protocol_version": PROTOCOL_VERSION if name != "sim" else None,
        "fresh_rate_hz": fresh,
        "fresh_fraction": fresh / n,
        "gyro_raw_span": max(raws) - min(raws),
        "encoder_counts_per_rev": info.encoder_counts_per_rev,
        "gyro_part": info.gyro_part or None,
        "battery_v": sum(volts) / len(volts) if volts else None,
    }
    if fresh < 0.5 * n:
        raise CommissionError(f"link: only {fresh} of {n} readings in one second were fresh: the sensors do not "
                              f"keep up with controller.rate_hz = {cfg.controller.rate_hz:g} (check the bridge's "
                              "STATE rate and hal.imu.sample_rate_div)")
    if result["gyro_raw_span"] == 0:
        session.notes.append("link: the gyro's reading did not change at all in one second (a real gyro is never "
                             "that quiet): check that it is configured (hal.imu)")
    session.say(f"link: ok ({fresh}/{n} fresh readings in 1 s"
                + (f", gyro {info.gyro_part}" if info.gyro_part else "")
                + (f", protocol v{result['protocol_version']} checked at HELLO"
                   if result["protocol_version"] is not None else "")
                + (f", supply {result['battery_v']:.2f} V" if result["battery_v"] is not None else
                   ", supply not measured") + ")")
    return result
