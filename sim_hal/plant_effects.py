"""Pieces of the plant's options that stand alone: a wandering scale error, a payload merged
into the platform, the MPU's FIFO size. The plant (sim_hal/plant.py) integrates with them."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Callable

from ddrt.config.sim_truth import WanderingScale
from ddrt.params.robot import RobotParams

FIFO_SAMPLES = 512  # the MPU-6050's 1024-byte FIFO holds this many 2-byte gyro z samples


def with_payload(p: RobotParams, mass: float, inertia: float, x: float, y: float) -> RobotParams:
    """`p` with a payload merged into the platform (m_p, its centre and its inertia I_p)."""
    m = p.m_p + mass
    cx = (p.m_p * p.d_xc + mass * x) / m
    cy = (p.m_p * p.d_yc + mass * y) / m
    i_p = (p.I_p + p.m_p * ((p.d_xc - cx) ** 2 + (p.d_yc - cy) ** 2)
           + inertia + mass * ((x - cx) ** 2 + (y - cy) ** 2))
    return replace(p, m_p=m, d_xc=cx, d_yc=cy, I_p=i_p)


class Wanderer:
    """An Ornstein-Uhlenbeck scale error 1 + mean + s, exact discretisation at step h."""

    def __init__(self, spec: WanderingScale, h: float) -> None:
        self.mean = spec.mean
        self.s = 0.0
        self.a = math.exp(-h / spec.tau_s)
        self.k = spec.sigma * math.sqrt(1.0 - self.a * self.a)

    def scale(self) -> float:
        return 1.0 + self.mean + self.s

    def step(self, gauss: Callable[[float, float], float]) -> None:
        """One step, drawing from `gauss(mu, sigma)` only when the scale wanders."""
        if self.k:
            self.s = self.a * self.s + self.k * gauss(0.0, 1.0)
