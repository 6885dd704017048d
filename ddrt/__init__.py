"""ddrt: a real-time controller for differential-drive wheeled robots."""

__version__ = "0.1.0"
