"""The `ddrt` command: sim, run, ctl, calibrate."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Sequence


def _pose(text: str) -> tuple[float, float, float]:
    try:
        x, y, th = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y,THETA (metres, radians), got {text!r}") from None
    return x, y, th


def _cmd_sim(args: argparse.Namespace) -> int:
    from ddrt.config import load_config
    from ddrt.simrun import resolve_path, run_sim, stderr_progress, summary_text, write_outputs

    overrides = {"sim": {"seed": args.seed}} if args.seed is not None else None
    cfg = load_config(args.config, overrides)
    path = resolve_path(cfg, args.path)
    result = run_sim(cfg, path, duration=args.duration, seed=args.seed, start=args.start,
                     progress=None if args.quiet else stderr_progress)
    if not args.quiet:
        sys.stderr.write("\n")
    write_outputs(result, args.out)
    if args.plot:
        from ddrt.plots import write_plots

        write_plots(result, args.out)
    print(summary_text(result.metrics))
    print(f"wrote {args.out}/telemetry.csv and {args.out}/metrics.json" + (" and figures" if args.plot else ""))
    return 0 if result.metrics["completed"] else 1


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="ddrt", description="Real-time controller for differential-drive robots.")
    sub = parser.add_subparsers(dest="command", required=True)

    sim = sub.add_parser("sim", help="run the closed loop on the simulated robot, as fast as possible")
    sim.add_argument("config", help="YAML config (e.g. configs/sim.yaml)")
    sim.add_argument("--path", help="path file (.csv or .yaml); default: the config's path:")
    sim.add_argument("--duration", type=float, help="stop after this many simulated seconds")
    sim.add_argument("--seed", type=int, help="noise seed of the simulated robot")
    sim.add_argument("--start", type=_pose, help="start pose X,Y,THETA (default: the path's start)")
    sim.add_argument("--out", default="out", help="output directory (default: out)")
    sim.add_argument("--plot", action="store_true", help="also write the seed's figures as PNG")
    sim.add_argument("--quiet", action="store_true", help="no progress line")
    sim.set_defaults(func=_cmd_sim)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except ValueError as exc:  # config, path and argument errors: one clear line, no trace
        print(f"ddrt: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
