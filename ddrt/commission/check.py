"""The check at the end: one lap of a figure-eight with the commissioned config, centred where
the robot stands. It ends where it started, so the end offset (a tape from the start mark to
the middle of the rear axle) says how far the robot really drifted, beside the estimator's own
tracking error; on the simulator the truth gives both."""

from __future__ import annotations

import math
from typing import Any

from ddrt.commission.session import CommissionError, Session, follow_to_end
from ddrt.config import Config
from ddrt.loop import ControlLoop, LoopState


def run(session: Session, cfg: Config) -> dict[str, Any]:
    from ddrt import calibrate as cal

    width, height = session.opts.area or (2.0, 1.5)
    try:
        path = cal.excitation_path(cfg, width, height, max_s=25.0, speed=min(0.5, cfg.limits.v_max or 0.5))
    except ValueError as exc:
        raise CommissionError(f"check: {exc}") from None
    session.answers.confirm(
        f"check: mark the floor under the middle of the rear axle again; the robot drives a {path.duration:.0f} s "
        f"figure-eight in the same {width:g} x {height:g} m area and stops where it started.")
    est_sq = true_sq = 0.0
    n = 0
    trace: list[tuple[float, ...]] = []  # every 10th tick: reference, estimate, truth (x, y), time (s)
    start = path.start_pose  # a simulated robot starts there too, so truth and estimate share a frame
    with session.robot(cfg, start=start) as hal:
        loop, clock = cal.start_loop(cfg, hal)
        truth = hal.robot
        p0 = truth.pose if truth is not None else None

        def record(lp: ControlLoop) -> None:
            nonlocal est_sq, true_sq, n
            if lp.state not in (LoopState.FOLLOWING, LoopState.STOPPING):
                return
            sp = lp.setpoint
            x, y, _ = lp.estimator_pose()
            est_sq += (x - sp.x_d) ** 2 + (y - sp.y_d) ** 2
            tx, ty = (truth.pose[0], truth.pose[1]) if truth is not None else (math.nan, math.nan)
            true_sq += (tx - sp.x_d) ** 2 + (ty - sp.y_d) ** 2
            n += 1
            if n % 10 == 0:
                trace.append((sp.x_d, sp.y_d, x, y, tx, ty, n * lp.period))

        loop.each_tick(record)
        follow_to_end(loop, clock, path, start, "check")
        p1 = truth.pose if truth is not None else None
    out: dict[str, Any] = {"path_s": path.duration, "path_m": path.length,
                           "est_rms_mm": 1e3 * math.sqrt(est_sq / max(n, 1)),
                           "true_rms_mm": 1e3 * math.sqrt(true_sq / max(n, 1)) if truth is not None else None,
                           "trace": trace}
    if p0 is not None and p1 is not None:
        out["true_end_offset_mm"] = 1e3 * math.hypot(p1[0] - p0[0], p1[1] - p0[1])
    elif not session.opts.from_sim_truth:
        try:
            out["end_offset_mm"] = session.answers.value(
                "check.end_offset_mm", "  Measure from the mark to the middle of the rear axle now (mm): ")
        except ValueError as exc:
            session.notes.append(f"check: no end offset measured ({exc})")
    session.say(f"check: estimated tracking RMS {out['est_rms_mm']:.2f} mm"
                + (f", true {out['true_rms_mm']:.2f} mm, end offset {out['true_end_offset_mm']:.1f} mm"
                   if out.get("true_rms_mm") is not None else "")
                + (f", measured end offset {out['end_offset_mm']:.0f} mm" if "end_offset_mm" in out else ""))
    return out
