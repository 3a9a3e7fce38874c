"""A study on a Dask cluster that loses parts: a real ``dask scheduler`` and real ``dask
worker`` processes on loopback, a part killed (SIGKILL) mid-study, and the same command run
again where that is what a user would do. Every run of the study ends exactly once, with the
values it has on the local pool: the same runs.csv, no run recorded failed, and no summary that
existed after the fault written again.

The study cannot end before its fault: the test holds the run lock of one run
(:func:`studies.tasks.run_lock`, what a task of an earlier start of the study would hold), so
that run's task waits, and lets go once the fault is done. No test asserts a duration; each
prints what the study printed and how long it took after the fault (``pytest -s``).
"""

from __future__ import annotations

import contextlib
import errno
import os
import pickle
import shutil
import socket
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pandas as pd
import pytest
from dask_cluster import LOOPBACK, LoopbackCluster
from study_helpers import TINY_RUNS, table, write_study
from study_process import (
    STUDY_TIMEOUT,
    Study,
    assert_each_run_once,
    one_run_held,
    record,
    summaries,
    surprise_study,
    wait_under_way,
)

import studies.tasks as tasks_module
from needs import missing
from studies.executors import SCHEDULER_CONNECT_TIMEOUT
from studies.runner import study_status
from studies.spec import expand, load_study
from studies.tasks import DiskFullError, finished, run_dir, run_lock, run_task

pytestmark = pytest.mark.slow

#: What a study stopped by a lost scheduler or a full disk exits with.
STOPPED = 3
#: The size of the small file system of the full-disk test (room for the tiny study).
SMALL_DISK = "16m"


# --------------------------------------------------------------------------- helpers


def study_command(study: Path, out: Path, address: str) -> list[str]:
    """``surprise-study run STUDY --out OUT --scheduler ADDRESS``, as a user types it."""
    return surprise_study("run", str(study), "--out", str(out), "--scheduler", address)


def assert_loopback_only(cluster: LoopbackCluster) -> None:
    """Nothing of the cluster listens beyond loopback."""
    listening = cluster.listening()
    assert listening and all(loopback for _, _, loopback in listening), listening


def free_port() -> int:
    """A loopback TCP port nothing listens on (bound, then let go)."""
    with socket.socket() as probe:
        probe.bind((LOOPBACK, 0))
        return probe.getsockname()[1]


# --------------------------------------------------------------------------- a worker killed


def test_a_worker_killed_mid_study_loses_no_finished_run(local_table, tmp_path):
    study, out = write_study(tmp_path), tmp_path / "study"
    with LoopbackCluster(tmp_path) as cluster:
        address = cluster.start_scheduler()
        cluster.start_workers(2, nanny=False)  # a worker killed stays dead
        with one_run_held(study, out):
            client = Study(study_command(study, out, address), tmp_path, "study")
            wait_under_way(out, client)
            assert_loopback_only(cluster)
            before = summaries(out)
            # Results of finished runs live on the workers: Dask used to run them again.
            cluster.kill(cluster.workers[0])
            killed = time.monotonic()
        assert client.wait() == 0, client
        record("worker killed", killed, client)
    assert_each_run_once(out, before, local_table)


# --------------------------------------------------------------------------- the client killed


def test_the_study_killed_and_run_again_waits_for_its_orphans(local_table, tmp_path):
    study, out = write_study(tmp_path), tmp_path / "study"
    command = lambda address: study_command(study, out, address)  # noqa: E731
    with LoopbackCluster(tmp_path) as cluster:
        address = cluster.start_scheduler()
        cluster.start_workers(2)
        with one_run_held(study, out) as held:
            first = Study(command(address), tmp_path, "first")
            wait_under_way(out, first)
            first.kill()  # its tasks go on running on the workers: orphans
            killed = time.monotonic()
            before = summaries(out)
            again = Study(command(address), tmp_path, "again")
            # The held run is running (its task waits for the lock): the study started again
            # says so and waits for it rather than running it a second time.
            again.wait_for(
                lambda: "still running from an earlier start" in again.out(),
                "the study started again did not say it waits for the earlier one's runs",
            )
            assert held.name in again.out() or "..." in again.out(), again
        assert again.wait() == 0, again
        record("client killed, then the same command again", killed, again)
        assert "surprise-master" not in again.out() + again.err()
        assert_loopback_only(cluster)
    assert_each_run_once(out, before, local_table)


