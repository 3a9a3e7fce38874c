"""Checkpoint and resume: a stopped, crashed or killed master continues without losing or
repeating an evaluation, and never reuses an evaluation id."""

from __future__ import annotations

import asyncio
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from master_helpers import (
    SECRET,
    assert_matches_reference,
    close,
    connect,
    experiment,
    make_robots,
    master_config,
    read_csv,
    robot_ids,
    run_with,
)

from master_service import Master
from master_service.rundir import RunDir, RunDirError
from minimize_surprise.errors import ConfigError


def ids_of(robots) -> list[int]:
    return [m.evaluation_id for r in robots for m in r.evaluations]


async def wait_rows(path: Path, rows: int, timeout: float = 10.0) -> None:
    """Poll evaluations.csv until it holds ``rows`` rows (the writer is another task/process)."""
    async with asyncio.timeout(timeout):
        while True:
            if path.exists() and len(path.read_text().splitlines()) > rows:
                return
            await asyncio.sleep(0.005)


async def test_a_stopped_run_resumes_where_it_stood(tmp_path):
    exp = experiment(evaluations=20)
    run = tmp_path / "run"
    async with Master(master_config(exp), run, secret=SECRET) as master:
        robots = make_robots(master.port, 3, delay=0.005)
        task = asyncio.create_task(master.run())
        await connect(robots)
        await wait_rows(run / "evaluations.csv", 6)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task
    await asyncio.gather(*(r.closed.wait() for r in robots))
    first_ids = ids_of(robots)
    counted = json.loads((run / "checkpoint.json").read_text())["csv_rows"]
    assert 6 <= counted < 20

    async with Master(master_config(exp), run, secret=SECRET, resume=True) as master:
        again = make_robots(master.port, 3)
        await run_with(master, again)
        await close(again)
    assert_matches_reference(run, exp, robot_ids(3))
    assert min(ids_of(again)) > max(first_ids)
    assert "resumed run run" in (run / "master.log").read_text()


async def test_a_crash_between_row_and_checkpoint_counts_the_row_once(tmp_path):
    exp = experiment(evaluations=10)
    run = tmp_path / "run"
    async with Master(master_config(exp), run, secret=SECRET) as master:
        commit = master.run_dir.commit

        def crashing_commit(state, row, header):
            if state.csv_rows == 5:
                # The row reaches the disk, then a torn line, and the checkpoint never does.
                with open(run / "evaluations.csv", "a") as file:
                    file.write(row + "6,offspring,0.5,0.")
                raise OSError("simulated crash")
            commit(state, row, header)

        master.run_dir.commit = crashing_commit
        robots = make_robots(master.port, 3)
        with pytest.raises(OSError, match="simulated crash"):
            await run_with(master, robots)
    assert len(read_csv(run / "evaluations.csv")) == 6  # 5 rows and a torn one

    async with Master(master_config(exp), run, secret=SECRET, resume=True) as master:
        again = make_robots(master.port, 3)
        await run_with(master, again)
        await close(again)
    assert_matches_reference(run, exp, robot_ids(3))


async def test_resuming_a_finished_run_does_nothing(tmp_path):
    exp = experiment(evaluations=3)
    run = tmp_path / "run"
    async with Master(master_config(exp), run, secret=SECRET) as master:
        robots = make_robots(master.port, 3)
        await run_with(master, robots)
        await close(robots)
    before = (run / "evaluations.csv").read_bytes()
    async with Master(master_config(exp), run, secret=SECRET, resume=True) as master:
        summary = await asyncio.wait_for(master.run(), 5)
    assert summary.evaluations == 3 and (run / "evaluations.csv").read_bytes() == before


