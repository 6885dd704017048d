"""`SimHal`: the `Hal` backend over a `SimRobot`, and the control loop's clock.

Unpaced (the default, for CI) the loop's computation takes no sim time and `sleep_until`
just integrates the plant to the deadline, so a run goes as fast as the CPU allows. Paced,
sim time follows the wall clock (time.monotonic since start, plus the sim time at start), so
the daemon can run against the simulator in real time.
"""

from __future__ import annotations

import math
import time

from ddrt.core.model import RobotParams
from ddrt.core.motor import MotorParams
from hal.base import Hal, HalInfo, HalIOError, HalValueError, Sample
from sim_hal.plant import PlantConfig, SimRobot


class SimHal(Hal):
    """A HAL whose sensors and motors are those of a simulated robot; its own clock."""

    owns_time = True

    def __init__(self, robot: SimRobot, paced: bool = False) -> None:
        self.robot = robot
        self.paced = paced
        self.info = HalInfo(
            encoder_counts_per_rev=robot.encoder_counts_per_rev,
            gyro_lsb_per_rad_s=robot.gyro_lsb_per_rad_s,
            gyro_full_scale_rad_s=robot.gyro_full_scale_rad_s,
            gyro_delay_s=robot.gyro_delay_s,
        )
        self.freeze_after: float | None = None  # fault injection: sensors stop updating
        self._last_sample: Sample | None = None
        self._wall0 = time.monotonic()
        self._sim0 = robot.t

    @classmethod
    def from_params(cls, params: RobotParams, motor_l: MotorParams | None = None,
                    motor_r: MotorParams | None = None, cfg: PlantConfig | None = None,
                    start: tuple[float, float, float] = (0.0, 0.0, 0.0),
                    paced: bool = False) -> "SimHal":
        """Build the robot too; motors default to `MotorParams()`, the plant to `PlantConfig()`."""
        robot = SimRobot(params, motor_l or MotorParams(), motor_r or MotorParams(), cfg, start)
        return cls(robot, paced=paced)

    # --- clock ------------------------------------------------------------------------------

    def _wall_sim_time(self) -> float:
        return time.monotonic() - self._wall0 + self._sim0

    def now(self) -> float:
        """Sim time (s). Paced, the plant is first brought up to the wall clock."""
        self.advance_to_wall_clock()
        return self.robot.t

    def advance_to_wall_clock(self) -> None:
        """Paced: integrate the plant up to the wall clock now (unpaced, sim time waits)."""
        if self.paced:
            self.robot.advance_to(self._wall_sim_time())

    def sleep_until(self, deadline: float) -> float:
        """Advance the plant to `deadline` (and, paced, wait for the wall clock); return now."""
        if not math.isfinite(deadline):
            raise HalValueError(f"deadline={deadline!r} is not finite")
        if self.paced:
            remaining = deadline - self._wall_sim_time()
            if remaining > 0.0:
                time.sleep(remaining)
            self.robot.advance_to(max(deadline, self._wall_sim_time()))
        else:
            self.robot.advance_to(deadline)
        return self.robot.t

    # --- Hal ------------------------------------------------------------------------------

    def read(self) -> Sample:
        if self._closed:
            raise HalIOError("SimHal.read: the HAL is closed")
        t = self.now()
        last = self._last_sample
        if self.freeze_after is not None and t >= self.freeze_after and last is not None:
            return Sample(t=last.t, encoder_count=last.encoder_count, gyro_z_raw=last.gyro_z_raw,
                          fresh=False, faults="sensors frozen (injected)")
        self._last_sample = Sample(t=t, encoder_count=self.robot.read_encoder(), gyro_z_raw=self.robot.read_gyro_raw())
        return self._last_sample

    def _write(self, duty_l: float, duty_r: float) -> None:
        if self._closed:
            raise HalIOError("SimHal.write: the HAL is closed")
        self.robot.command(duty_l, duty_r)

    def stop(self) -> None:
        if not self._closed:
            self.robot.command(0.0, 0.0)

    def _close(self) -> None:
        robot = getattr(self, "robot", None)
        if robot is not None:
            robot.command(0.0, 0.0)
