"""`ddrt commission`: from a new robot to a calibrated, validated config in one guided command.

The steps, in order, one module each: link (the devices answer), wiring (which output drives
which wheel, which way the sensors count), rest (gyro bias and noise, the supply voltage),
dynamics (identification inside --area), odometry (encoder radius and gyro scale from a tape
and a protractor), result (the merged config, the check path, the report). answers.py is where
the user's observations come from, state.py what each finished step stored (so a run resumes
and `--step NAME` re-runs one), session.py what the steps share. docs/commissioning.md is the
user's guide.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

from ddrt.commission.session import STEPS, CommissionError, Options, Session, Stopped

__all__ = ["STEPS", "CommissionError", "Options", "Outcome", "Stopped", "commission", "paths_for", "session_for"]


@dataclass
class Outcome:
    ran: list[str]
    skipped: list[str]
    config_file: Path | None
    report: Path | None
    check: dict[str, Any] | None


def paths_for(out_file: Path) -> tuple[Path, Path]:
    """The state file and the report folder that go with the output config."""
    return out_file.with_name(out_file.stem + ".state.json"), out_file.with_name(out_file.stem + "-report")


def session_for(config_path: str | Path, opts: Options, given: dict[str, Any] | None = None, yes: bool = False,
                ask: Callable[[str], str] | None = None, out: Any = None) -> Session:
    """A session over the config file, its answers and the state file beside `opts.out`."""
    from ddrt.commission.answers import Answers
    from ddrt.commission.state import State
    from ddrt.config import load_config

    from hal.registry import backend_name

    cfg = load_config(config_path)
    if opts.from_sim_truth and backend_name(cfg) == "real":
        raise CommissionError("--from-sim-truth: only on a simulated robot (hal.backend: sim, or the emulated devices "
                              "hal.imu.bus: sim): it reads the plant's true pose")
    import hashlib
    import json

    digest = hashlib.sha256(json.dumps(cfg.raw, sort_keys=True, default=str).encode()).hexdigest()[:16]
    state = State(paths_for(opts.out)[0], str(Path(config_path).resolve()), digest)
    return Session(cfg, str(config_path), opts, Answers(given, yes=yes, ask=ask, out=out), state)


def _step_module(name: str) -> Any:
    import importlib

    return importlib.import_module(f"ddrt.commission.{name}")


def commission(session: Session, step: str | None = None) -> Outcome:
    """Run the steps not yet done (or only `step`), storing each one's result as it finishes."""
    if step is not None and step not in STEPS:
        raise CommissionError(f"--step: unknown step {step!r} (steps: {', '.join(STEPS)})")
    ran, skipped = [], []
    if session.state.stale:
        session.say(f"note: {session.config_path} changed since the stored steps ran ({session.state.path}); they are "
                    "kept: run a step again with --step NAME, or remove that file to start over")
    for name in STEPS[:-1]:
        if step is not None and name != step:
            continue
        if step is None and session.state.done(name):
            session.say(f"== {name}: done before ({session.state.steps[name]['finished']}), skipped; "
                        f"--step {name} runs it again")
            skipped.append(name)
            continue
        session.say(f"== {name}")
        result = _step_module(name).run(session)
        session.state.put(name, result)
        ran.append(name)
    outcome = Outcome(ran, skipped, None, None, None)
    if step is None or step == "result":
        from ddrt.commission import check, report, result as res

        out_file = session.opts.out
        session.say("== result")
        res.write_config(session, out_file)
        session.say(f"result: wrote {out_file}")
        chk = None
        if session.opts.check:
            session.say("== check")
            from ddrt.config import load_config

            chk = check.run(session, load_config(out_file))
        folder = paths_for(out_file)[1]
        outcome.report = report.write_report(session, folder, out_file, chk)
        session.state.put("result", {"config_file": str(out_file), "report": str(outcome.report),
                                     "check": {k: v for k, v in (chk or {}).items() if k != "trace"}})
        outcome.config_file, outcome.check = out_file, chk
        ran.append("result")
    return outcome
