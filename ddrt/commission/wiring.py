"""Step 2, wiring: which output drives which wheel which way, and which way the sensors count.

Each motor output is pulsed alone at low duty (ramped up from below the deadband until
something moves), through the backend as it is wired (`hal.wiring` left out). The front
encoder and the gyro say how the robot moved; one observation says which wheel turned and
which way, because the sensors alone cannot tell "motors swapped" from "gyro upside down"
(both mirror the robot). From those the fix is derived and written as `hal.wiring`
(hal/wiring.py applies it); nobody is asked to rewire. The fix is then checked by pulsing
both outputs again through it.

A robot without a front encoder measures the pulse's travel with its drive wheels' encoders.
They share their motors' harnesses (hal/wiring.py), so they count the way each motor turns
whatever its wiring and say nothing of the robot's direction: the gyro and the observation
decide alone, and the check through the fix confirms it.

A wheel driven forward alone pivots the robot about the other wheel: the left wheel turns
it clockwise (yaw rate < 0) and the right one counter-clockwise, both roll it forward.

Motion is bounded: a pulse stops at 15 mm or 5 degrees (a few cm and degrees in all,
coasting included) and is cut at once beyond 50 mm or 15 degrees; Ctrl-C and the robot's
emergency-stop input stop the motors at any tick.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any

from ddrt.commission.session import CommissionError, Session, Stopped
from ddrt.config import Config
from hal.base import Hal

DUTY_START = 0.03
DUTY_STEP = 0.01  # every RAMP_S until something moves
RAMP_S = 0.15
MOVED_M, MOVED_RAD = 0.002, math.radians(1.0)  # motion seen
ENOUGH_M, ENOUGH_RAD = 0.015, math.radians(5.0)  # the pulse stops here
CUT_M, CUT_RAD = 0.05, math.radians(15.0)  # never beyond
SETTLE_S = 0.6
BIAS_S = 0.5


@dataclass
class Pulse:
    output: str  # "left" or "right": which driver output was pulsed
    duty: float  # the duty at which it moved (0: nothing moved)
    distance_m: float  # the front encoder's travel, else the drive wheels' mean (signed, forward > 0 when wired right)
    angle_rad: float  # the gyro's yaw change, bias removed (counter-clockwise > 0 when right)
    true_forward_m: float | None = None  # simulation: the truth
    true_angle_rad: float | None = None
    trace: list[tuple[float, float, float, float]] = field(default_factory=list)  # t, duty, m, rad

    @property
    def moved(self) -> bool:
        return abs(self.distance_m) >= MOVED_M or abs(self.angle_rad) >= MOVED_RAD


def _wrap32(d: int) -> int:
    return ((d + 2**31) % 2**32) - 2**31


def pulse(hal: Hal, clock: Any, cfg: Config, output: str, duty_max: float) -> Pulse:
    """Pulse one output (the other held at zero) until the robot has moved a little; see the
    module doc for the bounds. The motors are at zero when this returns or raises."""
    info = hal.info
    period = 1.0 / cfg.controller.rate_hz
    travel = _travel_meter(cfg, info)
    lsb = info.gyro_lsb_per_rad_s
    truth = hal.robot
    t = clock.now()

    def tick(duty: float) -> Any:
        nonlocal t
        t += period
        clock.sleep_until(t)
        s = hal.read()
        if s.hw_estop:
            hal.stop()
            raise Stopped("wiring: the robot's emergency stop is pressed: the motors are off; release it and "
                          "run the command again")
        if output == "left":
            hal.write(duty, 0.0)
        else:
            hal.write(0.0, duty)
        return s

    # The gyro's bias first, standing still.
    raws = [tick(0.0).gyro_z_raw for _ in range(max(5, int(BIAS_S / period)))]
    bias = sum(raws) / len(raws)
    s = tick(0.0)
    c0, dist, ang = travel.counts(s), 0.0, 0.0
    p0 = truth.pose if truth is not None else None
    res = Pulse(output, 0.0, 0.0, 0.0)
    duty, ramp_t, moved_at, settle_from = DUTY_START, 0.0, 0.0, math.inf
    elapsed = 0.0
    phase = "ramp"  # -> "hold" once it moved -> "settle" (motors at zero) -> done
    while elapsed - settle_from < SETTLE_S:
        s = tick(0.0 if phase == "settle" else duty)
        res.trace.append((elapsed, 0.0 if phase == "settle" else duty, dist, ang))
        elapsed += period
        dist = travel.metres(c0, travel.counts(s))
        ang += (s.gyro_z_raw - bias) / lsb * period
        if phase == "ramp" and (abs(dist) >= MOVED_M or abs(ang) >= MOVED_RAD):
            phase, moved_at, res.duty = "hold", elapsed, duty
        elif phase == "ramp" and elapsed - ramp_t >= RAMP_S:
            ramp_t = elapsed
            duty += DUTY_STEP
            if duty > duty_max + 1e-9:
                phase = "settle"  # nothing moved: the caller refuses
        if phase == "hold" and (abs(dist) >= ENOUGH_M or abs(ang) >= ENOUGH_RAD or elapsed - moved_at > 0.5):
            phase = "settle"
        if abs(dist) >= CUT_M or abs(ang) >= CUT_RAD:
            phase = "settle"
        if phase == "settle" and settle_from == math.inf:
            settle_from = elapsed
            hal.write(0.0, 0.0)
    hal.stop()
    res.distance_m, res.angle_rad = dist, ang
    if p0 is not None:
        p1 = truth.pose
        res.true_forward_m = (p1[0] - p0[0]) * math.cos(p0[2]) + (p1[1] - p0[1]) * math.sin(p0[2])
        res.true_angle_rad = p1[2] - p0[2]
    return res


@dataclass(frozen=True)
class _TravelMeter:
    """The pulse's travel from the front encoder (`per_wheel` None) or the drive wheels' mean."""

    per_count: float  # front encoder: metres a count
    per_wheel: tuple[float, float] | None  # drive wheels: metres a count, left and right

    def counts(self, s: Any) -> tuple[int, int]:
        return (s.count_left, s.count_right) if self.per_wheel is not None else (s.encoder_count, 0)

    def metres(self, c0: tuple[int, int], c: tuple[int, int]) -> float:
        if self.per_wheel is None:
            return _wrap32(c[0] - c0[0]) * self.per_count
        return 0.5 * (_wrap32(c[0] - c0[0]) * self.per_wheel[0] + _wrap32(c[1] - c0[1]) * self.per_wheel[1])


def _travel_meter(cfg: Config, info: Any) -> _TravelMeter:
    if info.encoder_counts_per_rev > 0:
        return _TravelMeter(2.0 * math.pi * cfg.robot.r_3 / info.encoder_counts_per_rev, None)
    if info.wheel_counts_per_rev <= 0:
        raise CommissionError("wiring: the robot reports neither a front encoder nor drive-wheel encoders "
                              "(HELLO's counts per revolution are 0): nothing can measure the pulses")
    cpr = info.wheel_counts_per_rev
    return _TravelMeter(0.0, (2.0 * math.pi * cfg.robot.r_L / cpr, 2.0 * math.pi * cfg.robot.r_R / cpr))


def _sign(x: float) -> int:
    return 1 if x > 0 else -1


def observed_from_truth(p: Pulse) -> str:
    """What someone watching would report: which wheel turned and which way (see module doc)."""
    fwd, ang = p.true_forward_m or 0.0, p.true_angle_rad or 0.0
    wheel = "left" if _sign(fwd) != _sign(ang) else "right"
    return f"{wheel} {'forward' if fwd > 0 else 'backward'}"


def derive(a: Pulse, b: Pulse, seen_a: str, front_encoder: bool = True) -> dict[str, Any]:
    """hal.wiring from the two pulses (a: the left output's, b: the right's) and what was seen
    on the first. Raises when the readings contradict each other. Without a front encoder the
    second wheel's direction comes from the gyro alone (nothing to cross-check; the caller's
    check through the fix does) and `encoder_sign` stays 1."""
    wheel_a, way_a = seen_a.split()
    sigma_a = 1 if way_a == "forward" else -1
    # A wheel rolling forward rolls the robot forward; the left one turns it clockwise.
    w_a = -sigma_a if wheel_a == "left" else sigma_a
    g = _sign(a.angle_rad) * w_a  # gyro sign
    wheel_b = "right" if wheel_a == "left" else "left"
    if front_encoder:
        e = _sign(a.distance_m) * sigma_a  # encoder sign
        sigma_b = _sign(b.distance_m) * e
        w_b_expected = -sigma_b if wheel_b == "left" else sigma_b
        if _sign(b.angle_rad) * g != w_b_expected:
            raise CommissionError(
                "wiring: the readings contradict each other: with the first pulse as you saw it, the second "
                f"({b.output} output) rolled the robot {'forward' if sigma_b > 0 else 'backward'} but turned it the "
                "way the same wheel would have. Both outputs may drive one motor, or a wheel slipped: check the "
                "motor leads by hand and run `ddrt commission --step wiring` again")
    else:
        e = 1
        w_b = _sign(b.angle_rad) * g  # the second wheel's direction from the gyro alone
        sigma_b = -w_b if wheel_b == "left" else w_b
    swapped = wheel_a == "right"
    left_sigma, right_sigma = (sigma_b, sigma_a) if swapped else (sigma_a, sigma_b)
    return {"motor_left_inverted": left_sigma < 0, "motor_right_inverted": right_sigma < 0,
            "motors_swapped": swapped, "encoder_sign": e, "gyro_sign": g}


PROMPT = ("  The robot's LEFT motor output was just pulsed. Stand behind the robot, facing where it faces.\n"
          "  Which wheel turned, and which way? (left forward / left backward / right forward / right backward): ")


def run(session: Session) -> dict[str, Any]:
    base = session.config("wiring")
    raw_cfg = session.config("wiring", extra={"hal": {"wiring": {
        "motor_left_inverted": False, "motor_right_inverted": False, "motors_swapped": False,
        "encoder_sign": 1, "gyro_sign": 1}}})
    duty_max = min(0.4, 0.5 * base.limits.duty_max)
    session.answers.confirm(
        "wiring: each motor output is pulsed alone at low duty, ramped up until the robot moves 1-2 cm or 5 degrees.\n"
        "  Put the robot on the floor with 30 cm free around it, wheels touching the ground, motor power ON.\n"
        "  Watch the wheels: you will be asked which one turned and which way. Ctrl-C stops the motors at once.")
    from ddrt.calibrate import clock_for

    with session.robot(raw_cfg) as hal:
        clock = clock_for(hal)
        a = pulse(hal, clock, raw_cfg, "left", duty_max)
        if not a.moved:
            raise CommissionError(
                f"wiring: nothing moved when the left output was pulsed up to duty {duty_max:.2f} (encoder "
                f"{a.distance_m * 1e3:+.1f} mm, gyro {math.degrees(a.angle_rad):+.1f} deg). Is the motor power on "
                "(battery, switch, driver enable)? Is the duty below the motors' deadband (a stiff gearbox: raise "
                "limits.duty_max)? Is hal.bridge.url this robot's port? Are the encoder and gyro connected?")
        if session.opts.from_sim_truth:
            seen = observed_from_truth(a)
            session.say(f"  (simulation truth: {seen})")
            session.answers.used["wiring.left_output_pulse"] = seen
        else:
            seen = session.answers.value("wiring.left_output_pulse", PROMPT)
        b = pulse(hal, clock, raw_cfg, "right", duty_max)
        front = hal.info.encoder_counts_per_rev > 0
        if not b.moved:
            raise CommissionError(
                f"wiring: the left output moved the robot but the right output did not, up to duty {duty_max:.2f}: "
                "check the right motor's leads and the driver's second channel")
    fix = derive(a, b, seen, front)
    fixed_cfg = session.config("wiring", extra={"hal": {"wiring": fix}})
    with session.robot(fixed_cfg) as hal:  # the check: through the fix, each wheel as documented
        clock = clock_for(hal)
        ca = pulse(hal, clock, fixed_cfg, "left", duty_max)
        cb = pulse(hal, clock, fixed_cfg, "right", duty_max)
    ok = (ca.moved and cb.moved and ca.distance_m > 0 and ca.angle_rad < 0 and cb.distance_m > 0
          and cb.angle_rad > 0)
    if not ok:
        raise CommissionError(
            f"wiring: with the fix {fix} the left output should roll the robot forward turning clockwise and the "
            f"right output forward turning counter-clockwise; it read {ca.distance_m * 1e3:+.1f} mm "
            f"{math.degrees(ca.angle_rad):+.1f} deg and {cb.distance_m * 1e3:+.1f} mm {math.degrees(cb.angle_rad):+.1f} "
            "deg: the wheels may slip, run the step again")
    was = asdict(base.hal.wiring)
    changed = {k: (was[k], v) for k, v in fix.items() if was[k] != v}
    session.say("wiring: " + ("as configured" if not changed else "fixed in hal.wiring: " + ", ".join(
        f"{k} {old} -> {new}" for k, (old, new) in changed.items())))
    return {"config": {"hal": {"wiring": fix}}, "seen": seen, "changed": {k: list(v) for k, v in changed.items()},
            "pulses": [_summary(p) for p in (a, b, ca, cb)],
            "traces": {f"{i}": p.trace[::2] for i, p in enumerate((a, b))}}


def _summary(p: Pulse) -> dict[str, Any]:
    return {"output": p.output, "duty": p.duty, "distance_mm": p.distance_m * 1e3,
            "angle_deg": math.degrees(p.angle_rad)}
