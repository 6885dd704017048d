"""`ddrt path FILE`: what a path file becomes before the robot drives it.

Length, duration, curvature, corners, how the points were read (waypoints, samples of a
curve, a grid plan: ddrt/path/condition.py), the reference's largest deviation from them, and
which limit sets the speed where. The profile (ddrt/path/profile.py) caps the progress rate
per sample, then limits it by acceleration and braking; this module takes the same caps
from the same function (`cap_terms`) and names, per sample, the one that binds:

  speed        the path's speed (its own `speed:` or limits.v_max)
  point cap    a waypoint's or a CSV row's `v`, or a grid plan's turn speed (ddrt/path/turnspeed.py)
  lateral      lateral acceleration: v^2 |kappa| <= limits.lateral_accel
  omega        yaw rate: v |kappa| <= limits.omega_max
  curv. rate   yaw acceleration from the change of curvature: v^2 |dkappa/ds| <= alpha_max / 2
  pivot omega  a turn in place at pivot_radius x omega_max
  accel        speeding up at the acceleration limit (min(accel, alpha_max / (2 |kappa|)))
  decel        braking at the deceleration limit (for the next cap, a pivot or the end)
  rest         standing: the ends and both sides of a turn in place
  motors: speed    the motors' torque envelope (ddrt/core/envelope.py) at a steady rate:
                   what the wheels' motors give at that speed, within limits.feedback_headroom
  motors: accel    speeding up as hard as the motors give
  motors: braking  braking as hard as the motors give
  other        a limit this module does not know (none today)

The motors' labels are found by elimination: the profile's bounds are the caps above and, when
the path was built for a robot, its motors' envelope; a sample that none of the config's limits
explains is held by the envelope (the profile is time-optimal, so every sample is held by
something), and the sign of its acceleration says which way.

`--plot` draws the input points against the reference, and the speed profile under its caps.
"""

from __future__ import annotations

import math
import textwrap
from dataclasses import dataclass, field
from pathlib import Path as FsPath
from typing import TYPE_CHECKING

import numpy as np

from ddrt.path.profile import CapTerms, cap_terms
from ddrt.path.sampled import Path, distances_to_polyline

if TYPE_CHECKING:
    from matplotlib.figure import Figure

__all__ = ["LABELS", "PathReport", "active_limits", "path_report", "report_figure", "report_text", "write_plot"]

LABELS = ("speed", "point cap", "lateral", "omega", "curv. rate", "pivot omega", "accel", "decel", "rest",
          "motors: speed", "motors: accel", "motors: braking", "other")
_STEADY_ACC = 1e-3  # m/s^2 (progress units): below it the rate is held, not rising or falling
_REL = 1e-6


def _terms(path: Path) -> CapTerms:
    a = path.arrays()
    return cap_terms(a["sigma"], a["kappa"], a["seg_pivot"], path.limits, path.pivot_radius)


def _caps(path: Path, terms: CapTerms | None = None) -> dict[str, np.ndarray]:
    """The per-sample caps of the profile, by name (inf where a cap does not apply)."""
    t = _terms(path) if terms is None else terms
    v_cap = path.arrays()["v_cap"]
    speed = np.full(len(v_cap), path.v_cap)
    point = np.where(v_cap < speed * (1.0 - _REL), v_cap, np.inf)
    caps = {"speed": speed, "point cap": point, "lateral": t.lateral, "omega": t.omega, "curv. rate": t.curv_rate}
    for name in caps:
        caps[name] = np.where(t.in_piv, np.inf, caps[name])
    caps["pivot omega"] = np.where(t.in_piv, path.pivot_radius * path.limits.omega_max, np.inf)
    return caps


def active_limits(path: Path) -> np.ndarray:
    """Index into LABELS of the limit that sets the speed at each sample."""
    a = path.arrays()
    lim = path.limits
    u, acc = a["u"], a["acc_u"]
    n = len(u)
    terms = _terms(path)
    caps = _caps(path, terms)
    names = list(caps)
    stack = np.vstack([caps[k] for k in names])
    static = stack.min(axis=0)
    which = np.argmin(stack, axis=0)
    out = np.full(n, LABELS.index("other"))
    at_cap = u >= static * (1.0 - 1e-6)
    out[at_cap] = [LABELS.index(names[j]) for j in which[at_cap]]
    acc_lim, dec_lim = terms.acc_lim, terms.dec_lim
    rising = np.zeros(n, dtype=bool)
    rising[1:] = acc >= acc_lim * (1.0 - 1e-3)
    falling = np.zeros(n, dtype=bool)
    falling[:-1] = acc <= -dec_lim * (1.0 - 1e-3)
    free = ~at_cap
    out[free & rising] = LABELS.index("accel")
    out[free & ~rising & falling] = LABELS.index("decel")
    if lim.envelope is not None:
        left = out == LABELS.index("other")
        after = np.zeros(n)
        after[:-1] = acc
        before = np.zeros(n)
        before[1:] = acc
        up = after > _STEADY_ACC
        down = (after < -_STEADY_ACC) | (before < -_STEADY_ACC)
        out[left & up] = LABELS.index("motors: accel")
        out[left & ~up & down] = LABELS.index("motors: braking")
        out[left & ~up & ~down] = LABELS.index("motors: speed")
    out[u <= 0.0] = LABELS.index("rest")
    return out


