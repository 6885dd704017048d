"""Random robot populations: physically consistent differential-drive robots drawn from a seed.

One generator for `ddrt sweep` (a campaign's `population:`) and bench/population.py, so a
population bench and a population campaign with the same seed drive the same robots:

- total mass 1-19 kg; size from the mass (the seed robot's half track 0.108 m at 4.34 kg,
  scaled by the cube root of the mass, +-20 %); drive wheels 0.3-0.55 of the half track,
  the omni-wheel 0.8-1.3 half tracks ahead of the axle;
- masses split into the two wheel assemblies (each 12-30 %), the omni-wheel (5-15 %) and the
  platform (the rest), its centre of mass -0.2..0.6 of H ahead of the axle and within 3 %
  of the half track sideways; yaw inertias of a box (the platform, 1.3 (H + r) long, 1.8 L
  wide) and of cylinders (the wheel assemblies), spin inertias of discs (35 % of each
  assembly's mass in its wheel);
- a gearmotor per robot: supply 6-24 V, full-voltage no-load ground speed 0.7-2.2 m/s, stall
  torque 0.4-1.2 x M g r / 2 (each wheel can push 20-60 % of the robot's weight), friction at
  no load 4-10 % of the stall torque (half Coulomb, half viscous);
- the truth (`plant:`) departs from the belief (`robot:`) by a few percent: every mass,
  inertia, length and the drive wheels' radii by N(0, 2 %) (clipped at 5 %), each wheel's
  motor constants by N(0, 3 %) (clipped at 8 %); the encoder wheel's radius by N(0, 0.05 %)
  (calibrated: `ddrt calibrate odometry` gets it within 0.1 %);
- latency: commands 0.5-3 ms, sensors 0.5-2 ms;
- the speed its paths ask for: 50-90 % of its motors' full-voltage no-load speed.
"""

from __future__ import annotations

import random
from dataclasses import dataclass, field
from typing import Any

from ddrt.params.robot import RobotParams

SEED = 20261201
G = 9.81


@dataclass(frozen=True)
class Robot:
    """One drawn robot: its config sections (robot:, plant:, sim:) and the figures a table shows."""

    name: str
    mass: float
    supply_v: float
    half_track: float
    wheel_r: float
    top_speed: float  # full-voltage no-load ground speed (m/s)
    speed: float  # the speed its paths ask for
    sections: dict[str, Any] = field(repr=False)

    @property
    def path_speed(self) -> float:
        """The speed written into its path (rounded, so a config file can say the same)."""
        return round(self.speed, 4)


def _u(rng: random.Random, lo: float, hi: float) -> float:
    return rng.uniform(lo, hi)


def _jitter(rng: random.Random, x: float, sd: float, clip: float) -> float:
    return x * (1.0 + max(-clip, min(clip, rng.gauss(0.0, sd))))


def make_robot(rng: random.Random, i: int) -> Robot:
    """One physically consistent robot (see the module doc), with its belief and truth."""
    while True:
        mass = _u(rng, 1.0, 19.0)
        L = 0.108 * (mass / 4.34) ** (1.0 / 3.0) * _u(rng, 0.8, 1.2)
        r = L * _u(rng, 0.3, 0.55)
        H = L * _u(rng, 0.8, 1.3)
        r3 = r * _u(rng, 0.6, 1.1)
        m_w = mass * _u(rng, 0.12, 0.30)
        m_3 = mass * _u(rng, 0.05, 0.15)
        m_p = mass - 2.0 * m_w - m_3
        if m_p < 0.15 * mass:
            continue
        d_xc = H * _u(rng, -0.2, 0.6)
        d_yc = L * _u(rng, -0.03, 0.03)
        length, width = 1.3 * (H + r), 1.8 * L
        I_p = m_p * (length ** 2 + width ** 2) / 12.0 * _u(rng, 0.7, 1.3)
        I_wheel_yaw = m_w * (3.0 * (0.6 * r) ** 2 + r ** 2) / 12.0
        I_3 = m_3 * (3.0 * (0.6 * r3) ** 2 + r3 ** 2) / 12.0
        I_w = 0.5 * 0.35 * m_w * r * r
        I_w3 = 0.5 * 0.5 * m_3 * r3 * r3
        robot = dict(H=H, L=L, R=L, r_L=r, r_R=r, r_3=r3, d_xc=d_xc, d_yc=d_yc, m_p=m_p, m_L=m_w, m_R=m_w,
                     m_3=m_3, I_p=I_p, I_L=I_wheel_yaw, I_R=I_wheel_yaw, I_3=I_3, I_wL=I_w, I_wR=I_w, I_w3=I_w3)
        volts = _u(rng, 6.0, 24.0)
        v_nl = _u(rng, 0.7, 2.2)
        k = volts / (v_nl / r)
        stall = _u(rng, 0.4, 1.2) * mass * G * r / 2.0
        res = k * volts / stall
        fric = _u(rng, 0.04, 0.10) * stall
        motor = dict(supply_v=volts, resistance_ohm=res, k_nm_per_a=k, viscous_nms=0.5 * fric / (v_nl / r),
                     coulomb_nm=0.5 * fric)
        plant = {key: (_jitter(rng, v, 0.0005, 0.001) if key == "r_3" else
                       v if key == "d_yc" else _jitter(rng, v, 0.02, 0.05)) for key, v in robot.items()}
        plant["d_yc"] = robot["d_yc"] + rng.gauss(0.0, 0.01 * L)
        plant["r_L"] = _jitter(rng, r, 0.02, 0.05)
        plant["r_R"] = _jitter(rng, r, 0.02, 0.05)
        for side in ("motor_l", "motor_r"):
            plant[side] = {key: _jitter(rng, motor[key], 0.03, 0.08)
                           for key in ("resistance_ohm", "k_nm_per_a", "viscous_nms", "coulomb_nm")}
        try:
            RobotParams(**robot)
            RobotParams(**{key: v for key, v in plant.items() if not key.startswith("motor")})
        except ValueError:
            continue
        speed = v_nl * _u(rng, 0.5, 0.9)
        sections = {
            "robot": dict(robot, motor=motor),
            "plant": plant,
            "sim": {"seed": i + 1, "command_latency_s": _u(rng, 0.0005, 0.003),
                    "sensor_latency_s": _u(rng, 0.0005, 0.002)},
        }
        return Robot(f"r{i:02d}", mass, volts, L, r, v_nl, speed, sections)


def population(n: int, seed: int = SEED) -> list[Robot]:
    """The first `n` robots of the generator seeded with `seed` (a longer list extends a shorter one)."""
    rng = random.Random(seed)
    return [make_robot(rng, i) for i in range(n)]
