"""The one bounded reader (ddrt/config/textfile.py): limits, UTF-8, and files that must never block."""

from __future__ import annotations

import os
import threading
from pathlib import Path

import pytest

from ddrt.commission.state import State, StateError
from ddrt.config.textfile import check_regular_file, read_state_text, read_text


class Refused(ValueError):
    pass


def test_text_is_read_whole_and_a_byte_order_mark_dropped(tmp_path: Path) -> None:
    f = tmp_path / "a.yaml"
    f.write_bytes("\ufeffrobot: {}\n# \u00e9\n".encode("utf-8"))
    assert read_text(f, Refused, 100) == "robot: {}\n# \u00e9\n"


def test_a_file_over_the_limit_is_refused_naming_the_setting(tmp_path: Path) -> None:
    f = tmp_path / "big.csv"
    f.write_text("x" * 101)
    with pytest.raises(Refused, match=r"big\.csv: larger than 100 bytes \(paths\.max_file_bytes\)"):
        read_text(f, Refused, 100, "paths.max_file_bytes")
    with pytest.raises(Refused, match=r"big\.csv: 101 bytes, more than paths\.max_file_bytes = 100"):
        read_text(f, Refused, 100, "paths.max_file_bytes", regular_only=True)
    assert read_text(f, Refused, 101) == "x" * 101


def test_bytes_that_are_not_utf8_are_named_by_offset(tmp_path: Path) -> None:
    f = tmp_path / "latin.csv"
    f.write_bytes(b"x,y\n0,\xe9\n")
    with pytest.raises(Refused, match=r"latin\.csv: not UTF-8 text: byte 6 \(0xe9\)"):
        read_text(f, Refused, 100)


@pytest.mark.parametrize("kind", ["fifo", "directory", "missing"])
def test_regular_only_refuses_what_would_block_or_is_no_file_unread(tmp_path: Path, kind: str) -> None:
    f = tmp_path / "p.csv"
    if kind == "fifo":
        os.mkfifo(f)  # nobody writes it: an open for reading would block for ever
    elif kind == "directory":
        f.mkdir()
    expect = {"fifo": "is a FIFO: a path is read from a regular file only",
              "directory": "is a directory: a path is read from a regular file only",
              "missing": "cannot read: No such file or directory"}[kind]
    with pytest.raises(Refused, match=expect):
        read_text(f, Refused, 100, regular_only=True, what="a path")
    with pytest.raises(Refused, match=expect):
        check_regular_file(f, 100, Refused, what="a path")


def test_a_config_may_be_a_pipe_that_is_written(tmp_path: Path) -> None:
    # `ddrt run <(...)`: without regular_only a FIFO is read like a file once someone writes it.
    f = tmp_path / "cfg.yaml"
    os.mkfifo(f)
    writer = threading.Thread(target=lambda: f.write_text("robot: {}\n"))
    writer.start()
    try:
        assert read_text(f, Refused, 100) == "robot: {}\n"
    finally:
        writer.join(timeout=10)


def test_a_state_file_that_is_a_fifo_is_refused_not_waited_for(tmp_path: Path) -> None:
    f = tmp_path / "state.json"
    os.mkfifo(f)
    with pytest.raises(ValueError, match="is a FIFO: a state file is read from a regular file only"):
        read_state_text(f, ValueError)
    with pytest.raises(StateError, match="not a commissioning state"):
        State(f, "configs/robot.yaml")
