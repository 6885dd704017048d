"""`ddrt sweep`: a campaign file to a table, a summary and figures in an output folder.

Check every case first (nothing runs if one is bad), then run the cases that have no row yet
on the executor, appending each row to the journal as it comes, and finally write the table,
the summary and the figures from every row the folder holds. A Ctrl-C stops the runs, keeps
what finished and still writes the table of it; `--resume` runs the rest.
"""

from __future__ import annotations

import signal
import threading
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path as FsPath
from typing import Iterator, Sequence

from ddrt.sweep.campaign import CampaignError, load_campaign
from ddrt.sweep.cases import Plan, expand
from ddrt.sweep.execute import DaskCluster, InProcess, machine_workers, silence_shutdown_logs
from ddrt.sweep.journal import Journal
from ddrt.sweep.progress import Progress
from ddrt.sweep.run import Row
from ddrt.sweep.summary import SUMMARY, summary_text
from ddrt.sweep.table import CSV, PARQUET, write_table


@dataclass(frozen=True)
class SweepRequest:
    """What `ddrt sweep` was asked."""

    campaign: str
    out: FsPath
    workers: int | None = None  # local worker processes; None: one per core
    scheduler: str | None = None  # a running Dask scheduler instead of a local cluster
    resume: bool = False
    limit: int | None = None  # run at most this many of the cases left
    quiet: bool = False


@dataclass
class SweepReport:
    """What a sweep did, for the command's last lines and its exit status."""

    plan: Plan
    out: FsPath
    ran: int = 0  # runs finished in this session
    resumed: int = 0  # rows kept from an earlier session
    rows: list[Row] = field(default_factory=list)  # every row the folder holds now
    interrupted: bool = False
    figures: int = 0

    @property
    def left(self) -> int:
        return len(self.plan.cases) - len(self.rows)

    @property
    def not_ok(self) -> int:
        return sum(r.get("status") != "ok" for r in self.rows)

    @property
    def exit_status(self) -> int:
        """130 interrupted; 1 when a run failed or timed out; else 0 (pass rates are in the summary)."""
        if self.interrupted:
            return 130
        return 1 if self.not_ok else 0

    def text(self) -> str:
        passed = sum(bool(r.get("pass")) for r in self.rows)
        lines = [f"sweep: {len(self.rows)} of {len(self.plan.cases)} cases have rows ({self.ran} run now, "
                 f"{self.resumed} kept from before); {self.not_ok} failed or timed out; {passed} passed",
                 f"wrote {self.out / PARQUET}, {self.out / CSV}, {self.out / SUMMARY}"
                 + (f" and {self.figures} figure{'s' * (self.figures != 1)}" if self.figures else "")]
        if self.left:
            lines.append(("interrupted: " if self.interrupted else "") + f"{self.left} cases left; "
                         "the same command with --resume runs them")
        return "\n".join(lines)


def make_executor(workers: int | None, scheduler: str | None = None) -> InProcess | DaskCluster:
    """In this process for one worker and no scheduler; else Dask."""
    if scheduler is None and workers == 1:
        return InProcess()
    return DaskCluster(workers, scheduler)


def run_plan(plan: Plan, workers: int | None = 2, scheduler: str | None = None,
             progress: Progress | None = None) -> list[Row]:
    """Every case of `plan`, in case order: the runner's API for a program (a benchmark)."""
    rows = []
    with make_executor(workers, scheduler) as ex:
        for row in ex.run(plan.cases, plan.paths, plan.campaign.run):
            rows.append(row)
            if progress is not None:
                progress.update(row["status"] == "ok")
    if progress is not None:
        progress.close()
    return sorted(rows, key=lambda r: r["case"])


def write_results(plan: Plan, rows: Sequence[Row], out: FsPath) -> int:
    """The table, the summary and the figures of `rows`; returns how many figures."""
    from ddrt.sweep.figures import write_figures

    write_table(plan, rows, out)
    (out / SUMMARY).write_text(summary_text(plan, rows), encoding="utf-8")
    return len(write_figures(plan, rows, out))


def sweep(req: SweepRequest) -> SweepReport:
    """Run a campaign file into `req.out` (see the module doc)."""
    if req.limit is not None and req.limit < 1:
        raise CampaignError(f"--limit: expected a number of runs >= 1, got {req.limit}")
    if req.workers is not None and req.workers < 1:
        raise CampaignError(f"--workers: expected a number of processes >= 1, got {req.workers}")
    if req.scheduler is not None and req.workers is not None:
        raise CampaignError("--workers sizes the local cluster; a cluster at --scheduler has its own workers")
    plan = expand(load_campaign(req.campaign))
    journal = Journal(FsPath(req.out), plan, req.resume)
    report = SweepReport(plan, FsPath(req.out), resumed=journal.resumed)
    todo = [c for c in plan.cases if c.case_id not in journal.rows]
    if req.limit is not None:
        todo = todo[:req.limit]
    progress = Progress(len(todo), enabled=not req.quiet)
    try:
        with _interrupt_flag() as interrupted:
            if todo:
                # No more local workers than runs: each is a process that costs a start-up.
                workers = None if req.scheduler is not None else min(req.workers or machine_workers(), len(todo))
                with DaskCluster(workers, req.scheduler) as cluster:
                    progress.start()
                    for row in cluster.run(todo, plan.paths, plan.campaign.run):
                        journal.append(row)
                        report.ran += 1
                        progress.update(row["status"] == "ok")
                        if interrupted.is_set():
                            raise KeyboardInterrupt
    except KeyboardInterrupt:
        report.interrupted = True
    finally:
        progress.close()
        journal.close()
    report.rows = sorted(journal.rows.values(), key=lambda r: r["case"])
    report.figures = write_results(plan, report.rows, report.out)
    return report


@contextmanager
def _interrupt_flag() -> Iterator[threading.Event]:
    """A Ctrl-C both raises KeyboardInterrupt (to leave a wait at once) and sets a flag the
    loop checks after every row: a KeyboardInterrupt that lands inside Dask's client code can
    be swallowed there (seen on a loaded machine: the campaign ran to its end and exited 0)."""
    flag = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield flag  # signal handlers belong to the main thread; nothing to install here
        return

    def on_sigint(signum: int, frame: object) -> None:
        flag.set()
        silence_shutdown_logs()  # before the shutdown's first cancelled callback can log
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGINT, on_sigint)
    try:
        yield flag
    finally:
        signal.signal(signal.SIGINT, previous)
