"""`ddrt commission` on the simulated robot: wiring faults found and fixed, answers, closed
stdin, refused measurements, resume and --step, Ctrl-C."""

from __future__ import annotations

import io
import itertools
import json
import math
from pathlib import Path
from typing import Any

import pytest
import yaml

from ddrt.cli import main
from ddrt.commission import Stopped, commission, paths_for, session_for
from ddrt.commission.answers import AnswersError, load_answers
from ddrt.commission.session import Options
from ddrt.config import ConfigError, load_config
from hal.base import Sample
from hal.registry import open_hal
from hal.wiring import WiredHal, negate_count, negate_gyro
from sim_hal.backend import SimHal
from tests.support.repo import REPO

SIM = REPO / "configs" / "sim.yaml"
FIX = {"left_motor_reversed": "motor_left_inverted", "right_motor_reversed": "motor_right_inverted",
       "motors_swapped": "motors_swapped", "encoder_reversed": "encoder_sign", "gyro_upside_down": "gyro_sign"}


def _config(tmp_path: Path, **over: Any) -> Path:
    f = tmp_path / "robot.yaml"
    f.write_text(yaml.safe_dump(dict({"extends": str(SIM)}, **over)))
    return f


def _session(src: Path, out: Path, given: dict | None = None, yes: bool = True, truth: bool = True,
             ask: Any = None) -> Any:
    return session_for(src, Options(out=out, from_sim_truth=truth, figures=False), given, yes=yes, ask=ask,
                       out=io.StringIO())


def _expected_fix(faults: dict[str, bool]) -> dict[str, Any]:
    fix = {"motor_left_inverted": False, "motor_right_inverted": False, "motors_swapped": False,
           "encoder_sign": 1, "gyro_sign": 1}
    for fault, on in faults.items():
        if on:
            key = FIX[fault]
            fix[key] = -1 if key.endswith("sign") else True
    return fix


# --------------------------------------------------------------------------- wiring


@pytest.mark.parametrize("bits", list(itertools.product((False, True), repeat=5)))
def test_every_combination_of_wiring_faults_is_found(tmp_path: Path, bits: tuple[bool, ...]) -> None:
    faults = dict(zip(FIX, bits))
    src = _config(tmp_path, sim={"wiring": faults})
    session = _session(src, tmp_path / "out.yaml")
    commission(session, step="wiring")
    assert session.state.get("wiring")["config"]["hal"]["wiring"] == _expected_fix(faults)


@pytest.mark.parametrize("fault", list(FIX))
def test_a_fault_fixed_in_the_config_drives_as_the_right_wiring(tmp_path: Path, fault: str) -> None:
    """The commissioned config on the miswired robot runs the figure-eight exactly as the
    correctly wired robot does (the fix undoes the fault at the boundary, bit for bit)."""
    from ddrt.path.spec import resolve_path
    from ddrt.simrun.runner import run_sim

    src = _config(tmp_path, sim={"wiring": {fault: True}})
    session = _session(src, tmp_path / "out.yaml")
    commission(session, step="wiring")
    fixed = load_config(src, {"hal": {"wiring": session.state.get("wiring")["config"]["hal"]["wiring"]},
                              "path": {"shape": "figure_eight", "width": 1.0, "height": 0.5, "speed": 0.4}})
    broken = load_config(src, {"path": {"shape": "figure_eight", "width": 1.0, "height": 0.5, "speed": 0.4}})
    right = load_config(SIM, {"path": {"shape": "figure_eight", "width": 1.0, "height": 0.5, "speed": 0.4}})
    m_fixed = run_sim(fixed, resolve_path(fixed, None)).metrics
    m_right = run_sim(right, resolve_path(right, None)).metrics
    assert m_fixed["completed"] and m_fixed["rms_cross_track_m"] == m_right["rms_cross_track_m"]
    assert not run_sim(broken, resolve_path(broken, None)).metrics["completed"]


def test_nothing_moves_is_refused_with_the_causes(tmp_path: Path) -> None:
    # A supply of 0.3 V: no duty up to the step's cap gets past the motors' friction.
    src = _config(tmp_path, plant={"motor": {"supply_v": 0.3}})
    with pytest.raises(ValueError, match="nothing moved.*motor power.*deadband.*port"):
        commission(_session(src, tmp_path / "out.yaml"), step="wiring")


