"""Step 4, dynamics: the identification run `ddrt calibrate identify` makes (a figure-eight
centred on the robot, inside `--area`), its fit turned into robot: keys."""

from __future__ import annotations

import math
from typing import Any

from ddrt.commission.session import CommissionError, Session

DEFAULT_AREA = (2.0, 1.5)


def held_text(c: dict[str, Any]) -> str:
    """A held parameter as the dynamics step stored it (ddrt/core/split.py's Held), in words."""
    from ddrt.core.split import Held

    return Held(c["name"], c["unconstrained"], c["value"], c["bound"]).describe()


def run(session: Session) -> dict[str, Any]:
    from ddrt import calibrate as cal

    cfg = session.config("dynamics")
    width, height = session.opts.area or DEFAULT_AREA
    try:
        path = cal.excitation_path(cfg, width, height)
    except ValueError as exc:
        raise CommissionError(f"dynamics: {exc}") from None
    session.answers.confirm(
        f"dynamics: the robot drives a {path.duration:.0f} s figure-eight centred where it stands, inside a free "
        f"{width:g} x {height:g} m area (--area); the area's {width:g} m side lies "
        f"{math.degrees(-path.start_pose[2]):+.0f} deg from the robot's heading. Clear the area; Ctrl-C stops.")
    with session.robot(cfg) as hal:
        try:
            res = cal.identify(cfg, hal, width, height)
        except cal.CalibrationRunError as exc:
            raise CommissionError(f"dynamics: {exc}") from None
    try:
        split = cal.platform_split(cfg, res)
    except cal.CalibrationRunError as exc:
        raise CommissionError(f"dynamics: {exc}") from None
    for line in cal.held_lines(split):
        session.say(f"dynamics: {line}")
    coulomb = max(0.0, cfg.robot_motor.coulomb_nm + 0.5 * (split.friction["fric_l"] + split.friction["fric_r"]))
    before = {"m_p": cfg.robot.m_p, "d_xc": cfg.robot.d_xc, "d_yc": cfg.robot.d_yc, "I_p": cfg.robot.I_p,
              "coulomb_nm": cfg.robot_motor.coulomb_nm}
    robot: dict[str, Any] = {k: float(f"{v:.6g}") for k, v in split.platform.items()}
    robot["motor"] = {"coulomb_nm": round(coulomb, 5)}
    session.say(f"dynamics: R^2 {res.r2:.4f} over {res.rows} rows; m_p {before['m_p']:.3f} -> {robot['m_p']:.3f} kg, "
                f"I_p {before['I_p']:.5f} -> {robot['I_p']:.5f} kg m^2, d_xc {before['d_xc']:.4f} -> "
                f"{robot['d_xc']:.4f} m")
    return {"config": {"robot": robot}, "before": before, "r2": res.r2, "rows": res.rows,
            "duration_s": res.duration_s, "area": list(res.area), "values": res.values, "std_err": res.std_err,
            "effect_n": res.effect_n, "residual_rms_n": res.residual_rms_n,
            "lumped": split.lumped, "constrained": [{"name": h.name, "unconstrained": h.unconstrained,
                                                     "value": h.value, "bound": h.bound} for h in split.held]}
