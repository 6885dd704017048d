"""`ddrt sweep` on real Dask clusters: a `dask scheduler` and `dask
worker` processes on loopback, started here and always stopped here.

- the same 40-case campaign on that cluster and on a LocalCluster gives the same table;
- a worker killed while it runs cases loses no row;
- Ctrl-C keeps what finished, and --resume runs only what is left.

Each waits on what it can observe (rows in the journal, tasks on a worker), never on a
fixed number of seconds, and asserts on what it measured.
"""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

import pytest

from ddrt.sweep.journal import ROWS
from ddrt.sweep.table import read_table, without_wall_time

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[1]
CASES = 40
CAMPAIGN = f"""\
name: cluster test
base: {REPO / "configs" / "scenarios" / "s_curve.yaml"}
overrides: {{sim: {{start_delay_s: 0}}}}
axes:
  controller.outer.k_y: [100, 200, 400, 800, 1600]
  controller.outer.k_theta: [20, 40]
seeds: 4
run: {{duration_s: 1.5}}
pass: ["rms_cross_track_m < 0.001"]
"""
START_TIMEOUT_S = 120.0
RUN_TIMEOUT_S = 300.0


def wait_for(what: str, ready: Callable[[], bool], timeout: float = START_TIMEOUT_S, every: float = 0.05) -> None:
    deadline = time.monotonic() + timeout
    while not ready():
        if time.monotonic() > deadline:
            raise AssertionError(f"gave up waiting {timeout:g} s for {what}")
        time.sleep(every)


def rows_in(out: Path) -> int:
    try:
        return (out / ROWS).read_bytes().count(b"\n")
    except FileNotFoundError:
        return 0


def interrupted_sweep(cmd: list[str], out: Path, rows: int, interrupt: Callable[[subprocess.Popen], None],
                      new_session: bool = False) -> tuple[subprocess.Popen, str, str]:
    """Start `cmd`, wait until `out` holds `rows` rows (or it ended), `interrupt` it, and
    return the finished process with its stdout and stderr."""
    sweep = subprocess.Popen(cmd, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                             start_new_session=new_session)
    try:
        wait_for(f"{rows} row(s)", lambda: rows_in(out) >= rows or sweep.poll() is not None, timeout=RUN_TIMEOUT_S)
        interrupt(sweep)
        stdout, stderr = sweep.communicate(timeout=RUN_TIMEOUT_S)
    finally:
        if sweep.poll() is None:
            sweep.kill()
    return sweep, stdout, stderr


def sweep_cmd(campaign: Path, out: Path, *extra: str) -> list[str]:
    return [sys.executable, "-m", "ddrt.cli", "sweep", str(campaign), "--out", str(out), "--quiet", *extra]


def run_sweep(campaign: Path, out: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(sweep_cmd(campaign, out, *extra), capture_output=True, text=True, timeout=RUN_TIMEOUT_S,
                          cwd=REPO)


def stop(procs: list[subprocess.Popen]) -> None:
    """Each worker, then the scheduler, one at a time: stopped together, a worker waits for
    its scheduler's goodbye that never comes."""
    for p in reversed(procs):
        if p.poll() is None:
            p.terminate()
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait(timeout=10)


@dataclass
class Cluster:
    """A scheduler and its workers, each a process this module started."""

    folder: Path
    scheduler_file: Path
    procs: list[subprocess.Popen] = field(default_factory=list)
    workers: dict[str, subprocess.Popen] = field(default_factory=dict)

    @property
    def address(self) -> str:
        return json.loads(self.scheduler_file.read_text())["address"]

    def start_worker(self, name: str) -> subprocess.Popen:
        log = open(self.folder / f"{name}.log", "w")
        p = subprocess.Popen([sys.executable, "-m", "dask", "worker", "--scheduler-file", str(self.scheduler_file),
                              "--name", name, "--nthreads", "1", "--no-nanny", "--no-dashboard",
                              "--host", "127.0.0.1"], stdout=log, stderr=subprocess.STDOUT, cwd=REPO)
        self.procs.append(p)
        self.workers[name] = p
        return p

    def client(self):
        from distributed import Client

        return Client(self.address, timeout="30s")


def names_up(client) -> set[str]:
    return {str(w["name"]) for w in client.scheduler_info()["workers"].values()}


@pytest.fixture(scope="module")
def campaign(tmp_path_factory: pytest.TempPathFactory) -> Path:
    p = tmp_path_factory.mktemp("campaign") / "cluster.yaml"
    p.write_text(CAMPAIGN)
    return p


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cluster]:
    folder = tmp_path_factory.mktemp("dask")
    c = Cluster(folder, folder / "scheduler.json")
    try:
        log = open(folder / "scheduler.log", "w")
        c.procs.append(subprocess.Popen([sys.executable, "-m", "dask", "scheduler", "--host", "127.0.0.1",
                                         "--port", "0", "--no-dashboard", "--scheduler-file", str(c.scheduler_file)],
                                        stdout=log, stderr=subprocess.STDOUT, cwd=REPO))
        wait_for("the scheduler's address", lambda: c.scheduler_file.exists() and c.scheduler_file.stat().st_size > 0)
        for name in ("w1", "w2"):
            c.start_worker(name)
        with c.client() as client:
            wait_for("two workers", lambda: names_up(client) >= {"w1", "w2"})
        yield c
    finally:
        stop(c.procs)


