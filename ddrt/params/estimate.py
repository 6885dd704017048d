"""The full robot parameters estimated from a few measured numbers (`robot.estimate:`).

A starting point for `ddrt calibrate identify` (or commissioning) to refine, not a
measurement. From the total mass, the track, the wheel radius, the encoder (front omni-)
wheel's position and radius and the body's shape, every RobotParams field is derived under
these stated assumptions:

- Masses: each drive-wheel assembly (wheel, gearmotor, bracket) is DRIVE_WHEEL_FRACTION of the
  total mass, the encoder wheel's assembly ENCODER_WHEEL_FRACTION; the platform is the rest.
- Drive-wheel assembly: its mass lies within the wheel's radius, so its yaw inertia about its
  own centre is a thin disc's about a diameter, m r^2 / 4. Only the wheel and tyre spin, taken
  as SPINNING_FRACTION of the assembly, a uniform disc: I_w = SPINNING_FRACTION m r^2 / 2.
- Encoder wheel: unpowered, the whole assembly is the wheel, a uniform disc: yaw m r^2 / 4,
  spin m r^2 / 2.
- Platform: a uniform box (length along x, width along y) or cylinder, its yaw inertia about
  its own centre m (length^2 + width^2) / 12 or m radius^2 / 2; its centre of mass is the
  body's centre, at (x_m, y_m), by default (H / 2, 0): midway between the drive axle and the
  encoder wheel, on the centre line.
- Geometry: the drive wheels sit at y = +-track / 2 and share one radius.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping

from ddrt.params.robot import RobotParams

DRIVE_WHEEL_FRACTION = 0.30
ENCODER_WHEEL_FRACTION = 0.15
SPINNING_FRACTION = 0.5

SHAPES = ("box", "cylinder")
# The keys of robot.estimate, each with whether it is required.
KEYS = {"mass_kg": True, "track_m": True, "wheel_radius_m": True, "encoder_wheel": True, "body": True}
ENCODER_KEYS = {"x_m": True, "radius_m": True}
BODY_KEYS = {"shape": True, "length_m": False, "width_m": False, "radius_m": False, "x_m": False, "y_m": False}
SHAPE_KEYS = {"box": ("length_m", "width_m"), "cylinder": ("radius_m",)}


@dataclass(frozen=True)
class RobotEstimate:
    """The minimal description, SI units; `body_x_m` None is midway between axle and encoder wheel."""

    mass_kg: float
    track_m: float
    wheel_radius_m: float
    encoder_x_m: float
    encoder_radius_m: float
    shape: str
    length_m: float = 0.0
    width_m: float = 0.0
    radius_m: float = 0.0
    body_x_m: float | None = None
    body_y_m: float = 0.0

    def params(self) -> RobotParams:
        """Every RobotParams field, derived as the module's docstring states."""
        m = self.mass_kg
        m_wheel = DRIVE_WHEEL_FRACTION * m
        m_3 = ENCODER_WHEEL_FRACTION * m
        m_p = m - 2.0 * m_wheel - m_3
        r, r_3 = self.wheel_radius_m, self.encoder_radius_m
        if self.shape == "box":
            i_p = m_p * (self.length_m ** 2 + self.width_m ** 2) / 12.0
        else:
            i_p = m_p * self.radius_m ** 2 / 2.0
        half = self.track_m / 2.0
        return RobotParams(
            H=self.encoder_x_m, L=half, R=half, r_L=r, r_R=r, r_3=r_3,
            d_xc=self.encoder_x_m / 2.0 if self.body_x_m is None else self.body_x_m, d_yc=self.body_y_m,
            m_p=m_p, m_L=m_wheel, m_R=m_wheel, m_3=m_3,
            I_p=i_p, I_L=m_wheel * r * r / 4.0, I_R=m_wheel * r * r / 4.0, I_3=m_3 * r_3 * r_3 / 4.0,
            I_wL=SPINNING_FRACTION * m_wheel * r * r / 2.0, I_wR=SPINNING_FRACTION * m_wheel * r * r / 2.0,
            I_w3=m_3 * r_3 * r_3 / 2.0,
        )


def _number(value: Any, key: str, problems: list[str], *, positive: bool = True) -> float:
    try:
        ok = not isinstance(value, bool) and isinstance(value, (int, float)) and math.isfinite(float(value))
    except OverflowError:  # an integer beyond any float
        ok = False
    if not ok:
        problems.append(f"{key}: expected a finite number, got {str(value)[:40]!s}")
        return 1.0
    if positive and value <= 0:
        problems.append(f"{key}: must be > 0, got {value!r}")
        return 1.0
    return float(value)


def _keys(mapping: Any, spec: Mapping[str, bool], where: str, problems: list[str]) -> dict[str, Any]:
    if not isinstance(mapping, Mapping):
        problems.append(f"{where}: expected a mapping of {', '.join(spec)}, got {mapping!r}"[:200])
        return {}
    for key in mapping:
        if key not in spec:
            problems.append(f"{where}.{key}: unknown key (known: {', '.join(spec)})")
    for key, required in spec.items():
        if required and key not in mapping:
            problems.append(f"{where}.{key}: missing (required)")
    return {k: v for k, v in mapping.items() if k in spec}


def estimate_from_mapping(mapping: Any, where: str = "estimate") -> RobotEstimate:
    """Read `robot.estimate:`; every bad, unknown or missing key is named in one ValueError."""
    problems: list[str] = []
    top = _keys(mapping, KEYS, where, problems)
    num = {k: _number(top[k], f"{where}.{k}", problems) for k in ("mass_kg", "track_m", "wheel_radius_m") if k in top}
    enc = _keys(top["encoder_wheel"], ENCODER_KEYS, f"{where}.encoder_wheel", problems) if "encoder_wheel" in top else {}
    enc_num = {k: _number(v, f"{where}.encoder_wheel.{k}", problems) for k, v in enc.items()}
    body = _keys(top["body"], BODY_KEYS, f"{where}.body", problems) if "body" in top else {}
    shape = body.get("shape")
    if "shape" in body and shape not in SHAPES:
        problems.append(f"{where}.body.shape: must be one of {', '.join(SHAPES)}, got {shape!r}"[:160])
    body_num = {k: _number(v, f"{where}.body.{k}", problems, positive=k not in ("x_m", "y_m"))
                for k, v in body.items() if k != "shape"}
    if shape in SHAPES:
        for key in SHAPE_KEYS[shape]:
            if key not in body:
                problems.append(f"{where}.body.{key}: missing (required for a {shape})")
        for key in ("length_m", "width_m", "radius_m"):
            if key in body and key not in SHAPE_KEYS[shape]:
                problems.append(f"{where}.body.{key}: not a {shape}'s dimension "
                                f"(a {shape} takes {', '.join(SHAPE_KEYS[shape])})")
    if problems:
        raise ValueError("; ".join(problems))
    est = RobotEstimate(
        mass_kg=num["mass_kg"], track_m=num["track_m"], wheel_radius_m=num["wheel_radius_m"],
        encoder_x_m=enc_num["x_m"], encoder_radius_m=enc_num["radius_m"], shape=shape,
        length_m=body_num.get("length_m", 0.0), width_m=body_num.get("width_m", 0.0),
        radius_m=body_num.get("radius_m", 0.0), body_x_m=body_num.get("x_m"), body_y_m=body_num.get("y_m", 0.0),
    )
    try:
        est.params()
    except ValueError as exc:  # e.g. a body centre beside the robot, a mass beyond any robot
        raise ValueError(f"{where}: the derived parameters are not a robot: {exc}") from None
    return est
