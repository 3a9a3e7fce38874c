"""``surprise-study run --slurm`` against a real single-node Slurm (slurm_helpers): the workers
are Slurm batch jobs, a study gives the same table as on the local pool, jobs that end mid-study
(their walltime, ``scancel``) are replaced and every run still ends once, and jobs that Slurm
refuses, that end early or that never start are one line each, with no job left behind."""

from __future__ import annotations

import os
import re
import time
from collections.abc import Iterator
from pathlib import Path

import pandas as pd
import pytest
from slurm_helpers import PARTITION, SingleNodeSlurm
from study_helpers import TINY, table, write_study
from study_process import (
    Study,
    assert_each_run_once,
    record,
    runs_held,
    summaries,
    surprise_study,
    wait_under_way,
)

from needs import require_module
from studies.cli import main
from studies.slurm import JOB_NAME, LOG_DIRECTORY, SlurmOptions, slurm_job_id, start_slurm

pytestmark = pytest.mark.slow

#: Seconds for the workers' jobs to start here (about 2 s: Slurm schedules a new job within
#: its first scheduling pass, a worker starts in about a second), with room for a loaded machine.
WORKERS_TIMEOUT = 120.0
#: Seconds for a job to end once the study is over (cancelled; KillWait in slurm_helpers).
JOB_END_TIMEOUT = 30.0
#: The slurm: section of the tests' studies: everything on loopback, small jobs.
SECTION = f"slurm:\n  interface: lo\n  memory: 1GB\n  start_timeout: {WORKERS_TIMEOUT:g}\n"
#: Jobs whose workers leave 5 s after they start: a walltime of one minute (Slurm's least)
#: less a margin of 55 s. The tiny study sees its jobs end, and replaced, again and again.
SHORT_LIVED = "  walltime: '1'\n  walltime_margin: 55\n"
#: What the study prints when jobs ended and new ones were submitted in their place.
REPLACED = re.compile(r"^slurm: \d+ jobs? ended \((?P<why>[^)]*)\); submitted (?P<new>.*)$", re.M)


@pytest.fixture(scope="module")
def slurm() -> Iterator[SingleNodeSlurm]:
    """A real single-node Slurm, its ``SLURM_CONF`` in the environment."""
    require_module("dask_jobqueue", "studies")
    with SingleNodeSlurm() as cluster, pytest.MonkeyPatch.context() as patch:
        patch.setenv("SLURM_CONF", str(cluster.conf))
        yield cluster


def wait_until_ended(slurm: SingleNodeSlurm, jobs: list[str]) -> dict[str, str]:
    """The jobs' final states, once none of them runs or waits any more."""
    deadline = time.monotonic() + JOB_END_TIMEOUT
    while True:
        states = {job: slurm.jobs().get(job, "GONE") for job in jobs}
        if not {"PENDING", "RUNNING", "COMPLETING", "CONFIGURING"} & set(states.values()):
            return states
        assert time.monotonic() < deadline, states
        time.sleep(0.2)


def test_a_study_on_slurm_gives_the_local_pool_s_table(slurm, local_table, tmp_path, capsys):
    # local_table (conftest): the tiny study's table on the local pool.
    out = tmp_path / "study"
    # The file asks for one job; the option overrides it.
    study = write_study(tmp_path, TINY + SECTION + "  jobs: 1\n")
    started = time.monotonic()
    code = main(["run", str(study), "--out", str(out), "--slurm", "--slurm-jobs", "2"])
    seconds = time.monotonic() - started
    printed = capsys.readouterr().out
    assert code == 0, printed
    (jobs,) = re.findall(r"slurm: submitted 2 jobs \((\d+), (\d+)\)", printed)
    assert "the first worker is up (job" in printed
    pd.testing.assert_frame_equal(table(out), local_table)
    # The workers were those Slurm jobs: Slurm ran them on its node, under the study's job name,
    # their output in the study's directory, each a Dask worker of this study's scheduler.
    logs = out / LOG_DIRECTORY
    for job in jobs:
        shown = slurm.run("scontrol", "-o", "show", "job", job).stdout
        assert f"JobName={JOB_NAME} " in shown and f"BatchHost={slurm.node} " in shown
        assert f"StdErr={logs}/{JOB_NAME}-%J.err" in shown  # %J: the job's id
        assert f"Partition={PARTITION} " in shown
        log = (logs / f"{JOB_NAME}-{job}.err").read_text()
        assert "Registered to:" in log and "tcp://127.0.0.1:" in log
    # ... and the study ended them.
    assert set(wait_until_ended(slurm, list(jobs)).values()) <= {"CANCELLED", "COMPLETED"}
    print(f"the tiny study on Slurm took {seconds:.1f} s")


