"""The control socket's file: never taken from a live daemon, never put in place of a file
that is not a socket, and removed at the end only if it is still the one this process made.

A socket file left behind by a crashed run (nobody listens: connect is refused) is replaced.
The mode is set before listen(), so there is no moment with looser permissions.
"""

from __future__ import annotations

import errno
import os
import socket
import stat


def listen_unix(path: str, mode: int, backlog: int) -> socket.socket:
    """A non-blocking AF_UNIX listener on `path` with file mode `mode` (OSError naming the path)."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        pass
    else:
        if not stat.S_ISSOCK(st.st_mode):
            raise FileExistsError(errno.EEXIST,
                                  f"control socket {path}: exists and is not a socket, not replacing it")
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
            probe.settimeout(0.5)
            try:
                probe.connect(path)
            except ConnectionRefusedError:
                os.unlink(path)  # left behind by a crashed run: nobody listens
            except OSError as exc:
                raise OSError(exc.errno, f"control socket {path}: exists and cannot be probed: {exc}") from exc
            else:
                raise OSError(errno.EADDRINUSE, f"control socket {path}: another process is listening on it")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
    try:
        sock.bind(path)
        # Before listen(), nobody can connect, so there is no window with looser permissions.
        os.chmod(path, mode)
        sock.listen(backlog)
    except OSError as exc:
        sock.close()
        raise OSError(exc.errno, f"control socket {path}: {exc.strerror or exc}") from exc
    sock.setblocking(False)
    return sock


def remove_if_ours(path: str, inode: int) -> None:
    """Unlink `path` if it is still the file with `inode` (another daemon may have replaced it)."""
    try:
        if os.stat(path).st_ino == inode:
            os.unlink(path)
    except FileNotFoundError:
        pass
