"""The figures: path.png says what happened at one look, path_report.png
gives a thin path the room its aspect needs, legends sit outside the data.

The runs here are made up (the path's own points, shifted sideways), so the figures are
checked against numbers known exactly and no simulation runs."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path as FsPath

import numpy as np
import pytest

pytest.importorskip("matplotlib")

from ddrt.path import load_path  # noqa: E402
from ddrt.path.report import path_report, report_figure  # noqa: E402
from ddrt.path.sampled import Path  # noqa: E402
from ddrt.simrun.metrics import path_polyline, tracking_metrics  # noqa: E402
from ddrt.simrun.plots import cross_track_mm, path_figure, run_title, write_plots  # noqa: E402
from ddrt.simrun.runner import SIM_COLUMNS, SimResult  # noqa: E402

THREE_POINT = "x,y,v\n0,0,0.3\n0.6,0,0.3\n0.3,0.3,-0.25\n0.9,0.45,0.3\n"


def _thin(tmp_path: FsPath, tall: bool = False) -> Path:
    """A 10 m x 0.2 m lane change (or the same standing up)."""
    x = np.linspace(0.0, 10.0, 201)
    y = 0.1 * (1.0 - np.cos(np.pi * x / 10.0))
    pts = np.column_stack([y, x] if tall else [x, y])
    f = tmp_path / ("tall.csv" if tall else "thin.csv")
    f.write_text("x,y\n" + "".join(f"{a:.5f},{b:.5f}\n" for a, b in pts))
    return load_path(f)


def _run(path: Path, left_m: float = 0.002, completed: bool = True, n: int = 600) -> SimResult:
    """A run that drives the path `left_m` to its left (the estimate half as far)."""
    s = np.linspace(0.0, path.length, n)
    poly = path_polyline(path)
    i = np.clip(np.round(s / path.length * (len(poly) - 1)).astype(int), 1, len(poly) - 2)
    tan = poly[np.minimum(i + 5, len(poly) - 1)] - poly[i - 1]
    normal = np.column_stack([-tan[:, 1], tan[:, 0]]) / np.maximum(np.hypot(tan[:, 0], tan[:, 1]), 1e-12)[:, None]
    true, est = poly[i] + left_m * normal, poly[i] + 0.5 * left_m * normal
    rows = np.zeros((n, len(SIM_COLUMNS)))
    col = SIM_COLUMNS.index
    rows[:, col("t")] = np.linspace(0.0, 5.0, n)
    rows[:, col("x")], rows[:, col("y")] = true.T
    rows[:, col("x_est")], rows[:, col("y_est")] = est.T
    rows[:, col("sigma")] = s
    m = tracking_metrics(path, true, est, np.zeros(n), np.zeros(n), s)
    m.update(controller="dynamic", completed=completed, state="stopped" if completed else "following",
             fault="", sim_duration_s=5.0)
    return SimResult(metrics=m, path=path, table=rows)


def _drawn(fig):
    """The figure laid out and drawn, as savefig would (constrained layout runs at draw)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig).draw()
    return fig


def _box(artist, fig):
    return artist.get_window_extent(fig.canvas.get_renderer())


def _overlap(a, b) -> bool:
    return a.x0 < b.x1 and b.x0 < a.x1 and a.y0 < b.y1 and b.y0 < a.y1


def _scale_is_equal(ax) -> bool:
    """Metres per pixel the same on both axes of the drawn panel."""
    box = ax.get_window_extent()
    (x0, x1), (y0, y1) = ax.get_xlim(), ax.get_ylim()
    return abs((x1 - x0) / box.width / ((y1 - y0) / box.height) - 1.0) < 0.02


def test_path_png_has_the_map_and_the_error_panel_and_a_title_with_the_outcome(tmp_path) -> None:
    path = load_path({"shape": "figure_eight", "size": 1.2, "speed": 0.3})
    r = _run(path)
    fig = path_figure(r, "sim.yaml: figure8_slow.yaml")
    ax_xy, ax_err = fig.axes[:2]
    title = fig.get_suptitle()
    m = r.metrics
    for v in (m["rms_cross_track_m"], m["rms_tracking_m"], m["max_cross_track_m"]):
        assert f"{v * 1000:.3g} mm" in title
    assert "sim.yaml: figure8_slow.yaml" in title and "completed" in title and "NOT" not in title
    assert title == run_title(m, "sim.yaml: figure8_slow.yaml")
    assert "NOT completed" in run_title(_run(path, completed=False).metrics)
    # The error panel: the run is 2 mm left (+) of the path, its estimate 1 mm.
    lines = {ln.get_label(): np.asarray(ln.get_ydata()) for ln in ax_err.get_lines()}
    assert np.allclose(lines["true pose"], 2.0, atol=0.01) and np.allclose(lines["estimated pose"], 1.0, atol=0.01)
    assert "mm" in ax_err.get_ylabel()
    e_true, _ = cross_track_mm(_run(path, left_m=-0.003))
    assert np.allclose(e_true, -3.0, atol=0.01)  # right of the path: negative
    labels = [t.get_text() for t in ax_xy.get_legend().get_texts()]
    assert {"path", "robot (true)", "estimate", "start", "end", "direction"} <= set(labels)
    # The start marker is the path's first point.
    start = next(ln for ln in ax_xy.get_lines() if ln.get_label() == "start")
    p0 = path.at(0.0)
    assert np.allclose(np.ravel(start.get_xydata()), [p0.x, p0.y])


