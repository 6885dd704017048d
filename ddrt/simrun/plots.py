"""The seed's figures for a simulated run, as PNG (matplotlib is imported only here)."""

from __future__ import annotations

from pathlib import Path as FsPath

import numpy as np

from ddrt.simrun.metrics import path_polyline
from ddrt.simrun.runner import SimResult


def write_plots(result: SimResult, out_dir: str | FsPath) -> list[FsPath]:
    """path.png, velocities.png, position_errors.png, velocity_errors.png, torques.png."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = FsPath(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    c = result.column
    t = c("t")
    written = []

    def save(fig, name: str) -> None:
        fig.tight_layout()
        p = out / name
        fig.savefig(p, dpi=110)
        plt.close(fig)
        written.append(p)

    poly = path_polyline(result.path)
    fig, ax = plt.subplots(figsize=(6, 5))
    ax.plot(poly[:, 0], poly[:, 1], "k--", lw=1, label="path")
    ax.plot(c("x_ref"), c("y_ref"), color="tab:orange", lw=1, label="reference")
    ax.plot(c("x"), c("y"), color="tab:blue", lw=1, label="robot (true)")
    ax.set_aspect("equal")
    ax.set_xlabel("X (m)")
    ax.set_ylabel("Y (m)")
    ax.legend()
    save(fig, "path.png")

    fig, (a1, a2) = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
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

    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(t, (c("x_est") - c("x")) * 1000, label="x_est - x")
    ax.plot(t, (c("y_est") - c("y")) * 1000, label="y_est - y")
    ax.plot(t, c("cross_track_est") * 1000, label="cross-track (estimated pose)")
    ax.set_ylabel("mm")
    ax.set_xlabel("t (s)")
    ax.legend()
    save(fig, "position_errors.png")

    fig, (a1, a2) = plt.subplots(2, 1, figsize=(7, 5), sharex=True)
    a1.plot(t, (c("v_cmd") - c("v")) * 1000)
    a1.set_ylabel("v_cmd - v (mm/s)")
    a2.plot(t, np.degrees(c("omega_cmd") - c("omega")))
    a2.set_ylabel("omega_cmd - omega (deg/s)")
    a2.set_xlabel("t (s)")
    save(fig, "velocity_errors.png")

    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(t, c("tau_l"), label="tau_L")
    ax.plot(t, c("tau_r"), label="tau_R")
    ax.set_ylabel("wheel torque (N m)")
    ax.set_xlabel("t (s)")
    ax.legend()
    save(fig, "torques.png")
    return written
