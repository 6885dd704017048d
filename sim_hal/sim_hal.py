"""`SimHal`: the `Hal` backend over a `SimRobot`, and the control loop's clock.

Its time is sim_hal.simtime's: unpaced (the default, for CI) the loop's computation takes no
sim time and a run goes as fast as the CPU allows; paced, sim time follows the wall clock, so
the daemon can run against the simulator in real time.
"""

from __future__ import annotations

from ddrt.core.model import RobotParams
from ddrt.core.motor import MotorParams
from hal.base import Hal, HalInfo, HalIOError, Sample
from sim_hal.plant import PlantConfig, SimRobot
from sim_hal.simtime import SimTime


class SimHal(Hal):
    """A HAL whose sensors and motors are those of a simulated robot; its own clock."""

    owns_time = True

    def __init__(self, robot: SimRobot, paced: bool = False) -> None:
        self.robot = robot
        self.time = SimTime(lambda: robot.t, robot.advance_to, paced)
        self.info = HalInfo(
            encoder_counts_per_rev=robot.encoder_counts_per_rev,
            gyro_lsb_per_rad_s=robot.gyro_lsb_per_rad_s,
            gyro_full_scale_rad_s=robot.gyro_full_scale_rad_s,
            gyro_delay_s=robot.gyro_delay_s,
        )
        self.freeze_after: float | None = None  # fault injection: sensors stop updating
        self._last_sample: Sample | None = None

    @classmethod
    def from_params(cls, params: RobotParams, motor_l: MotorParams | None = None,
                    motor_r: MotorParams | None = None, cfg: PlantConfig | None = None,
                    start: tuple[float, float, float] = (0.0, 0.0, 0.0),
                    paced: bool = False) -> "SimHal":
        """Build the robot too; motors default to `MotorParams()`, the plant to `PlantConfig()`."""
        robot = SimRobot(params, motor_l or MotorParams(), motor_r or MotorParams(), cfg, start)
        return cls(robot, paced=paced)

    # --- clock (sim_hal.simtime) ------------------------------------------------------------

    @property
    def paced(self) -> bool:
        return self.time.paced

    def now(self) -> float:
        """Sim time (s). Paced, the plant is first brought up to the wall clock."""
        return self.time.now()

    def advance_to_wall_clock(self) -> None:
        """Paced: integrate the plant up to the wall clock now (unpaced, sim time waits)."""
        self.time.catch_up()

    def sleep_until(self, deadline: float) -> float:
        """Advance the plant to `deadline` (and, paced, wait for the wall clock); return now."""
        return self.time.sleep_until(deadline)

    # --- Hal ------------------------------------------------------------------------------

    def read(self) -> Sample:
        if self._closed:
            raise HalIOError("SimHal.read: the HAL is closed")
        t = self.time.now()
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
