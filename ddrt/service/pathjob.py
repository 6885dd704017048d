"""A path build as the daemon asks for it and the checks it runs first, in whichever process
builds it (the worker, ddrt/service/pathworker.py, or the caller when no loop runs).

`BuildJob` is what to build (picklable: it crosses to the worker), `Build` how it is going as
the loop sees it. A path file must be a regular file of at most `paths.max_file_bytes`
(checked with stat, then an O_NONBLOCK open and fstat, so a FIFO or a device never blocks
anything), and the CSV an inline or YAML `file:` names likewise.
"""

from __future__ import annotations

import os
import stat
import time
from dataclasses import dataclass, field
from typing import Any, Mapping


@dataclass(frozen=True)
class BuildJob:
    """What to build: load_path's arguments (picklable), and where to name it in messages."""

    source: Any  # a file name or a path mapping
    limits: Any  # ddrt.path.SpeedLimits
    paths: Any  # ddrt.config.sections.PathsConfig
    base_dir: str | None = None
    where: str = "<mapping>"


@dataclass(eq=False)
class Build:
    """One submitted job, as the loop sees it: poll `done`, then `path` or `error`."""

    job: BuildJob
    t_submit: float = field(default_factory=time.monotonic)
    path: Any = None
    error: str = ""
    done: bool = False
    cancelled: bool = False
    phase: str = "queued"  # queued, starting, building, receiving, done

    def _finish(self, path: Any = None, error: str = "") -> None:
        self.path = path
        self.error = error
        self.phase = "done"
        self.done = True  # last: the loop thread reads `done` first

    @property
    def elapsed_s(self) -> float:
        return time.monotonic() - self.t_submit


def describe(source: Any) -> str:
    """A short name of a path source for logs and status."""
    if isinstance(source, str):
        return source
    if isinstance(source, Mapping):
        for key in ("shape", "file"):
            if isinstance(source.get(key), str):
                return f"{key} {source[key][:60]}"
        if "points" in source:
            pts = source["points"]
            return f"{len(pts)} points" if isinstance(pts, (list, tuple)) else "points"
    return type(source).__name__


def check_path_file(fname: str, max_bytes: int, error: type[Exception]) -> None:
    """A path file must be a readable regular file of at most `max_bytes`; never blocks.

    stat first (a FIFO, a device or a directory is refused by its type), then an O_NONBLOCK
    open and fstat of what was opened (the name may have been swapped in between).
    """
    try:
        st = os.stat(fname)
    except OSError as exc:
        raise error(f"{fname}: cannot read: {exc.strerror or exc}") from None
    _check_stat(fname, st, max_bytes, error)
    try:
        fd = os.open(fname, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC)
    except OSError as exc:
        raise error(f"{fname}: cannot read: {exc.strerror or exc}") from None
    try:
        _check_stat(fname, os.fstat(fd), max_bytes, error)
    finally:
        os.close(fd)


def _check_stat(fname: str, st: os.stat_result, max_bytes: int, error: type[Exception]) -> None:
    mode = st.st_mode
    if not stat.S_ISREG(mode):
        kind = ("a directory" if stat.S_ISDIR(mode) else "a FIFO" if stat.S_ISFIFO(mode)
                else "a device" if stat.S_ISCHR(mode) or stat.S_ISBLK(mode)
                else "a socket" if stat.S_ISSOCK(mode) else "not a regular file")
        raise error(f"{fname}: is {kind}: a path is read from a regular file only")
    if st.st_size > max_bytes:
        raise error(f"{fname}: {st.st_size} bytes, more than paths.max_file_bytes = {max_bytes}")


def _nested_file(data: Any, base_dir: str | None) -> str | None:
    """The CSV a path mapping's `file:` names, resolved as the loader resolves it."""
    if isinstance(data, Mapping) and isinstance(data.get("file"), str):
        fname = data["file"]
        if base_dir is not None and not os.path.isabs(fname):
            fname = os.path.join(base_dir, fname)
        return fname
    return None


def build_path(job: BuildJob) -> Any:
    """Check the files, then load_path (in the worker; also usable in-process)."""
    from ddrt.config.yamlio import read_yaml
    from ddrt.path.spec import PathError, load_path

    limit = job.paths.max_file_bytes
    src = job.source
    nested = None
    if isinstance(src, (str, os.PathLike)):
        fname = os.fspath(src)
        check_path_file(fname, limit, PathError)
        if fname.lower().endswith((".yaml", ".yml")):
            data = read_yaml(fname, PathError)
            nested = _nested_file(data, job.base_dir if job.base_dir is not None else os.path.dirname(fname))
            where = fname
        src = fname
    else:
        nested = _nested_file(src, job.base_dir)
        where = job.where
    if nested is not None and nested.lower().endswith(".csv"):
        try:
            check_path_file(nested, limit, PathError)
        except PathError as exc:
            raise PathError(f"{where}: key 'file': {exc}") from None
    return load_path(src, job.limits, base_dir=job.base_dir, paths=job.paths, where=job.where)
