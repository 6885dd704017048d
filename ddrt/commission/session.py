"""What every commissioning step shares: the input config, the answers, the stored results,
the config as calibrated so far, and opening the robot with its motors guarded."""

from __future__ import annotations

import contextlib
import math
import random
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator, Mapping

from ddrt.errors import DdrtError
from ddrt.commission.answers import Answers
from ddrt.commission.state import State
from ddrt.config import Config, config_from_mapping
from ddrt.config.load import merge_mappings
from hal.base import Hal


class CommissionError(DdrtError, ValueError):
    """A step cannot go on (nothing moved, a measurement refused, a bad area): one clear line."""


class Stopped(CommissionError):
    """Ctrl-C or the robot's emergency stop during a step: the motors were stopped."""


STEPS = ("link", "wiring", "rest", "dynamics", "odometry", "result")
DEFAULT_NOISE = (2.0, 0.5)  # --measurement-noise: a tape's mm and a protractor's degrees (1 sigma)


@dataclass
class Options:
    out: Path
    area: tuple[float, float] | None = None
    from_sim_truth: bool = False
    noise_mm_deg: tuple[float, float] = DEFAULT_NOISE
    turns: int = 5
    distance_m: float = 1.0
    umbmark_side_m: float | None = None
    check: bool = True
    figures: bool = True


@dataclass
class Session:
    cfg: Config  # the input, as loaded
    config_path: str
    opts: Options
    answers: Answers
    state: State
    notes: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.rng = random.Random(f"commission/{self.cfg.sim.seed}")

    def say(self, text: str) -> None:
        self.answers.say(text)

    def overrides(self, upto: str | None = None) -> dict[str, Any]:
        """The config keys the finished steps measured, merged in step order (before `upto`)."""
        out: dict[str, Any] = {}
        for step in STEPS:
            if step == upto:
                break
            res = self.state.get(step)
            if res and res.get("config"):
                out = merge_mappings(out, res["config"])
        return out

    def config(self, upto: str | None = None, extra: Mapping[str, Any] | None = None) -> Config:
        """The input config with what the steps before `upto` measured (and `extra`) merged in."""
        data = merge_mappings(explicit_robot(self.cfg), self.overrides(upto))
        if extra:
            data = merge_mappings(data, extra)
        return config_from_mapping(data, source=f"{self.config_path} (as commissioned so far)",
                                   base_dir=self.cfg.base_dir)

    def truth_noise(self) -> tuple[float, float]:
        """One tape reading's error (m) and one protractor reading's (rad), for --from-sim-truth."""
        mm, deg = self.opts.noise_mm_deg
        return self.rng.gauss(0.0, mm * 1e-3), math.radians(self.rng.gauss(0.0, deg))

    @contextlib.contextmanager
    def robot(self, cfg: Config, start: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Iterator[Hal]:
        """The robot, opened as `cfg` says; the motors stop however the block ends, and Ctrl-C
        becomes `Stopped` (one clear line) once they have."""
        from hal.registry import open_hal

        hal = open_hal(cfg, start=start)
        try:
            yield hal
        except KeyboardInterrupt:
            hal.stop()
            raise Stopped("stopped by Ctrl-C: the motors are off; run the command again to resume") from None
        finally:
            try:
                hal.stop()
            finally:
                hal.close()


def explicit_robot(cfg: Config) -> dict[str, Any]:
    """The config's mapping with robot: as its full parameters (an estimate: replaced by what it
    derived), so measured values can be merged over it; plant: (the simulated truth) explicit
    too, so that what is measured about the belief never leaks into the truth through the
    plant keys that default to robot:'s."""
    from dataclasses import asdict

    data = dict(cfg.raw)
    robot = {k: v for k, v in dict(data.get("robot") or {}).items() if k != "estimate"}
    robot.update({name: float(f"{value:.6g}") for name, value in asdict(cfg.robot).items()})
    data["robot"] = robot
    if cfg.hal.backend == "sim" or "plant" in data:
        plant: dict[str, Any] = asdict(cfg.plant)
        plant["motor_l"] = asdict(cfg.plant_motor_l)
        plant["motor_r"] = asdict(cfg.plant_motor_r)
        data["plant"] = plant
    return data


def follow_to_end(loop: Any, clock: Any, path: Any, start: tuple[float, float, float], step: str) -> None:
    """Follow `path` from `start` to its end and let the robot settle; a run that ends early
    (a fault, estop, Ctrl-C) is this step's CommissionError."""
    from ddrt import calibrate as cal  # the loop helpers, imported when a step drives

    loop.follow(path, start)
    try:
        cal.run_until_stopped(loop, clock, path.duration + 15.0)
    except cal.CalibrationRunError as exc:
        raise CommissionError(f"{step}: {exc}") from None
    cal.settle(loop, clock)
