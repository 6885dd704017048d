"""The `ddrt` command: sim, path, run, ctl, calibrate, commission, sweep."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Sequence


from ddrt.ctlcli import FOLLOW_TIMEOUT_S, RELOAD_TIMEOUT_S, add_ctl_parser, control_socket

if TYPE_CHECKING:
    from ddrt.config import Config

__all__ = ["main", "build_parser", "FOLLOW_TIMEOUT_S", "RELOAD_TIMEOUT_S", "control_socket", "sim_exit_status"]


def _pose(text: str) -> tuple[float, float, float]:
    try:
        x, y, th = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y,THETA (metres, radians), got {text!r}") from None
    return x, y, th


def _seconds(text: str) -> float:
    """A duration argument: a finite number of seconds > 0."""
    import math

    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected seconds, got {text!r}") from None
    if not (math.isfinite(value) and value > 0.0):
        raise argparse.ArgumentTypeError(f"expected a finite number of seconds > 0, got {text!r}")
    return value


def sim_exit_status(metrics: dict, duration_given: bool) -> int:
    """0 when the run did what was asked: the path completed, or, with --duration, the run
    lasted that long without a fault or estop; else 1."""
    if metrics["completed"]:
        return 0
    return 0 if duration_given and not metrics.get("fault") and metrics.get("state") not in ("fault", "estop") else 1


def _run_name(config: str, source: object) -> str:
    """The figures' name of a run: the config's file and the path's (or its inline shape)."""
    if isinstance(source, dict):
        what = f"inline {source.get('shape', 'path')}" if "file" not in source else Path(str(source["file"])).name
    else:
        what = Path(str(source)).name
    return Path(config).name if what == Path(config).name else f"{Path(config).name}: {what}"


def _start_from(args: argparse.Namespace, cfg: "Config") -> str:
    """What put the simulated robot where `ddrt sim` started it (run_sim's order: --start, the
    config's start, the path's start pose), named when a path that starts far from it is refused."""
    if args.start is not None:
        return "--start"
    if cfg.start is not None:
        return f"{cfg.source}: start"
    given = args.path if args.path is not None else cfg.path if isinstance(cfg.path, str) else f"{cfg.source}: path"
    return f"{given}: key 'start_pose' (or 'start')"


def _cmd_sim(args: argparse.Namespace) -> int:
    from ddrt.config import load_config
    from ddrt.loop import StartTooFar
    from ddrt.path.spec import path_source, resolve_path
    from ddrt.simrun.progress import StderrProgress
    from ddrt.simrun.runner import run_sim, summary_text, write_outputs

    if args.plot:
        import importlib.util

        if importlib.util.find_spec("matplotlib") is None:
            raise ValueError("--plot needs matplotlib, which is not installed: pip install 'ddrt[plot]'")
    if args.mcap is not None:
        from ddrt.viz.optional import foxglove

        foxglove("--mcap")  # a clear error now, not after the run
    overrides = {"sim": {"seed": args.seed}} if args.seed is not None else None
    cfg = load_config(args.config, overrides)
    if cfg.hal.backend == "real" and cfg.hal.imu.bus != "sim":
        raise ValueError(f"{args.config}: hal.backend: real with hal.imu.bus: {cfg.hal.imu.bus} drives the "
                         "robot itself; `ddrt sim` needs hal.backend: sim (or hal.imu.bus: sim, the emulated devices)")
    path = resolve_path(cfg, args.path)
    for note in path.notes:
        print(f"ddrt: {note}", file=sys.stderr)
    for warning in path.warnings:
        print(f"ddrt: warning: {warning}", file=sys.stderr)
    # The rows go to telemetry.csv as the run makes them (the figures read them back from it),
    # so an earlier run's metrics.json, which no longer describes them, goes first.
    (_out_dir(args.out, make=True) / "metrics.json").unlink(missing_ok=True)
    progress = None if args.quiet else StderrProgress()
    try:
        result = run_sim(cfg, path, duration=args.duration, seed=args.seed, start=args.start,
                         progress=progress, telemetry=Path(args.out) / "telemetry.csv", mcap=args.mcap)
    except StartTooFar as exc:
        if progress is not None:
            progress.end()
        x, y, theta = args.start or cfg.start or path.start_pose
        raise ValueError(f"{_start_from(args, cfg)}: the robot starts at ({x:g}, {y:g}, {theta:g}); {exc}") from None
    except KeyboardInterrupt:
        if progress is not None:
            progress.end()  # past the progress line
        print(f"ddrt: interrupted: {args.out}/telemetry.csv holds the rows up to now; no metrics.json", file=sys.stderr)
        return 130
    if progress is not None:
        progress.end()
    write_outputs(result, args.out)
    if args.plot:
        from ddrt.simrun.plots import write_plots

        write_plots(result, args.out, name=_run_name(args.config, path_source(cfg, args.path)[0]))
    print(summary_text(result.metrics))
    print(f"wrote {args.out}/telemetry.csv and {args.out}/metrics.json" + (" and figures" if args.plot else "")
          + (f" and {args.mcap}" if args.mcap else ""))
    return sim_exit_status(result.metrics, args.duration is not None)


