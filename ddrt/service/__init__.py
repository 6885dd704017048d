"""The long-running process around one ControlLoop: the daemon, its control socket and
commands, the path worker, sd_notify, loop timing and telemetry."""