@dataclass
class Stretch:
    start_m: float
    end_m: float
    label: str


@dataclass
class PathReport:
    source: str
    length_m: float
    duration_s: float
    v_cap: float
    kappa_max: float
    kappa_max_at_m: float
    pivots: list[tuple[float, float, float, float]]  # (sigma, x, y, turn rad)
    blends: int
    mode: str
    summary: str
    tolerance_m: float | None
    deviation_m: float
    deviation_at: str
    corridor_m: float | None  # largest distance of the reference from the input polyline (None: not known)
    share_length: dict[str, float]
    share_time: dict[str, float]
    stretches: list[Stretch]
    labels: np.ndarray = field(repr=False)
    warnings: list[str] = field(default_factory=list)
    cusps: list[tuple[float, float, float]] = field(default_factory=list)  # (sigma, x, y) where it reverses
    reverse_m: float = 0.0  # length driven backwards
    # The length the wheels drive the robot: progress less the turns in place, which the
    # profile steps as pivot_radius of progress a radian.
    driven_m: float = 0.0


def pivot_interior(path: Path) -> np.ndarray:
    """The samples inside a turn in place (not its two ends, where the robot is at rest)."""
    piv = path.arrays()["seg_pivot"]
    inside = np.zeros(len(piv) + 1, dtype=bool)
    inside[1:-1] = piv[:-1] & piv[1:]
    return inside


def pivot_runs(path: Path) -> list[tuple[int, int]]:
    piv = path.arrays()["seg_pivot"]
    runs, start = [], None
    for i, flag in enumerate(np.append(piv, False)):
        if flag and start is None:
            start = i
        elif not flag and start is not None:
            runs.append((start, i))
            start = None
    return runs


def turn_spans(path: Path) -> list[tuple[float, float]]:
    """(start, end) progress of the turns not driven gently: the turns in place, and a grid
    plan's blended turns (taken at the profile's own yaw limits, ddrt/path/turnspeed.py)."""
    sig = path.arrays()["sigma"]
    spans = [(float(sig[i]), float(sig[j])) for i, j in pivot_runs(path)]
    c = path.conditioning
    return spans + list(c.blended) if c is not None else spans


def _corridor(path: Path) -> float | None:
    """Largest distance of the reference's samples from the input polyline (samples only;
    None where the conditioning keeps no progress of its points, as for a path joined at
    cusps, so the report does not claim a figure it did not compute)."""
    c = path.conditioning
    if c is None or c.mode == "waypoints" or len(c.points) < 2:
        return 0.0
    if c.point_sigma is None:
        return None
    a = path.arrays()
    ps = np.maximum.accumulate(np.asarray(c.point_sigma, dtype=float))
    near = np.clip(np.searchsorted(ps, a["sigma"]) - 1, 0, len(c.points) - 2)
    d = distances_to_polyline(np.asarray(c.points, dtype=float), np.column_stack((a["x"], a["y"])), near, window=12)
    return float(d.max())


