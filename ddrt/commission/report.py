"""The commissioning report: what was measured, before and after, how well, and the check
path, as Markdown beside the config, with figures when matplotlib is installed."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path
from typing import Any

from ddrt.calibrate import SEEN_MIN
from ddrt.commission.dynamics import held_text
from ddrt.commission.odometry import radius_rows, radius_uncertainty
from ddrt.commission.session import STEPS, Session

# A platform key and the identified terms it comes from (ddrt/calibrate.py robot_update).
TERMS = {"m_p": ("m_k",), "d_xc": ("m_x",), "d_yc": ("mbar",), "I_p": ("I",), "coulomb_nm": ("fric_l", "fric_r")}


def _figures(session: Session, check: dict[str, Any] | None, folder: Path) -> list[str]:
    if importlib.util.find_spec("matplotlib") is None:
        return []
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = []
    w = session.state.get("wiring")
    if w and w.get("traces"):
        # One quantity a row, each on its own axis in its own unit.
        rows = (("duty (%)", lambda r: 100 * r[1]), ("encoder (mm)", lambda r: 1e3 * r[2]),
                ("gyro (deg)", lambda r: math.degrees(r[3])))
        fig, axes = plt.subplots(3, 2, figsize=(9, 5.4), sharex="col", constrained_layout=True)
        for col, (key, title) in enumerate((("0", "left output"), ("1", "right output"))):
            tr = w["traces"].get(key) or []
            axes[0, col].set_title(f"{title} pulsed alone (as wired)")
            axes[-1, col].set_xlabel("time (s)")
            for row, (label, value) in enumerate(rows):
                axes[row, col].set_ylabel(label)
                if tr:
                    axes[row, col].plot([r[0] for r in tr], [value(r) for r in tr], color=f"C{row}")
        fig.savefig(folder / "wiring.png", dpi=90)
        plt.close(fig)
        names.append("wiring.png")
    if check and check.get("trace"):
        tr = check["trace"]
        fig, (ax, ax2) = plt.subplots(1, 2, figsize=(10, 3.6), constrained_layout=True)
        # The reference wide and light under the estimate (orange) and the truth (blue).
        ax.plot([r[0] for r in tr], [r[1] for r in tr], "-", color="0.75", lw=3.0, label="reference")
        ax.plot([r[2] for r in tr], [r[3] for r in tr], "-", color="tab:orange", lw=0.9, label="estimate")
        t = [r[6] for r in tr]
        ax2.plot(t, [1e3 * math.hypot(r[2] - r[0], r[3] - r[1]) for r in tr], "-", color="tab:orange", lw=0.9,
                 label="estimate")
        if not math.isnan(tr[0][4]):
            ax.plot([r[4] for r in tr], [r[5] for r in tr], "--", color="tab:blue", lw=0.9, label="truth (simulation)")
            ax2.plot(t, [1e3 * math.hypot(r[4] - r[0], r[5] - r[1]) for r in tr], "-", color="tab:blue", lw=0.9,
                     label="truth")
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_title("check path with the commissioned config")
        ax.legend(fontsize=7)
        ax2.set_xlabel("time on the check path (s)")
        ax2.set_ylabel("distance to the reference point (mm)")
        ax2.set_title("tracking error")
        ax2.legend(fontsize=7)
        fig.savefig(folder / "check.png", dpi=90)
        plt.close(fig)
        names.append("check.png")
    return names


def _seen(d: dict[str, Any], key: str) -> float | None:
    """How many times the fit's residual the terms behind `key` account for (None: not stored)."""
    effect, resid = d.get("effect_n"), d.get("residual_rms_n")
    if not effect or not resid:
        return None
    return sum(effect[t] for t in TERMS[key]) / len(TERMS[key]) / resid