def test_a_start_far_off_the_path_does_not_flatten_the_rest_of_the_error_panel() -> None:
    path = load_path({"shape": "circle", "radius": 0.5, "speed": 0.3})
    assert path_figure(_run(path)).axes[1].get_yscale() == "linear"
    r = _run(path)
    r.table[:20, SIM_COLUMNS.index("y")] -= 0.05  # the first ticks 50 mm off, the rest 2 mm
    ax_err = path_figure(r).axes[1]
    assert ax_err.get_yscale() == "symlog" and "log beyond" in ax_err.get_ylabel()


def test_the_legends_keep_off_the_data_and_the_title(tmp_path) -> None:
    path = load_path({"shape": "figure_eight", "size": 1.2, "speed": 0.3})
    fig = _drawn(path_figure(_run(path)))
    ax_xy = fig.axes[0]
    legend = _box(ax_xy.get_legend(), fig)
    assert not _overlap(legend, ax_xy.get_window_extent())  # the crossing at the centre stays in view
    assert not _overlap(legend, fig._suptitle.get_window_extent())
    rep_fig = _drawn(report_figure(path, path_report(path, "figure8.yaml")))
    for ax in rep_fig.axes[:2]:
        box = _box(ax.get_legend(), rep_fig)
        assert not _overlap(box, ax.get_window_extent())
        assert not _overlap(box, rep_fig._suptitle.get_window_extent())


@pytest.mark.parametrize("tall", [False, True])
def test_a_thin_path_gets_an_equal_scale_panel_that_is_not_squashed(tmp_path, tall) -> None:
    path = _thin(tmp_path, tall)
    for fig in (report_figure(path, path_report(path, "thin.csv")), path_figure(_run(path))):
        ax = _drawn(fig).axes[0]
        assert _scale_is_equal(ax)
        box = ax.get_window_extent()
        w, h = box.width / fig.bbox.width, box.height / fig.bbox.height
        along, across = (h, w) if tall else (w, h)
        assert along > 0.55 and across > 0.15, (w, h)
        # The data fill the panel along the path: no blank band at either end.
        lim = ax.get_ylim() if tall else ax.get_xlim()
        assert lim[1] - lim[0] < 1.3 * 10.0


def test_a_reversing_path_shows_its_cusps_and_the_stretch_driven_backwards(tmp_path) -> None:
    f = tmp_path / "three_point.csv"
    f.write_text(THREE_POINT)
    path = load_path(f)
    assert len(path.cusps) == 2
    for fig in (report_figure(path, path_report(path, str(f))), path_figure(_run(path))):
        ax = fig.axes[0]
        lines = {ln.get_label(): ln for ln in ax.get_lines()}
        cusps = np.asarray(lines["cusp (reverses)"].get_xydata())
        want = [(p.x, p.y) for p in (path.at(s) for s in path.cusps)]
        assert np.allclose(cusps, want, atol=1e-6)
        back = np.asarray(lines["driven backwards"].get_xydata())
        back = back[np.all(np.isfinite(back), axis=1)]
        assert len(back) and np.all(back[:, 1] >= -1e-9) and np.all(back[:, 1] <= 0.3 + 1e-6)  # the middle leg


def test_write_plots_writes_the_five_figures(tmp_path) -> None:
    path = load_path({"shape": "circle", "radius": 0.3, "speed": 0.3})
    written = write_plots(_run(path), tmp_path, name="sim.yaml")
    assert sorted(p.name for p in written) == sorted(
        ["path.png", "velocities.png", "position_errors.png", "velocity_errors.png", "torques.png"])
    assert all(p.stat().st_size > 10_000 for p in written)


def test_the_figure_modules_do_not_import_matplotlib() -> None:
    code = ("import sys, ddrt.path.figure, ddrt.path.report, ddrt.simrun.plots; "
            "sys.exit('matplotlib' in sys.modules)")
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0


def test_the_title_names_the_config_and_its_path() -> None:
    from ddrt.cli import _run_name

    assert _run_name("configs/sim.yaml", "/r/configs/paths/figure8_slow.yaml") == "sim.yaml: figure8_slow.yaml"
    assert _run_name("configs/scenarios/s_curve.yaml", "/r/configs/paths/s_curve.yaml") == "s_curve.yaml"
    assert _run_name("circle_fast.yaml", {"shape": "circle", "radius": 0.5}) == "circle_fast.yaml: inline circle"
