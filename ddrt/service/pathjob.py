"""A path build as the daemon asks for it and the checks it runs first, in whichever process
builds it (the worker, ddrt/service/pathworker.py, or the caller when no loop runs).

`BuildJob` is what to build (picklable: it crosses to the worker), `Build` how it is going as
the loop sees it. A path file must be a regular file of at most `paths.max_file_bytes`
(checked with stat, then an O_NONBLOCK open and fstat, so a FIFO or a device never blocks
anything), and the CSV an inline or YAML `file:` names likewise.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from typing import Any, Mapping

from ddrt.config.textfile import check_regular_file


CONTENT_FORMATS = {"csv": ".csv", "yaml": ".yaml"}
CONTENT_KEYS = ("cmd", "id", "pose", "here", "frame", "content", "format", "name")


@dataclass(frozen=True)
class PathContent:
    """A path file's content sent over the socket (`ddrt ctl follow FILE`), so a sandboxed
    daemon (ProtectHome, PrivateTmp) follows a file it cannot see: read as that file would be."""

    text: str
    format: str  # "csv" or "yaml"
    name: str  # the file's name on the client's side, for messages

    @property
    def label(self) -> str:
        return f"{self.name} (sent as content)"


def content_source(req: Mapping[str, Any], max_bytes: int) -> PathContent:
    """The follow request's content form, checked as strictly as a file; ValueError naming
    the field."""
    extra = sorted(k for k in req if k not in CONTENT_KEYS)
    if extra:
        raise ValueError(f"{extra[0]}: not a key of the content form (it takes content, format, name, pose)")
    text = req["content"]
    if not isinstance(text, str):
        raise ValueError("content: expected the file's text as a string")
    name = req.get("name", "content")
    if not isinstance(name, str) or not name or "\0" in name or "/" in name or len(name) > 255:
        raise ValueError(f"name: expected a file name without a directory, got {name!r:.80}")
    fmt = req.get("format")
    if fmt is None:
        fmt = next((f for f, ext in CONTENT_FORMATS.items() if name.lower().endswith(ext)), None)
        if fmt is None and name.lower().endswith(".yml"):
            fmt = "yaml"
    if fmt not in CONTENT_FORMATS:
        raise ValueError(f"format: expected 'csv' or 'yaml', got {fmt!r:.40}")
    try:
        size = len(text.encode("utf-8"))
    except UnicodeEncodeError:
        raise ValueError(f"content: {name} is not valid UTF-8 text") from None
    if size > max_bytes:
        raise ValueError(f"content: {name}: {size} bytes, more than paths.max_file_bytes = {max_bytes}")
    return PathContent(text, fmt, name)


@dataclass(frozen=True)
class BuildJob:
    """What to build: load_path's arguments (picklable), and where to name it in messages."""

    source: Any  # a file name or a path mapping
    limits: Any  # ddrt.path.SpeedLimits
    paths: Any  # ddrt.config.sections.PathsConfig
    base_dir: str | None = None
    where: str = "<mapping>"
    place_at: tuple[float, float, float] | None = None  # --here: the path moved to start at this pose
    to_odom: tuple[float, float, float] | None = None  # frame map: then moved rigidly by this (map -> odom)


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

    def advance(self, phase: str) -> None:
        """The builder's progress, for status (it runs on another thread than the loop's)."""
        self.phase = phase

    def finish(self, path: Any = None, error: str = "") -> None:
        """The builder's result: the path, or why there is none."""
        self.path = path
        self.error = error
        self.phase = "done"
        self.done = True  # last: the loop thread reads `done` first

    def take(self) -> Any:
        """The built path, handed over once (the build holds it no longer)."""
        path, self.path = self.path, None
        return path

    def cancel(self) -> Any:
        """The result is no longer wanted: a path already built is handed back to be freed."""
        self.cancelled = True
        return self.take() if self.done else None

    @property
    def elapsed_s(self) -> float:
        return time.monotonic() - self.t_submit


def describe(source: Any) -> str:
    """A short name of a path source for logs and status."""
    if isinstance(source, PathContent):
        return source.label
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
    """A path file must be a readable regular file of at most `max_bytes`; never blocks."""
    check_regular_file(fname, max_bytes, error, "paths.max_file_bytes", "a path")


def _nested_file(data: Any, base_dir: str | None) -> str | None:
    """The CSV a path mapping's `file:` names, resolved as the loader resolves it."""
    if isinstance(data, Mapping) and isinstance(data.get("file"), str):
        fname = data["file"]
        if base_dir is not None and not os.path.isabs(fname):
            fname = os.path.join(base_dir, fname)
        return fname
    return None


def build_path(job: BuildJob) -> Any:
    """Check the files, then load_path (in the worker; also usable in-process); moved to
    start at `job.place_at` when given (follow --here)."""
    path = _load(job)
    if job.place_at is not None:
        path = path.moved(job.place_at)
    if job.to_odom is not None:  # a rigid motion is fixed by where it takes one pose: the start
        from ddrt.path.frame import compose

        path = path.moved(compose(job.to_odom, path.start_pose))
    return path


def _load(job: BuildJob) -> Any:
    from ddrt.config.yamlio import read_yaml
    from ddrt.path.spec import PathError, load_path

    limit = job.paths.max_file_bytes
    src = job.source
    if isinstance(src, PathContent):
        return _build_content(job, src)
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


def _build_content(job: BuildJob, content: PathContent) -> Any:
    """A path sent as content: written to a private temporary file and loaded as a file is
    (the same size, UTF-8 and loader checks); messages name the client's file name."""
    import tempfile

    from ddrt.config.yamlio import load_yaml_text
    from ddrt.path.spec import PathError

    label = content.label
    if content.format == "yaml":
        data = load_yaml_text(content.text, label, PathError)
        if isinstance(data, Mapping) and "file" in data:
            fname = data["file"]
            if not isinstance(fname, str) or not os.path.isabs(fname):
                raise PathError(f"{label}: key 'file': {fname!r} is relative, and a path sent as content has "
                                "no directory to resolve it against: send the CSV itself "
                                "(ddrt ctl follow FILE.csv), or name it by an absolute path the daemon can read")
            try:
                check_path_file(fname, job.paths.max_file_bytes, PathError)
            except PathError as exc:
                raise PathError(f"{label}: key 'file': {exc} (the daemon reads that file itself, as uid "
                                f"{os.getuid()}: a sandboxed service (ProtectHome, PrivateTmp) cannot see "
                                "/home or /tmp; send the CSV itself)") from None
    with tempfile.TemporaryDirectory(prefix="ddrt-follow-") as tmp:
        base = os.path.splitext(content.name)[0] or "content"
        fname = os.path.join(tmp, base + CONTENT_FORMATS[content.format])
        with open(fname, "w", encoding="utf-8") as fh:
            fh.write(content.text)
        try:
            return build_path(BuildJob(fname, job.limits, job.paths, None, label))
        except PathError as exc:
            raise PathError(str(exc).replace(fname, label)) from None