def write_report(session: Session, folder: Path, config_file: Path, check: dict[str, Any] | None) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    st = session.state
    figs = _figures(session, check, folder) if session.opts.figures else []
    lines = [f"# Commissioning report: {session.config_path}", "",
             f"Config written: `{config_file.name}`. Steps and when they finished:", ""]
    for step in STEPS[:-1]:
        res = st.get(step)
        lines.append(f"- {step}: {res['finished'] if res else 'not run'}")
    lines.append(f"- result: `{config_file.name}` written with this report")
    lines.append("- check: " + ("driven with the commissioned config (below)" if check
                                else "not run (--no-check, or no robot to drive it)"))
    link = st.get("link")
    if link:
        lines += ["", "## Link", "",
                  f"Backend `{link['backend']}`; {link['fresh_fraction']:.0%} of readings fresh at the loop's rate; "
                  + (f"protocol v{link['protocol_version']} (checked at HELLO); "
                     if link.get("protocol_version") is not None else "")
                  + (f"supply {link['battery_v']:.2f} V." if link.get("battery_v") is not None
                     else "supply voltage not measured by this driver.")]
    w = st.get("wiring")
    if w:
        lines += ["", "## Wiring", "", f"Seen on the left output's pulse: **{w['seen']}**.", "",
                  "| pulse | output | duty | encoder (mm) | gyro (deg) |", "|---|---|---|---|---|"]
        for i, p in enumerate(w["pulses"]):
            lines.append(f"| {'as wired' if i < 2 else 'through the fix'} | {p['output']} | {p['duty']:.2f} | "
                         f"{p['distance_mm']:+.1f} | {p['angle_deg']:+.1f} |")
        changed = w.get("changed") or {}
        lines += ["", "Fix written to `hal.wiring`: " + (", ".join(f"`{k}` {a} -> {b}" for k, (a, b) in changed.items())
                                                       if changed else "none needed (wired as documented).")]
    r = st.get("rest")
    if r:
        lines += ["", "## At rest", "",
                  f"Gyro bias {r['bias_dps']:+.4f} deg/s over {r['seconds']:g} s (re-measured at every start), noise "
                  f"{r['noise_dps']:.4f} deg/s per sample (`estimator.gyro_noise_dps` is {r['configured_noise_dps']:g}). "
                  f"Temperature: {r['temperature']}. Battery: "
                  + (f"driver {r['battery_v']:.2f} V, multimeter {r['multimeter_v']:.2f} V."
                     if r.get("multimeter_v") else f"{r.get('battery')}.")]
    d = st.get("dynamics")
    if d:
        lines += ["", "## Dynamics", "",
                  f"{d['duration_s']:.0f} s figure-eight in {d['area'][0]:g} x {d['area'][1]:g} m, {d['rows']} rows, "
                  f"R^2 {d['r2']:.4f}.", "", "| key | before | after | seen in the data |", "|---|---|---|---|"]
        after = dict(d["config"]["robot"], coulomb_nm=d["config"]["robot"]["motor"]["coulomb_nm"])
        unseen = []
        for k, v in d["before"].items():
            seen = _seen(d, k)
            lines.append(f"| {k} | {v:.6g} | {after[k]:.6g} | "
                         + ("" if seen is None else f"{seen:.1f}x the residual{' (not separated)' * (seen < SEEN_MIN)}")
                         + " |")
            if seen is not None and seen < SEEN_MIN:
                unseen.append(k)
        if unseen:
            one = len(unseen) == 1
            lines += ["", f"Not separated by this run: {', '.join(unseen)}. The identified term behind "
                      f"{'it' if one else 'each'} accounts for less than {SEEN_MIN:g} times the fit's residual "
                      f"({d['residual_rms_n']:.3f} N rms), so the run cannot tell {'its value' if one else 'their values'} "
                      "from what the model leaves out (two motors that differ, say), however small the standard error. "
                      f"Measure {'it' if one else 'them'} another way (for d_xc and d_yc: a scale under each wheel), or "
                      "keep the value before in the config."]
        held = d.get("constrained", [])
        if held:
            lines += ["", "The fit left these physically impossible: the run could not separate them, so each was "
                      "held at its physical bound and the rest refitted (docs/commissioning.md, step 4):", ""] \
                + [f"- {held_text(c)}" for c in held]
    o = st.get("odometry")
    if o:
        lines += ["", "## Odometry", "", f"{o['distance_cmd_m']:g} m straight, then {o['turns']} turns in place; "
                  f"{o['source']}.", "",
                  "| | robot's own | measured | truth (simulation) |", "|---|---|---|---|",
                  f"| distance (m) | {o['est_distance_m']:.4f} | {o['measured_distance_m']:.4f} | "
                  f"{'' if o['true_distance_m'] is None else format(o['true_distance_m'], '.4f')} |",
                  f"| turn (deg) | {o['est_turn_deg']:.2f} | {o['measured_turn_deg']:.2f} | "
                  f"{'' if o['true_turn_deg'] is None else format(o['true_turn_deg'], '.2f')} |", "",
                  "| key | before | after | one reading's uncertainty |", "|---|---|---|---|",
                  *(f"| robot.{k} (m) | {b:.5f} | {a:.5f} | {100 * radius_uncertainty(o):.2f} % |"
                    for k, b, a in radius_rows(o)),
                  f"| estimator.gyro_scale | {o['gyro_scale_before']:.5f} | {o['gyro_scale']:.5f} | "
                  f"{100 * o['gyro_scale_rel_uncertainty']:.3f} % |"]
        u = o.get("umbmark")
        if u:
            lines += ["", f"UMBmark, a {u['side_m']:g} m square both ways: ends at ({1e3 * u['cw_end_m'][0]:+.1f}, "
                      f"{1e3 * u['cw_end_m'][1]:+.1f}) mm clockwise and ({1e3 * u['ccw_end_m'][0]:+.1f}, "
                      f"{1e3 * u['ccw_end_m'][1]:+.1f}) mm counter-clockwise (ahead, left); gyro scale "
                      f"{u['gyro_scale']:.5f} +- {100 * u['k_rel_uncertainty']:.3f} % from it, {u['turns_gyro_scale']:.5f} "
                      f"from the turns, weighted together as above; {1e3 * u['residual_m']:.1f} mm rms the scale "
                      "does not explain."]
    if check:
        lines += ["", "## Check", "",
                  f"A {check['path_m']:.1f} m, {check['path_s']:.0f} s figure-eight with the commissioned config: "
                  f"estimated tracking RMS {check['est_rms_mm']:.2f} mm"
                  + (f", true {check['true_rms_mm']:.2f} mm, true end offset {check['true_end_offset_mm']:.1f} mm"
                     if check.get("true_rms_mm") is not None else "")
                  + (f", measured end offset {check['end_offset_mm']:.0f} mm" if check.get("end_offset_mm") is not None
                     else "") + "."]
    if session.notes:
        lines += ["", "## Notes", ""] + [f"- {n}" for n in session.notes]
    for f in figs:
        lines += ["", f"![{f}]({f})"]
    out = folder / "report.md"
    out.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return out