def test_the_workers_run_in_the_slurm_jobs_and_end_with_the_study(slurm, tmp_path):
    options = SlurmOptions(interface="lo", memory="1GB", jobs=2, start_timeout=WORKERS_TIMEOUT)
    said: list[str] = []
    executor = start_slurm(options, tmp_path, say=said.append)
    try:
        (jobs,) = re.findall(r"^slurm: submitted 2 jobs \((\d+), (\d+)\)", said[0])
        jobs = set(jobs)
        executor.client.wait_for_workers(2, timeout=WORKERS_TIMEOUT)
        assert executor.workers == 2
        # Each worker's environment is a Slurm job's: one of the two dask-jobqueue submitted.
        assert set(executor.client.run(slurm_job_id).values()) == jobs
        # A task, like a study's run, runs in one of them.
        assert executor.submit(slurm_job_id).result(timeout=WORKERS_TIMEOUT) in jobs
        running = slurm.run("squeue", "--noheader", "--format=%i %T %j").stdout.split("\n")
        assert {f"{job} RUNNING {JOB_NAME}" for job in jobs} <= set(running)
    finally:
        executor.close()
    assert set(wait_until_ended(slurm, sorted(jobs)).values()) <= {"CANCELLED", "COMPLETED"}


def slurm_study(study: Path, out: Path) -> list[str]:
    """``surprise-study run STUDY --out OUT --slurm``, as a user types it."""
    return surprise_study("run", str(study), "--out", str(out), "--slurm")


def replaced(printed: str) -> tuple[dict[str, str], list[str]]:
    """What a study said of its jobs' replacement (REPLACED lines): the jobs that ended, by id,
    with why, and the jobs submitted in their place."""
    ended, new = {}, []
    for line in REPLACED.finditer(printed):
        for part in line["why"].split("; "):
            why, jobs = part.split(": ")
            ended |= dict.fromkeys(jobs.split(", "), why)
        new += re.findall(r"\d+", re.match(r"[^(]*\(([\d, ]+)\)", line["new"])[1])
    return ended, new


@pytest.mark.parametrize(
    ("jobs", "cores"),
    # Two jobs of one worker each, and one job of two worker processes (named <job>-0, <job>-1:
    # the jobs dask-jobqueue's adapt() would never replace).
    [(2, 1), (1, 2)],
)
def test_jobs_at_their_walltime_are_replaced_and_each_run_ends_once(
    slurm, local_table, tmp_path, jobs, cores
):
    earlier = set(slurm.jobs())
    section = SECTION + f"  jobs: {jobs}\n  cores: {cores}\n" + SHORT_LIVED
    study, out = write_study(tmp_path, TINY + section), tmp_path / "s"
    # The held runs keep the study going (and both jobs wanted) until they have been replaced.
    with runs_held(study, out, 2):
        running = Study(slurm_study(study, out), tmp_path, "study")
        running.wait_for(lambda: replaced(running.out())[1], "no job was replaced")
        before = summaries(out)
        released = time.monotonic()
    assert running.wait() == 0, str(running)  # what the study printed
    record("jobs at their walltime", released, running)
    assert_each_run_once(out, before, local_table)
    ended, new = replaced(running.out())
    assert set(ended.values()) == {"walltime"}, running
    # The held runs wanted a job each: as many new ones as ended (both jobs at once, or not).
    first = REPLACED.search(running.out())[0]
    assert re.fullmatch(
        r"slurm: (\d) jobs? ended \(walltime: [\d, ]+\); submitted \1 new ones? \([\d, ]+\)", first
    ), first
    # More jobs than it started with, each one the study named; none left at the end.
    ours = sorted(set(slurm.jobs()) - earlier)
    assert len(ours) > jobs and set(ended) | set(new) <= set(ours), (ours, running)
    assert set(wait_until_ended(slurm, ours).values()) <= {"CANCELLED", "COMPLETED", "TIMEOUT"}


def test_jobs_cancelled_mid_study_are_replaced_and_each_run_ends_once(slurm, local_table, tmp_path):
    study, out = write_study(tmp_path, TINY + SECTION + "  jobs: 2\n"), tmp_path / "s"
    # The study's process never collects reference cycles: a refused job kept alive by its
    # error's traceback is still there when the cluster closes, every time, not now and then.
    nogc = tmp_path / "nogc"
    nogc.mkdir()
    (nogc / "sitecustomize.py").write_text("import gc\ngc.disable()\n")
    with runs_held(study, out, 2):
        path = os.pathsep.join(p for p in (str(nogc), os.environ.get("PYTHONPATH")) if p)
        running = Study(slurm_study(study, out), tmp_path, "study", env={"PYTHONPATH": path})
        wait_under_way(out, running)
        (first,) = re.findall(r"slurm: submitted 2 jobs \((\d+), (\d+)\)", running.out())
        before = summaries(out)
        slurm.run("scancel", *first)  # as an administrator would, or a node's failure
        cancelled = time.monotonic()
        running.wait_for(
            lambda: set(replaced(running.out())[0]) >= set(first),
            "the cancelled jobs were not replaced",
        )
    assert running.wait() == 0, str(running)  # what the study printed
    record("jobs cancelled", cancelled, running)
    assert_each_run_once(out, before, local_table)
    ended, new = replaced(running.out())
    assert ended == dict.fromkeys(first, "cancelled") and len(new) == 2, running
    assert set(wait_until_ended(slurm, [*first, *new]).values()) <= {"CANCELLED", "COMPLETED"}


