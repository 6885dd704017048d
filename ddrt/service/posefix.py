"""The control socket's two pose commands (docs/estimation.md, "Setting the pose and fixing it"):

- `pose` sets the pose: {"cmd": "pose", "pose": [x, y, theta], "cov": optional 3x3}. The robot
  is there in both frames (the map correction is cleared, the history starts again), known to
  `cov` (default: exactly). Only at rest: it moves the odometry, which a path in odom follows.
- `pose_fix` fuses a measured pose: {"cmd": "pose_fix", "x", "y", "theta", "cov", "stamp"}
  in `map`, true at `stamp` on the loop's clock (status' `clock_s`; default: now). Any state:
  only the map correction moves, smoothly for a path in map. An outlier is counted and not
  fused (the reply says so).

Bad input (a missing or non-finite value, a covariance that is not a symmetric positive
definite 3x3, a stamp in the future, older than the history or before the last fix) gets an
error naming the field and changes nothing.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

from ddrt.core.pose_fix import FixError, parse_cov, parse_fix
from ddrt.core.wrap import wrap_angle
from ddrt.loop import Event
from ddrt.loop.modes import refused_in
from ddrt.service.commands import Request, ctl_number

if TYPE_CHECKING:
    from ddrt.service.daemon import Daemon

log = logging.getLogger("ddrt.service.daemon")


def pose_cmd(d: Daemon, req: Request, who: str) -> dict[str, Any]:
    """Set the estimator's pose (m, m, rad), optionally with its covariance. Refused while the
    robot moves along a reference or a follow is prepared; changes nothing then."""
    loop = d.loop
    assert loop is not None
    pose = req.args["pose"]  # [x, y, theta], finite and within bounds (its declaration)
    cov = None
    if req.get("cov") is not None:
        try:
            cov = parse_cov(req.args["cov"])
        except FixError as exc:
            return {"ok": False, "error": f"pose: {exc}"}
    if why := refused_in(Event.POSE, loop.state):  # the mode machine's (ddrt/loop/modes.py)
        return {"ok": False, "error": why}
    if d.follows.busy_text():
        return {"ok": False, "error": f"pose: refused while preparing {d.follows.busy_text()} to follow: "
                                      "send stop to cancel it"}
    x, y, theta = float(pose[0]), float(pose[1]), wrap_angle(float(pose[2]))
    loop.estimator.set_pose((x, y, theta), cov)
    log.info("pose set to (%.4f, %.4f, %.4f) %s", x, y, theta, who)
    return {"ok": True, "state": loop.state.label, "pose": [x, y, theta]}


def pose_fix_cmd(d: Daemon, req: Request, who: str) -> dict[str, Any]:
    """Fuse a pose fix into the map frame; any state but before the estimator has started."""
    loop = d.loop
    assert loop is not None
    est = loop.estimator
    try:
        fix = parse_fix(dict(req.args), est.t_est)
        result = est.fuse_fix(fix)
    except FixError as exc:
        return {"ok": False, "error": f"pose_fix: {exc}"}
    xm, ym, thm = est.map_pose()
    sx, sy, sth = est.track.std
    if result["fused"]:
        log.debug("pose fix at %.3f s fused (d2 %.2f) %s", fix.stamp, result["d2"], who)
    else:
        log.warning("pose fix at %.3f s is an outlier (d2 %.1f > %.2f), not fused %s", fix.stamp, result["d2"],
                    result["gate"], who)
    return {"ok": True, "state": loop.state.label, **result, "stamp": fix.stamp,
            "pose_map": [xm, ym, thm], "std": [sx, sy, sth],
            "fixes": {"fused": est.frame.counters.fused, "outliers": est.frame.counters.outliers}}


def ctl_fix_request(xyt: list[float], cov: str | None, stamp: str | None) -> dict[str, Any]:
    """`ddrt ctl pose X Y THETA --cov C [--stamp T]` as a pose_fix request: C is 3 variances
    (x, y, theta: m^2, m^2, rad^2) or the 9 entries of the 3x3 row by row, comma-separated;
    ValueError naming the option (the daemon checks the values themselves)."""
    if cov is None:
        raise ValueError("ctl pose: --cov: a fix (--stamp) needs its covariance: 3 variances (m^2, m^2, rad^2) "
                         "or 9 entries, comma-separated")
    parts = [p for p in cov.replace(" ", ",").split(",") if p]
    if len(parts) not in (3, 9):
        raise ValueError(f"ctl pose: --cov: expected 3 variances or 9 entries, comma-separated, got {len(parts)}")
    values = [ctl_number(p, "--cov", "pose") for p in parts]
    if len(values) == 3:
        values = [values[0], 0.0, 0.0, 0.0, values[1], 0.0, 0.0, 0.0, values[2]]
    req: dict[str, Any] = {"cmd": "pose_fix", "x": xyt[0], "y": xyt[1], "theta": xyt[2],
                           "cov": [values[0:3], values[3:6], values[6:9]]}
    if stamp is not None:
        req["stamp"] = ctl_number(stamp, "--stamp", "pose")
    return req
