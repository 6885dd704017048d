"""Optional part of the odometry step: Borenstein and Feng's UMBmark, a square driven both
ways with the end offsets measured (`--umbmark SIDE`).

The robot follows the square by its own estimate, so it really turns each estimated 90 degrees
as 90 / k, k = (the gyro's true scale) / (the believed one), and really drives each estimated
metre as c metres (c from the straight run). Its end point is then
    c S sum_{i=0..3} (cos(i s pi/2 / k), sin(i s pi/2 / k)),  s = +1 counter-clockwise, -1 clockwise,
in the frame of its start pose. Near k = 1 the ends move by c S (-pi, +pi) per unit of k
counter-clockwise and c S (-pi, -pi) clockwise: to the left one way and to the right the other.
k is fitted to the four measured numbers by least squares; with each end moving pi S sqrt(2)
per unit of k, a tape read to sigma gives k to sigma / (2 pi S) from both squares.
"""

from __future__ import annotations

import math
from typing import Any

from ddrt.commission.session import CommissionError, Session, follow_to_end


def predicted_end(k: float, c: float, side: float, direction: int) -> tuple[float, float]:
    """Where the square ends (m, start frame) for gyro ratio k and distance ratio c."""
    x = y = 0.0
    for i in range(4):
        th = i * direction * 0.5 * math.pi / k
        x += math.cos(th)
        y += math.sin(th)
    return c * side * x, c * side * y


def fit_scale(side: float, c: float, cw: tuple[float, float], ccw: tuple[float, float]) -> tuple[float, float]:
    """k that best explains both end offsets (m), and the rms residual (m) it leaves."""
    def cost(k: float) -> float:
        e = 0.0
        for direction, (mx, my) in ((-1, cw), (1, ccw)):
            px, py = predicted_end(k, c, side, direction)
            e += (px - mx) ** 2 + (py - my) ** 2
        return e

    lo, hi = 0.7, 1.4  # golden-section search: the cost has one minimum within +-30 %
    g = (math.sqrt(5.0) - 1.0) / 2.0
    a, b = hi - g * (hi - lo), lo + g * (hi - lo)
    for _ in range(80):
        if cost(a) < cost(b):
            hi = b
        else:
            lo = a
        a, b = hi - g * (hi - lo), lo + g * (hi - lo)
    k = 0.5 * (lo + hi)
    return k, math.sqrt(cost(k) / 4.0)


def _square(session: Session, cfg: Any, side: float, direction: int) -> tuple[float, float]:
    """Drive one square; the end offset (m, start frame): measured, or the truth plus tape noise."""
    from ddrt import calibrate as cal
    from ddrt.path import load_path
    from ddrt.path.spec import speed_limits

    way = "counter-clockwise" if direction > 0 else "clockwise"
    session.answers.confirm(
        f"odometry (UMBmark): mark the floor under the middle of the rear axle and draw the heading line again; the "
        f"robot drives a {side:g} m square {way}, turning in place at the corners, and stops near the start.")
    limits = speed_limits(cfg)
    path = load_path({"shape": "rectangle", "width": side, "height": side, "direction": "ccw" if direction > 0 else "cw",
                      "speed": min(0.3, limits.v_max)}, limits, paths=cfg.paths)
    with session.robot(cfg) as hal:
        loop, clock = cal.start_loop(cfg, hal)
        truth = hal.robot
        p0 = truth.pose if truth is not None else None
        follow_to_end(loop, clock, path, (0.0, 0.0, 0.0), "odometry (UMBmark)")
        p1 = truth.pose if truth is not None else None
    if session.opts.from_sim_truth and p0 is not None and p1 is not None:
        dx, dy = p1[0] - p0[0], p1[1] - p0[1]
        c0, s0 = math.cos(p0[2]), math.sin(p0[2])
        ex, _ = session.truth_noise()
        ey, _ = session.truth_noise()
        return c0 * dx + s0 * dy + ex, -s0 * dx + c0 * dy + ey
    key = "odometry.umbmark_ccw_mm" if direction > 0 else "odometry.umbmark_cw_mm"
    x, y = session.answers.value(key, "  Where is the middle of the rear axle now, from the mark: how far ahead "
                                      "along the heading line and how far to its left (mm, e.g. 12,-30)? ")
    return 1e-3 * x, 1e-3 * y


def run(session: Session, cfg: Any, side: float, c: float) -> dict[str, Any]:
    cw = _square(session, cfg, side, -1)
    ccw = _square(session, cfg, side, 1)
    k, residual = fit_scale(side, c, cw, ccw)
    if not 0.8 <= k <= 1.25:
        raise CommissionError(f"odometry (UMBmark): the end offsets {cw} and {ccw} m imply a gyro {abs(k - 1):.0%} off, "
                              "more than 20%: refused; measure again (ahead along the heading line, then to its left)")
    tape = session.opts.noise_mm_deg[0] * 1e-3
    return {"side_m": side, "cw_end_m": list(cw), "ccw_end_m": list(ccw), "k": k, "residual_m": residual,
            "k_rel_uncertainty": tape / (2.0 * math.pi * side * c)}
