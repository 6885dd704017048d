"""What a new user reads in the first hour says what it means: the summary's wall time and
real-time factor, the progress line in a log, `ddrt path`'s length, the command line's help."""

from __future__ import annotations

import io
import re
import subprocess
import sys
from pathlib import Path

import pytest

from ddrt.cli import main
from ddrt.simrun.progress import StderrProgress
from ddrt.simrun.runner import summary_text
from tests.support.repo import REPO, SIM_YAML

METRICS = {"controller": "outer", "completed": True, "state": "stopped", "fault": None, "sim_duration_s": 12.65,
           "ticks": 2530, "wall_s": 0.27, "realtime_factor": 51.0, "rms_cross_track_m": 1e-4,
           "max_cross_track_m": 2e-4, "rms_tracking_m": 1e-4, "max_tracking_m": 2e-4, "rms_heading_err_rad": 0.01,
           "final_pos_err_m": 1e-3, "saturated_fraction": 0.0}


# ---------------------------------------------------------------------------------------------
# The summary's wall time


def test_the_summary_says_which_wall_time_the_real_time_factor_is_of() -> None:
    text = summary_text(METRICS)
    line = next(ln for ln in text.splitlines() if ln.startswith("wall time"))
    # 12.65 s / 51 = 0.248 s following; 0.27 s in all with the set-up.
    assert "0.27 s in all" in line and "0.25 s of it following the path (51x real time)" in line


def test_a_run_s_wall_time_figures_agree_with_each_other(tmp_path, capsys) -> None:
    assert main(["sim", str(SIM_YAML), "--duration", "3", "--out", str(tmp_path), "--quiet"]) == 0
    out = capsys.readouterr().out
    m = re.search(r"wall time +([\d.]+) s in all, ([\d.]+) s of it following the path \((\d+)x real time\)", out)
    assert m, out
    total, following, factor = float(m[1]), float(m[2]), int(m[3])
    sim = float(re.search(r"simulated +([\d.]+) s", out)[1])
    assert following <= total
    # The figures are printed rounded (0.01 s, 0.01 s, 1x): the factor is sim / following for
    # some following within half a hundredth of the printed one.
    sim_low, sim_high = sim - 0.005, sim + 0.005
    assert sim_low / (following + 0.005) - 0.5 <= factor <= sim_high / max(following - 0.005, 1e-9) + 0.5


# ---------------------------------------------------------------------------------------------
# Progress


