"""The seed's figures for a simulated run, as PNG (matplotlib is imported only in these functions).

path.png is the one to look at first: the path, the true and the estimated pose at equal scale
(start, end, direction, cusps marked), and below (or beside) it their distance from the path in
mm over time, since at sub-millimetre error the three lines are one on the map. The title
names the run and says whether it completed and how far off it was (the metrics' RMS).
"""

from __future__ import annotations

from pathlib import Path as FsPath
from typing import TYPE_CHECKING, Any

import numpy as np

from ddrt.path.figure import legend_above, mark_route, xy_figure
from ddrt.simrun.metrics import WINDOW, TrackingAccumulator, path_polyline
from ddrt.simrun.runner import SimResult

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ["cross_track_mm", "path_figure", "path_side", "run_title", "write_plots"]


def _mm(v: float) -> str:
    return f"{v * 1000:.3g} mm"


def run_title(m: dict[str, Any], name: str = "") -> str:
    """Two lines: the run (config, path, controller) and its outcome (completion, RMS and max
    cross-track of the true and the estimated pose)."""
    head = f"{name}, {m['controller']} controller" if name else f"{m['controller']} controller"
    if m["completed"]:
        outcome = f"completed in {m['sim_duration_s']:.2f} s"
    else:
        outcome = f"NOT completed: {m['state']}{' (' + m['fault'] + ')' if m.get('fault') else ''} after {m['sim_duration_s']:.2f} s"
    return (f"{head}: {outcome}\ncross-track RMS {_mm(m['rms_cross_track_m'])} true, {_mm(m['rms_tracking_m'])} "
            f"estimated (max {_mm(m['max_cross_track_m'])}, {_mm(m['max_tracking_m'])})")


def _nearest(poly: np.ndarray, xy: np.ndarray, near: np.ndarray, reach: int,
             chunk: int = 1024) -> tuple[np.ndarray, np.ndarray]:
    """Per point, the nearest segment of `poly` within `reach` segments of `near` and the
    point's distance to it, positive left of the segment's direction (no empty segments)."""
    a, ab = poly[:-1], np.diff(poly, axis=0)
    len2 = np.einsum("ij,ij->i", ab, ab)
    offsets = np.arange(-min(reach, len(a)), min(reach, len(a)) + 1)
    seg, out = np.empty(len(xy), dtype=int), np.empty(len(xy))
    for lo in range(0, len(xy), chunk):
        p = xy[lo:lo + chunk]
        idx = np.clip(near[lo:lo + chunk, None] + offsets[None, :], 0, len(a) - 1)
        ap = p[:, None, :] - a[idx]
        t = np.clip(np.einsum("mij,mij->mi", ap, ab[idx]) / len2[idx], 0.0, 1.0)
        diff = ap - t[:, :, None] * ab[idx]
        best = np.argmin(np.einsum("mij,mij->mi", diff, diff), axis=1)
        rows = np.arange(len(p))
        k, d, w = idx[rows, best], diff[rows, best], ap[rows, best]
        side = np.where(ab[k, 0] * w[:, 1] - ab[k, 1] * w[:, 0] < 0.0, -1.0, 1.0)
        seg[lo:lo + chunk], out[lo:lo + chunk] = k, side * np.hypot(d[:, 0], d[:, 1])
    return seg, out