def path_report(path: Path, source: str) -> PathReport:
    a = path.arrays()
    labels = active_limits(path)
    s, t = a["sigma"], a["t"]
    ds = np.where(a["seg_pivot"], 0.0, np.diff(s))  # a turn in place has no length, only time
    dt = np.diff(t)
    wl = np.zeros(len(s))
    wt = np.zeros(len(s))
    wl[:-1] += 0.5 * ds
    wl[1:] += 0.5 * ds
    wt[:-1] += 0.5 * dt
    wt[1:] += 0.5 * dt
    share_l = {name: float(wl[labels == i].sum() / max(wl.sum(), 1e-300)) for i, name in enumerate(LABELS)}
    share_t = {name: float(wt[labels == i].sum() / max(wt.sum(), 1e-300)) for i, name in enumerate(LABELS)}
    stretches: list[Stretch] = []
    change = np.flatnonzero(np.diff(labels)) + 1
    bounds = np.concatenate(([0], change, [len(labels)]))
    for i0, i1 in zip(bounds[:-1], bounds[1:]):
        stretches.append(Stretch(float(s[i0]), float(s[min(i1, len(s) - 1)]), LABELS[int(labels[i0])]))
    kap = np.where(np.append(a["seg_pivot"], False), 0.0, np.abs(a["kappa"]))
    j = int(np.argmax(kap))
    pivots = []
    for i0, i1 in pivot_runs(path):
        pivots.append((float(s[i0]), float(a["x"][i0]), float(a["y"][i0]), float(a["theta"][i1] - a["theta"][i0])))
    c = path.conditioning
    mode = "shape" if c is None else c.mode
    blends = (len(c.blended) if c.mode == "grid" else int(c.extra.get("blends", 0))) if c is not None else 0
    summary = "an analytic shape" if c is None else c.summary()
    return PathReport(
        source=source, length_m=path.length, duration_s=path.duration, v_cap=path.v_cap,
        kappa_max=float(kap[j]), kappa_max_at_m=float(s[j]), pivots=pivots, blends=blends, mode=mode, summary=summary,
        tolerance_m=None if c is None or c.mode == "waypoints" else c.tolerance_m,
        deviation_m=path.deviation_m, deviation_at="" if c is None or c.mode == "waypoints" else c.names[c.worst],
        corridor_m=_corridor(path), share_length=share_l, share_time=share_t, stretches=stretches, labels=labels,
        warnings=list(path.warnings), cusps=[(c, path.at(c).x, path.at(c).y)
                                             for c in path.cusps],
        reverse_m=float(np.sum(np.diff(s)[(a["direction"] < 0) & ~a["seg_pivot"]])), driven_m=float(ds.sum()))


def report_text(r: PathReport, max_stretches: int = 24) -> str:
    lines = [f"path          {r.source}", f"read as       {r.summary}"]
    turned = sum(abs(p[3]) for p in r.pivots)
    pivots = f" and {len(r.pivots)} turn{'s' * (len(r.pivots) != 1)} in place ({math.degrees(turned):.0f} deg)"
    lines.append(f"length        {r.driven_m:.3f} m driven{pivots if r.pivots else ''}   duration {r.duration_s:.2f} s   "
                 f"mean speed {r.driven_m / r.duration_s if r.duration_s > 0 else 0.0:.3f} m/s "
                 f"(path speed {r.v_cap:g} m/s)")
    radius = f" (radius {1.0 / r.kappa_max:.3g} m)" if r.kappa_max > 0 else ""
    lines.append(f"curvature     max {r.kappa_max:.3g} /m at {r.kappa_max_at_m:.3f} m{radius}")
    lines.append(f"corners       {len(r.pivots)} turned in place" + (f", {r.blends} blended" if r.mode in ("waypoints", "grid") else "")
                 + f"; cusps: {len(r.cusps) or 'none'}"
                 + (f" ({r.reverse_m:.3f} m driven in reverse)" if r.reverse_m > 0 else ""))
    for sig, x, y in r.cusps[:12]:
        lines.append(f"              cusp at {sig:8.3f} m ({x:.3f}, {y:.3f}): at rest, the direction reverses")
    for sig, x, y, turn in r.pivots[:12]:
        lines.append(f"              at {sig:8.3f} m ({x:.3f}, {y:.3f}): {math.degrees(turn):+.1f} deg")
    if len(r.pivots) > 12:
        lines.append(f"              ... and {len(r.pivots) - 12} more")
    if r.tolerance_m is not None:
        within = ("" if r.corridor_m is None
                  else f"; the reference lies within {r.corridor_m * 1000:.2f} mm of the input polyline")
        lines.append(f"deviation     largest {r.deviation_m * 1000:.2f} mm from the input points (at {r.deviation_at}), "
                     f"tolerance {r.tolerance_m * 1000:.1f} mm{within}")
    elif r.mode == "waypoints":
        lines.append("deviation     none: straight segments through the waypoints (corners blended or turned in place)")
    lines.append("speed set by  (share of length, of time)")
    for name in LABELS:
        if r.share_length[name] > 0.0 or r.share_time[name] > 0.0:
            lines.append(f"  {name:<16s} {100 * r.share_length[name]:6.1f} %  {100 * r.share_time[name]:6.1f} %")
    lines.append("where         (progress in m" + (", a turn in place counting pivot_radius a radian)" if r.pivots else ")"))
    shown = r.stretches
    if len(shown) > max_stretches:
        keep = sorted(sorted(range(len(shown)), key=lambda i: -(shown[i].end_m - shown[i].start_m))[:max_stretches])
        lines.append(f"  ({len(shown)} stretches; the {max_stretches} longest)")
        shown = [shown[i] for i in keep]
    for st in shown:
        lines.append(f"  {st.start_m:8.3f} - {st.end_m:8.3f}  {st.label}")
    for w in r.warnings:
        lines.append(f"warning       {w}")
    return "\n".join(lines)


