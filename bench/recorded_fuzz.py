"""Recorded paths as they come: a fuzz of arcs, S-curves, U-turns and lane changes, recorded
at 5 mm to 10 cm spacing with 0 to 20 mm of noise, loaded at the default tolerance (`auto`)
and driven on the simulated robot.

`python -m bench.recorded_fuzz [--n N] [--seed S]` prints one line per path and the worst
margins; tests/test_recorded_fuzz.py runs the same draws. Each path must load (no curve is
refused), an arc never turns in place, an S-curve or a lane change never turns back in place
(90 degrees or more: at 20 mm of noise and 5 cm spacing a sharp S-bend may still read as a
corner at the scale the noise allows), and complete in `ddrt sim`
(run_sim on configs/sim.yaml, as `ddrt sim --path FILE` runs a CSV) within
1.3 x length / speed + 3 s, the length being the recorded curve's own.

The curves, each in arc length from the origin heading along +x:
- arc: radius 0.4-3 m through 45-270 degrees (at most 4 m);
- S-curve: curvature k0 sin(2 pi s / L), k0 0.5-2.5 /m, L 1.5-4 m;
- U-turn: a straight of 0.5-1.5 m, a half circle whose legs are 2 mm to 0.8 m apart, the
  straight back;
- lane change: a straight of 0.2-0.8 m, a cosine step of 0.1-0.8 m sideways over 0.6-2 m,
  a straight of 0.2-0.8 m.
Points are taken every `spacing` (log-uniform in 5 mm - 10 cm) along the curve, each moved by
Gaussian noise of `noise` (uniform in 0-20 mm) per axis; speed 0.2-0.6 m/s.
"""

from __future__ import annotations

import argparse
import math
import tempfile
from dataclasses import dataclass
from pathlib import Path as FsPath
from typing import Callable

import numpy as np

from bench.paths_as_given import SIM_CONFIG, write_csv
from ddrt.config import load_config
from ddrt.path.report import path_report, pivot_runs
from ddrt.path.spec import PathError, load_path, speed_limits
from ddrt.simrun.runner import run_sim

KINDS = ("arc", "s_curve", "u_turn", "lane_change")
TIME_FACTOR, TIME_EXTRA_S = 1.3, 3.0
STEP_M = 0.001  # the curves' own resolution
REVERSAL_DEG = 90.0  # a turn in place this large on an S-curve or a lane change would be a reversal


@dataclass(frozen=True)
class Recording:
    """One drawn path: its points (as recorded), the curve they stand for, and how it was drawn."""

    kind: str
    xy: np.ndarray
    curve: np.ndarray
    spacing: float
    noise: float
    speed: float
    detail: str

    @property
    def length(self) -> float:
        return float(np.sum(np.hypot(*np.diff(self.curve, axis=0).T)))

    @property
    def bound_s(self) -> float:
        return TIME_FACTOR * self.length / self.speed + TIME_EXTRA_S


@dataclass
class Outcome:
    """What became of one recording: loaded or refused, its turns in place, the closed loop."""

    rec: Recording
    error: str = ""
    pivots: int = 0
    duration_s: float = math.nan
    sim_s: float = math.nan
    completed: bool = False
    tolerance_m: float = math.nan
    noise_m: float = math.nan

    largest_turn_deg: float = 0.0  # of its turns in place

    @property
    def ok(self) -> bool:
        """Loaded, completed in time; an arc never turned in place, no other curve but a U-turn
        turned back (REVERSAL_DEG or more) in place."""
        turned = self.pivots > 0 if self.rec.kind == "arc" else (
            self.rec.kind != "u_turn" and self.largest_turn_deg >= REVERSAL_DEG)
        return not self.error and not turned and self.completed and self.sim_s <= self.rec.bound_s


def _integrate(kappa: Callable[[np.ndarray], np.ndarray], length: float) -> np.ndarray:
    """The curve whose curvature is kappa(s), from the origin along +x, every STEP_M."""
    s = np.linspace(0.0, length, max(2, int(math.ceil(length / STEP_M)) + 1))
    k = kappa(s)
    th = np.concatenate(([0.0], np.cumsum(0.5 * (k[1:] + k[:-1]) * np.diff(s))))
    ds = np.diff(s)
    x = np.concatenate(([0.0], np.cumsum(np.cos(0.5 * (th[1:] + th[:-1])) * ds)))
    y = np.concatenate(([0.0], np.cumsum(np.sin(0.5 * (th[1:] + th[:-1])) * ds)))
    return np.column_stack((x, y))


def _arc(rng: np.random.Generator) -> tuple[np.ndarray, str]:
    radius = float(rng.uniform(0.4, 3.0))
    sweep = min(math.radians(float(rng.uniform(45.0, 270.0))), 4.0 / radius)
    sign = float(rng.choice([-1.0, 1.0]))
    curve = _integrate(lambda s: np.full_like(s, sign / radius), radius * sweep)
    return curve, f"R {radius:.2f} m, {math.degrees(sweep):.0f} deg"


def _s_curve(rng: np.random.Generator) -> tuple[np.ndarray, str]:
    k0, length = float(rng.uniform(0.5, 2.5)), float(rng.uniform(1.5, 4.0))
    return _integrate(lambda s: k0 * np.sin(2.0 * math.pi * s / length), length), f"k0 {k0:.2f} /m, L {length:.2f} m"


