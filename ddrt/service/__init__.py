"""The long-running process around one ControlLoop: the daemon, its control socket, sd_notify,
real-time set-up, the clock, loop timing and telemetry."""
