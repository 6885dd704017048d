"""Step 5, odometry: the distance sensor's radius and the gyro's scale, from a tape and a protractor.

The robot drives `--distance` m straight ahead, stops, and turns `--turns` full turns in place
counter-clockwise about the middle of its rear axle (point A). Measured: how far A went (a
tape, from the mark under A at the start to A at the end) and how far past the whole turns
the robot's heading ended (a protractor, on the line drawn along its side at the start).
The encoder's distance is counts x r_3, so r_3 scales with measured / estimated distance (on a
robot without a front encoder the drive wheels' r_L and r_R, together); a robot that counts its
drive wheels also has their radius difference, learnt on the straight, written into r_L and r_R
(ddrt/calibrate.py corrected_radii). The estimated turn is the gyro's integral / gyro_scale,
so the scale goes with estimated / measured turn. A tape read to +-2 mm over 1 m gives r_3 to 0.2 %; a protractor read to
+-0.5 deg over 5 turns gives the scale to 0.03 %.

`--umbmark SIDE` also drives a square both ways (umbmark.py) and weighs its gyro scale with the
turns' one.

On the simulator `--from-sim-truth` reads the plant's true pose instead, plus the noise of a
tape and a protractor (`--measurement-noise MM,DEG`, default 2 mm and 0.5 deg, one sigma).
"""

from __future__ import annotations

import math
from dataclasses import asdict
from typing import Any

from ddrt.commission.session import CommissionError, Session
from ddrt.config import Config
from hal.base import Hal

MAX_OFF = 0.2  # a measurement more than 20 % off the robot's own is refused


def drive(cfg: Config, hal: Hal, distance: float, turns: int) -> dict[str, float | None]:
    """The straight then the turns; the estimator's distance and total turn, and the truth."""
    from ddrt import calibrate as cal
    from ddrt.path import load_path
    from ddrt.path.spec import speed_limits

    loop, clock = cal.start_loop(cfg, hal)
    truth = hal.robot
    true0 = truth.pose if truth is not None else None
    limits = speed_limits(cfg)
    line = load_path({"shape": "line", "length": distance, "speed": min(0.3, limits.v_max)}, limits, paths=cfg.paths)
    loop.follow(line, (0.0, 0.0, 0.0))
    cal.run_until_stopped(loop, clock, line.duration + 15.0)
    cal.settle(loop, clock)
    x1, y1, th1 = loop.estimator_pose()
    spin = cal.SpinReference((x1, y1, th1), 2.0 * math.pi * turns, min(1.5, cfg.limits.omega_max),
                             min(3.0, cfg.limits.alpha_max), loop.period)
    loop.follow_reference(spin)
    cal.run_until_stopped(loop, clock, spin.turn.t_end + 15.0)
    cal.settle(loop, clock)
    x2, y2, th2 = loop.estimator_pose()
    wheels = loop.estimator.wheels  # their radius difference: learnt on the straight, not in the turns
    out: dict[str, float | None] = {"est_distance_m": math.hypot(x2, y2), "est_turn_rad": th2,
                                    "true_distance_m": None, "true_turn_rad": None,
                                    "wheel_delta": wheels.delta if wheels is not None else None}
    if true0 is not None and truth is not None:
        p2 = truth.pose
        out["true_distance_m"] = math.hypot(p2[0] - true0[0], p2[1] - true0[1])
        out["true_turn_rad"] = p2[2] - true0[2]
    return out