@pytest.fixture(scope="module")
def reference(campaign: Path, tmp_path_factory: pytest.TempPathFactory):
    """The campaign on a LocalCluster of two worker processes (the command's default kind)."""
    out = tmp_path_factory.mktemp("local")
    done = run_sweep(campaign, out, "--workers", "2")
    assert done.returncode == 0, done.stderr
    assert f"{CASES} of {CASES} cases have rows ({CASES} run now" in done.stdout
    table = read_table(out / "results.parquet")
    assert table.num_rows == CASES and set(table.column("status").to_pylist()) == {"ok"}
    return without_wall_time(table)


def test_a_real_cluster_gives_the_same_table_as_a_local_one(cluster: Cluster, campaign: Path, reference,
                                                            tmp_path: Path) -> None:
    done = run_sweep(campaign, tmp_path, "--scheduler", cluster.address)
    assert done.returncode == 0, done.stderr
    table = without_wall_time(read_table(tmp_path / "results.parquet"))
    assert table.equals(reference)
    assert len(set(table.column("rms_cross_track_m").to_pylist())) == CASES  # 40 different runs, not one 40 times


def test_a_worker_killed_mid_campaign_loses_no_row(cluster: Cluster, campaign: Path, reference, tmp_path: Path) -> None:
    victim = cluster.start_worker("w3")
    with cluster.client() as client:
        wait_for("the third worker", lambda: "w3" in names_up(client))
        sweep = subprocess.Popen(sweep_cmd(campaign, tmp_path, "--scheduler", cluster.address), cwd=REPO,
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            addr = next(a for a, w in client.scheduler_info()["workers"].items() if str(w["name"]) == "w3")
            held: list[str] = []

            def w3_busy() -> bool:
                held[:] = [str(k) for k in client.processing().get(addr, ())]
                return any(k.startswith("ddrt-case-") for k in held) or sweep.poll() is not None

            wait_for("w3 to run a case", w3_busy, timeout=RUN_TIMEOUT_S)
            rows_before = rows_in(tmp_path)
            victim.kill()
            victim.wait(timeout=10)
            out, err = sweep.communicate(timeout=RUN_TIMEOUT_S)
        finally:
            if sweep.poll() is None:
                sweep.kill()
    assert held and rows_before < CASES, "the campaign ended before the worker could be killed in it"
    assert sweep.returncode == 0, err
    assert f"{CASES} of {CASES} cases have rows" in out and "0 failed" in out
    table = without_wall_time(read_table(tmp_path / "results.parquet"))
    assert table.equals(reference)  # the killed worker's cases ran again elsewhere, with the same results


def test_ctrl_c_keeps_what_finished_and_resume_runs_only_the_rest(cluster: Cluster, campaign: Path, reference,
                                                                  tmp_path: Path) -> None:
    sweep, out, err = interrupted_sweep(sweep_cmd(campaign, tmp_path, "--scheduler", cluster.address), tmp_path,
                                        rows=3, interrupt=lambda p: p.send_signal(signal.SIGINT))
    kept = rows_in(tmp_path)
    assert sweep.returncode == 130, (out, err)
    assert "Traceback" not in err
    assert 3 <= kept < CASES
    assert f"{kept} of {CASES} cases have rows" in out and f"interrupted: {CASES - kept} cases left" in out
    assert read_table(tmp_path / "results.parquet").num_rows == kept  # the table of what finished

    done = run_sweep(campaign, tmp_path, "--scheduler", cluster.address, "--resume")
    assert done.returncode == 0, done.stderr
    m = re.search(r"(\d+) run now, (\d+) kept from before", done.stdout)
    assert m is not None and (int(m.group(1)), int(m.group(2))) == (CASES - kept, kept)
    assert rows_in(tmp_path) == CASES  # no case ran twice
    assert without_wall_time(read_table(tmp_path / "results.parquet")).equals(reference)


def test_ctrl_c_at_a_terminal_stops_a_local_cluster_cleanly(campaign: Path, tmp_path: Path) -> None:
    """A terminal's Ctrl-C reaches the whole process group, the LocalCluster's workers too:
    only `ddrt sweep` answers it (no worker prints a traceback), keeps what finished, and no
    process of the group outlives it."""
    import os

    sweep, out, err = interrupted_sweep(sweep_cmd(campaign, tmp_path, "--workers", "2"), tmp_path, rows=1,
                                        interrupt=lambda p: os.killpg(p.pid, signal.SIGINT), new_session=True)
    kept = rows_in(tmp_path)
    assert sweep.returncode == 130, (out, err)
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err
    assert 1 <= kept < CASES and read_table(tmp_path / "results.parquet").num_rows == kept
    ps = subprocess.run(["ps", "-o", "pid=,stat=,args=", "-g", str(sweep.pid)], capture_output=True, text=True).stdout
    alive = [line for line in ps.splitlines() if line.split()[1][0] != "Z"]  # a zombie has exited already
    assert alive == []
