"""Running studies: on local worker processes, on a real distributed.LocalCluster, and on a Dask
scheduler and two workers started as separate processes on loopback, with the same table; a
study killed mid-way and run again does each run once; a run that raises is recorded and the
study completes."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pandas as pd
import pytest
import yaml
from dask_cluster import LoopbackCluster, listening_addresses, wait_until
from study_helpers import TINY, TINY_RUNS, table, write_study

from needs import processes
from studies.cli import main
from studies.executors import DaskCluster, LocalPool
from studies.report import write_study_report
from studies.runner import run_study, study_status
from studies.spec import expand, load_study
from studies.tasks import run_dir, run_lock

pytestmark = pytest.mark.slow

#: Seconds a tiny study may take on a loaded CI machine (it takes a few).
STUDY_TIMEOUT = 120.0


def test_local_pool_runs_every_run_and_reports(local_table, tmp_path):
    assert len(local_table) == TINY_RUNS and set(local_table["status"]) == {"done"}
    assert set(local_table["group"]) == {"evolved", "random"}
    assert local_table["best_fitness"].between(0, 1).all()


def test_runs_stepped_together_give_the_table_of_runs_alone(local_table, tmp_path):
    # The four evolved runs of the tiny study as one batch on one worker, and each alone: both
    # give the local pool's table (two batches of two there) to the last digit.
    def run(batch: int) -> pd.DataFrame:
        out = tmp_path / f"batch-{batch}"
        pool = LocalPool(1)
        try:
            counts = run_study(write_study(tmp_path), out, pool, batch=batch)
        finally:
            pool.close()
        assert counts.done == TINY_RUNS
        pd.testing.assert_frame_equal(table(out), local_table)
        return pd.read_csv(out / "report" / "runs.csv")

    together, alone = run(4), run(1)
    evolved = together["kind"] == "evolved"
    assert set(together.loc[evolved, "batch"]) == {4}
    assert "batch" not in alone or alone["batch"].isna().all()


def test_a_local_dask_cluster_gives_the_same_table(local_table, tmp_path):
    cluster = DaskCluster(None, workers=2)
    try:
        counts = run_study(write_study(tmp_path), tmp_path / "study", cluster)
    finally:
        cluster.close()
    assert counts.done == TINY_RUNS
    pd.testing.assert_frame_equal(table(tmp_path / "study"), local_table)


def test_a_local_dask_cluster_listens_on_loopback_only(tmp_path):
    cluster = DaskCluster(None, workers=1)
    try:
        ours = {os.getpid()} | {p.pid for p in processes() if p.ppid == os.getpid()}
        found = [(pid, address) for pid in ours for address in listening_addresses(pid)]
        assert found and all(loopback for _, (_, loopback) in found), found
    finally:
        cluster.close()


def test_a_dask_scheduler_and_two_workers_in_their_own_processes(local_table, tmp_path):
    with LoopbackCluster(tmp_path) as cluster:
        address = cluster.start_scheduler()
        cluster.start_workers(2)
        code = main(
            ["run", str(write_study(tmp_path)), "--out", str(tmp_path / "study"),
             "--scheduler", address]
        )  # fmt: skip
        assert code == 0
        listening = cluster.listening()
        assert listening and all(loopback for _, _, loopback in listening), listening
    workers = {
        json.loads(p.read_text())["host"] for p in (tmp_path / "study").rglob("summary.json")
    }
    assert workers  # ran somewhere, with a host recorded
    pd.testing.assert_frame_equal(table(tmp_path / "study"), local_table)


def test_a_study_killed_midway_and_run_again_does_each_run_once(tmp_path):
    study = write_study(tmp_path)
    out = tmp_path / "study"
    last = expand(load_study(study))[-1]
    # What a run killed half-way leaves: a directory without a summary.
    half = run_dir(out, last)
    half.mkdir(parents=True)
    (half / "half-written").write_text("what a killed run left\n")
    # The last run's lock, held here, keeps the study from ending before it is killed: with one
    # worker it is the last run started, and its task waits for the lock.
    with run_lock(half):
        process = subprocess.Popen(
            [sys.executable, "-m", "studies.cli", "run", str(study), "--out", str(out),
             "--workers", "1"],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        wait_until(
            lambda: (
                len(list(out.rglob("summary.json"))) == TINY_RUNS - 1 or process.poll() is not None
            ),
            "the study did not finish every run but the held one",
            STUDY_TIMEOUT,
        )
        process.kill()  # SIGKILL: no clean-up; a run may be half written
        process.wait()
    before = {p: p.stat().st_mtime_ns for p in out.rglob("summary.json")}
    assert len(before) == TINY_RUNS - 1
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
    assert not (half / "half-written").exists()  # started afresh


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


def test_a_study_that_changed_only_where_it_runs_goes_on(tmp_path, capsys):
    out = tmp_path / "study"
    assert main(["run", str(write_study(tmp_path)), "--out", str(out), "--workers", "1"]) == 0
    moved = write_study(tmp_path, TINY + "slurm: {jobs: 3}\n# run on the cluster now\n", "b.yaml")
    assert main(["run", str(moved), "--out", str(out), "--workers", "1"]) == 0
    assert "from before" in capsys.readouterr().out
