"""The control loop: one tick, the same on the robot and in simulation
(read -> estimate -> reference -> control -> write -> record).

- `tick.py`: `ControlLoop`, the tick and the commands (follow, drive, stop, estop, reset).
- `states.py`: `LoopState`, whose values are telemetry's state codes.
- `modes.py`: the mode machine: every change of state, its guards and refusals, in one table.
- `hold.py`: transient faults: when the loop holds, how a hold ends, when a fault latches.
- `record.py`: the telemetry row, its columns declared once (`COLUMNS`).
- `reload.py`: a new config put in force between two ticks.
"""

from ddrt.loop.hold import RecoveryCounters
from ddrt.loop.modes import Event, ModeRefused
from ddrt.loop.record import COLUMNS
from ddrt.loop.states import LoopState, state_label
from ddrt.loop.tick import ControlLoop, StartTooFar

__all__ = ["COLUMNS", "ControlLoop", "Event", "LoopState", "ModeRefused", "RecoveryCounters", "StartTooFar", "state_label"]
