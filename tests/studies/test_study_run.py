"""Running studies: on local worker processes, on a real distributed.LocalCluster, and on a Dask
scheduler and two workers started as separate processes on loopback, with the same table; a
study killed mid-way and run again does each run once; a run that raises is recorded and the
study completes."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
import yaml
from study_helpers import TINY, TINY_RUNS, write_study

from studies.cli import main
from studies.executors import DaskCluster, LocalPool
from studies.report import write_study_report
from studies.runner import run_study, study_status

pytestmark = pytest.mark.slow

#: Columns that depend on where and when a run ran, not on what it computed.
VOLATILE = ("seconds", "host")
#: Seconds for a Dask scheduler or worker process to come up (a loaded CI machine).
DASK_START_TIMEOUT = 60.0


def table(out: Path) -> pd.DataFrame:
    """The study's runs.csv without the volatile columns, in run order."""
    write_study_report(out)
    frame = pd.read_csv(out / "report" / "runs.csv")
    return (
        frame.drop(columns=[c for c in VOLATILE if c in frame])
        .sort_values("run")
        .reset_index(drop=True)
    )


@pytest.fixture(scope="module")
def local_table(tmp_path_factory) -> pd.DataFrame:
    """The tiny study on the local pool, the reference for the other executors."""
    tmp = tmp_path_factory.mktemp("local")
    pool = LocalPool(2)
    try:
        counts = run_study(write_study(tmp), tmp / "study", pool)
    finally:
        pool.close()
    assert counts.done == TINY_RUNS and counts.failed == 0
    return table(tmp / "study")


def test_local_pool_runs_every_run_and_reports(local_table, tmp_path):
    assert len(local_table) == TINY_RUNS and set(local_table["status"]) == {"done"}
    assert set(local_table["group"]) == {"evolved", "random"}
    assert local_table["best_fitness"].between(0, 1).all()


def test_a_local_dask_cluster_gives_the_same_table(local_table, tmp_path):
    cluster = DaskCluster(None, workers=2)
    try:
        counts = run_study(write_study(tmp_path), tmp_path / "study", cluster)
    finally:
        cluster.close()
    assert counts.done == TINY_RUNS
    pd.testing.assert_frame_equal(table(tmp_path / "study"), local_table)


def _start(args: list[str], log: Path) -> subprocess.Popen[bytes]:
    with open(log, "wb") as out:
        return subprocess.Popen(
            args, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )  # fmt: skip


def test_a_dask_scheduler_and_two_workers_in_their_own_processes(local_table, tmp_path):
    dask = shutil.which("dask", path=str(Path(sys.executable).parent)) or shutil.which("dask")
    assert dask is not None, "the dask command comes with distributed"
    scheduler_file = tmp_path / "scheduler.json"
    common = ["--no-dashboard"]
    processes = [
        _start(
            [dask, "scheduler", "--host", "127.0.0.1", "--port", "0",
             "--scheduler-file", str(scheduler_file), *common],
            tmp_path / "scheduler.log",
        )
    ]  # fmt: skip
    try:
        deadline = time.monotonic() + DASK_START_TIMEOUT
        while not scheduler_file.exists():
            assert time.monotonic() < deadline, (tmp_path / "scheduler.log").read_text()
            time.sleep(0.1)
        for i in range(2):
            processes.append(
                _start(
                    [dask, "worker", "--scheduler-file", str(scheduler_file), "--nthreads", "1",
                     "--nworkers", "1", *common],
                    tmp_path / f"worker-{i}.log",
                )
            )  # fmt: skip
        address = json.loads(scheduler_file.read_text())["address"]
        from distributed import Client

        with Client(address) as client:
            client.wait_for_workers(2, timeout=DASK_START_TIMEOUT)
        code = main(
            ["run", str(write_study(tmp_path)), "--out", str(tmp_path / "study"),
             "--scheduler", address]
        )  # fmt: skip
        assert code == 0
        workers = {
            json.loads(p.read_text())["host"] for p in (tmp_path / "study").rglob("summary.json")
        }
        assert workers  # ran somewhere, with a host recorded
        pd.testing.assert_frame_equal(table(tmp_path / "study"), local_table)
    finally:
        for process in reversed(processes):
            process.send_signal(signal.SIGTERM)
        for process in processes:
            try:
                process.wait(timeout=15)
            except subprocess.TimeoutExpired:
                process.kill()


