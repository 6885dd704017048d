"""The `ddrt` command's own rough edges: finding the daemon's socket, `ddrt sim`'s
--duration and exit status, strict metrics.json, and a closed pipe on stdout."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from ddrt import cli
from ddrt.simrun.runner import json_ready
from ddrt.service.ctlclient import DEFAULT_SOCKET

REPO = Path(__file__).resolve().parents[1]
SIM = REPO / "configs" / "sim.yaml"


def _answer_once(path: str, reply: dict) -> threading.Thread:
    """A one-shot listener on `path` that reads one request line and sends `reply`."""
    srv = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    srv.bind(path)
    srv.listen(1)
    seen: list[dict] = []

    def serve() -> None:
        conn, _ = srv.accept()
        with conn, srv:
            buf = b""
            while b"\n" not in buf:
                buf += conn.recv(4096)
            seen.append(json.loads(buf))
            conn.sendall((json.dumps(reply) + "\n").encode())

    t = threading.Thread(target=serve, daemon=True)
    t.seen = seen  # type: ignore[attr-defined]
    t.start()
    return t


def test_ctl_finds_the_socket_in_the_config(tmp_path, monkeypatch, capsys) -> None:
    sock = tmp_path / "d.sock"
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(f"extends: {SIM}\ndaemon: {{socket: {sock}}}\n")
    monkeypatch.setenv("DDRT_SOCKET", str(tmp_path / "elsewhere.sock"))  # --config wins over the variable
    t = _answer_once(str(sock), {"ok": True, "state": "idle"})
    assert cli.main(["ctl", "--config", str(cfg), "status"]) == 0
    t.join(5)
    assert t.seen == [{"cmd": "status"}]  # type: ignore[attr-defined]
    assert json.loads(capsys.readouterr().out)["state"] == "idle"


def test_ctl_reaches_the_daemon_of_a_config_with_a_typo_and_says_what_is_wrong(tmp_path, capsys) -> None:
    # Live tuning: the file is being edited; estop (and the reload that reports the typo) must
    # still find the socket the file names.
    sock = tmp_path / "d.sock"
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(f"extends: {SIM}\ncontroller: {{outer: {{k_yy: 300}}}}\ndaemon: {{socket: {sock}}}\n")
    t = _answer_once(str(sock), {"ok": True, "state": "estop"})
    assert cli.main(["ctl", "--config", str(cfg), "estop"]) == 0
    t.join(5)
    assert t.seen == [{"cmd": "estop"}]  # type: ignore[attr-defined]
    err = capsys.readouterr().err
    assert err == (f"ddrt ctl: warning: {cfg}: controller.outer.k_yy: unknown key (known: k_theta, k_x, k_y); "
                   "its daemon.socket is used all the same\n")


@pytest.mark.parametrize("text", ["daemon: {socket: [1]}\n", "daemon: {socket: 1}\n", "robot: {H: 1\n"])
def test_ctl_with_a_config_whose_socket_cannot_be_read_names_the_file(tmp_path, capsys, text) -> None:
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(text)
    assert cli.main(["ctl", "--config", str(cfg), "estop"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"ddrt: error: {cfg}: ") and err.count("\n") == 1


def test_ctl_takes_the_socket_from_the_environment(tmp_path, monkeypatch, capsys) -> None:
    sock = tmp_path / "e.sock"
    monkeypatch.setenv("DDRT_SOCKET", str(sock))
    t = _answer_once(str(sock), {"ok": True})
    assert cli.main(["ctl", "status"]) == 0
    t.join(5)
    assert t.seen == [{"cmd": "status"}]  # type: ignore[attr-defined]


@pytest.mark.parametrize("how, source", [
    (lambda tmp, env: ["--socket", str(tmp / "none.sock")], "--socket"),
    (lambda tmp, env: env.setenv("DDRT_SOCKET", str(tmp / "none.sock")) or [], "$DDRT_SOCKET"),
])
def test_an_unreachable_socket_is_named_with_where_it_came_from(tmp_path, monkeypatch, capsys, how, source) -> None:
    monkeypatch.delenv("DDRT_SOCKET", raising=False)
    argv = ["ctl", *how(tmp_path, monkeypatch), "status"]
    assert cli.main(argv) == 1
    err = capsys.readouterr().err
    assert str(tmp_path / "none.sock") in err and source in err


def test_the_default_socket_says_how_to_name_another(monkeypatch) -> None:
    monkeypatch.delenv("DDRT_SOCKET", raising=False)
    args = cli.build_parser().parse_args(["ctl", "status"])
    path, source = cli.control_socket(args)
    assert path == DEFAULT_SOCKET and "--config" in source and "DDRT_SOCKET" in source


def test_a_config_without_a_socket_is_a_clear_error(tmp_path, capsys) -> None:
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(f"extends: {SIM}\ndaemon: {{socket: null}}\n")
    assert cli.main(["ctl", "--config", str(cfg), "status"]) == 2
    assert "daemon.socket" in capsys.readouterr().err


@pytest.mark.parametrize("value", ["0", "-1", "nan", "inf", "abc"])
def test_sim_refuses_a_duration_that_is_not_positive_seconds(value, capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        cli.build_parser().parse_args(["sim", str(SIM), "--duration", value])
    assert exc.value.code == 2
    assert "--duration" in capsys.readouterr().err


def test_sim_with_a_duration_exits_zero_when_it_ran_that_long_without_a_fault(tmp_path) -> None:
    assert cli.main(["sim", str(SIM), "--duration", "0.5", "--quiet", "--out", str(tmp_path)]) == 0
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["completed"] is False and metrics["ticks"] > 0


def test_sim_interrupted_says_so_and_leaves_no_earlier_metrics_beside_its_rows(tmp_path, monkeypatch, capsys) -> None:
    import ddrt.simrun.runner as runner

    (tmp_path / "metrics.json").write_text("{}\n")  # an earlier run's, in the same --out

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(runner, "run_sim", interrupted)
    assert cli.main(["sim", str(SIM), "--quiet", "--out", str(tmp_path)]) == 130
    assert not (tmp_path / "metrics.json").exists()
    err = capsys.readouterr().err
    assert err == f"ddrt: interrupted: {tmp_path}/telemetry.csv holds the rows up to now; no metrics.json\n"


def test_sim_names_an_out_that_cannot_be_a_directory(tmp_path, capsys) -> None:
    a_file = tmp_path / "afile"
    a_file.write_text("")
    said = f"ddrt: error: --out {a_file}: is a file, not a directory; give a directory for the output\n"
    assert cli.main(["sim", str(SIM), "--quiet", "--out", str(a_file)]) == 2  # bad input
    assert capsys.readouterr().err == said
    assert cli.main(["path", str(REPO / "configs/paths/s_curve.yaml"), "--plot", "--out", str(a_file)]) == 2
    assert capsys.readouterr().err == said
    assert cli.main(["sim", str(SIM), "--quiet", "--out", str(a_file / "sub")]) == 1
    assert capsys.readouterr().err.startswith(f"ddrt: error: --out {a_file / 'sub'}: cannot make the directory: ")


@pytest.mark.parametrize("metrics, duration_given, status", [
    ({"completed": True, "fault": "", "state": "stopped"}, False, 0),
    ({"completed": False, "fault": "", "state": "following"}, False, 1),
    ({"completed": False, "fault": "", "state": "following"}, True, 0),
    ({"completed": False, "fault": "path error 0.2 m", "state": "fault"}, True, 1),
    ({"completed": False, "fault": "", "state": "estop"}, True, 1),
])
def test_sim_exit_status(metrics, duration_given, status) -> None:
    assert cli.sim_exit_status(metrics, duration_given) == status


def test_metrics_are_strict_json() -> None:
    import numpy as np

    m = {"a": float("nan"), "b": [float("inf"), 1.5, np.float64("nan")], "c": {"d": np.float64(2.0)}, "e": "x"}
    out = json_ready(m)
    assert out == {"a": None, "b": [None, 1.5, None], "c": {"d": 2.0}, "e": "x"}
    json.dumps(out, allow_nan=False)  # raises on NaN or Infinity


def test_a_closed_pipe_on_stdout_is_not_an_error(tmp_path) -> None:
    r, w = os.pipe()
    os.close(r)  # the reader (e.g. `head`) has gone before anything is written
    try:
        proc = subprocess.run([sys.executable, "-m", "ddrt.cli", "path", str(REPO / "configs/paths/figure8_slow.yaml")],
                              stdout=w, stderr=subprocess.PIPE, cwd=REPO, timeout=120, text=True)
    finally:
        os.close(w)
    assert proc.returncode == 0, proc.stderr
    assert "Broken pipe" not in proc.stderr and "Traceback" not in proc.stderr


def test_every_missing_robot_key_is_named_at_once(tmp_path, capsys) -> None:
    import yaml

    data = yaml.safe_load(SIM.read_text())
    for key in ("r_3", "d_xc", "I_p"):
        del data["robot"][key]
    data["path"] = str(REPO / "configs" / "paths" / "figure8_slow.yaml")
    cfg = tmp_path / "partial.yaml"
    cfg.write_text(yaml.safe_dump(data))
    assert cli.main(["sim", str(cfg), "--duration", "0.1", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "robot.r_3, robot.d_xc, robot.I_p: missing (required)" in err and str(cfg) in err


@pytest.mark.parametrize("paths_section, names", [
    ({}, "paths.max_points = 10000 waypoints"),
    ({"max_points": 100_000, "max_file_bytes": 1_000_000}, "paths.max_file_bytes"),
])
def test_a_csv_too_large_names_the_setting_that_limits_it(tmp_path, paths_section, names) -> None:
    from ddrt.config.sections import PathsConfig
    from ddrt.path.spec import PathError, load_path
    from ddrt.path.profile import SpeedLimits

    f = tmp_path / "big.csv"
    f.write_text("x,y\n# " + "c" * 1_400_000 + "\n0,0\n1,0\n")
    with pytest.raises(PathError) as exc:
        load_path(str(f), SpeedLimits(), paths=PathsConfig(**paths_section))
    assert names in str(exc.value) and str(f) in str(exc.value)


def _stdin(monkeypatch, text: str) -> None:
    import io

    monkeypatch.setattr(sys, "stdin", io.StringIO(text))  # not a terminal


def test_calibrate_odometry_reads_piped_answers_before_it_drives(tmp_path, monkeypatch, capsys) -> None:
    from ddrt import calibrate

    def must_not_drive(*a, **k):
        raise AssertionError("drove before it had the measurements")

    monkeypatch.setattr(calibrate, "odometry_run", must_not_drive)
    _stdin(monkeypatch, "")
    assert cli.main(["calibrate", "odometry", str(SIM), "--out", str(tmp_path / "c.yaml")]) == 2
    err = capsys.readouterr().err
    assert "--measured-distance" in err and "Traceback" not in err
    _stdin(monkeypatch, "1.0\n")  # the turn is missing
    assert cli.main(["calibrate", "odometry", str(SIM), "--out", str(tmp_path / "c.yaml")]) == 2
    assert "--measured-turn-deg" in capsys.readouterr().err


def test_calibrate_odometry_asks_again_after_a_typo_and_refuses_a_wild_measurement(tmp_path, monkeypatch,
                                                                                  capsys) -> None:
    out = tmp_path / "c.yaml"
    _stdin(monkeypatch, "abc\n1.0\n\n360\n")
    assert cli.main(["calibrate", "odometry", str(SIM), "--out", str(out)]) == 0
    assert "not a number: 'abc'" in capsys.readouterr().err and "r_3:" in out.read_text()
    _stdin(monkeypatch, "1.5\n360\n")
    assert cli.main(["calibrate", "odometry", str(SIM), "--out", str(tmp_path / "d.yaml")]) == 2
    err = capsys.readouterr().err
    assert "20%" in err and "Traceback" not in err and not (tmp_path / "d.yaml").exists()


def test_python_dash_m_ddrt_is_the_ddrt_command(tmp_path) -> None:
    """`python -m ddrt` runs the same command as the `ddrt` script, exit status and errors included."""
    ok = subprocess.run([sys.executable, "-m", "ddrt", "--help"], cwd=tmp_path, capture_output=True, text=True,
                        timeout=120)
    assert ok.returncode == 0 and ok.stdout.startswith("usage: ddrt ") and "sweep" in ok.stdout, ok.stderr
    bad = subprocess.run([sys.executable, "-m", "ddrt", "sim", str(tmp_path / "missing.yaml"), "--out", str(tmp_path / "o")],
                         cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and bad.stderr.startswith("ddrt: error:") and "missing.yaml" in bad.stderr
    assert "Traceback" not in bad.stderr


def test_ctrl_c_at_a_commissioning_prompt_says_the_motors_are_off(tmp_path, monkeypatch, capsys) -> None:
    """A driven step's Ctrl-C says so itself (ddrt/commission/session.py); one at a prompt, between
    steps, must say so too, not exit 130 without a word."""
    import ddrt.commission

    def interrupted(session, step):
        raise KeyboardInterrupt

    monkeypatch.setattr(ddrt.commission, "commission", interrupted)
    code = cli.main(["commission", str(SIM), "--out", str(tmp_path / "c.yaml"), "--yes"])
    err = capsys.readouterr().err
    assert code == 130 and "stopped by Ctrl-C: the motors are off" in err and "Traceback" not in err


@pytest.mark.parametrize("source", ["path", "--start", "config"])
def test_sim_names_what_put_the_robot_far_from_the_paths_start(tmp_path, capsys, source) -> None:
    """`ddrt sim` refuses a path that starts beyond limits.max_path_error_m from the robot
    (exit 2, no trace), naming what put the robot there: the path's start_pose, --start or the
    config's start."""
    import yaml

    spec = {"points": [[0.0, 0.0], [1.0, 0.0]]}
    if source == "path":
        spec["start_pose"] = [5.0, 5.0, 0.0]
    path = tmp_path / "far.yaml"
    path.write_text(yaml.safe_dump(spec))
    cfg = SIM
    if source == "config":
        data = yaml.safe_load(SIM.read_text())
        data["start"] = [5.0, 5.0, 0.0]
        cfg = tmp_path / "started.yaml"
        cfg.write_text(yaml.safe_dump(data))
    argv = ["sim", str(cfg), "--path", str(path), "--duration", "0.1", "--quiet", "--out", str(tmp_path / "out")]
    if source == "--start":
        argv += ["--start", "5,5,0"]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    named = {"path": f"{path}: key 'start_pose'", "--start": "--start:", "config": f"{cfg}: start:"}[source]
    assert named in err and "the robot starts at (5, 5, 0)" in err and "7.071 m from the robot" in err, err
    assert "Traceback" not in err
