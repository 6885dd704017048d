"""Step 6, result: one complete config (the input with every measured value merged in, with
comments saying what was measured, how and when), validated by loading it back, then the
check path and the report."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import yaml

from ddrt.commission.dynamics import held_text
from ddrt.commission.odometry import radius_changes, radius_uncertainty
from ddrt.commission.session import STEPS, CommissionError, Session
from ddrt.config import load_config
from ddrt.config.load import files_relative_to, merge_mappings


def _comment_lines(session: Session) -> list[str]:
    st = session.state
    lines = [f"# Commissioned by `ddrt commission {session.config_path}` on {time.strftime('%Y-%m-%d %H:%M %Z')}.",
             "# Every value below is the input config's, except these, measured:"]
    w = st.get("wiring")
    if w:
        changed = w.get("changed") or {}
        lines.append(f"#   hal.wiring ({w['finished']}): each motor output pulsed alone; the left output turned the "
                     f"{w['seen'].replace(' ', ' wheel ')}" + (f"; changed: {', '.join(f'{k} {a} -> {b}' for k, (a, b) in changed.items())}"
                                             if changed else "; the wiring is as documented"))
    r = st.get("rest")
    if r:
        lines.append(f"#   (at rest, {r['finished']}: gyro bias {r['bias_dps']:+.3f} deg/s, re-measured at every start; "
                     f"noise {r['noise_dps']:.4f} deg/s per sample; battery: {r.get('battery', 'checked')})")
        if r.get("bias_per_c_dps") is not None:
            lines.append(f"#   estimator.gyro_bias_per_c_dps ({r['finished']}): the gyro's bias at two rests, "
                         f"{r['temperature']}")
    d = st.get("dynamics")
    if d:
        lines.append(f"#   robot.m_p, d_xc, d_yc, I_p, motor.coulomb_nm ({d['finished']}): identified over a "
                     f"{d['duration_s']:.0f} s figure-eight in {d['area'][0]:g} x {d['area'][1]:g} m, R^2 {d['r2']:.4f}")
        for c in d.get("constrained", []):
            lines.append(f"#     held physical, not separable by the run: {held_text(c)}")
    o = st.get("odometry")
    if o:
        lines.append(f"#   robot.{radius_changes(o)} (+-{100 * radius_uncertainty(o):.2f}%), "
                     f"estimator.gyro_scale {o['gyro_scale_before']:.5f} -> {o['gyro_scale']:.5f} "
                     f"(+-{100 * o['gyro_scale_rel_uncertainty']:.3f}%) ({o['finished']}): {o['distance_cmd_m']:g} m "
                     f"straight and {o['turns']} turns, {o['source']}")
    return lines


def final_mapping(session: Session, out_file: Path) -> dict[str, Any]:
    from ddrt.commission.session import explicit_robot

    data = merge_mappings(explicit_robot(session.cfg), session.overrides("result"))
    return files_relative_to(data, out_file.resolve().parent, Path(session.cfg.base_dir))


def write_config(session: Session, out_file: Path) -> str:
    """Write the commissioned config to `out_file` and load it back (it must validate)."""
    missing = [s for s in STEPS[:-1] if not session.state.done(s)]
    if missing:
        raise CommissionError(f"result: steps not done yet: {', '.join(missing)} (run without --step to do them)")
    data = final_mapping(session, out_file)
    text = "\n".join(_comment_lines(session)) + "\n" + yaml.safe_dump(data, sort_keys=False, width=110)
    out_file.parent.mkdir(parents=True, exist_ok=True)
    out_file.write_text(text, encoding="utf-8")
    try:
        load_config(out_file)
    except ValueError as exc:
        raise CommissionError(f"result: the merged config does not validate: {exc}") from None
    return text