def path_side(poly: np.ndarray, xy: np.ndarray, near: np.ndarray, dist: np.ndarray, window: int = WINDOW,
              coarse: int = 10) -> np.ndarray:
    """+1 where a point lies left of the polyline's direction of travel, -1 right: the side of
    its nearest segment within `window` segments of `near`, where `dist` (its distance, as the
    metrics measure it) is, so a robot far from its progress (a stalled run) does not flip
    sign on a stray tangent. Searched near `near` first; a point whose distance is not found
    there is searched on every `coarse`-th point of the window, then finely around that."""
    keep = np.ones(len(poly), dtype=bool)
    keep[1:] = np.any(np.diff(poly, axis=0) != 0.0, axis=1)  # a turn in place: one point, no empty segments
    pts = poly[keep]
    if len(pts) < 2:
        return np.ones(len(xy))
    near = np.cumsum(keep)[np.asarray(near, dtype=int)] - 1
    _, sd = _nearest(pts, xy, near, coarse)
    far = np.abs(sd) > dist * (1.0 + 1e-9) + 1e-12
    if far.any():
        sparse = np.vstack([pts[::coarse], pts[-1:]]) if (len(pts) - 1) % coarse else pts[::coarse]
        seg, _ = _nearest(sparse, xy[far], near[far] // coarse, max(1, window // coarse))
        sd[far] = _nearest(pts, xy[far], seg * coarse + coarse // 2, 2 * coarse)[1]
    return np.where(sd < 0.0, -1.0, 1.0)


def cross_track_mm(result: SimResult) -> tuple[np.ndarray, np.ndarray]:
    """Signed cross-track (mm, left of the direction of travel positive) of the true and the
    estimated pose per tick: the metrics' own distances, so the panel's RMS is the title's,
    on the side `path_side` finds."""
    c = result.column
    acc = TrackingAccumulator(result.path)
    h = result.path.length / (len(acc.poly) - 1) if result.path.length > 0.0 else 1.0
    sigma = c("sigma")
    near = np.clip(np.round(sigma / h).astype(int), 0, len(acc.poly) - 2)
    out = []
    for x, y in (("x", "y"), ("x_est", "y_est")):
        xy = np.column_stack([c(x), c(y)])
        d = acc.distances(xy, sigma)
        out.append(path_side(acc.poly, xy, near, d) * d * 1000.0)
    return out[0], out[1]


def path_figure(result: SimResult, name: str = "") -> Figure:
    """path.png's figure: the map and the error over time, titled with the run's outcome."""
    c = result.column
    path = result.path
    poly = path_polyline(path)
    true = np.column_stack([c("x"), c("y")])
    est = np.column_stack([c("x_est"), c("y_est")])
    fig, ax, ax_err = xy_figure(np.vstack([poly, true, est]), run_title(result.metrics, name))
    ax.plot(poly[:, 0], poly[:, 1], "-", lw=5, color="0.82", solid_capstyle="round", label="path", zorder=1)
    ax.plot(true[:, 0], true[:, 1], "-", lw=1.3, color="tab:blue", label="robot (true)", zorder=3)
    ax.plot(est[:, 0], est[:, 1], "--", lw=1.0, color="tab:orange", label="estimate", zorder=4)
    cusps = [(p.x, p.y) for p in (path.at(s) for s in path.cusps)]
    a = path.arrays()
    s = np.linspace(0.0, path.length, len(poly))  # path_polyline's own spacing
    i = np.clip(np.searchsorted(a["sigma"], s, side="right") - 1, 0, len(a["direction"]) - 1)
    mark_route(ax, poly, cusps, a["direction"][i] < 0.0)
    legend_above(ax)
    t = c("t")
    e_true, e_est = cross_track_mm(result)
    ax_err.axhline(0.0, color="0.6", lw=0.8)
    ax_err.plot(t, e_true, "-", lw=1.2, color="tab:blue", label="true pose")
    ax_err.plot(t, e_est, "--", lw=1.0, color="tab:orange", label="estimated pose")
    ax_err.set_xlabel("t (s)")
    ax_err.set_ylabel("cross-track (mm), left +")
    both = np.abs(np.concatenate([e_true, e_est]))
    typical = float(np.nanpercentile(both, 90)) if len(both) else 0.0
    if typical > 0.0 and np.nanmax(both) > 20.0 * typical:
        # A start far off the path (or one excursion) would flatten the rest of the run to a line.
        ax_err.set_yscale("symlog", linthresh=2.0 * typical, linscale=2.0)
        ax_err.set_ylabel(f"cross-track (mm), left +\n(linear within {2.0 * typical:.2g} mm, log beyond)")
    if len(t) > 1:
        ax_err.set_xlim(t[0], t[-1])
    legend_above(ax_err)
    return fig


def write_plots(result: SimResult, out_dir: str | FsPath, name: str = "") -> list[FsPath]:
    """path.png, velocities.png, position_errors.png, velocity_errors.png, torques.png.
    `name`: the run's config and path, for the titles."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    out = FsPath(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    c = result.column
    t = c("t")
    written = []
    head = run_title(result.metrics, name).split("\n")[0]

    def save(fig: Figure, fname: str) -> None:
        p = out / fname
        fig.savefig(p, dpi=110)
        written.append(p)

    def panels(rows: int, size: tuple[float, float]) -> tuple[Figure, list]:
        fig = Figure(figsize=size, layout="constrained")
        fig.suptitle(head, fontsize=9)
        return fig, list(np.atleast_1d(fig.subplots(rows, 1, sharex=True)))

    save(path_figure(result, name), "path.png")

    fig, (a1, a2) = panels(2, (7, 5))
    a1.plot(t, c("v_ref"), label="v_ref")
    a1.plot(t, c("v"), label="v (true)")
    a1.set_ylabel("v (m/s)")
    a1.legend()
    a2.plot(t, c("omega_ref"), label="omega_ref")
    a2.plot(t, c("omega"), label="omega (true)")
    a2.set_ylabel("omega (rad/s)")
    a2.set_xlabel("t (s)")
    a2.legend()
    save(fig, "velocities.png")

    fig, (ax,) = panels(1, (7, 4))
    ax.plot(t, (c("x_est") - c("x")) * 1000, label="x_est - x")
    ax.plot(t, (c("y_est") - c("y")) * 1000, label="y_est - y")
    ax.plot(t, c("cross_track_est") * 1000, label="cross-track (estimated pose)")
    ax.set_ylabel("mm")
    ax.set_xlabel("t (s)")
    ax.legend()
    save(fig, "position_errors.png")

    fig, (a1, a2) = panels(2, (7, 5))
    a1.plot(t, (c("v_cmd") - c("v")) * 1000)
    a1.set_ylabel("v_cmd - v (mm/s)")
    a2.plot(t, np.degrees(c("omega_cmd") - c("omega")))
    a2.set_ylabel("omega_cmd - omega (deg/s)")
    a2.set_xlabel("t (s)")
    save(fig, "velocity_errors.png")

    fig, (ax,) = panels(1, (7, 4))
    ax.plot(t, c("tau_l"), label="tau_L")
    ax.plot(t, c("tau_r"), label="tau_R")
    ax.set_ylabel("wheel torque (N m)")
    ax.set_xlabel("t (s)")
    ax.legend()
    save(fig, "torques.png")
    return written
