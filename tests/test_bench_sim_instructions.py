"""bench/sim_instructions.py: the instruction count is read from valgrind's own report, the
per-tick figure is a difference of two runs, and a missing valgrind is said, not crashed on."""

from __future__ import annotations

import shutil

import pytest

from bench import sim_instructions as si

CACHEGRIND_TAIL = """==2964== 
==2964== I   refs:      3,000,430,342
"""


def test_the_count_is_cachegrinds_i_refs_line() -> None:
    assert si.parse_irefs("noise\n" + CACHEGRIND_TAIL) == 3_000_430_342


def test_no_count_is_an_error_that_shows_the_output() -> None:
    with pytest.raises(si.InstructionCountError, match="no 'I refs'"):
        si.parse_irefs("==1== valgrind: failed to start tool 'cachegrind'")


def test_a_tick_costs_the_difference_over_the_extra_ticks() -> None:
    short = si.Count(ticks=400, instructions=3_000_000_000, cpu_s=0.1)
    long = si.Count(ticks=4400, instructions=4_200_000_000, cpu_s=0.25)
    assert si.per_tick(short, long, "instructions") == pytest.approx(300_000.0)
    assert si.per_tick(short, long, "cpu_s") == pytest.approx(37.5e-6)
    with pytest.raises(si.InstructionCountError, match="no more ticks"):
        si.per_tick(long, short, "instructions")


def test_without_valgrind_the_command_says_what_to_install(monkeypatch, capsys) -> None:
    monkeypatch.setattr(si.shutil, "which", lambda name: None)
    assert si.main(["--short", "0.05", "--long", "0.1", "--no-cpu"]) == 1
    assert "apt-get install valgrind" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("valgrind") is None, reason="valgrind is not installed (the bench's own tool)")
def test_two_counts_of_the_same_code_agree(tmp_path) -> None:
    """What makes the count worth having on a noisy machine: the same run, counted twice,
    gives the same figure to well under a percent."""
    path_file = si.figure8_path(2, tmp_path / "figure8.yaml")
    a, b = (si.run_child(si.REPO, path_file, 0.5, counted=True) for _ in range(2))
    assert a.ticks == b.ticks > 0
    assert abs(a.instructions - b.instructions) < 0.005 * a.instructions


def test_the_simulated_robots_own_loop_runs_and_counts_its_ticks(tmp_path) -> None:
    """The loop that stands for the simulator's part of a tick (no valgrind here: its output)."""
    path_file = si.figure8_path(1, tmp_path / "figure8.yaml")
    c = si.run_child(si.REPO, path_file, 0.5, counted=False, robot_only=True)
    assert c.ticks == 100 and c.instructions == 0
