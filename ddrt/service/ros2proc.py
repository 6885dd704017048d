"""`daemon.ros2.enabled`: the ROS 2 bridge as a child process the daemon supervises.

The bridge (ddrt/ros2) runs as `python -m ddrt.ros2 --socket S --config C`: a process of its
own, so nothing DDS does (discovery, a slow reader, a flood of cmd_vel) takes the loop's
CPU time or its GIL. A thread waits on it and starts it again after RESTART_S when it exits;
an exit status of 2 (bad config, the `ros2` extra not installed) is not retried. Closing
stops it with SIGTERM (SIGKILL after STOP_S).
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import threading

log = logging.getLogger("ddrt.service.ros2")

RESTART_S = 2.0
STOP_S = 3.0


class BridgeProcess:
    def __init__(self, socket_path: str, config_path: str, argv: list[str] | None = None,
                 extra: tuple[str, ...] = ()) -> None:
        self.argv = argv or [sys.executable, "-m", "ddrt.ros2", "--socket", socket_path, "--config", config_path,
                             "--supervised", str(os.getpid()), *extra]
        self.starts = 0
        self.proc: subprocess.Popen[bytes] | None = None
        self._closed = threading.Event()
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._run, name="ddrt-ros2", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._closed.is_set():
            with self._lock:
                if self._closed.is_set():
                    return
                try:
                    self.proc = subprocess.Popen(self.argv, stdin=subprocess.DEVNULL)
                except OSError as exc:
                    log.error("ros2: cannot start the bridge (%s): %s", " ".join(self.argv[:3]), exc)
                    return
                self.starts += 1
            code = self.proc.wait()
            if self._closed.is_set():
                return
            if code == 2:
                log.error("ros2: the bridge cannot run (exit status 2, see its message above); not restarted")
                return
            log.warning("ros2: the bridge exited with status %s; starting it again in %g s", code, RESTART_S)
            self._closed.wait(RESTART_S)

    def close(self) -> None:
        with self._lock:
            self._closed.set()
            proc = self.proc
        if proc is not None and proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(STOP_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        self._thread.join(timeout=1.0)
