"""docs/guide.md runs as written: every shell block marked to run on the simulated robot is run
here, in a copy of configs/ and firmware/, with the venv's `ddrt` on PATH, and what the guide
says you should see after it is checked against what it printed and wrote.

A shell block is preceded by one marker line:

- `<!-- guide: run -->`: run it alone (`needs=A,B` skips it without those tools or modules);
- `<!-- guide: run daemon -->`: start it in the background and wait for the daemon to be
  ready; the `<!-- guide: run with daemon -->` blocks after it run against it, then it is
  stopped with Ctrl-C (SIGINT) and must exit 0;
- `<!-- guide: install -->`: the README's install command (the test environment ran it);
- `<!-- guide: hardware -->`: needs the robot; not run.

"You should see" claims: each `code span` in the paragraph that follows a block (or group)
and begins with "**You should see**" must occur in its output (whitespace-normalised) or name
a file it wrote; spans with "..." and commands (`ddrt ...`, `sudo ...`) are not claims.
"""

from __future__ import annotations

import importlib.util
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from tests.support.repo import REPO

GUIDE = REPO / "docs" / "guide.md"
README = REPO / "README.md"
MARKER = re.compile(r"^<!-- guide: (run daemon|run with daemon|run|install|hardware)((?: [a-z]+=\S+)*) -->$")
KINDS_NOT_RUN = ("install", "hardware")
COMMAND_WORDS = ("ddrt", "ros2", "sudo", "pip", "python", "python3", "make", "ls", "journalctl", "systemctl")
BLOCK_TIMEOUT_S = 300.0
READY_TIMEOUT_S = 60.0
SIM_COMMAND = ("python3 -m venv .venv && .venv/bin/pip install -q -e '.[plot]' && "
               ".venv/bin/ddrt sim configs/sim.yaml --plot")
TEST_COMMAND = ("python3 -m venv .venv && .venv/bin/pip install -q -e '.[test]' && "
                ".venv/bin/python -m pytest")


@dataclass(frozen=True)
class Block:
    kind: str
    code: str
    line: int  # of the opening fence, 1-based
    needs: tuple[str, ...]
    claims: tuple[str, ...]  # the code spans of the "You should see" paragraph after it


@dataclass
class Case:
    """One test: a block run alone, or a daemon block with the blocks run against it."""

    blocks: list[Block] = field(default_factory=list)

    @property
    def name(self) -> str:
        return f"line{self.blocks[0].line}"


def _claims_after(lines: list[str], start: int) -> tuple[str, ...]:
    """The code spans of the first "**You should see**" paragraph after line `start`, up to the
    next shell block."""
    for i in range(start, len(lines)):
        if lines[i].startswith("```sh"):
            return ()
        if lines[i].startswith("**You should see**"):
            para = []
            for j in range(i, len(lines)):
                if not lines[j].strip():
                    break
                para.append(lines[j])
            spans = re.findall(r"`([^`]+)`", " ".join(para))
            return tuple(s for s in spans if "..." not in s and s.split()[0] not in COMMAND_WORDS)
    return ()


def parse_guide(text: str) -> list[Block]:
    """Every ```sh block of the guide with its marker; a block without one is an error."""
    lines = text.splitlines()
    blocks = []
    for i, line in enumerate(lines):
        if not line.startswith("```sh"):
            continue
        m = MARKER.match(lines[i - 1]) if i > 0 else None
        if m is None:
            raise ValueError(f"docs/guide.md line {i + 1}: a shell block without a <!-- guide: ... --> marker")
        options = dict(opt.split("=", 1) for opt in m.group(2).split())
        end = lines.index("```", i + 1)
        blocks.append(Block(kind=m.group(1), code="\n".join(lines[i + 1:end]) + "\n", line=i + 1,
                            needs=tuple(options.get("needs", "").split(",")) if "needs" in options else (),
                            claims=_claims_after(lines, end + 1)))
    return blocks


def cases(blocks: list[Block]) -> list[Case]:
    out: list[Case] = []
    for b in blocks:
        if b.kind in KINDS_NOT_RUN:
            continue
        if b.kind == "run with daemon":
            if not out or out[-1].blocks[0].kind != "run daemon":
                raise ValueError(f"docs/guide.md line {b.line}: 'run with daemon' without a daemon block before it")
            out[-1].blocks.append(b)
        else:
            out.append(Case([b]))
    return out


BLOCKS = parse_guide(GUIDE.read_text(encoding="utf-8"))
CASES = cases(BLOCKS)


def _missing(needs: tuple[str, ...]) -> list[str]:
    missing = []
    for need in needs:
        if need == "avr-gcc":
            ok = shutil.which("avr-gcc") is not None and Path("/usr/lib/avr/include/avr/io.h").exists()
        elif need == "simavr":
            ok = Path("/usr/include/simavr/sim_avr.h").exists()
        else:
            ok = importlib.util.find_spec(need) is not None
        if not ok:
            missing.append(need)
    return missing