def test_new_jobs_that_sbatch_refuses_are_submitted_once_it_takes_them(
    slurm, local_table, tmp_path
):
    study, out = write_study(tmp_path, TINY + SECTION + "  jobs: 2\n"), tmp_path / "s"
    partition = f"PartitionName={PARTITION}"
    # The study's process never collects reference cycles: a refused job kept alive by its
    # error's traceback is still there when the cluster closes, every time, not now and then.
    nogc = tmp_path / "nogc"
    nogc.mkdir()
    (nogc / "sitecustomize.py").write_text("import gc\ngc.disable()\n")
    with runs_held(study, out, 2):
        path = os.pathsep.join(p for p in (str(nogc), os.environ.get("PYTHONPATH")) if p)
        running = Study(slurm_study(study, out), tmp_path, "study", env={"PYTHONPATH": path})
        wait_under_way(out, running)
        (first,) = re.findall(r"slurm: submitted 2 jobs \((\d+), (\d+)\)", running.out())
        before = summaries(out)
        # A drained partition takes no new jobs: the jobs' end comes with none to replace them.
        slurm.run("scontrol", "update", partition, "State=DRAIN")
        try:
            slurm.run("scancel", *first)
            running.wait_for(
                lambda: "sbatch refused" in running.out(), "sbatch did not refuse the new jobs"
            )
        finally:
            slurm.run("scontrol", "update", partition, "State=UP")
        reopened = time.monotonic()
        again = re.compile(r"^slurm: submitted (\d+) new jobs? \(([\d, ]+)\)$", re.M)
        running.wait_for(
            lambda: again.search(running.out()), "no new job once the partition took them again"
        )
    assert running.wait() == 0, str(running)  # what the study printed
    record("sbatch refused, then took the jobs", reopened, running)
    assert_each_run_once(out, before, local_table)
    # As many as the runs left need (the two held), refused, then submitted.
    printed = running.out()
    (refusal,) = re.findall(
        r"^slurm: 2 jobs ended \(cancelled: \d+, \d+\); sbatch refused (\d+) new ones? "
        r"\((sbatch: error: .*)\); trying again soon$",
        printed,
        re.M,
    )
    (submitted,) = again.findall(printed)
    assert submitted[0] == refusal[0], printed
    new = submitted[1].split(", ")
    assert set(wait_until_ended(slurm, [*first, *new]).values()) <= {"CANCELLED", "COMPLETED"}


def test_jobs_that_never_start_end_the_study_after_the_start_timeout(slurm, tmp_path, capsys):
    # Jobs that may start in an hour only: pending (BeginTime) all the while.
    section = "slurm:\n  interface: lo\n  memory: 1GB\n  start_timeout: 2\n"
    study = write_study(tmp_path, TINY + section + "  directives: ['--begin=now+3600']\n")
    started = time.monotonic()
    assert main(["run", str(study), "--out", str(tmp_path / "study"), "--slurm"]) == 2
    assert time.monotonic() - started < WORKERS_TIMEOUT
    captured = capsys.readouterr()
    (job,) = re.findall(r"submitted 1 job \((\d+)\)", captured.out)
    (line,) = captured.err.splitlines()
    assert line == (
        f"surprise-study: no Slurm job started a worker within 2 s (jobs {job} PENDING "
        "(BeginTime)); give slurm.start_timeout more time or ask for less"
    )
    assert wait_until_ended(slurm, [job]) == {job: "CANCELLED"}  # not left waiting


def test_jobs_that_end_before_a_worker_connects_are_one_line(slurm, tmp_path, capsys):
    study = write_study(tmp_path, TINY + SECTION + "  prologue: ['exit 3']\n")
    assert main(["run", str(study), "--out", str(tmp_path / "study"), "--slurm"]) == 2
    captured = capsys.readouterr()
    (job,) = re.findall(r"submitted 1 job \((\d+)\)", captured.out)
    (line,) = captured.err.splitlines()
    assert line == (
        f"surprise-study: the Slurm jobs ended before a worker connected ({job} FAILED "
        f"(NonZeroExitCode)); see their logs in {tmp_path / 'study' / LOG_DIRECTORY}"
    )


@pytest.mark.parametrize(
    ("option", "asked", "error"),
    [
        (
            ["--slurm-memory", "100TB"],
            "1 cores, 100TB, 01:00:00 each, partition (default)",
            "allocation failure: Requested node configuration is not available",
        ),
        (
            ["--slurm-queue", "nowhere"],
            "1 cores, 1GB, 01:00:00 each, partition nowhere",
            "sbatch: error: invalid partition specified: nowhere; "
            "allocation failure: Invalid partition name specified",
        ),
    ],
)
def test_jobs_slurm_refuses_are_one_line_and_none_is_submitted(
    slurm, tmp_path, capsys, option, asked, error
):
    before = set(slurm.jobs())
    study = write_study(tmp_path, TINY + SECTION)
    assert main(["run", str(study), "--out", str(tmp_path / "study"), "--slurm", *option]) == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line == f"surprise-study: Slurm refuses the workers' jobs ({asked}): {error}"
    assert set(slurm.jobs()) == before
