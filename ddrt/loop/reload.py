"""What a new config puts in force between two ticks (`ControlLoop.reconfigure`), worked out
here and applied by the loop: everything new is built before anything is swapped, so a part
that refuses leaves all as it was; a new robot model re-profiles the rest of the path being
followed when that path asks more than the new motors give."""

from __future__ import annotations

from dataclasses import dataclass, replace

from ddrt.config import Config
from ddrt.config.sections import LimitsConfig
from ddrt.core.adapt import DynamicsAdapter
from ddrt.core.drive import DriveReference
from ddrt.core.envelope import ResolvedLimits, resolve_limits
from ddrt.core.model import Dynamics
from ddrt.core.motor import Motor
from ddrt.params.motor import MotorParams
from ddrt.core.reference import Reference
from ddrt.path import Path
from ddrt.path.reference import PathReference

__all__ = ["REPROFILE_MAX_SAMPLES", "LimitsPlan", "Model", "Reload", "Reprofile", "drive_limits", "limits_plan",
           "prepare_reload", "reprofile"]

# A path with more samples left than this keeps its profile when a reload changes the robot
# (re-profiling 20 000 samples, 40 m at 2 mm, takes 0.05-0.1 s: ten to twenty ticks at 200 Hz).
REPROFILE_MAX_SAMPLES = 20_000


def drive_limits(resolved: ResolvedLimits) -> LimitsConfig:
    """The velocity mode's limits for these resolved limits (ControlLoop.drive_limits)."""
    return replace(resolved.limits, v_max=resolved.profile_v_max)


@dataclass(frozen=True)
class Model:
    """A new robot description's models; `adapter` None when the loop runs without one (what
    the old adapter learnt was about the old robot)."""

    dyn: Dynamics
    seed_dyn: Dynamics
    motor: Motor
    adapter: DynamicsAdapter | None


@dataclass(frozen=True)
class Reload:
    """A config to put in force: its resolved limits, and a new model when the robot changed."""

    cfg: Config
    limits: ResolvedLimits
    model: Model | None


def prepare_reload(cfg: Config, running: Config, period_s: float, adapting: bool) -> Reload:
    """Build what `cfg` needs over the `running` config (raises before anything is swapped).

    `cfg` is what ddrt.config.policy.prepare_reload returned (its restart-only fields are the
    running ones, so the rate, the mode and the devices never change here)."""
    model = None
    if cfg.robot != running.robot or cfg.robot_motor != running.robot_motor:
        dyn = Dynamics.from_params(cfg.robot)
        motor = Motor(cfg.robot_motor)
        model = Model(dyn, Dynamics.from_params(cfg.robot, seed_report=True), motor,
                      DynamicsAdapter(dyn, motor, cfg.controller.adaptation, period_s) if adapting else None)
    return Reload(cfg, resolve_limits(cfg.limits, cfg.robot, cfg.robot_motor), model)


@dataclass(frozen=True)
class LimitsPlan:
    """New limits for the loop: the controller's now, and the lower ones it takes once a drive
    has braked within them (None: none wait)."""

    now: LimitsConfig
    after_braking: LimitsConfig | None


def limits_plan(limits: ResolvedLimits, ref: Reference | None, cfg: Config) -> LimitsPlan:
    """The controller's limits for `limits` while `ref` runs; a drive's ramp takes them at once."""
    ctrl = limits.limits
    if isinstance(ref, DriveReference):
        ref.configure(drive_limits(limits), cfg.drive, cfg.daemon.command_timeout_s)
        if ref.over(ctrl.v_max, ctrl.omega_max):
            # Lower top speeds while the robot is faster: the ramp brakes it to them within
            # the limits; the controller's clamps, cut at once, would brake it as hard as
            # the inner loop can (5 m/s^2 from 0.8 to 0.3 m/s, measured). They take the new
            # limits once the setpoint is within them (ControlLoop.steer).
            return LimitsPlan(replace(ctrl, v_max=max(ctrl.v_max, abs(ref.v.value)),
                                      omega_max=max(ctrl.omega_max, abs(ref.w.value))), ctrl)
    return LimitsPlan(ctrl, None)


@dataclass(frozen=True)
class Reprofile:
    """What a new model did to the path being followed: the re-profiled path (None: it keeps
    its profile) and what was done, for `ControlLoop.reprofiled` ('' when nothing was needed)."""

    path: Path | None = None
    note: str = ""


def reprofile(ref: Reference | None, path: Path | None, dyn: Dynamics, motor: MotorParams) -> Reprofile:
    """If the rest of `path`, followed by `ref`, asks more than the model (`dyn`, `motor` at the
    supply the limits use) gives, beyond the profile's headroom, its profile rebuilt for it.

    The schedule's interval and everything before it keep their speeds and times, so the
    reference does not jump; the path's own limits (and the headroom it was built with)
    stay, only the model changes. A path with more than REPROFILE_MAX_SAMPLES samples left
    keeps its profile (rebuilding it would hold up the loop); the next path uses the new
    model whatever happens here. The caller asks only while following."""
    if path is None or not isinstance(ref, PathReference) or ref.path is not path or path.limits.envelope is None:
        return Reprofile()
    env = replace(path.limits.envelope, dyn=dyn, motor=motor)
    first = path.index(path.at_time(ref.t_sched).sigma) + 1
    left = len(path.sigma) - first
    if left < 2:
        return Reprofile()
    if left > REPROFILE_MAX_SAMPLES:
        return Reprofile(None, f"the path being followed has {left} samples left, more than "
                               f"{REPROFILE_MAX_SAMPLES} to re-profile between two ticks: it keeps its profile; "
                               "the next path uses the new model")
    excess = path.envelope_excess(env, first)
    if excess <= 1e-9:
        return Reprofile()
    new = path.reprofiled(replace(path.limits, envelope=env), first)
    return Reprofile(new, f"the rest of the path asked up to {excess:.1%} beyond the new robot's motors: "
                          f"re-profiled from progress {path.sigma[first]:.3f} m ({path.duration:.2f} -> "
                          f"{new.duration:.2f} s)")