def test_a_second_task_of_a_running_run_waits_and_takes_its_result(tmp_path, monkeypatch):
    # Two tasks of one run at once (a study started again while its earlier start's task still
    # runs): one runs it, the other waits and returns the stored summary.
    study = write_study(tmp_path)
    task = expand(load_study(study))[0]
    started = []
    afresh = tasks_module._run_afresh

    def counted(*args):
        started.append(threading.get_ident())
        return afresh(*args)

    monkeypatch.setattr(tasks_module, "_run_afresh", counted)
    results: list[dict] = []
    with run_lock(run_dir(tmp_path, task)):
        threads = [
            threading.Thread(target=lambda: results.append(run_task(task, str(tmp_path))))
            for _ in range(2)
        ]
        for thread in threads:
            thread.start()
        time.sleep(0.2)  # not needed for the outcome; gives both a chance to be waiting
    for thread in threads:
        thread.join(timeout=STUDY_TIMEOUT)
    assert len(started) == 1 and len(results) == 2
    assert results[0] == results[1] and results[0]["status"] == "done"


def test_a_run_counts_as_done_only_with_its_complete_summary(tmp_path):
    # A run of the grid world writes a summary of its own first; the study's, written last and
    # atomically, adds the status and the host. Only that one makes the run done.
    task = expand(load_study(write_study(tmp_path)))[0]
    directory = run_dir(tmp_path, task)
    directory.mkdir(parents=True)
    (directory / "summary.json").write_text('{"pattern": "line", "seconds": 1.0}')
    assert not finished(directory)
    (directory / "summary.json").write_text('{"status": "done", "seconds": 1.0')  # cut short
    assert not finished(directory)
    (directory / "summary.json").write_text('{"status": "done", "seconds": 1.0, "host": "h"}')
    assert finished(directory)


# --------------------------------------------------------------------------- the scheduler killed


def test_a_scheduler_killed_leaves_the_runs_pending_and_the_same_command_finishes(
    local_table, tmp_path
):
    study, out = write_study(tmp_path), tmp_path / "study"
    with LoopbackCluster(tmp_path) as cluster:
        address = cluster.start_scheduler()
        cluster.start_workers(2)
        with one_run_held(study, out):
            first = Study(study_command(study, out, address), tmp_path, "first")
            wait_under_way(out, first)
            cluster.kill(cluster.scheduler)
            killed = time.monotonic()
            assert first.wait() == STOPPED, first
            record("scheduler killed", killed, first)
            # Still holding the lock: the workers outlive their scheduler, and the held run's
            # task, let go, would finish behind the study's back.
            status = study_status(out)
            assert status["failed"] == 0 and status["done"] < TINY_RUNS  # pending, not failed
            assert not list(out.rglob("failed.json")), "runs taken for failed"
        lines = [line for line in first.err().splitlines() if line.startswith("surprise-study")]
        assert len(lines) == 1, first
        assert f"lost the Dask scheduler at {address}" in lines[0]
        assert "run the same command again" in lines[0]
        before = summaries(out)
        # A scheduler back on the same port, with workers: the very same command finishes.
        cluster.start_scheduler(cluster.port)
        cluster.start_workers(2)
        restarted = time.monotonic()
        again = Study(study_command(study, out, address), tmp_path, "again")
        assert again.wait() == 0, again
        record("the same command with a new scheduler", restarted, again)
        assert_loopback_only(cluster)
    assert_each_run_once(out, before, local_table)


# --------------------------------------------------------------------------- nothing there


def test_a_scheduler_address_with_nothing_behind_it_is_one_line_in_seconds(tmp_path):
    address = f"tcp://{LOOPBACK}:{free_port()}"
    started = time.monotonic()
    study = Study(study_command(write_study(tmp_path), tmp_path / "study", address), tmp_path, "s")
    assert study.wait() == 2, study
    record("nothing behind the address", started, study)
    (line,) = study.err().splitlines()
    assert line.startswith("surprise-study: no Dask scheduler answers at " + address), line
    assert f"within {SCHEDULER_CONNECT_TIMEOUT:g} s" in line
    assert not (tmp_path / "study" / "runs").exists()