def _cmd_sweep(args: argparse.Namespace) -> int:
    from ddrt.sweep.driver import SweepRequest, sweep

    if not args.out:  # Path("") is the current folder: the table would land wherever the command ran
        raise ValueError("--out: expected a folder, got ''")
    report = sweep(SweepRequest(args.campaign, Path(args.out), workers=args.workers, scheduler=args.scheduler,
                                resume=args.resume, limit=args.limit, quiet=args.quiet))
    print(report.text())
    return report.exit_status


def _cmd_path(args: argparse.Namespace) -> int:
    from ddrt.config.sections import LimitsConfig, PathsConfig
    from ddrt.path.profile import SpeedLimits
    from ddrt.path.report import path_report, report_text, write_plot
    from ddrt.path.spec import load_path, speed_limits

    if args.plot:
        import importlib.util

        if importlib.util.find_spec("matplotlib") is None:
            raise ValueError("--plot needs matplotlib, which is not installed: pip install 'ddrt[plot]'")
    if args.config is not None:
        from ddrt.config import load_config

        cfg = load_config(args.config)
        limits, paths = speed_limits(cfg), cfg.paths
    else:
        # No robot to derive v_max and accel from (null by default): the seed configs' 1 m/s
        # and 1 m/s^2 (SpeedLimits' defaults), no motor envelope.
        d = LimitsConfig()
        limits = SpeedLimits(lateral_accel=d.lateral_accel, omega_max=d.omega_max, alpha_max=d.alpha_max)
        paths = PathsConfig()
    path = load_path(args.file, limits, paths=paths)
    report = path_report(path, args.file)
    print(report_text(report))
    if args.plot:
        out = write_plot(path, report, _out_dir(args.out) / "path_report.png")
        print(f"wrote {out}")
    return 0


def _cmd_run(args: argparse.Namespace) -> int:
    import os

    # One BLAS thread: the loop does no large linear algebra, and each OpenBLAS thread
    # holds buffers that mlockall would pin (must be set before numpy is imported).
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    from ddrt.service.daemon import run_daemon
    from ddrt.service.telemetry import configure_logging

    configure_logging(args.log_level)
    return run_daemon(args.config, args.socket, args.duration, args.stats_json, args.follow)


def _cmd_ros2(args: argparse.Namespace) -> int:
    from ddrt.ros2.main import run
    from ddrt.service.telemetry import configure_logging

    configure_logging(args.log_level)
    return run(args)