async def test_resume_refuses_another_experiment_and_missing_or_damaged_files(tmp_path):
    run = tmp_path / "run"
    with pytest.raises(RunDirError, match="not a run directory"):
        await Master(master_config(), run, secret=SECRET, resume=True).start()
    async with Master(master_config(), run, secret=SECRET):
        pass
    other = master_config(experiment(evaluations=99))
    with pytest.raises(ConfigError, match="differs") as info:
        await Master(other, run, secret=SECRET, resume=True).start()
    assert info.value.key == "experiment"
    # A new run refuses a used directory.
    with pytest.raises(RunDirError, match="resume"):
        await Master(master_config(), run, secret=SECRET).start()
    # A checkpoint counting rows the CSV does not have is damage, not something to paper over.
    (run / "checkpoint.json").write_text(json.dumps({"format": 1}))
    with pytest.raises(RunDirError, match="cannot be read"):
        await Master(master_config(), run, secret=SECRET, resume=True).start()


def test_prepare_resume_keeps_exactly_the_counted_rows(tmp_path):
    run = RunDir(tmp_path)
    path = tmp_path / "evaluations.csv"
    path.write_text("h\n1\n2\n3\n4")

    class State:
        csv_rows = 2

    run.prepare_resume(State())  # type: ignore[arg-type]
    assert path.read_text() == "h\n1\n2\n"
    State.csv_rows = 3
    with pytest.raises(RunDirError, match="holds 2"):
        run.prepare_resume(State())  # type: ignore[arg-type]


# ---------------------------------------------------------------------------------------------
# SIGKILL: the real command line in a subprocess, killed and resumed.


def _write_config(tmp_path: Path, exp_evaluations: int) -> Path:
    (tmp_path / "secret.txt").write_bytes(SECRET + b"\n")
    config = {
        "experiment": {
            "robots": 3,
            "evaluation_steps": 1,
            "post_evaluation_steps": 4,
            "seed": 3,
            "evolution": {"evaluations": exp_evaluations},
        },
        "port": 0,
        "secret_file": "secret.txt",
        "round_margin": 1.0,
        "heartbeat_interval": 0.5,
    }
    path = tmp_path / "master.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def _start(tmp_path: Path, name: str, *args: str) -> subprocess.Popen:
    log = open(tmp_path / f"{name}.out", "wb")  # noqa: SIM115 - lives as long as the process
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen(
        [sys.executable, "-m", "master_service", *args], stdout=log, stderr=log, env=env
    )


async def _port_of(run: Path, proc: subprocess.Popen, timeout: float = 15.0) -> int:
    """The port the master process ``proc`` listens on, from its live.json."""
    async with asyncio.timeout(timeout):
        while True:
            assert proc.poll() is None, "the master exited early"
            try:
                live = json.loads((run / "live.json").read_text())
                if live["pid"] == proc.pid and live["running"]:
                    return live["port"]
            except (OSError, ValueError):
                pass
            await asyncio.sleep(0.02)


async def _wait_exit(proc: subprocess.Popen, timeout: float = 30.0) -> int:
    deadline = time.monotonic() + timeout
    while proc.poll() is None:
        assert time.monotonic() < deadline, "the master did not finish"
        await asyncio.sleep(0.02)
    return proc.returncode


