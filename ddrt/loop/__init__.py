"""The control loop: one tick, the same on the robot and in simulation
(read -> estimate -> reference -> control -> write -> record).

- `tick.py`: `ControlLoop`, the tick and the commands (follow, drive, stop, estop, reset).
- `states.py`: `LoopState`, whose values are telemetry's state codes.
- `hold.py`: transient faults: when the loop holds, how a hold ends, when a fault latches.
- `record.py`: the telemetry row, its columns declared once (`COLUMNS`).
- `reload.py`: a new config put in force between two ticks.
"""

from ddrt.loop.hold import RecoveryCounters
from ddrt.loop.record import COLUMNS
from ddrt.loop.states import LoopState, state_label
from ddrt.loop.tick import ControlLoop, StartTooFar

__all__ = ["COLUMNS", "ControlLoop", "LoopState", "RecoveryCounters", "StartTooFar", "state_label"]