def _cmd_bag(args: argparse.Namespace) -> int:
    from ddrt.config import load_config
    from ddrt.config.ros2 import Ros2Config

    cfg = load_config(args.config).daemon.ros2 if args.config else Ros2Config()
    try:
        from ddrt.ros2.bag import export_csv
    except ImportError as exc:
        raise ValueError(f"bag export: needs the ros2 extra (pip install 'ddrt[ros2]'): {exc}") from None
    print(json.dumps(export_csv(args.telemetry, args.out, cfg, args.epoch), indent=2))
    return 0


def _cmd_calibrate(args: argparse.Namespace) -> int:
    import math

    from ddrt import calibrate as cal
    from ddrt.config import load_config
    from hal.registry import open_hal

    cfg = load_config(args.config)
    kind = args.kind
    if kind == "gyro":
        with open_hal(cfg) as hal:
            text = cal.gyro_fragment(cal.calibrate_gyro_at_rest(cfg, hal))
    elif kind == "identify":
        width, height = cal.parse_area(args.area)
        path = cal.excitation_path(cfg, width, height, args.duration, args.speed)
        print(f"identify: a {path.duration:.1f} s figure-eight, {path.length:.1f} m, centred on the robot; the "
              f"area's {width:g} m side lies {math.degrees(-path.start_pose[2]):+.1f} deg from the robot's "
              f"heading (counter-clockwise positive)", file=sys.stderr)
        with open_hal(cfg, start=(0.0, 0.0, 0.0)) as hal:
            res = cal.identify(cfg, hal, width, height, args.duration, args.speed)
        text = cal.identify_fragment(cfg, res)
    else:
        if args.from_sim_truth and cfg.hal.backend != "sim":
            raise ValueError("--from-sim-truth: only with hal.backend: sim")
        questions = _odometry_questions(args)
        answers: dict[str, float] = {}
        if not args.from_sim_truth and not sys.stdin.isatty():
            # Piped answers are read before the robot moves: an empty stdin stops nothing mid-run.
            answers = {key: _ask(prompt, key) for key, prompt in questions.items()}
        with open_hal(cfg, start=(0.0, 0.0, 0.0)) as hal:
            run = cal.odometry_run(cfg, hal, args.distance)
        if args.from_sim_truth:
            dist, turn, source = run.true_distance_m, run.true_turn_rad, "simulation truth"
        else:
            for key, prompt in questions.items():
                if key not in answers:
                    answers[key] = _ask(prompt, key)
            dist = args.measured_distance if args.measured_distance is not None else answers["distance"]
            turn_deg = args.measured_turn_deg if args.measured_turn_deg is not None else answers["turn"]
            turn, source = math.radians(turn_deg), "measured by hand"
        try:
            corr = cal.odometry_correction(cfg, run, dist, turn)
        except cal.CalibrationRunError as exc:
            raise ValueError(f"calibrate odometry: {exc}") from None
        text = cal.odometry_fragment(cfg, run, corr, dist, turn, source)
    print(text, end="")
    out = args.out or f"calibration-{kind}.yaml"
    Path(out).write_text(text, encoding="utf-8")
    print(f"wrote {out}", file=sys.stderr)
    return 0


def _odometry_questions(args: argparse.Namespace) -> dict[str, str]:
    """The measurements `calibrate odometry` still needs, key -> prompt."""
    questions = {}
    if args.measured_distance is None:
        questions["distance"] = f"Distance the robot actually drove, in metres (commanded {args.distance:g}): "
    if args.measured_turn_deg is None:
        questions["turn"] = "Angle the robot actually turned, in degrees (360 if it ended facing exactly as it started): "
    return questions


def _ask(prompt: str, what: str, tries: int = 5) -> float:
    """A finite number from stdin, asked again (up to `tries` times) after anything else; the
    end of stdin is a clear error naming the flag that would have given it."""
    import math

    flag = {"distance": "--measured-distance", "turn": "--measured-turn-deg"}[what]
    for _ in range(tries):
        try:
            text = input(prompt)
        except EOFError:
            raise ValueError(f"calibrate odometry: no {what} measurement on stdin (it ended); give it with {flag}") from None
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if math.isfinite(value):
            return value
        print(f"  not a number: {text.strip()!r}; type the {what} you measured, e.g. "
              f"{'1.002' if what == 'distance' else '358.5'}", file=sys.stderr)
    raise ValueError(f"calibrate odometry: no usable {what} after {tries} tries; give it with {flag}")


