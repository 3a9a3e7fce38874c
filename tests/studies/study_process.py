"""A study as its user runs it: ``surprise-study run`` in a process of its own, broken from
outside, and what must hold of its runs afterwards (each ended once, with the local pool's
values). Shared by the tests that break a Dask cluster and those that end Slurm jobs."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pandas as pd
from dask_cluster import wait_until
from study_helpers import TINY_RUNS, table

from studies.runner import study_status
from studies.spec import expand, load_study
from studies.tasks import run_dir, run_lock

__all__ = [
    "STUDY_TIMEOUT",
    "UNDER_WAY",
    "Study",
    "assert_each_run_once",
    "one_run_held",
    "record",
    "runs_held",
    "summaries",
    "surprise_study",
    "wait_under_way",
]

#: Seconds a tiny study may take on a loaded CI machine (it takes a few).
STUDY_TIMEOUT = 120.0
#: Summaries to wait for before the fault: the study is under way, not just started.
UNDER_WAY = 3


def surprise_study(*args: str) -> list[str]:
    """The ``surprise-study`` command with ``args``, as a user types it."""
    command = Path(sys.executable).parent / "surprise-study"
    assert command.exists(), "surprise-study comes with the project (pip install -e '.[dev]')"
    return [str(command), *args]


class Study:
    """``surprise-study run`` in a process of its own, its output in ``folder``; ``env``: more
    variables of its environment."""

    def __init__(
        self, command: list[str], folder: Path, name: str, env: dict[str, str] | None = None
    ) -> None:
        self.stdout = folder / f"{name}.out"
        self.stderr = folder / f"{name}.err"
        with open(self.stdout, "wb") as out, open(self.stderr, "wb") as err:
            self.process = subprocess.Popen(
                command, stdout=out, stderr=err, stdin=subprocess.DEVNULL,
                env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})},
            )  # fmt: skip

    def wait(self) -> int:
        """Its exit code, once it has ended (it must within :data:`STUDY_TIMEOUT`)."""
        try:
            return self.process.wait(timeout=STUDY_TIMEOUT)
        except subprocess.TimeoutExpired:
            self.process.kill()
            raise AssertionError(
                f"the study did not end within {STUDY_TIMEOUT:.0f} s\n{self}"
            ) from None

    def wait_for(self, condition: Callable[[], object], what: str) -> None:
        """Wait until ``condition()`` holds while the study still runs; fail saying ``what`` if it
        does not within :data:`STUDY_TIMEOUT`, or if the study ended first."""
        wait_until(
            lambda: condition() or self.process.poll() is not None, what, STUDY_TIMEOUT, self.stdout
        )
        assert self.process.poll() is None, f"the study ended first ({what})\n{self}"

    def kill(self) -> None:
        """SIGKILL: no clean-up of any kind."""
        self.process.send_signal(signal.SIGKILL)
        self.process.wait()

    def out(self) -> str:
        """What it printed on stdout so far."""
        return self.stdout.read_text(errors="replace")

    def err(self) -> str:
        """What it printed on stderr so far."""
        return self.stderr.read_text(errors="replace")

    def __str__(self) -> str:
        return f"stdout:\n{self.out()}\nstderr:\n{self.err()}"


def summaries(out: Path) -> dict[Path, tuple[int, int]]:
    """Every run's summary.json with its inode and time: a run written again changes both."""
    found = {}
    for path in out.rglob("summary.json"):
        stat = path.stat()
        found[path] = (stat.st_ino, stat.st_mtime_ns)
    return found


def wait_under_way(out: Path, study: Study) -> None:
    """Wait until :data:`UNDER_WAY` runs have finished (the study must still run)."""
    study.wait_for(lambda: len(summaries(out)) >= UNDER_WAY, f"{UNDER_WAY} runs did not finish")


@contextlib.contextmanager
def one_run_held(study: Path, out: Path) -> Iterator[Path]:
    """Hold the last run's lock: its task waits, so the study cannot end before the fault."""
    with runs_held(study, out, 1) as (held,):
        yield held


@contextlib.contextmanager
def runs_held(study: Path, out: Path, count: int) -> Iterator[list[Path]]:
    """Hold the locks of the last ``count`` runs: their tasks wait (the study runs its tasks
    in order, so the others end first), and the study cannot end before the fault."""
    held = [run_dir(out, task) for task in expand(load_study(study))[-count:]]
    with contextlib.ExitStack() as stack:
        for directory in held:
            stack.enter_context(run_lock(directory))
        yield held


def assert_each_run_once(
    out: Path, before: dict[Path, tuple[int, int]], local_table: pd.DataFrame
) -> None:
    """Every run ended once, with the local pool's values: no failure recorded anywhere, the
    summaries there after the fault untouched, the same runs.csv."""
    leftovers = sorted(out.rglob("failed.json")) + sorted(out.rglob("error.txt"))
    assert not leftovers, leftovers
    after = summaries(out)
    assert len(after) == TINY_RUNS
    rewritten = [path for path, stamp in before.items() if after[path] != stamp]
    assert not rewritten, f"finished runs were run again: {rewritten}"
    assert study_status(out)["done"] == TINY_RUNS
    pd.testing.assert_frame_equal(table(out), local_table)


def record(fault: str, started: float, study: Study) -> None:
    """Print, for the record, what the study printed and how long it took after the fault."""
    print(f"\n[{fault}] ended {time.monotonic() - started:.1f} s after the fault, exit "
          f"{study.process.returncode}\n{study}")  # fmt: skip
