"""Where the cases run: one after another in this process, or on a Dask cluster.

Both yield rows as runs finish. The Dask executor starts a LocalCluster of worker processes
(one thread each: the simulator is pure Python and holds the GIL) sized to the machine, or
connects to a running scheduler (`tcp://host:8786`). Each distinct path is one task whose
argument is the built path, so the scheduler can rebuild it wherever it is needed, also
after the worker that held it died; each case is one task keyed by its case id. When a
worker dies, Dask runs its cases again elsewhere (a row depends only on its case, so the
rerun gives the same row); a case whose workers keep dying becomes a failed row.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
from typing import Any, Iterator, Mapping, Sequence

from ddrt.path import Path
from ddrt.sweep.campaign import RunSettings
from ddrt.sweep.cases import Case
from ddrt.sweep.run import Row, blank_row, run_case

CONNECT_TIMEOUT_S = 10.0


def machine_workers() -> int:
    """The cores this process may use (its CPU affinity, else the machine's count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


class InProcess:
    """Case after case in this process: the sequential baseline, and a campaign without Dask."""

    workers = 1

    def __enter__(self) -> "InProcess":
        return self

    def __exit__(self, *exc: object) -> None:
        pass

    def run(self, cases: Sequence[Case], paths: Mapping[str, Path], settings: RunSettings) -> Iterator[Row]:
        for case in cases:
            yield run_case(case, paths[case.path_key], settings)


def _path_of(path: Path) -> Path:
    """A task whose result is its argument: the path lives in the graph, so it can be recomputed."""
    return path


@contextlib.contextmanager
def _sigint_ignored() -> Iterator[None]:
    """SIGINT ignored while the local worker processes start, so they inherit that: a Ctrl-C
    at the terminal (sent to the whole process group) reaches only `ddrt sweep`, which keeps
    what finished and shuts the cluster down, instead of every worker printing a traceback."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _quiet() -> None:
    for name in ("distributed", "distributed.worker", "distributed.nanny", "distributed.scheduler"):
        logging.getLogger(name).setLevel(logging.ERROR)


SHUTDOWN_LOGGERS = ("tornado", "asyncio", "distributed")


def silence_shutdown_logs() -> None:
    """Only CRITICAL from tornado, asyncio and distributed, and from each of their loggers that
    has a level of its own (Dask's logging config gives `tornado.application`, which logs a
    failed callback's traceback, ERROR): leaving on Ctrl-C or an error, the client's event loop
    may still run callbacks for futures the shutdown cancels. What finished is in the journal."""
    names = [n for n in logging.root.manager.loggerDict if n.split(".")[0] in SHUTDOWN_LOGGERS]
    for name in (*SHUTDOWN_LOGGERS, *names):
        logging.getLogger(name).setLevel(logging.CRITICAL)


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split())
    return text if isinstance(exc, (OSError, ValueError)) and text else f"{type(exc).__name__}: {text}"


def probe_scheduler(address: str, timeout_s: float | None = None) -> None:
    """Connect to `address` and exchange Dask's handshake within `timeout_s` in all, else an
    OSError naming the address. Client(timeout=) bounds the TCP connect but not the handshake,
    so a server that accepts and stays silent (a web server, an SSH port) held `ddrt sweep`
    for ever; one that answers with other bytes raised whatever Dask made of them (a
    MemoryError for a frame length read from text, a TypeError for tls:// without a context)."""
    import asyncio

    from distributed.comm import connect

    limit = CONNECT_TIMEOUT_S if timeout_s is None else timeout_s

    async def handshake() -> None:
        comm = await connect(address, timeout=limit)
        await comm.close()

    try:  # with a margin, so a connect that times out by itself says so
        asyncio.run(asyncio.wait_for(handshake(), 1.5 * limit))
    except asyncio.TimeoutError:
        raise OSError(f"cannot reach the Dask scheduler at {address}: no Dask handshake within {1.5 * limit:g} s "
                      "(is a Dask scheduler listening there?)") from None
    except Exception as exc:  # noqa: BLE001 - whatever the address did, one line naming it
        raise OSError(f"cannot reach the Dask scheduler at {address}: {_one_line(exc)}") from None


class DaskCluster:
    """A Dask client on a LocalCluster of `workers` processes, or on the scheduler at `scheduler`."""

    def __init__(self, workers: int | None = None, scheduler: str | None = None) -> None:
        self.requested = workers
        self.scheduler = scheduler
        self.client: Any = None
        self.cluster: Any = None

    @property
    def workers(self) -> int:
        if self.client is None:
            return 0
        return len(self.client.scheduler_info().get("workers", {}))

    def __enter__(self) -> "DaskCluster":
        try:
            from distributed import Client, LocalCluster
        except ImportError:
            raise ValueError("ddrt sweep runs on Dask, which is not installed: pip install 'ddrt[sweep]'") from None
        _quiet()
        if self.scheduler is not None:
            probe_scheduler(self.scheduler)
            try:
                self.client = Client(self.scheduler, timeout=f"{CONNECT_TIMEOUT_S}s")
            except Exception as exc:  # noqa: BLE001 - whatever the address did, one line naming it
                raise OSError(f"cannot reach the Dask scheduler at {self.scheduler}: {_one_line(exc)}") from None
        else:
            with _sigint_ignored():
                # No dashboard, and the scheduler's plain HTTP endpoint on a free loopback port (with
                # dashboard_address=None alone it still takes :8787, and warns when that is in use).
                # Workers log CRITICAL only: a heartbeat that meets a scheduler already closing at
                # Ctrl-C is expected, and a case's own failure comes back as its row's error.
                self.cluster = LocalCluster(n_workers=self.requested or machine_workers(), threads_per_worker=1,
                                            processes=True, dashboard_address=None,
                                            scheduler_kwargs={"dashboard": False, "dashboard_address": "127.0.0.1:0"},
                                            silence_logs=logging.CRITICAL)
            self.client = Client(self.cluster)
        return self

    def __exit__(self, *exc: object) -> None:
        if exc and exc[0] is not None:
            silence_shutdown_logs()  # a cancelled future's callback logged a traceback once in ten Ctrl-Cs
        for thing in (self.client, self.cluster):
            if thing is not None:
                try:
                    thing.close()
                except Exception:  # noqa: BLE001 - closing after a failure must not hide it
                    pass
        self.client = self.cluster = None

    def run(self, cases: Sequence[Case], paths: Mapping[str, Path], settings: RunSettings) -> Iterator[Row]:
        from distributed import as_completed

        client = self.client
        path_tasks = {key: client.submit(_path_of, paths[key], key=f"ddrt-path-{key}", pure=False)
                      for key in dict.fromkeys(c.path_key for c in cases)}
        futures = [client.submit(run_case, case, path_tasks[case.path_key], settings, key=f"ddrt-case-{case.case_id}",
                                 priority=int(case.expected_s * 1000), pure=False)
                   for case in cases]
        by_key = {f.key: case for f, case in zip(futures, cases)}
        pending = {f.key: f for f in futures}
        try:
            for fut in as_completed(futures):
                case = by_key[fut.key]
                del pending[fut.key]
                if fut.status == "finished":
                    row = fut.result()
                elif fut.status == "cancelled":
                    row = blank_row(case, settings, "failed", "cancelled on the cluster")
                else:
                    exc = fut.exception()
                    row = blank_row(case, settings, "failed", f"{type(exc).__name__}: {' '.join(str(exc).split())}")
                fut.release()
                yield row
        finally:  # interrupted (Ctrl-C) or done: nothing of this campaign stays queued on the cluster
            client.cancel(list(pending.values()) + list(path_tasks.values()))