def _workdir(tmp_path: Path) -> Path:
    """A copy of what the guide's commands read: configs/ and the firmware's sources."""
    work = tmp_path / "repo"
    work.mkdir()
    shutil.copytree(REPO / "configs", work / "configs")
    shutil.copytree(REPO / "firmware", work / "firmware", ignore=shutil.ignore_patterns("build"))
    return work


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env["MPLBACKEND"] = "Agg"
    env.pop("DDRT_SOCKET", None)
    return env


def _run(block: Block, work: Path) -> str:
    proc = subprocess.run(["bash", "-euo", "pipefail", "-c", block.code], cwd=work, env=_env(),
                          capture_output=True, text=True, timeout=BLOCK_TIMEOUT_S)
    out = proc.stdout + proc.stderr
    assert proc.returncode == 0, f"docs/guide.md line {block.line}: exit {proc.returncode}\n{block.code}\n{out[-4000:]}"
    return out


def _check_claims(block: Block, output: str, work: Path) -> None:
    said = " ".join(output.split())
    for claim in block.claims:
        wanted = " ".join(claim.split())
        assert wanted in said or (work / claim).exists(), \
            f"docs/guide.md line {block.line}: you should see `{claim}`, but it was not printed nor written:\n{output[-3000:]}"


def _run_with_daemon(case: Case, work: Path) -> None:
    daemon, *clients = case.blocks
    log = work / "daemon.log"
    with open(log, "w") as sink:
        proc = subprocess.Popen(["bash", "-euo", "pipefail", "-c", daemon.code], cwd=work, env=_env(),
                                stdout=sink, stderr=subprocess.STDOUT, start_new_session=True)
    try:
        deadline = time.monotonic() + READY_TIMEOUT_S
        while "ready after" not in log.read_text():
            assert proc.poll() is None, f"docs/guide.md line {daemon.line}: the daemon exited {proc.returncode}:\n{log.read_text()}"
            assert time.monotonic() < deadline, f"docs/guide.md line {daemon.line}: not ready:\n{log.read_text()}"
            time.sleep(0.1)
        outputs = [_run(b, work) for b in clients]
        os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C in the daemon's terminal
        assert proc.wait(timeout=30) == 0, f"docs/guide.md line {daemon.line}: exit {proc.returncode}:\n{log.read_text()}"
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    _check_claims(daemon, log.read_text() + "".join(outputs), work)
    for b, out in zip(clients, outputs):
        _check_claims(b, out, work)


def test_every_shell_block_is_marked_and_runs_somewhere() -> None:
    kinds = [b.kind for b in BLOCKS]
    assert kinds.count("run") >= 5 and "run daemon" in kinds and "hardware" in kinds
    assert sum(len(c.blocks) for c in CASES) == sum(k not in KINDS_NOT_RUN for k in kinds)


def test_a_block_without_a_marker_is_refused() -> None:
    with pytest.raises(ValueError, match="line 3: a shell block without"):
        parse_guide("# g\n\n```sh\nddrt sim x\n```\n")
    with pytest.raises(ValueError, match="without a daemon block"):
        cases(parse_guide("<!-- guide: run with daemon -->\n```sh\nddrt ctl status\n```\n"))


def test_claims_are_the_code_spans_after_the_block() -> None:
    (b,) = parse_guide("<!-- guide: run -->\n```sh\nx\n```\n\n**You should see** `a  b`, `ddrt x`, `c ... d`\n"
                       "and `e`.\n\nNot `f`.\n")
    assert b.claims == ("a  b", "e")


def test_the_install_block_is_the_readme_command_and_ci_runs_the_test_command() -> None:
    readme = README.read_text(encoding="utf-8")
    assert f"    {SIM_COMMAND}\n" in readme and f"    {TEST_COMMAND}\n" in readme
    (install,) = [b for b in BLOCKS if b.kind == "install"]
    assert install.code.splitlines()[0] == SIM_COMMAND
    ci = (REPO / ".ci" / "run").read_text(encoding="utf-8").strip().splitlines()
    assert ci[-1] == TEST_COMMAND


@pytest.mark.slow  # 40 to 50 s in all on 2 cores
@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_the_guide_runs_as_written(case: Case, tmp_path: Path) -> None:
    needs = [n for b in case.blocks for n in b.needs]
    missing = _missing(tuple(needs))
    if missing:
        if os.environ.get("DDRT_REQUIRE_FIRMWARE") == "1" and {"avr-gcc", "simavr"} & set(missing):
            pytest.fail(f"docs/guide.md line {case.blocks[0].line} needs {missing} (DDRT_REQUIRE_FIRMWARE=1)")
        pytest.skip(f"docs/guide.md line {case.blocks[0].line} needs {', '.join(missing)}")
    work = _workdir(tmp_path)
    if case.blocks[0].kind == "run daemon":
        _run_with_daemon(case, work)
    else:
        (block,) = case.blocks
        _check_claims(block, _run(block, work), work)
