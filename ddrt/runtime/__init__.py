"""The runtime layer: what the daemon, the drivers, the viewer and the simulator all need from
the operating system (the monotonic clock, real-time set-up, file rotation).

A leaf: it imports nothing of ddrt but `ddrt.core.types`, so hal/, viz/, service/ and simrun/ can
all use it without depending on each other.
"""