def _u_turn(rng: np.random.Generator) -> tuple[np.ndarray, str]:
    leg = float(rng.uniform(0.5, 1.5))
    width = float(np.exp(rng.uniform(math.log(0.002), math.log(0.8))))
    r = 0.5 * width
    sign = float(rng.choice([-1.0, 1.0]))
    total = 2.0 * leg + math.pi * r
    return (_integrate(lambda s: np.where((s > leg) & (s < leg + math.pi * r), sign / r, 0.0), total),
            f"legs {leg:.2f} m, {width * 1000:.0f} mm apart")


def _lane_change(rng: np.random.Generator) -> tuple[np.ndarray, str]:
    a, b = float(rng.uniform(0.2, 0.8)), float(rng.uniform(0.2, 0.8))
    shift, over = float(rng.uniform(0.1, 0.8)) * float(rng.choice([-1.0, 1.0])), float(rng.uniform(0.6, 2.0))
    x = np.arange(0.0, a + over + b + 0.5 * STEP_M, STEP_M)
    t = np.clip((x - a) / over, 0.0, 1.0)
    return np.column_stack((x, 0.5 * shift * (1.0 - np.cos(math.pi * t)))), f"{shift:+.2f} m over {over:.2f} m"


SHAPES = {"arc": _arc, "s_curve": _s_curve, "u_turn": _u_turn, "lane_change": _lane_change}


def _sample(curve: np.ndarray, spacing: float, noise: float, rng: np.random.Generator) -> np.ndarray:
    """Points every `spacing` along the curve (and its end), with Gaussian noise per axis."""
    s = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(curve, axis=0).T))))
    at = np.append(np.arange(0.0, s[-1], spacing), s[-1])
    if at[-1] - at[-2] < 0.3 * spacing:
        at = np.delete(at, -2)
    xy = np.column_stack((np.interp(at, s, curve[:, 0]), np.interp(at, s, curve[:, 1])))
    return xy + rng.normal(0.0, noise, xy.shape)


def draw(rng: np.random.Generator, kind: str | None = None) -> Recording:
    """One recording: a kind (or the one given), its curve, spacing, noise and speed."""
    kind = kind or str(rng.choice(KINDS))
    curve, detail = SHAPES[kind](rng)
    spacing = float(np.exp(rng.uniform(math.log(0.005), math.log(0.1))))
    noise = float(rng.uniform(0.0, 0.02))
    speed = float(rng.uniform(0.2, 0.6))
    return Recording(kind, _sample(curve, spacing, noise, rng), curve, spacing, noise, speed, detail)


def recordings(n: int, seed: int) -> list[Recording]:
    """n draws, the kinds in turn (each kind as often as the others)."""
    rng = np.random.default_rng(seed)
    return [draw(rng, KINDS[i % len(KINDS)]) for i in range(n)]


def check(rec: Recording, sim: bool = True, seed: int = 1) -> Outcome:
    """Load the recording as `ddrt sim --path FILE` does (a CSV, configs/sim.yaml) and drive it."""
    cfg = load_config(SIM_CONFIG)
    out = Outcome(rec)
    with tempfile.TemporaryDirectory() as tmp:
        fname = FsPath(tmp) / f"{rec.kind}.csv"
        write_csv(fname, rec.xy, rec.speed)
        try:
            path = load_path(str(fname), speed_limits(cfg), paths=cfg.paths)
        except PathError as exc:
            out.error = str(exc).replace(str(fname), rec.kind)
            return out
    out.pivots = len(pivot_runs(path))
    out.largest_turn_deg = max((abs(math.degrees(t)) for *_, t in path_report(path, rec.kind).pivots), default=0.0)
    out.duration_s = path.duration
    if path.conditioning is not None:
        out.tolerance_m, out.noise_m = path.conditioning.tolerance_m, path.conditioning.noise_m
    if sim:
        m = run_sim(cfg, path, seed=seed).metrics
        out.completed, out.sim_s = bool(m["completed"]), float(m["sim_duration_s"])
    return out


def line(o: Outcome) -> str:
    r = o.rec
    head = (f"{'ok ' if o.ok else 'BAD'} {r.kind:<11s} {r.detail:<28s} spacing {r.spacing * 1000:5.1f} mm noise "
            f"{r.noise * 1000:4.1f} mm v {r.speed:.2f}")
    if o.error:
        return f"{head}: refused: {o.error}"
    return (f"{head}: noise ~{o.noise_m * 1000:4.1f} mm tol {o.tolerance_m * 1000:5.1f} mm, {o.pivots} pivot(s), "
            f"sim {o.sim_s:5.2f} s of {r.bound_s:5.2f} s{'' if o.completed else ' (not completed)'}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=40)
    ap.add_argument("--seed", type=int, default=22)
    ap.add_argument("--no-sim", action="store_true", help="load only")
    args = ap.parse_args(argv)
    outs = []
    for rec in recordings(args.n, args.seed):
        outs.append(check(rec, sim=not args.no_sim))
        print(line(outs[-1]), flush=True)
    bad = [o for o in outs if not o.ok]
    slack = [o.rec.bound_s - o.sim_s for o in outs if o.completed]
    print(f"{len(outs) - len(bad)} of {len(outs)} ok" + (f"; least time margin {min(slack):.2f} s" if slack else ""))
    return 1 if bad else 0


if __name__ == "__main__":
    raise SystemExit(main())
