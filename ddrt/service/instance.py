"""One daemon per robot: an exclusive lock taken before any device is opened.

`fcntl.flock` on a lock file: beside the control socket (`<socket>.lock`, e.g.
/run/ddrt/ddrt.sock.lock), or, for a daemon without a socket, `ddrt.lock` in its telemetry
directory. The kernel drops the lock when the process ends however it ends (a crash, kill
-9), so a stale file never blocks a restart; the file itself stays (removing it would let a
third daemon lock a new file while the second still holds the old one) and holds the pid of
the daemon that took it last, for the error message of the next one.
"""

from __future__ import annotations

import errno
import fcntl
import os
import stat

from ddrt.errors import DdrtError


class AlreadyRunning(DdrtError, OSError):
    """Another process holds the lock."""

    def __init__(self, path: str, pid: int | None) -> None:
        holder = f"pid {pid}" if pid is not None else "another process"
        super().__init__(errno.EWOULDBLOCK,
                         f"another ddrt daemon ({holder}) already controls this robot: it holds {path}; "
                         "not starting (no device opened, nothing sent)")
        self.path = path
        self.pid = pid


def lock_path_for(socket_path: str | None, telemetry_dir: str) -> str:
    """Where the lock lives: beside the socket, else in the telemetry directory."""
    if socket_path:
        return os.fspath(socket_path) + ".lock"
    return os.path.join(os.fspath(telemetry_dir), "ddrt.lock")


class InstanceLock:
    """`acquire()` or raise AlreadyRunning; held until `release()` or the process ends."""

    def __init__(self, path: str) -> None:
        self.path = path
        self._fd: int | None = None

    def acquire(self) -> None:
        parent = os.path.dirname(self.path)
        if parent:
            os.makedirs(parent, exist_ok=True)
        # O_NOFOLLOW: never truncate whatever a planted symlink points at.
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC | os.O_NOFOLLOW, 0o644)
        try:
            if not stat.S_ISREG(os.fstat(fd).st_mode):
                raise OSError(errno.EINVAL, f"lock file {self.path}: not a regular file")
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                raise AlreadyRunning(self.path, _read_pid(fd)) from None
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        except BaseException:
            os.close(fd)
            raise
        self._fd = fd

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing the only descriptor drops the flock
            self._fd = None

    @property
    def held(self) -> bool:
        return self._fd is not None


def _read_pid(fd: int) -> int | None:
    try:
        text = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
        pid = int(text)
    except (OSError, ValueError):
        return None
    return pid if pid > 0 else None