def run(session: Session) -> dict[str, Any]:
    cfg = session.config("odometry")
    d, n = session.opts.distance_m, session.opts.turns
    session.answers.confirm(
        "odometry: on a flat floor with 1.5 m free ahead, put masking tape beside the robot and\n"
        "  1. mark the floor under the middle of the rear axle (halfway between the drive wheels' contact points),\n"
        "  2. draw a straight line on the tape along the robot's side, showing where it faces.\n"
        f"  The robot drives {d:g} m straight ahead, stops, then turns {n} full turns counter-clockwise in place.")
    from ddrt import calibrate as cal

    with session.robot(cfg) as hal:
        try:
            run_ = drive(cfg, hal, d, n)
        except cal.CalibrationRunError as exc:
            raise CommissionError(f"odometry: {exc}") from None
    whole = 2.0 * math.pi * n
    if session.opts.from_sim_truth:
        if run_["true_distance_m"] is None:
            raise CommissionError("odometry: --from-sim-truth needs the simulated robot (hal.backend: sim)")
        e_d, e_t = session.truth_noise()
        dist = run_["true_distance_m"] + e_d
        offset = math.degrees(run_["true_turn_rad"] - whole + e_t)
        source = f"simulation truth with tape/protractor noise {session.opts.noise_mm_deg[0]:g} mm, " \
                 f"{session.opts.noise_mm_deg[1]:g} deg"
    else:
        dist = session.answers.value(
            "odometry.distance_m", f"  Measure with a tape from the first mark to the point under the middle of the "
            f"rear axle now (metres, e.g. {d:.3f}): ")
        offset = session.answers.value(
            "odometry.turn_offset_deg", f"  Lay a protractor on the line you drew: how many degrees past {n} whole "
            "turns does the robot's side point now? (counter-clockwise past: positive, short of: negative, e.g. -1.5): ")
        source = "measured by hand"
    turn = whole + math.radians(offset)
    d_ratio = dist / run_["est_distance_m"]
    t_ratio = run_["est_turn_rad"] / turn
    for what, ratio, said, got in (("distance", d_ratio, f"{run_['est_distance_m']:.4f} m", f"{dist:.4f} m"),
                                   ("turn", 1.0 / t_ratio, f"{math.degrees(run_['est_turn_rad']):.1f} deg",
                                    f"{math.degrees(turn):.1f} deg")):
        if not (1.0 - MAX_OFF <= ratio <= 1.0 + MAX_OFF):
            raise CommissionError(
                f"odometry: the measured {what} {got} is {abs(ratio - 1):.0%} off the robot's own {said}, more than "
                f"{MAX_OFF:.0%}: refused. Measure again (from the mark under the rear axle's middle; a turn offset is "
                "the angle past the whole turns, not the total) and run `ddrt commission --step odometry`")
    tape_m, prot_deg = session.opts.noise_mm_deg[0] * 1e-3, session.opts.noise_mm_deg[1]
    from ddrt.calibrate import corrected_radii

    radii = corrected_radii(cfg, d_ratio, run_["wheel_delta"])
    robot = asdict(cfg.robot)
    radii_before = {k: robot[k] for k in radii}
    scale = cfg.estimator.gyro_scale * t_ratio
    scale_rel = math.radians(prot_deg) / turn
    umb = None
    if session.opts.umbmark_side_m:
        from ddrt.commission import umbmark

        umb = umbmark.run(session, cfg, session.opts.umbmark_side_m, d_ratio)
        # Both estimates of the scale, weighted by what one reading's uncertainty implies.
        w_turn, w_umb = scale_rel ** -2, umb["k_rel_uncertainty"] ** -2
        scale_umb = cfg.estimator.gyro_scale * umb["k"]
        umb["gyro_scale"] = scale_umb
        umb["turns_gyro_scale"] = scale
        scale = (w_turn * scale + w_umb * scale_umb) / (w_turn + w_umb)
        scale_rel = (w_turn + w_umb) ** -0.5
    out = {
        "config": {"robot": {k: float(f"{v:.6g}") for k, v in radii.items()},
                   "estimator": {"gyro_scale": float(f"{scale:.6g}")}},
        "source": source, "distance_cmd_m": d, "turns": n,
        "est_distance_m": run_["est_distance_m"], "measured_distance_m": dist,
        "est_turn_deg": math.degrees(run_["est_turn_rad"]), "measured_turn_deg": math.degrees(turn),
        "true_distance_m": run_["true_distance_m"],
        "true_turn_deg": None if run_["true_turn_rad"] is None else math.degrees(run_["true_turn_rad"]),
        "radii_before": radii_before, "radii": radii,
        "gyro_scale_before": cfg.estimator.gyro_scale, "gyro_scale": scale,
        # What one reading's uncertainty implies (one sigma, relative).
        "radius_rel_uncertainty": tape_m / dist, "gyro_scale_rel_uncertainty": scale_rel,
        "umbmark": umb,
    }
    session.say(f"odometry: {radius_changes(out)} (+-{100 * out['radius_rel_uncertainty']:.2f}%), "
                f"gyro_scale {cfg.estimator.gyro_scale:.5f} -> {scale:.5f} "
                f"(+-{100 * out['gyro_scale_rel_uncertainty']:.3f}%)")
    return out


def radius_rows(o: dict[str, Any]) -> list[tuple[str, float, float]]:
    """(key, before, after) for each radius the step scaled; a result from before the drive
    wheels were handled carries r_3 alone."""
    before = o.get("radii_before") or {"r_3": o["r_3_before"]}
    after = o.get("radii") or {"r_3": o["r_3"]}
    return [(k, before[k], after[k]) for k in after]


def radius_changes(o: dict[str, Any]) -> str:
    """"r_3 0.05000 -> 0.05100 m", or the drive wheels' pair."""
    return ", ".join(f"{k} {b:.5f} -> {a:.5f} m" for k, b, a in radius_rows(o))


def radius_uncertainty(o: dict[str, Any]) -> float:
    """One tape reading's relative uncertainty, which each scaled radius carries."""
    return o.get("radius_rel_uncertainty", o.get("r_3_rel_uncertainty", math.nan))
