"""The x/y panel that `ddrt path --plot` and `ddrt sim --plot` share (matplotlib is imported
only inside these functions, so the package runs without it).

A path is drawn at equal scale. In a fixed figure a thin path (10 m x 0.2 m) is then a sliver
between blank bands, so the layout follows the extent of what is drawn: a wide path gets a
wide, short x/y panel above the second panel, a tall one a narrow panel beside it. Each panel
keeps the box it was given and its data limits grow to fill it (adjustable="datalim"), so the
scale stays equal and the box is never squashed. Legends go above their axes, outside the
data (a figure-eight's crossing is never hidden); the title is the figure's, above them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Sequence

import numpy as np

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = ["legend_above", "mark_route", "xy_figure"]

TALL = 1.25  # extent height / width above which the x/y panel goes beside the other panel
XY_MIN, XY_MAX = 2.4, 5.5  # the x/y panel's short side, clamped (inches)
SPAN = 7.5  # the panels' long side (inches)
OTHER = 2.8  # the other panel's short side (inches)
EXTRA = 1.6  # title, legends and labels (inches)


def xy_figure(points: np.ndarray, title: str) -> tuple[Figure, Axes, Axes]:
    """A constrained-layout figure with an equal-scale x/y panel sized for the (N, 2) `points`
    it will show, and a second panel: below it for a wide extent, beside it for a tall one."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    w, h = np.ptp(pts, axis=0) if len(pts) else (1.0, 1.0)
    aspect = max(h, 1e-3) / max(w, 1e-3)
    if aspect <= TALL:
        xy_h = min(max(SPAN * aspect, XY_MIN), XY_MAX)
        fig = Figure(figsize=(SPAN + 1.0, xy_h + OTHER + EXTRA), layout="constrained")
        gs = fig.add_gridspec(2, 1, height_ratios=[xy_h, OTHER])
        ax_xy, ax_other = fig.add_subplot(gs[0, 0]), fig.add_subplot(gs[1, 0])
    else:
        xy_w = min(max(SPAN / aspect, XY_MIN), XY_MAX)
        fig = Figure(figsize=(xy_w + SPAN + 1.5, SPAN * 0.8 + EXTRA), layout="constrained")
        gs = fig.add_gridspec(1, 2, width_ratios=[xy_w, SPAN])
        ax_xy, ax_other = fig.add_subplot(gs[0, 0]), fig.add_subplot(gs[0, 1])
    ax_xy.set_aspect("equal", adjustable="datalim")
    ax_xy.set_xlabel("x (m)")
    ax_xy.set_ylabel("y (m)")
    fig.suptitle(title, fontsize=10)
    return fig, ax_xy, ax_other


def mark_route(ax: Axes, xy: np.ndarray, cusps: Sequence[tuple[float, float]] = (),
               backwards: np.ndarray | None = None, arrows: int = 8) -> None:
    """Start and end markers, arrows the way the route is driven, its cusps and the stretches
    driven backwards, so one look says where a run begins and which way it goes. `xy`: the
    route's points in order; `backwards`: per point, whether it lies on a reversing stretch."""
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    if backwards is not None and np.any(backwards):
        ax.plot(*np.where(np.asarray(backwards)[:, None], xy, np.nan).T, "-", lw=7, color="tab:purple",
                alpha=0.25, solid_capstyle="butt", zorder=2, label="driven backwards")
    ax.plot(*xy[0], "o", ms=8, mfc="tab:green", mec="black", zorder=7, label="start")
    ax.plot(*xy[-1], "s", ms=8, mfc="none", mec="tab:red", mew=1.5, zorder=6, label="end")
    if len(cusps):
        c = np.asarray(cusps, dtype=float).reshape(-1, 2)
        ax.plot(c[:, 0], c[:, 1], "X", ms=9, mfc="tab:purple", mec="white", zorder=6, label="cusp (reverses)")
    d = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
    if d[-1] <= 0.0:
        return
    at = (np.arange(arrows) + 0.5) / arrows * d[-1]  # midway between ends: clear of the start
    step = 0.01 * d[-1]
    p = np.column_stack([np.interp(at, d, xy[:, k]) for k in (0, 1)])
    ahead = np.column_stack([np.interp(at + step, d, xy[:, k]) for k in (0, 1)])
    behind = np.column_stack([np.interp(at - step, d, xy[:, k]) for k in (0, 1)])
    u = ahead - behind
    n = np.hypot(u[:, 0], u[:, 1])
    ok = n > 0.0
    if ok.any():  # fixed-size arrows (inches), pointing along the data (equal scale)
        ax.quiver(p[ok, 0], p[ok, 1], u[ok, 0] / n[ok], u[ok, 1] / n[ok], angles="xy", pivot="mid",
                  units="inches", scale_units="inches", scale=3.5, width=0.025, headwidth=4,
                  headlength=4, headaxislength=3.5, color="black", zorder=6)
        ax.plot([], [], ls="none", marker=r"$\rightarrow$", ms=14, color="black", label="direction")  # legend entry


def legend_above(ax: Axes) -> None:
    """The axes' legend in rows above them, outside the data (as many columns as their width holds)."""
    handles, labels = ax.get_legend_handles_labels()
    if handles:
        width_in = ax.get_position().width * ax.figure.get_figwidth()
        ncol = min(len(handles), max(2, int(width_in / 1.25)))
        ax.legend(handles, labels, loc="lower center", bbox_to_anchor=(0.5, 1.0), ncol=ncol,
                  fontsize=8, frameon=False, borderaxespad=0.3)