class _Tty(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_progress_off_a_terminal_is_whole_lines_of_the_expected_time() -> None:
    out = io.StringIO()
    p = StderrProgress(out)
    for t in range(0, 30, 1):  # a path of 12.65 s (its run limited to 29 s)
        p(float(t), 12.65)
    p.end()
    text = out.getvalue()
    assert "\r" not in text and text.endswith("\n")
    lines = text.splitlines()
    assert 10 <= len(lines) <= 25  # one a tenth of the run, not one a call
    assert all(ln.endswith("of 12.7 s") and "at most" not in ln for ln in lines)


def test_progress_on_a_terminal_rewrites_one_line_and_ends_it() -> None:
    out = _Tty()
    p = StderrProgress(out)
    p(0.0, 5.0)
    p(2.5, 5.0)
    assert out.getvalue().count("\r") == 2 and "\n" not in out.getvalue()
    p.end()
    p.end()
    assert out.getvalue().endswith("of 5.0 s\n") and out.getvalue().count("\n") == 1


def test_ddrt_sim_into_a_log_writes_lines_that_end(tmp_path) -> None:
    r = subprocess.run([sys.executable, "-m", "ddrt.cli", "sim", str(SIM_YAML), "--duration", "12", "--out",
                        str(tmp_path)], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    progress = [ln for ln in r.stderr.splitlines() if "simulated" in ln]
    assert "\r" not in r.stderr and r.stderr.endswith("\n")
    assert progress and all(ln.endswith("of 12.0 s") for ln in progress)


# ---------------------------------------------------------------------------------------------
# The command line's help


def test_ddrt_version_is_the_package_s(capsys) -> None:
    import tomllib

    from ddrt import __version__

    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"ddrt {__version__}"
    assert tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["version"] == __version__


def test_ddrt_ctl_help_lists_every_command_with_what_it_does(capsys) -> None:
    from ddrt.service.commands import COMMANDS, DECLARED, STREAMS, ctl_commands

    offered = [c for c in COMMANDS if c not in STREAMS and c != "pose_fix"]
    assert ctl_commands() == offered
    with pytest.raises(SystemExit):
        main(["ctl", "-h"])
    text = capsys.readouterr().out
    listed = text[text.index("commands:"):].splitlines()[1:]
    assert [ln.split()[0] for ln in listed] == offered
    assert all(DECLARED[ln.split()[0]].help in ln for ln in listed)  # a name and what it does


# ---------------------------------------------------------------------------------------------
# ddrt path: turns in place have no length


def _two_pivots(tmp_path):
    from ddrt.path import load_path

    f = tmp_path / "pivots.csv"
    f.write_text("x,y\n0,0\n1,0\n1,1\n2,1\n")  # 3 m with two 90 degree turns in place
    return load_path(f), str(f)


def test_ddrt_path_reports_the_driven_length_without_the_turns_in_place(tmp_path) -> None:
    from ddrt.path.report import path_report, report_text

    path, name = _two_pivots(tmp_path)
    assert path.length > 3.2  # progress counts pivot_radius a radian of turning
    r = path_report(path, name)
    assert r.driven_m == pytest.approx(3.0, abs=1e-9)
    text = report_text(r)
    assert "length        3.000 m driven and 2 turns in place (180 deg)" in text
    assert f"mean speed {3.0 / r.duration_s:.3f} m/s" in text
    assert sum(r.share_length.values()) == pytest.approx(1.0) and r.share_length["pivot omega"] == 0.0
    assert r.share_time["pivot omega"] > 0.0


def test_path_report_png_shows_no_speed_in_a_turn_in_place_and_every_cap_in_its_own_colour(tmp_path) -> None:
    import matplotlib
    import numpy as np
    from matplotlib.colors import to_rgb

    from ddrt.path import load_path
    from ddrt.path.report import CAP_STYLE, path_report, pivot_runs, report_figure

    matplotlib.use("Agg")
    path, name = _two_pivots(tmp_path)
    ax1 = report_figure(path, path_report(path, name)).axes[1]
    profile = next(ln for ln in ax1.get_lines() if ln.get_label().startswith("profile"))
    s, u = (np.asarray(v, dtype=float) for v in profile.get_data())
    for i0, i1 in pivot_runs(path):  # inside each turn: no speed drawn (it was pivot_radius x omega)
        assert np.all(np.isnan(u[i0 + 1:i1]))
    assert any(p.get_label() == "turn in place" for p in ax1.patches)
    # A path with a point cap: drawn above the profile.
    f = tmp_path / "caps.csv"
    f.write_text("x,y,v\n0,0,1\n1,0,0.3\n1.5,0.4,1\n")
    capped = load_path(f)
    ax1 = report_figure(capped, path_report(capped, str(f))).axes[1]
    lines = {ln.get_label(): ln for ln in ax1.get_lines()}
    assert lines["point cap"].get_zorder() > lines["profile (speed)"].get_zorder()
    colours = [to_rgb(style["color"]) for style in CAP_STYLE.values()]
    for i, a in enumerate(colours):
        for b in colours[i + 1:]:
            assert sum(abs(x - y) for x, y in zip(a, b)) > 0.3  # omega and pivot omega were two blues


# ---------------------------------------------------------------------------------------------
# The commissioning report


def test_the_commissioning_report_lists_its_steps_flags_what_it_cannot_separate_and_labels_its_figures(
        tmp_path, monkeypatch) -> None:
    """configs/sim-minimal.yaml's plant has d_yc 0 and two motors that differ: the run reads
    the difference as a lateral offset, which the report must not present as measured."""
    import matplotlib
    from matplotlib.colors import to_rgb
    from matplotlib.figure import Figure

    from ddrt.commission import commission, paths_for, session_for
    from ddrt.commission.session import STEPS, Options

    matplotlib.use("Agg")
    saved: dict[str, Figure] = {}
    savefig = Figure.savefig

    def keep(fig: Figure, fname, *args, **kw):
        saved[Path(fname).name] = fig
        return savefig(fig, fname, *args, **kw)

    monkeypatch.setattr(Figure, "savefig", keep)
    out = tmp_path / "robot.yaml"
    session = session_for(REPO / "configs" / "sim-minimal.yaml", Options(out=out, from_sim_truth=True), yes=True,
                          out=io.StringIO())
    commission(session)
    report = (paths_for(out)[1] / "report.md").read_text()
    listed = [ln[2:].split(":")[0] for ln in report.splitlines() if ln.startswith("- ")]
    assert listed[:7] == [*STEPS, "check"]
    rows = {ln.split("|")[1].strip(): ln for ln in report.splitlines() if ln.startswith("| ")}
    assert "(not separated)" in rows["d_yc"] and "Not separated by this run: d_yc" in report
    for key in ("m_p", "d_xc", "I_p"):
        assert "x the residual" in rows[key] and "(not separated)" not in rows[key], rows[key]
    # check.png: against time, the reference, estimate and truth in colours far apart
    track, error = saved["check.png"].axes
    assert "time" in error.get_xlabel() and "(s)" in error.get_xlabel()
    t = error.get_lines()[0].get_xdata()
    assert t[-1] == pytest.approx(session.state.get("result")["check"]["path_s"], abs=3.0)
    colours = [to_rgb(ln.get_color()) for ln in track.get_lines()]
    assert len(colours) == 3
    for i, a in enumerate(colours):
        for b in colours[i + 1:]:
            assert sum(abs(x - y) for x, y in zip(a, b)) > 0.5
    # wiring.png: one quantity an axis, each labelled with its unit
    labels = [ax.get_ylabel() for ax in saved["wiring.png"].axes]
    assert sorted(labels) == sorted(["duty (%)", "encoder (mm)", "gyro (deg)"] * 2)


# ---------------------------------------------------------------------------------------------
# The docs name commands as the command line does


def test_every_command_the_docs_show_is_one_ddrt_has() -> None:
    """`ddrt X ...` in a code span or block of README.md and docs/*.md names a subcommand (and
    for ctl, calibrate and bag, one of theirs); no doc writes `python -m ddrt.cli`."""
    import argparse

    from ddrt.cli import build_parser

    def choices(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
        return next(a.choices for a in parser._actions if isinstance(a, argparse._SubParsersAction))

    top = choices(build_parser())
    nested = {"calibrate": set(choices(top["calibrate"])), "bag": set(choices(top["bag"])),
              "ctl": set(next(a.choices for a in top["ctl"]._actions if a.dest == "command_name"))}
    pattern = re.compile(r"(?:`|^ {4,}(?:\$ )?)(?:[\w./-]*/)?ddrt ([a-z][\w-]*)(?: (?:--?[\w-]+(?: [\w./]+)? )*([a-z]\w*))?",
                         re.M)
    wrong, seen = [], 0
    for doc in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]:
        text = doc.read_text(encoding="utf-8")
        assert "python -m ddrt.cli" not in text, doc.name
        for m in pattern.finditer(text):
            seen += 1
            if m[1] not in top:
                wrong.append(f"{doc.name}: ddrt {m[1]}")
            elif m[1] in nested and m[2] is not None and m[2] not in nested[m[1]]:
                wrong.append(f"{doc.name}: ddrt {m[1]} {m[2]}")
    assert seen > 50 and not wrong, wrong


def test_calibrate_identify_says_which_terms_the_run_cannot_separate() -> None:
    """A term no larger than a few times the residual is flagged, however small its formal
    standard error (here, mbar's 0.00012 kg m: the figures of configs/sim-minimal.yaml)."""
    from ddrt import calibrate as cal
    from ddrt.config import load_config

    values = {"m_k": 4.54442, "mbar": -0.01735, "I": 0.05028, "m_x": 0.09203, "fric_l": 0.01069, "fric_r": -0.00432}
    effect = {"m_k": 1.562, "mbar": 0.0663, "I": 0.982, "m_x": 0.653, "fric_l": 0.213, "fric_r": 0.0861}
    res = cal.IdentifyResult(values=values, std_err={k: 1e-4 for k in values}, r2=0.9996, residual_rms_n=0.041,
                             rows=8418, duration_s=21.8, area=(2.0, 1.5), effect_n=effect)
    assert res.seen("mbar") == pytest.approx(0.0663 / 0.041)
    text = cal.identify_fragment(load_config(REPO / "configs" / "sim-minimal.yaml"), res)
    flagged = {ln.split()[1] for ln in text.splitlines() if ln.endswith("not separated from what the model leaves out")}
    assert flagged == {"mbar", "fric_r"}