def test_a_study_killed_midway_and_run_again_does_each_run_once(tmp_path):
    study = write_study(tmp_path, TINY.replace("evaluations: 3", "evaluations: 40"))
    out = tmp_path / "study"
    process = subprocess.Popen(
        [sys.executable, "-m", "studies.cli", "run", str(study), "--out", str(out),
         "--workers", "1"],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    deadline = time.monotonic() + 120
    while len(list(out.rglob("summary.json"))) < 2:
        assert process.poll() is None and time.monotonic() < deadline
        time.sleep(0.05)
    process.kill()  # SIGKILL: no clean-up; a run may be half written
    process.wait()
    before = {p: p.stat().st_mtime_ns for p in out.rglob("summary.json")}
    assert 2 <= len(before) < TINY_RUNS
    pool = LocalPool(2)
    try:
        counts = run_study(study, out, pool)
    finally:
        pool.close()
    assert counts.done == TINY_RUNS and counts.skipped == len(before) and counts.failed == 0
    after = {p: p.stat().st_mtime_ns for p in out.rglob("summary.json")}
    assert len(after) == TINY_RUNS
    assert all(after[p] == t for p, t in before.items())  # finished runs were not run again
    assert study_status(out)["done"] == TINY_RUNS


def test_a_run_that_raises_is_recorded_and_the_study_completes(tmp_path, capsys):
    # Its parameters are fine (they are checked before the study starts): the run it reruns
    # does not exist, which only running it finds out. (The Thymio defaults go into the Thymio
    # groups, as the grid run takes none of them.)
    study = yaml.safe_load(TINY)
    defaults = study.pop("defaults")
    for group in study["groups"]:
        group["params"] = {**defaults, **group["params"]}
    study["groups"].append(
        {
            "name": "broken",
            "kind": "grid-rerun",
            "params": {"genome_run": "nowhere/seed-1", "size": 7, "agents": 5},
        }
    )
    text = yaml.safe_dump(study)
    out = tmp_path / "study"
    code = main(["run", str(write_study(tmp_path, text)), "--out", str(out), "--workers", "2"])
    assert code == 1
    printed = capsys.readouterr().out
    assert f"{TINY_RUNS}/{TINY_RUNS + 1} runs done" in printed and "1 failed" in printed
    failed = out / "runs" / "broken" / "seed-1"
    assert "genome_run" in json.loads((failed / "failed.json").read_text())["error"]
    assert "Traceback" in (failed / "error.txt").read_text()
    status = study_status(out)
    assert status["failed"] == 1 and status["groups"]["broken"]["failed"] == 1
    result = write_study_report(out)
    assert result["failed"] == 1 and result["done"] == TINY_RUNS
    # Run again: the finished runs are skipped, the failed one is tried again (and fails again).
    assert main(["run", str(write_study(tmp_path, text)), "--out", str(out)]) == 1
    assert "(8 from before)" in capsys.readouterr().out


def test_bad_parameters_stop_the_study_before_any_run(tmp_path, capsys):
    text = TINY + "  - {name: broken, kind: evolved, params: {simulation: {arena_side: -1}}}\n"
    path = write_study(tmp_path, text)
    out = tmp_path / "study"
    assert main(["run", str(path), "--out", str(out), "--workers", "1"]) == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith(f"surprise-study: {path}: key 'groups[2].params.simulation.arena_side'")
    assert not (out / "runs").exists()


def test_another_study_into_the_same_directory_is_refused(tmp_path, capsys):
    out = tmp_path / "study"
    assert main(["run", str(write_study(tmp_path)), "--out", str(out), "--workers", "1"]) == 0
    other = write_study(tmp_path, TINY.replace("seeds: 2", "seeds: 3"), "other.yaml")
    assert main(["run", str(other), "--out", str(out)]) == 2
    assert "holds another study" in capsys.readouterr().err
