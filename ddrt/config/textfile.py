"""One bounded reader for every whole file ddrt reads: configs, path files and the CSVs they
name, campaigns, answers, commissioning and campaign state.

A file is read whole only up to a limit (the setting that makes the limit is named in the
error), must be UTF-8 (a leading byte-order mark is dropped), and each failure is one line
naming the file, raised as the caller's error type. Where a read must never block (a path
file the daemon is handed, a state file a command resumes from), `regular_only` refuses a
FIFO, a device or a directory by its type before anything is read; a config may still be a
pipe (`ddrt run <(...)`), and the reloader bounds that read with a deadline of its own.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import Callable

__all__ = ["mode_kind", "check_regular_file", "read_text", "read_state_text"]

ErrorType = Callable[[str], Exception]


def mode_kind(mode: int) -> str:
    """What a stat mode is, for a message: "a file" (regular), "a directory", "a FIFO", ..."""
    if stat.S_ISREG(mode):
        return "a file"
    return ("a directory" if stat.S_ISDIR(mode) else "a FIFO" if stat.S_ISFIFO(mode)
            else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode)
            else "a socket" if stat.S_ISSOCK(mode) else "not a regular file")


def _check_stat(name: str, st: os.stat_result, limit: int, error: ErrorType, limit_from: str, what: str) -> None:
    kind = mode_kind(st.st_mode)
    if kind != "a file":
        raise error(f"{name}: is {kind}: {what} is read from a regular file only")
    if st.st_size > limit:
        raise error(f"{name}: {st.st_size} bytes, more than {limit_from or 'the limit of'} = {limit}")


def _open_regular(name: str, limit: int, error: ErrorType, limit_from: str, what: str) -> int:
    """A descriptor of a regular file of at most `limit` bytes; never blocks. stat first (a FIFO
    is refused by its type), then an O_NONBLOCK open and fstat of what was opened (the name may
    have been swapped in between)."""
    try:
        _check_stat(name, os.stat(name), limit, error, limit_from, what)
        fd = os.open(name, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC)
    except OSError as exc:
        raise error(f"{name}: cannot read: {exc.strerror or exc}") from None
    try:
        _check_stat(name, os.fstat(fd), limit, error, limit_from, what)
    except BaseException:
        os.close(fd)
        raise
    return fd


def check_regular_file(path: str | os.PathLike[str], limit: int, error: ErrorType,
                       limit_from: str = "", what: str = "it") -> None:
    """Refuse, without reading it, a file that is not a readable regular file of at most `limit` bytes."""
    os.close(_open_regular(os.fspath(path), limit, error, limit_from, what))


def read_text(path: str | os.PathLike[str], error: ErrorType, limit: int, limit_from: str = "",
              regular_only: bool = False, what: str = "it") -> str:
    """The file's text: UTF-8, at most `limit` bytes (`limit_from` names the setting that makes
    that limit); with `regular_only`, a file that is not a regular file is refused unread."""
    name = os.fspath(path)
    try:
        if regular_only:
            fh = os.fdopen(_open_regular(name, limit, error, limit_from, what), "rb")
        else:
            fh = open(name, "rb")
        with fh:
            data = fh.read(limit + 1)
    except OSError as exc:
        raise error(f"{name}: cannot read: {exc.strerror or exc}") from None
    if len(data) > limit:
        raise error(f"{name}: larger than {limit} bytes{f' ({limit_from})' if limit_from else ''}: "
                    "not a file ddrt reads")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise error(f"{name}: not UTF-8 text: byte {exc.start} (0x{data[exc.start]:02x}) "
                    f"cannot be decoded") from None
    return text.removeprefix("\ufeff")


def read_state_text(path: Path, error: ErrorType, limit: int = 16 * 1024 * 1024) -> str:
    """A state file ddrt wrote itself (commissioning's, a campaign's): never a FIFO, at most `limit`."""
    return read_text(path, error, limit, regular_only=True, what="a state file")