# Each cap its own colour, far from the others'; the point cap above the profile (which often
# runs along it), thick and dotted. A turn in place is shaded instead of its pivot omega cap.
CAP_STYLE: dict[str, dict[str, object]] = {
    "speed": {"color": "0.55", "lw": 0.9, "ls": "--"},
    "point cap": {"color": "tab:purple", "lw": 2.2, "ls": ":", "zorder": 4},
    "lateral": {"color": "tab:green", "lw": 0.9, "ls": "--"},
    "omega": {"color": "tab:orange", "lw": 0.9, "ls": "--"},
    "curv. rate": {"color": "tab:brown", "lw": 0.9, "ls": "--"},
    "pivot omega": {"color": "tab:cyan", "lw": 0.9, "ls": "-."},  # never drawn: it lies inside the turns
}


def report_figure(path: Path, r: PathReport) -> "Figure":
    """The input against the reference at equal scale (start, direction, corners, cusps), and
    the speed profile under its caps; the layout follows the path's extent (ddrt/path/figure.py)."""
    from ddrt.path.figure import legend_above, mark_route, xy_figure

    a = path.arrays()
    c = path.conditioning
    pts = np.asarray(c.points, dtype=float).reshape(-1, 2) if c is not None else np.empty((0, 2))
    ref = np.column_stack([a["x"], a["y"]])
    head = (f"{FsPath(r.source).name}: {r.driven_m:.2f} m in {r.duration_s:.1f} s"
            + (f", {len(r.pivots)} turned in place" if r.pivots else ""))
    title = "\n".join([head] + textwrap.wrap(r.summary, 110))
    fig, ax0, ax1 = xy_figure(np.vstack([pts, ref]), title)
    if len(pts):
        ax0.plot(pts[:, 0], pts[:, 1], ".", ms=3, color="0.45", label=f"input ({len(pts)} points)", zorder=2)
    ax0.plot(ref[:, 0], ref[:, 1], "-", lw=1.2, color="tab:red", label="reference", zorder=3)
    if r.pivots:
        pv = np.array([(x, y) for _, x, y, _ in r.pivots])
        ax0.plot(pv[:, 0], pv[:, 1], "o", ms=9, mfc="none", mec="tab:blue", mew=1.5, label="turn in place", zorder=5)
    d = a["direction"]  # per interval: a point is backwards when an interval beside it is
    back = np.zeros(len(ref), dtype=bool)
    back[:-1] |= d < 0.0
    back[1:] |= d < 0.0
    mark_route(ax0, ref, [(x, y) for _, x, y in r.cusps], back)
    legend_above(ax0)
    s = a["sigma"]
    # A turn in place is a span of progress with no speed: shaded, its pivot_radius x omega
    # left out so that it does not read as m/s.
    inside = pivot_interior(path)
    u = np.where(inside, np.nan, a["u"])
    top = 1.3 * max(r.v_cap, float(np.nanmax(u)) if np.any(np.isfinite(u)) else 0.0, 1e-9)
    terms = _terms(path)
    for name, cap in _caps(path, terms).items():
        cap = np.where(terms.in_piv | (cap >= top), np.nan, cap)  # the pivot omega cap: all of it
        if np.any(np.isfinite(cap)):
            ax1.plot(s, cap, label=name if "cap" in name else f"{name} cap", **CAP_STYLE[name])
    for k, (i0, i1) in enumerate(pivot_runs(path)):
        ax1.axvspan(s[i0], s[i1], color="tab:blue", alpha=0.15, lw=0, label="turn in place" if k == 0 else None)
    ax1.plot(s, u, "k-", lw=1.4, label="profile (speed)", zorder=3)
    ax1.set_xlim(s[0], s[-1])
    ax1.set_ylim(0.0, top)
    ax1.set_xlabel("progress (m)")
    ax1.set_ylabel("speed (m/s)")
    legend_above(ax1)
    return fig


def write_plot(path: Path, r: PathReport, out_file: str | FsPath) -> FsPath:
    """`report_figure` as a PNG (matplotlib)."""
    out = FsPath(out_file)
    out.parent.mkdir(parents=True, exist_ok=True)
    report_figure(path, r).savefig(out, dpi=110)
    return out