@pytest.mark.slow
async def test_a_killed_run_resumes_to_the_same_evaluations_as_an_uninterrupted_one(tmp_path):
    evaluations = 40
    config_path = _write_config(tmp_path, evaluations)
    run = tmp_path / "run"

    master = _start(tmp_path, "run", "run", "--config", str(config_path), "--out", str(run))
    try:
        # A 20 ms answer makes the 40 evaluations take about a second: the kill lands mid-run.
        robots = make_robots(await _port_of(run, master), 3, delay=0.02)
        await connect(robots)
        await wait_rows(run / "evaluations.csv", 8)
        master.send_signal(signal.SIGKILL)
        assert await _wait_exit(master) == -signal.SIGKILL
    finally:
        if master.poll() is None:
            master.kill()
    await asyncio.gather(*(r.closed.wait() for r in robots))
    killed_at = len(read_csv(run / "evaluations.csv"))
    assert 8 <= killed_at < evaluations

    resumed = _start(tmp_path, "resume", "resume", str(run))
    try:
        again = make_robots(await _port_of(run, resumed), 3)
        await connect(again)
        assert await _wait_exit(resumed) == 0, (tmp_path / "resume.out").read_text()
    finally:
        if resumed.poll() is None:
            resumed.kill()
    await close(again)
    assert min(ids_of(again)) > max(ids_of(robots))

    # The same experiment uninterrupted, in process.
    reference = tmp_path / "reference"
    loaded = RunDir(run).load_config()
    async with Master(master_config(loaded.experiment), reference, secret=SECRET) as m:
        robots = make_robots(m.port, 3)
        await run_with(m, robots)
        await close(robots)
    columns = ["evaluation", "kind", "fitness", "best_fitness", "accepted"]
    columns += [f"fitness_{r}" for r in robot_ids(3)]
    killed = [[row[c] for c in columns] for row in read_csv(run / "evaluations.csv")]
    whole = [[row[c] for c in columns] for row in read_csv(reference / "evaluations.csv")]
    assert killed == whole and len(whole) == evaluations
    assert_matches_reference(run, loaded.experiment, robot_ids(3))
    assert json.loads((run / "checkpoint.json").read_text())["phase"] == "done"
    assert (run / "traces" / "r2.npz").exists()


async def test_sigterm_stops_the_command_cleanly(tmp_path):
    config_path = _write_config(tmp_path, 5)
    run = tmp_path / "run"
    master = _start(tmp_path, "run", "run", "--config", str(config_path), "--out", str(run))
    try:
        robots = make_robots(await _port_of(run, master), 3, delay=0.05)
        await connect(robots)
        master.send_signal(signal.SIGTERM)
        assert await _wait_exit(master) == 128 + signal.SIGTERM
    finally:
        if master.poll() is None:
            master.kill()
    # The robots were told goodbye, not cut off.
    await asyncio.gather(*(r.closed.wait() for r in robots))
    log = (run / "master.log").read_text()
    assert "left: master shutting down" in log
    assert "stopped by SIGTERM; continue with `surprise-master resume" in log
    assert json.loads((run / "live.json").read_text())["running"] is False


@pytest.mark.parametrize("first_rows", [0, 3])
async def test_ids_are_never_reused_when_a_resumed_master_dies_before_its_first_commit(
    tmp_path, first_rows
):
    # Each master sends an attempt while the commit reserving its id is still being written. A
    # master killed before its first commit reached the disk (a fresh one, or a resumed one) has
    # sent an id the checkpoint on disk does not account for: the next resume must skip it too.
    exp = experiment(evaluations=12)
    run = tmp_path / "run"
    sent: list[int] = []
    if first_rows:
        async with Master(master_config(exp), run, secret=SECRET) as master:
            robots = make_robots(master.port, 3, delay=0.005)
            task = asyncio.create_task(master.run())
            await connect(robots)
            await wait_rows(run / "evaluations.csv", first_rows)
            task.cancel()
            with pytest.raises(asyncio.CancelledError):
                await task
        await asyncio.gather(*(r.closed.wait() for r in robots))
        sent += ids_of(robots)
    for _ in range(2):
        async with Master(master_config(exp), run, secret=SECRET, resume=run.exists()) as master:

            def crash(state, row, header):
                raise OSError("simulated kill before the commit reached the disk")

            master.run_dir.commit = crash
            robots = make_robots(master.port, 3)
            with pytest.raises(OSError, match="simulated kill"):
                await run_with(master, robots)
        await asyncio.gather(*(r.closed.wait() for r in robots))
        ids = ids_of(robots)
        assert ids and not set(ids) & set(sent), f"ids {ids} were sent before: {sent}"
        sent += ids
    async with Master(master_config(exp), run, secret=SECRET, resume=True) as master:
        again = make_robots(master.port, 3)
        await run_with(master, again)
        await close(again)
    assert not set(ids_of(again)) & set(sent)
    assert_matches_reference(run, exp, robot_ids(3))
