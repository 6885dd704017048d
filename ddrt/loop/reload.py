"""A new config put in force between two ticks (`ControlLoop.reconfigure`): every part of the
loop that holds a copy gets it, and a new robot model re-profiles the rest of the path being
followed when that path asks more than the new motors give."""

from __future__ import annotations

import logging
from dataclasses import replace
from typing import TYPE_CHECKING

from ddrt.config import Config
from ddrt.config.sections import LimitsConfig
from ddrt.core.adapt import DynamicsAdapter
from ddrt.core.drive import DriveReference
from ddrt.core.envelope import ResolvedLimits, resolve_limits
from ddrt.core.model import Dynamics
from ddrt.core.motor import Motor
from ddrt.loop.hold import HoldBounds
from ddrt.loop.states import LoopState
from ddrt.path.reference import PathReference

if TYPE_CHECKING:
    from ddrt.loop.tick import ControlLoop

__all__ = ["REPROFILE_MAX_SAMPLES", "drive_limits", "put_limits", "reconfigure", "reprofile"]

log = logging.getLogger("ddrt.loop")

# A path with more samples left than this keeps its profile when a reload changes the robot
# (re-profiling 20 000 samples, 40 m at 2 mm, takes 0.05-0.1 s: ten to twenty ticks at 200 Hz).
REPROFILE_MAX_SAMPLES = 20_000


def drive_limits(resolved: ResolvedLimits) -> LimitsConfig:
    """The velocity mode's limits for these resolved limits (ControlLoop.drive_limits)."""
    return replace(resolved.limits, v_max=resolved.profile_v_max)


def reconfigure(loop: ControlLoop, cfg: Config) -> None:
    """Put `cfg` in force on `loop` between two ticks: every part that holds a copy gets it.

    `cfg` is what ddrt.config.policy.plan_reload returned (its restart-only fields are the
    running ones, so the rate, the mode and the devices never change here). Everything
    new is built before anything is swapped, so a part that refuses leaves all as it was.
    """
    model_changed = cfg.robot != loop.cfg.robot or cfg.robot_motor != loop.cfg.robot_motor
    if model_changed:
        dyn = Dynamics.from_params(cfg.robot)
        seed_dyn = Dynamics.from_params(cfg.robot, seed_report=True)
        motor = Motor(cfg.robot_motor)
        adapter = (DynamicsAdapter(dyn, motor, cfg.controller.adaptation, loop.period)
                   if loop.adapter is not None else None)
    else:
        dyn, seed_dyn, motor, adapter = loop.dyn, loop.seed_dyn, loop.motor, loop.adapter
    limits = resolve_limits(cfg.limits, cfg.robot, cfg.robot_motor)
    # Swap (nothing below raises for values that passed validation).
    loop.estimator.reconfigure(cfg.estimator, cfg.robot.r_3,
                               loop.estimator.dyn if not model_changed else dyn, motor)
    loop.controller.retune(cfg.controller, put_limits(loop, limits, cfg))
    if model_changed:
        loop.dyn, loop.seed_dyn, loop.motor = dyn, seed_dyn, motor
        loop.controller.set_model(seed_dyn if cfg.controller.mode == "seed" else dyn, motor)
        # A new robot description invalidates what the adapter learnt about the old one.
        loop.adapter = adapter
        loop.adapt_active = False
    loop.cfg = cfg
    loop.holds.bounds = HoldBounds.of(cfg, loop.hal.info.drive_timeout_s, loop.period)
    loop.power.reconfigure(loop, cfg)  # the measured supply into the new motor model and limits
    if model_changed:
        reprofile(loop)


def put_limits(loop: ControlLoop, limits: ResolvedLimits, cfg: Config) -> LimitsConfig:
    """Make `limits` the loop's (the velocity mode's ramp included); returns the limits the
    controller takes now (the caller sets them)."""
    ctrl = limits.limits
    loop.limits_after_braking = None
    ref = loop.reference
    if isinstance(ref, DriveReference):
        ref.configure(drive_limits(limits), cfg.drive, cfg.daemon.command_timeout_s)
        if ref.over(ctrl.v_max, ctrl.omega_max):
            # Lower top speeds while the robot is faster: the ramp brakes it to them within
            # the limits; the controller's clamps, cut at once, would brake it as hard as
            # the inner loop can (5 m/s^2 from 0.8 to 0.3 m/s, measured). They take the new
            # limits once the setpoint is within them (ControlLoop.steer).
            loop.limits_after_braking = ctrl
            ctrl = replace(ctrl, v_max=max(ctrl.v_max, abs(ref.v.value)),
                           omega_max=max(ctrl.omega_max, abs(ref.w.value)))
    loop.limits = limits
    return ctrl


def reprofile(loop: ControlLoop) -> None:
    """A new robot model: if the rest of the path being followed asks more than its motors
    give (beyond the profile's headroom), rebuild the rest of the profile for it; what was
    done goes in `loop.reprofiled`.

    The schedule's interval and everything before it keep their speeds and times, so the
    reference does not jump; the path's own limits (and the headroom it was built with)
    stay, only the model changes. A path with more than REPROFILE_MAX_SAMPLES samples left
    keeps its profile (rebuilding it would hold up the loop); the next path uses the new
    model whatever happens here."""
    loop.reprofiled = ""
    ref, path = loop.reference, loop.path
    if (path is None or not isinstance(ref, PathReference) or ref.path is not path
            or loop.state != LoopState.FOLLOWING or path.limits.envelope is None):
        return
    env = replace(path.limits.envelope, dyn=loop.dyn, motor=replace(loop.motor.params, supply_v=loop.power.limits_v))
    first = path.index(path.at_time(ref.t_sched).sigma) + 1
    left = len(path.sigma) - first
    if left < 2:
        return
    if left > REPROFILE_MAX_SAMPLES:
        loop.reprofiled = (f"the path being followed has {left} samples left, more than {REPROFILE_MAX_SAMPLES} "
                           "to re-profile between two ticks: it keeps its profile; the next path uses the new model")
        log.warning("reload: %s", loop.reprofiled)
        return
    excess = path.envelope_excess(env, first)
    if excess <= 1e-9:
        return
    new = path.reprofiled(replace(path.limits, envelope=env), first)
    ref.path = new
    ref.pursuit.path = new
    loop.path = new
    loop.reprofiled = (f"the rest of the path asked up to {excess:.1%} beyond the new robot's motors: re-profiled "
                       f"from progress {path.sigma[first]:.3f} m ({path.duration:.2f} -> {new.duration:.2f} s)")
    log.info("reload: %s", loop.reprofiled)