def _cmd_commission(args: argparse.Namespace) -> int:
    """`ddrt commission`: the guided steps of ddrt/commission (docs/commissioning.md)."""
    from ddrt.calibrate import parse_area
    from ddrt.commission import commission, session_for
    from ddrt.commission.answers import load_answers
    from ddrt.commission.session import DEFAULT_NOISE, Options

    if args.measurement_noise is not None and not args.from_sim_truth:
        raise ValueError("--measurement-noise: only with --from-sim-truth")
    noise = DEFAULT_NOISE
    if args.measurement_noise is not None:
        try:
            noise = tuple(float(v) for v in args.measurement_noise.split(","))  # type: ignore[assignment]
        except ValueError:
            noise = ()  # type: ignore[assignment]
        if len(noise) != 2 or not all(0.0 <= v < 1000.0 for v in noise):
            raise ValueError(f"--measurement-noise: expected MM,DEG (two numbers >= 0), got {args.measurement_noise!r}")
    if not 1 <= args.turns <= 20:
        raise ValueError(f"--turns: 1 to 20, got {args.turns}")
    if not 0.2 <= args.distance <= 10.0:
        raise ValueError(f"--distance: 0.2 to 10 m, got {args.distance:g}")
    if args.umbmark is not None and not 0.3 <= args.umbmark <= 10.0:
        raise ValueError(f"--umbmark: a square's side of 0.3 to 10 m, got {args.umbmark:g}")
    out = Path(args.out or f"{Path(args.config).stem}.commissioned.yaml")
    given = load_answers(args.answers) if args.answers else {}
    opts = Options(out=out, area=parse_area(args.area) if args.area else None, from_sim_truth=args.from_sim_truth,
                   noise_mm_deg=noise, turns=args.turns, distance_m=args.distance, check=not args.no_check,
                   umbmark_side_m=args.umbmark)
    session = session_for(args.config, opts, given, yes=args.yes)
    try:
        outcome = commission(session, args.step)
    except KeyboardInterrupt:  # at a prompt: a driven step's own Ctrl-C is a Stopped (a ValueError)
        print("\nddrt: stopped by Ctrl-C: the motors are off; run the command again to resume", file=sys.stderr)
        return 130
    if outcome.config_file is not None:
        print(f"wrote {outcome.config_file} and {outcome.report}")
    else:
        print(f"done: {', '.join(outcome.ran)} (stored in {session.state.path})")
    return 0