def test_the_wiring_pulses_stay_within_a_few_centimetres_and_degrees(tmp_path: Path) -> None:
    src = _config(tmp_path)
    session = _session(src, tmp_path / "out.yaml")
    commission(session, step="wiring")
    for p in session.state.get("wiring")["pulses"]:
        assert 2.0 <= abs(p["distance_mm"]) <= 30.0 or 1.0 <= abs(p["angle_deg"]) <= 10.0
        assert abs(p["distance_mm"]) <= 30.0 and abs(p["angle_deg"]) <= 10.0


def test_ctrl_c_in_a_pulse_stops_the_motors(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    src = _config(tmp_path)
    opened: list[SimHal] = []
    reads = [0]
    real_read = SimHal.read

    def read(self: SimHal) -> Sample:
        reads[0] += 1
        if reads[0] == 140:  # inside the first pulse's ramp: the left motor is driven
            assert self.robot.applied_duty[0] > 0.0
            raise KeyboardInterrupt
        return real_read(self)

    import hal.registry

    real_open = hal.registry.open_hal

    def spy(cfg: Any, **kw: Any) -> Any:
        h = real_open(cfg, **kw)
        opened.append(h)
        return h

    monkeypatch.setattr(SimHal, "read", read)
    monkeypatch.setattr(hal.registry, "open_hal", spy)
    with pytest.raises(Stopped, match="Ctrl-C: the motors are off"):
        commission(_session(src, tmp_path / "out.yaml"), step="wiring")
    robot = opened[-1].robot
    robot.advance_to(robot.t + 0.05)  # past the command latency
    assert robot.applied_duty == (0.0, 0.0)


def test_wired_hal_undoes_each_fault_at_the_boundary() -> None:
    assert negate_count(-2**31) == -2**31 and negate_count(5) == -5 and negate_count(2**31 - 1) == -(2**31 - 1)
    assert negate_gyro(-32768) == 32767 and negate_gyro(100) == -100
    right = load_config(SIM)
    assert type(open_hal(right)) is SimHal  # the documented wiring: no wrapper, today's path
    cfg = load_config(SIM, {"sim": {"wiring": {"motors_swapped": True, "left_motor_reversed": True}},
                            "hal": {"wiring": {"motors_swapped": True, "motor_left_inverted": True}}})
    with open_hal(cfg) as hal:
        assert isinstance(hal, WiredHal)
        hal.write(0.5, -0.25)
        hal.robot.advance_to(0.01)
        assert hal.robot.applied_duty == (0.5, -0.25)
        assert hal.now() == hal.inner.now()


def test_wiring_keys_are_typed() -> None:
    with pytest.raises(ConfigError, match=r"hal\.wiring\.gyro_sign: must be one of 1, -1"):
        load_config(SIM, {"hal": {"wiring": {"gyro_sign": 0}}})
    with pytest.raises(ConfigError, match=r"sim\.wiring\.encoder_reversed"):
        load_config(SIM, {"sim": {"wiring": {"encoder_reversed": "yes"}}})


# --------------------------------------------------------------------------- answers and prompts


@pytest.mark.parametrize("text, message", [
    ("odometry: {distance_m: one}", r"odometry\.distance_m: expected a number"),
    ("odometry: {distance: 1.0}", r"odometry\.distance: unknown answer \(known in odometry: distance_m"),
    ("wheels: {x: 1}", r"wheels: unknown section"),
    ("wiring: {left_output_pulse: sideways}", r"wiring\.left_output_pulse: expected one of left forward"),
    ("- 1\n- 2", r"expected a mapping of sections"),
    ("odometry: [1, 2]", r"odometry: expected a mapping of answers"),
    ("odometry: {distance_m: .nan}", r"odometry\.distance_m: expected a number in"),
    ("odometry: {distance_m: 1.0", r"answers\.yaml"),
])
def test_a_malformed_answers_file_is_a_clear_error(tmp_path: Path, text: str, message: str,
                                                    capsys: pytest.CaptureFixture) -> None:
    f = tmp_path / "answers.yaml"
    f.write_text(text)
    with pytest.raises(AnswersError, match=message):
        load_answers(f)
    assert main(["commission", str(SIM), "--out", str(tmp_path / "o.yaml"), "--answers", str(f), "--yes"]) == 2
    err = capsys.readouterr().err
    assert "answers.yaml" in err and "Traceback" not in err


def test_closed_stdin_is_no_answer(tmp_path: Path, capsys: pytest.CaptureFixture,
                                   monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr("sys.stdin", io.StringIO(""))
    out = tmp_path / "o.yaml"
    # No --yes: the first confirmation meets the closed stdin.
    assert main(["commission", str(SIM), "--out", str(out), "--step", "wiring"]) == 2
    err = capsys.readouterr().err
    assert "no answer on stdin (it is closed)" in err and "--yes" in err and "Traceback" not in err
    # --yes, no answers file: the wiring observation is a measurement, not skipped.
    assert main(["commission", str(SIM), "--out", str(out), "--step", "wiring", "--yes"]) == 2
    err = capsys.readouterr().err
    assert "wiring.left_output_pulse" in err and "--answers" in err and "Traceback" not in err


def test_a_typed_answer_is_asked_again_until_usable(tmp_path: Path) -> None:
    said = iter(["", "sideways", "Left  Forward"])
    session = _session(_config(tmp_path), tmp_path / "o.yaml", truth=False, ask=lambda _: next(said))
    commission(session, step="wiring")
    assert session.state.get("wiring")["seen"] == "left forward"


def test_a_measurement_more_than_20_percent_off_is_refused(tmp_path: Path) -> None:
    src = _config(tmp_path)
    for given, what in (({"odometry.distance_m": 1.3, "odometry.turn_offset_deg": 0.0}, "distance"),
                        ({"odometry.distance_m": 1.0, "odometry.turn_offset_deg": 400.0}, "turn")):
        session = _session(src, tmp_path / "o.yaml", given, truth=False)
        with pytest.raises(ValueError, match=f"measured {what} .* more than 20%: refused"):
            commission(session, step="odometry")
        assert not session.state.done("odometry")
    good = _session(src, tmp_path / "o.yaml", {"odometry.distance_m": 1.0, "odometry.turn_offset_deg": 0.3},
                    truth=False)
    commission(good, step="odometry")
    o = good.state.get("odometry")
    assert o["radii"] == {"r_3": pytest.approx(0.052 * 1.0 / o["est_distance_m"])}
    assert o["gyro_scale"] == pytest.approx(o["est_turn_deg"] / (1800.3))


def test_the_supply_reading_is_held_against_a_multimeter(tmp_path: Path) -> None:
    src = _config(tmp_path)
    out = tmp_path / "o.yaml"
    commission(_session(src, out, truth=False), step="link")  # the simulated driver reads 12.00 V
    with pytest.raises(ValueError, match="more than 20% apart"):
        commission(_session(src, out, {"battery.multimeter_v": 15.5}, truth=False), step="rest")
    s = _session(src, out, {"battery.multimeter_v": 12.5}, truth=False)
    commission(s, step="rest")
    r = s.state.get("rest")
    assert r["battery_v"] == pytest.approx(12.0) and r["battery_ratio"] == pytest.approx(12.0 / 12.5)
    assert any("divider" in n for n in s.notes)
    no_battery = _config(tmp_path, sim={"battery_measured": False})
    s = _session(no_battery, tmp_path / "n.yaml", truth=False)
    commission(s, step="link")
    commission(s, step="rest")
    assert "skipped" in s.state.get("rest")["battery"]


WHEELS_ONLY = {"encoder_counts_per_rev": 0, "wheel_counts_per_rev": 1440}


@pytest.mark.parametrize("bits", list(itertools.product((False, True), repeat=4)))
def test_a_robot_without_front_encoder_has_its_wiring_found_by_its_wheels(tmp_path: Path,
                                                                        bits: tuple[bool, ...]) -> None:
    """No front encoder: the drive wheels' counts measure the pulses (they follow their motors,
    so the gyro and the observation decide) and every motor and gyro fault is still found."""
    faults = dict(zip([f for f in FIX if f != "encoder_reversed"], bits))
    src = _config(tmp_path, sim={"wiring": faults}, sensors=WHEELS_ONLY)
    session = _session(src, tmp_path / "out.yaml")
    commission(session, step="wiring")
    assert session.state.get("wiring")["config"]["hal"]["wiring"] == _expected_fix(faults)


def test_a_robot_without_front_encoder_is_commissioned_by_its_drive_wheels(tmp_path: Path) -> None:
    """Drive wheels 2 % larger than the config says, 4 % apart, and no front encoder: the
    odometry step scales r_L and r_R (the estimator's distance), writes their difference, and
    leaves r_3 alone."""
    src = _config(tmp_path, plant={"r_L": 0.049 * 1.02, "r_R": 0.051 * 1.02}, sensors=WHEELS_ONLY)
    out = tmp_path / "robot.yaml"
    outcome = commission(_session(src, out))
    cfg, before = load_config(out), load_config(src)
    assert cfg.robot.r_3 == before.robot.r_3
    assert 0.5 * (cfg.robot.r_L + cfg.robot.r_R) == pytest.approx(0.050 * 1.02, rel=0.006)  # 2 mm over 1 m
    # Their 4 % difference, learnt on the straight (config: equal radii).
    assert cfg.robot.r_R / cfg.robot.r_L == pytest.approx(0.051 / 0.049, rel=0.002)
    assert outcome.check["true_rms_mm"] < 5.0
    assert "robot.r_L" in (paths_for(out)[1] / "report.md").read_text() and "robot.r_L" in out.read_text()


# --------------------------------------------------------------------------- resume, --step, result


def test_resume_skips_finished_steps_and_step_reruns_one(tmp_path: Path) -> None:
    src = _config(tmp_path)
    out = tmp_path / "out" / "robot.yaml"
    given = {"wiring.left_output_pulse": "left forward", "battery.multimeter_v": 12.02, "odometry.distance_m": 1.5,
             "odometry.turn_offset_deg": 0.0}
    first = _session(src, out, given, truth=False)
    with pytest.raises(ValueError, match="refused"):
        commission(first)
    state_file = paths_for(out)[0]
    stored = json.loads(state_file.read_text())["steps"]
    assert sorted(stored) == ["dynamics", "link", "rest", "wiring"]
    given["odometry.distance_m"] = 1.0
    second = _session(src, out, given, truth=False)
    done = commission(second)
    assert done.skipped == ["link", "wiring", "rest", "dynamics"] and done.ran == ["odometry", "result"]
    assert stored["dynamics"]["finished"] == second.state.get("dynamics")["finished"]
    cfg = load_config(out)
    assert cfg.robot.r_3 == pytest.approx(second.state.get("odometry")["radii"]["r_3"], rel=1e-5)
    assert cfg.robot.m_p == pytest.approx(second.state.get("dynamics")["config"]["robot"]["m_p"])
    assert cfg.plant == load_config(src).plant  # the truth is never touched
    assert "Commissioned by" in out.read_text() and (paths_for(out)[1] / "report.md").exists()
    third = _session(src, out, given, truth=False)
    again = commission(third, step="rest")
    assert again.ran == ["rest"] and again.config_file is None
    assert third.state.get("rest")["finished"] >= stored["rest"]["finished"]
    assert third.state.get("odometry") == second.state.get("odometry")


def test_a_full_commission_from_truth_calibrates_a_harsh_robot(tmp_path: Path) -> None:
    """Gyro 3 % high and the encoder wheel 2 % large: commissioned within the measurement noise."""
    src = _config(tmp_path, plant={"r_3": 0.052 * 1.02}, sim={"gyro": {"scale_error": 0.03, "bias_dps": 4.0}})
    out = tmp_path / "robot.yaml"
    outcome = commission(_session(src, out))
    cfg = load_config(out)
    assert cfg.estimator.gyro_scale == pytest.approx(1.03, rel=0.001)  # 0.5 deg over 5 turns: 0.03 %
    assert cfg.robot.r_3 == pytest.approx(0.052 * 1.02, rel=0.006)  # 2 mm over 1 m: 0.2 % (3 sigma)
    assert outcome.check["true_rms_mm"] < 5.0 and math.isfinite(outcome.check["est_rms_mm"])


def test_an_impossible_split_is_held_physical_said_and_drives(tmp_path: Path) -> None:
    """The wheels configured 18 times too inertial in yaw: they alone exceed the robot's identified
    yaw inertia, so no platform inertia is left. Commissioning holds I_p at its floor, says so in
    its output, the config's comments and the report, and the config it writes drives."""
    src = _config(tmp_path, robot={"I_L": 0.0064, "I_R": 0.0064})
    out = tmp_path / "robot.yaml"
    session = _session(src, out)
    outcome = commission(session)
    said = session.answers.out.getvalue()
    assert "physically impossible" in said and "I_p" in said.split("physically impossible")[1]
    assert "robot.I_L" in said  # what to check
    held = session.state.get("dynamics")["constrained"]
    assert [c["name"] for c in held] == ["I_p"] and held[0]["unconstrained"] < 0.0
    cfg = load_config(out)
    assert cfg.robot.I_p == pytest.approx(held[0]["value"]) and cfg.robot.I_p > 0.0
    assert "not separable by the run: I_p" in out.read_text()
    assert "- I_p" in (paths_for(out)[1] / "report.md").read_text()
    assert outcome.check["true_rms_mm"] < 5.0


def test_the_cli_writes_config_and_report(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    out = tmp_path / "c.yaml"
    assert main(["commission", str(SIM), "--out", str(out), "--from-sim-truth", "--yes",
                 "--measurement-noise", "0,0", "--no-check"]) == 0
    assert "wrote" in capsys.readouterr().out
    assert load_config(out).hal.wiring.encoder_sign == 1
    assert main(["commission", str(SIM), "--out", str(out), "--measurement-noise", "1,1"]) == 2
    assert "--measurement-noise: only with --from-sim-truth" in capsys.readouterr().err


# --------------------------------------------------------------------------- UMBmark


def test_umbmark_model_closes_and_opens_as_derived() -> None:
    from ddrt.commission.umbmark import fit_scale, predicted_end

    for d in (-1, 1):
        assert predicted_end(1.0, 1.01, 2.0, d) == pytest.approx((0.0, 0.0), abs=1e-12)
        h = 1e-6  # the derivative at k = 1 against the closed form c S (-pi, d pi)
        (x1, y1), (x0, y0) = predicted_end(1.0 + h, 1.01, 2.0, d), predicted_end(1.0 - h, 1.01, 2.0, d)
        assert ((x1 - x0) / (2 * h), (y1 - y0) / (2 * h)) == pytest.approx((-math.pi * 2.02, d * math.pi * 2.02),
                                                                            rel=1e-6)
    cw, ccw = predicted_end(1.02, 1.0, 1.5, -1), predicted_end(1.02, 1.0, 1.5, 1)
    k, res = fit_scale(1.5, 1.0, cw, ccw)
    assert k == pytest.approx(1.02, abs=1e-7) and res < 1e-7


def test_umbmark_weighs_in_with_the_turns(tmp_path: Path) -> None:
    src = _config(tmp_path, sim={"gyro": {"scale_error": -0.025}})
    session = session_for(src, Options(out=tmp_path / "o.yaml", from_sim_truth=True, figures=False,
                                       umbmark_side_m=0.8), yes=True, out=io.StringIO())
    commission(session, step="odometry")
    o = session.state.get("odometry")
    u = o["umbmark"]
    assert u["gyro_scale"] == pytest.approx(0.975, abs=4 * u["k_rel_uncertainty"])
    lo, hi = sorted((u["gyro_scale"], u["turns_gyro_scale"]))
    assert lo <= o["gyro_scale"] <= hi and o["gyro_scale_rel_uncertainty"] < u["k_rel_uncertainty"]


# --------------------------------------------------------------------------- emergency stop


def test_the_emergency_stop_input_stops_a_pulse(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The robot's emergency-stop input opening mid-pulse (Sample.hw_estop) ends the step, motors off."""
    reads = [0]
    real_read = SimHal.read
    opened: list[SimHal] = []

    def read(self: SimHal) -> Sample:
        reads[0] += 1
        if reads[0] == 130:
            opened.append(self)
            assert self.robot.applied_duty[0] > 0.0  # the left motor is driven
            self.estop_input_open = True
        return real_read(self)

    monkeypatch.setattr(SimHal, "read", read)
    session = _session(_config(tmp_path), tmp_path / "o.yaml")
    with pytest.raises(Stopped, match="emergency stop is pressed"):
        commission(session, step="wiring")
    assert not session.state.done("wiring")
    robot = opened[0].robot
    robot.advance_to(robot.t + 0.05)
    assert robot.applied_duty == (0.0, 0.0)


def test_the_emergency_stop_input_stops_a_driven_run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Through the loop (ddrt/loop/power.py latches estop): the odometry run ends with a clear error."""
    reads = [0]
    real_read = SimHal.read

    def read(self: SimHal) -> Sample:
        reads[0] += 1
        if reads[0] == 600:  # after the calibration at rest, on the straight
            self.estop_input_open = True
        return real_read(self)

    monkeypatch.setattr(SimHal, "read", read)
    session = _session(_config(tmp_path), tmp_path / "o.yaml")
    with pytest.raises(ValueError, match="emergency stop"):
        commission(session, step="odometry")


# --------------------------------------------------------------------------- link


@pytest.mark.parametrize("message, hint", [
    ("/dev/ttyACM0: cannot open serial port: [Errno 13] could not open port /dev/ttyACM0: [Errno 13] Permission "
     "denied: '/dev/ttyACM0'", "dialout group"),
    ("/dev/ttyACM3: cannot open serial port: [Errno 2] could not open port /dev/ttyACM3: [Errno 2] No such file or "
     "directory", "ls /dev/ttyACM*"),
    ("/dev/i2c-7: cannot open I2C bus: [Errno 2] No such file or directory: '/dev/i2c-7'", "hal.imu.bus"),
    ("i2c-1@0x68: WHO_AM_I (0x75) read 0x70, expected 0x68 (wrong part or address?)", "hal.imu.address"),
    ("/dev/ttyUSB0: no HELLO_REPLY within 2 s (is the microcontroller powered and running protocol v1 firmware?)",
     "flashed with the ddrt bridge firmware"),
    ("something else entirely", "docs/hardware.md"),
])
def test_a_link_failure_says_what_to_do_next(message: str, hint: str) -> None:
    from ddrt.commission.link import next_step

    assert hint in next_step(message)


def test_the_link_step_on_the_emulated_devices(tmp_path: Path) -> None:
    src = _config(tmp_path, hal={"backend": "real", "imu": {"bus": "sim"}, "bridge": {"url": "ddrtsim://commission"}})
    session = _session(src, tmp_path / "o.yaml")
    commission(session, step="link")
    link = session.state.get("link")
    assert link["backend"] == "emulated" and link["protocol_version"] == 2
    assert link["fresh_fraction"] > 0.5 and link["gyro_raw_span"] > 0


@pytest.mark.parametrize("part, who", [("MPU-6050", 0x68), ("MPU-6500", 0x70), ("ICM-20689", 0x98)])
def test_the_link_step_says_which_gyro_part_it_found(tmp_path: Path, part: str, who: int) -> None:
    src = _config(tmp_path, hal={"backend": "real", "imu": {"bus": "sim"}, "bridge": {"url": "ddrtsim://commission"}},
                  sim={"gyro": {"part": part}})
    said = io.StringIO()
    session = session_for(src, Options(out=tmp_path / "o.yaml", from_sim_truth=True, figures=False), yes=True, out=said)
    commission(session, step="link")
    assert session.state.get("link")["gyro_part"] == f"{part} (WHO_AM_I 0x{who:02x})"
    assert f"gyro {part} (WHO_AM_I 0x{who:02x})" in said.getvalue()


def test_a_changed_config_is_said_and_a_foreign_state_refused(tmp_path: Path) -> None:
    src = _config(tmp_path)
    out = tmp_path / "o.yaml"
    commission(_session(src, out), step="link")
    src.write_text(src.read_text() + "sim: {seed: 7}\n")
    said = io.StringIO()
    s = session_for(src, Options(out=out, from_sim_truth=True), yes=True, out=said)
    commission(s, step="link")
    assert "changed since the stored steps ran" in said.getvalue()
    other = tmp_path / "other.yaml"
    other.write_text(src.read_text())
    with pytest.raises(ValueError, match="belongs to the commissioning of"):
        session_for(other, Options(out=out), yes=True)
    paths_for(out)[0].write_text("{not json")
    with pytest.raises(ValueError, match="not a commissioning state"):
        session_for(src, Options(out=out), yes=True)