# --------------------------------------------------------------------------- a full disk


@contextlib.contextmanager
def small_disk(folder: Path) -> Iterator[Path]:
    """A tmpfs of :data:`SMALL_DISK` mounted on ``folder`` (needs root), unmounted after."""
    if os.geteuid() != 0 or shutil.which("mount") is None:
        missing("the full-disk test mounts a small tmpfs: it needs root and mount (util-linux)")
    folder.mkdir()
    mounted = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={SMALL_DISK}", "study-disk", str(folder)],
        capture_output=True, text=True,
    )  # fmt: skip
    if mounted.returncode != 0:
        missing(f"cannot mount a tmpfs here ({mounted.stderr.strip()}): it needs CAP_SYS_ADMIN")
    try:
        yield folder
    finally:
        subprocess.run(["umount", "--lazy", str(folder)], check=False)


def fill(path: Path) -> None:
    """Write ``path`` until its file system is full."""
    with open(path, "wb", buffering=0) as filler:
        for size in (1 << 20, 4096, 1):
            try:
                while True:
                    filler.write(b"\0" * size)
            except OSError as exc:
                assert exc.errno == errno.ENOSPC, exc


def test_a_full_disk_names_the_path_and_the_study_goes_on_once_there_is_room(local_table, tmp_path):
    study = write_study(tmp_path)
    with small_disk(tmp_path / "disk") as disk, LoopbackCluster(tmp_path) as cluster:
        out, filler = disk / "study", disk / "filler"
        address = cluster.start_scheduler()
        cluster.start_workers(2)
        with one_run_held(study, out):
            first = Study(study_command(study, out, address), tmp_path, "first")
            wait_under_way(out, first)
            fill(filler)
            full = time.monotonic()
        # The held run, and whichever runs next, now meet the full disk.
        assert first.wait() == STOPPED, first
        record("disk full", full, first)
        lines = [line for line in first.err().splitlines() if line.startswith("surprise-study")]
        assert len(lines) == 1, first
        assert lines[0].startswith(f"surprise-study: cannot write {out}"), lines
        assert "no space left on device" in lines[0] and "run the same command again" in lines[0]
        assert not list(out.rglob("failed.json")), "a full disk taken for a failed run"
        before = summaries(out)
        filler.unlink()
        freed = time.monotonic()
        again = Study(study_command(study, out, address), tmp_path, "again")
        assert again.wait() == 0, again
        record("the same command once there is room", freed, again)
        copy = tmp_path / "copy"
        shutil.copytree(out, copy)  # compared after the small disk is gone
        before = {copy / path.relative_to(out): stamp for path, stamp in before.items()}
    stamps = summaries(copy)
    assert all(stamps[path][1] == stamp[1] for path, stamp in before.items())
    leftovers = sorted(copy.rglob("failed.json")) + sorted(copy.rglob("error.txt"))
    assert not leftovers and len(stamps) == TINY_RUNS, leftovers
    pd.testing.assert_frame_equal(table(copy), local_table)


def test_a_run_meeting_a_full_disk_stays_pending_and_names_the_path(tmp_path, monkeypatch):
    study = write_study(tmp_path)
    task = expand(load_study(study))[0]

    def full(task, directory):
        directory.mkdir(parents=True)
        with open(directory / "evaluations.csv", "w") as file:
            file.write("x")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))  # as a failed write(): no path

    monkeypatch.setitem(tasks_module._KIND_RUNNERS, task["kind"], full)
    with pytest.raises(DiskFullError) as raised:
        run_task(task, str(tmp_path))
    directory = run_dir(tmp_path, task)
    assert raised.value.path == str(directory) and raised.value.errno == errno.ENOSPC
    assert str(raised.value).startswith(f"cannot write {directory}: no space left on device; ")
    assert not (directory / "failed.json").exists() and not (directory / "error.txt").exists()
    copy = pickle.loads(pickle.dumps(raised.value))  # as it crosses from a worker
    assert isinstance(copy, DiskFullError) and str(copy) == str(raised.value)