def build_parser() -> argparse.ArgumentParser:
    from ddrt import __version__

    parser = argparse.ArgumentParser(prog="ddrt", description="Real-time controller for differential-drive robots.")
    parser.add_argument("--version", action="version", version=f"ddrt {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    sim = sub.add_parser("sim", help="run the closed loop on the simulated robot, as fast as possible")
    sim.add_argument("config", help="YAML config (e.g. configs/sim.yaml)")
    sim.add_argument("--path", help="path file (.csv or .yaml); default: the config's path:")
    sim.add_argument("--duration", type=_seconds,
                     help="stop after this many simulated seconds (then exit 0 unless the run faulted)")
    sim.add_argument("--seed", type=int, help="noise seed of the simulated robot")
    sim.add_argument("--start", type=_pose, help="start pose X,Y,THETA (default: the path's start)")
    sim.add_argument("--out", default="out", help="output directory (default: out)")
    sim.add_argument("--plot", action="store_true", help="also write the seed's figures as PNG")
    sim.add_argument("--quiet", action="store_true", help="no progress line")
    sim.add_argument("--mcap", metavar="FILE", help="also record the run as MCAP on the Foxglove channels "
                                                    "(pip install 'ddrt[foxglove]')")
    sim.set_defaults(func=_cmd_sim)

    pth = sub.add_parser("path", help="what a path file becomes: length, time, corners, deviation, speed limits")
    pth.add_argument("file", help="path file (.csv, .yaml or .yml)")
    pth.add_argument("--config", help="YAML config whose limits: and paths: apply (default: the defaults)")
    pth.add_argument("--plot", action="store_true", help="also draw the input, the reference and the speed profile")
    pth.add_argument("--out", default="out", help="directory for path_report.png (default: out)")
    pth.set_defaults(func=_cmd_path)

    run = sub.add_parser("run", help="the long-running controller (systemd service)")
    run.add_argument("config", help="YAML config (e.g. /etc/ddrt/ddrt.yaml)")
    run.add_argument("--socket", default=None, help="control socket path (e.g. /run/ddrt/ddrt.sock)")
    run.add_argument("--duration", type=_seconds, help="stop after this many seconds")
    run.add_argument("--follow", action="store_true", help="start following the config's path at once")
    run.add_argument("--stats-json", help="write timing statistics to this file at exit")
    run.add_argument("--log-level", default="info", help="debug, info, warning or error")
    run.set_defaults(func=_cmd_run)

    add_ctl_parser(sub)

    r2 = sub.add_parser("ros2", help="the ROS 2 bridge to a running daemon (pip install 'ddrt[ros2]'; docs/ros2.md)")
    from ddrt.ros2.main import add_arguments as ros2_arguments

    ros2_arguments(r2)
    r2.add_argument("--log-level", default="info", help="debug, info, warning or error")
    r2.set_defaults(func=_cmd_ros2)

    bag = sub.add_parser("bag", help="rosbag2 recordings (pip install 'ddrt[ros2]'; docs/ros2.md)")
    bag_sub = bag.add_subparsers(dest="bag_command", required=True)
    b_exp = bag_sub.add_parser("export", help="a telemetry CSV as a rosbag2 (MCAP): /odom, /tf, /diagnostics")
    b_exp.add_argument("telemetry", help="telemetry.csv of ddrt run or ddrt sim")
    b_exp.add_argument("out", help="the rosbag2 folder to write (must not exist)")
    b_exp.add_argument("--config", help="frames, namespace and rates from this config's daemon.ros2")
    b_exp.add_argument("--epoch", type=float, help="wall time (s since 1970) of t = 0 (default: from the file's time)")
    b_exp.set_defaults(func=_cmd_bag)

    swp = sub.add_parser("sweep", help="a campaign of simulated runs on Dask: a table, a summary, figures "
                                       "(pip install 'ddrt[sweep]')")
    swp.add_argument("campaign", help="campaign file (YAML; docs/sweep.md)")
    swp.add_argument("--out", required=True, metavar="DIR", help="output folder: results.parquet, results.csv, summary.md, figures/")
    swp.add_argument("--workers", type=int, metavar="N", help="local worker processes (default: one per core)")
    swp.add_argument("--scheduler", metavar="ADDRESS", help="run on this Dask scheduler (tcp://host:8786) instead "
                                                            "of a local cluster")
    swp.add_argument("--resume", action="store_true", help="keep the rows already in --out and run the rest")
    swp.add_argument("--limit", type=int, metavar="N", help="run at most N of the cases left")
    swp.add_argument("--quiet", action="store_true", help="no progress bar")
    swp.set_defaults(func=_cmd_sweep)

    cal = sub.add_parser("calibrate", help="gyro at rest, dynamic identification, odometry")
    cal_sub = cal.add_subparsers(dest="kind", required=True)
    c_gyro = cal_sub.add_parser("gyro", help="gyro bias and noise at rest")
    c_id = cal_sub.add_parser("identify", help="identify the dynamic parameters in a bounded excitation run")
    c_id.add_argument("--area", required=True, help="free area WIDTHxHEIGHT in metres, centred on the robot")
    c_id.add_argument("--duration", type=float, default=30.0, help="longest run in seconds (default 30)")
    c_id.add_argument("--speed", type=float, help="top speed in m/s (default min(limits.v_max, 0.8))")
    c_odo = cal_sub.add_parser("odometry", help="straight run and full turn: encoder radius and gyro scale")
    c_odo.add_argument("--distance", type=float, default=1.0, help="straight distance in metres (default 1)")
    c_odo.add_argument("--measured-distance", type=float, help="what you measured (m); else asked on stdin")
    c_odo.add_argument("--measured-turn-deg", type=float, help="what you measured (deg); else asked on stdin")
    c_odo.add_argument("--from-sim-truth", action="store_true", help="simulation: use the plant's true pose")
    for c in (c_gyro, c_id, c_odo):
        c.add_argument("config", help="YAML config of the robot")
        c.add_argument("--out", help="write the config fragment here (default calibration-KIND.yaml)")
        c.set_defaults(func=_cmd_calibrate)

    com = sub.add_parser("commission", help="guided: link, wiring, at rest, dynamics, odometry -> a calibrated "
                                            "config and a report (docs/commissioning.md)")
    com.add_argument("config", help="YAML config of the robot (what a ruler, a scale and the datasheets give)")
    com.add_argument("--out", metavar="FILE", help="the commissioned config (default CONFIG.commissioned.yaml); "
                                                   "its state file and report folder go beside it")
    com.add_argument("--area", metavar="WxH", help="free area in metres centred on the robot (default 2x1.5)")
    com.add_argument("--answers", metavar="FILE", help="YAML file of answers to the prompts (docs/commissioning.md)")
    com.add_argument("--from-sim-truth", action="store_true",
                     help="simulation: take the measurements from the plant's true pose")
    com.add_argument("--measurement-noise", metavar="MM,DEG",
                     help="with --from-sim-truth: tape and protractor noise, one sigma (default 2,0.5)")
    com.add_argument("--step", metavar="NAME", help="re-run one step: link, wiring, rest, dynamics, odometry, result")
    com.add_argument("--yes", action="store_true", help="skip confirmations (never measurements), for scripts")
    com.add_argument("--turns", type=int, default=5, help="odometry: full turns in place (default 5)")
    com.add_argument("--distance", type=float, default=1.0, help="odometry: straight distance in m (default 1)")
    com.add_argument("--umbmark", type=float, metavar="SIDE", help="odometry: also drive a SIDE m square both ways "
                                                                     "(UMBmark) and measure where each ends")
    com.add_argument("--no-check", action="store_true", help="result: no check path at the end")
    com.set_defaults(func=_cmd_commission)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except ValueError as exc:  # config, path and argument errors: one clear line, no trace
        print(f"ddrt: error: {_one_line(exc)}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # `ddrt path FILE | head`: the reader has what it wanted
        _silence_stdout()
        return 0
    except OSError as exc:  # a device that cannot be opened, an output that cannot be written
        print(f"ddrt: error: {_one_line(exc)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


def _silence_stdout() -> None:
    """Point stdout at /dev/null so the interpreter's final flush does not fail again."""
    import os

    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())
    os.close(devnull)


def _out_dir(arg: str, make: bool = False) -> Path:
    """--out DIR, or one line naming --out: a file is bad input (exit 2), a directory that cannot
    be made the machine's (exit 1); made at once with `make`. (ddrt sweep's journal checks its own.)"""
    out = Path(arg)
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {arg}: is a file, not a directory; give a directory for the output")
    try:
        if make:
            out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OSError(f"--out {arg}: cannot make the directory: {exc.strerror or exc}") from None
    return out


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


if __name__ == "__main__":
    sys.exit(main())
