"""Controller properties that hold whatever the path: bumpless retune, limits, saturation."""

from __future__ import annotations

import dataclasses
import math

from ddrt.config import load_config
from ddrt.core.control import DynamicController, KinematicController, _scale_to_limit
from ddrt.core.types import Setpoint
from ddrt.core.model import Dynamics
from ddrt.core.motor import Motor
from tests.support.repo import SIM_YAML


def _controller(kind=DynamicController, **limits):
    cfg = load_config(SIM_YAML, {"limits": limits} if limits else None)
    dyn = Dynamics.from_params(cfg.robot)
    return cfg, kind(dyn, Motor(cfg.robot_motor), cfg.controller, cfg.limits, 0.005)


def _drive(ctl, n=200):
    """Run the controller against a crude first-order robot so its integrators hold state."""
    sp = Setpoint(x_d=0.0, y_d=0.01, theta_d=0.0, v_d=0.3, omega_d=0.2, path_frame=True, active=True)
    v = w = 0.0
    for _ in range(n):
        cmd = ctl.update(0.0, 0.0, 0.0, v, w, sp)
        v += 0.2 * (cmd.v_c - v)
        w += 0.2 * (cmd.omega_c - w)
    return sp, v, w


def test_retune_is_bumpless():
    cfg, ctl = _controller()
    sp, v, w = _drive(ctl)
    _, twin = _controller()  # the same history, gains untouched
    _drive(twin)
    _, naive = _controller()  # the same history, gains swapped without re-seeding
    _drive(naive)
    new = dataclasses.replace(cfg.controller, inner=dataclasses.replace(cfg.controller.inner, kp=120.0, ki=100.0))
    ctl.retune(new, cfg.limits)
    for pid in (naive.pid_v, naive.pid_w):
        pid.kp, pid.ki = 120.0, 100.0
    after = ctl.update(0.0, 0.0, 0.0, v, w, sp)
    same = twin.update(0.0, 0.0, 0.0, v, w, sp)
    jumped = naive.update(0.0, 0.0, 0.0, v, w, sp)
    step = max(abs(after.duty_l - same.duty_l), abs(after.duty_r - same.duty_r))
    naive_step = max(abs(jumped.duty_l - same.duty_l), abs(jumped.duty_r - same.duty_r))
    assert step < 1e-3
    assert naive_step > 20 * step  # the re-seeding is what makes it bumpless


def test_saturation_scales_both_wheels_together():
    a, b, sat = _scale_to_limit(1.5, 0.75, 1.0)
    assert sat and a == 1.0 and b == 0.5  # the ratio (the curve) is kept
    a, b, sat = _scale_to_limit(0.5, -0.2, 1.0)
    assert not sat and (a, b) == (0.5, -0.2)


def test_commands_respect_the_limits_whatever_the_error():
    for kind in (DynamicController, KinematicController):
        cfg, ctl = _controller(kind, duty_max=0.6)
        for dy in (-5.0, -0.5, 0.0, 0.5, 5.0):
            for th in (-3.0, 0.0, 3.0):
                sp = Setpoint(x_d=1.0, y_d=dy, theta_d=th, v_d=0.9, omega_d=2.0, kappa=2.0,
                              pp_curvature=50.0, path_frame=True, active=True)
                cmd = ctl.update(0.0, 0.0, 0.0, 0.0, 0.0, sp)
                assert abs(cmd.duty_l) <= 0.6 + 1e-12 and abs(cmd.duty_r) <= 0.6 + 1e-12
                assert abs(cmd.v_c) <= cfg.limits.v_max + 1e-12
                assert abs(cmd.omega_c) <= cfg.limits.omega_max + 1e-12
                assert math.isfinite(cmd.tau_l) and math.isfinite(cmd.tau_r)
