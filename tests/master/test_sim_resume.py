"""A stopped simulated run resumes to the result an uninterrupted one reaches, on either engine,
and stopping ``surprise-master sim`` is one line, not tracebacks.

Each run stops part-way (a stop asked between evaluations on the engine, the task cancelled as
Ctrl-C does with the agents), resumes from its checkpoint (world, safety layers, optimizer), and
is compared row by row and trace by trace with a run that never stopped.
"""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import msgspec
import pytest
from master_helpers import assert_same_run, write_experiment

from master_service.experiments.engine_run import FastRun
from master_service.experiments.simulate import SimulatedSwarm, simulation_experiment
from master_service.rundir import RunDir
from needs import obeying_modes

pytestmark = pytest.mark.slow

#: Columns that depend on the wall clock or on the stop itself (the attempt in flight when the
#: run stopped is counted again), not on the simulation.
TIMING_COLUMNS = {"duration_s", "attempts"}


def small(scenario: str, evaluations: int, **overrides):
    experiment = simulation_experiment(scenario, setting="paper", robots=3, seed=5)
    return msgspec.structs.replace(
        experiment,
        evolution=msgspec.structs.replace(experiment.evolution, evaluations=evaluations),
        evaluation_steps=60,
        post_evaluation_steps=80,
        **overrides,
    )


@pytest.mark.parametrize("scenario", ["basic", "boxes"])
def test_a_stopped_engine_run_resumes_to_the_uninterrupted_result(tmp_path: Path, scenario: str):
    config = small(scenario, 30)
    whole, stopped = tmp_path / "whole", tmp_path / "stopped"
    FastRun(config).run(whole, plots=False)

    counted: list[int] = []
    run = FastRun(config, on_progress=lambda p: counted.append(p.evaluations))
    assert (
        run.run(stopped, plots=False, should_stop=lambda: bool(counted) and counted[-1] >= 11)
        is None
    )
    state = RunDir(stopped).read_state(RunDir(stopped).load_config())
    assert state is not None and state.optimizer.evaluations == 11
    assert state.phase == "evolution" and state.simulation is not None

    result = FastRun(config).run(stopped, plots=False, resume=True)
    assert result is not None and result.summary.evaluations == 30
    assert_same_run(stopped, whole, config.robots, TIMING_COLUMNS)


def test_a_resumed_run_needs_the_experiment_it_was_started_with(tmp_path: Path):
    config = small("basic", 10)
    FastRun(config).run(tmp_path / "run", plots=False, should_stop=lambda: True)
    other = msgspec.structs.replace(config, seed=6)
    with pytest.raises(Exception, match="experiment differs"):
        FastRun(other).run(tmp_path / "run", plots=False, resume=True)


def test_a_cancelled_agents_run_resumes_to_the_uninterrupted_result(tmp_path: Path):
    config = small("boxes", 16)
    whole, stopped = tmp_path / "whole", tmp_path / "stopped"
    asyncio.run(SimulatedSwarm(config).run(whole))

    async def stop_part_way() -> None:
        task = asyncio.current_task()
        assert task is not None

        def on_progress(progress) -> None:
            if progress.evaluations >= 6:
                task.cancel()  # what the CLI does on Ctrl-C

        with pytest.raises(asyncio.CancelledError):
            await SimulatedSwarm(config, on_progress=on_progress).run(stopped)

    asyncio.run(stop_part_way())
    state = RunDir(stopped).read_state(RunDir(stopped).load_config())
    # Cancelled at the sixth evaluation's progress, perhaps before its commit landed.
    assert state is not None and 5 <= state.optimizer.evaluations < 16
    assert state.simulation is not None

    result = asyncio.run(SimulatedSwarm(config).run(stopped, resume=True))
    assert result.summary.evaluations == 16
    assert_same_run(stopped, whole, config.robots, TIMING_COLUMNS)


# -- the command line ------------------------------------------------------------------------------


def start(argv: list[str], cwd: Path, prefix: tuple[str, ...] = ()) -> subprocess.Popen[str]:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen(
        [*prefix, sys.executable, "-m", "master_service", *argv],
        cwd=cwd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def counted(run: Path) -> int:
    """Evaluations the run's checkpoint counts (0 before its first commit)."""
    if not (run / "checkpoint.json").exists():
        return 0
    checkpoint = RunDir(run).read_checkpoint()
    return 0 if checkpoint is None else checkpoint.evaluations


def wait_for_checkpoint(run: Path, process: subprocess.Popen[str], timeout: float = 120) -> None:
    deadline = time.monotonic() + timeout
    while counted(run) < 1:
        assert process.poll() is None, process.communicate()
        assert time.monotonic() < deadline, "no evaluation committed in time"
        time.sleep(0.05)


@pytest.mark.parametrize(
    ("engine", "signum", "evaluations", "steps"),
    # The fast run is long enough (9e6 robot-steps, seconds) to be still going at its first
    # commit, two seconds in, on a faster engine too.
    [("fast", signal.SIGINT, 3000, 1000), ("agents", signal.SIGTERM, 400, 40)],
)
def test_sim_stops_quietly_on_a_signal_and_resume_finishes_the_run(
    tmp_path: Path, engine: str, signum: int, evaluations: int, steps: int
):
    config = write_experiment(tmp_path / "experiment.yaml", evaluations, steps)
    run = tmp_path / "run"
    process = start(
        ["sim", "--config", str(config), "--engine", engine, "--out", str(run)], tmp_path
    )
    wait_for_checkpoint(run, process)
    process.send_signal(signum)
    out, err = process.communicate(timeout=60)
    assert process.returncode == 128 + signum, (out, err)
    assert "Traceback" not in out + err
    assert "watchdog tripped" not in out + err
    name = signal.Signals(signum).name
    last = err.strip().splitlines()[-1]
    assert last.startswith(f"stopped by {name} at evaluation ")
    assert last.endswith(f"/{evaluations}; continue with `surprise-master resume {run}`")
    done = int(last.split("at evaluation ")[1].split("/")[0])
    assert 0 < done < evaluations

    process = start(["resume", str(run)], tmp_path)
    out, err = process.communicate(timeout=300)
    assert process.returncode == 0, (out, err)
    assert f"run directory: {run}" in out
    assert f"evaluations: {evaluations} (resumed; " in out
    assert len(RunDir(run).read_rows()) == evaluations
    checkpoint = RunDir(run).read_checkpoint()
    assert checkpoint is not None and checkpoint.phase == "done"


@pytest.mark.parametrize("engine", ["fast", "agents"])
def test_sim_into_a_directory_that_cannot_be_made_is_one_clear_line(tmp_path: Path, engine: str):
    # A file where a folder should be fails for every user, root included.
    (tmp_path / "notes.txt").write_text("not a folder\n")
    out = tmp_path / "notes.txt" / "run"
    argv = ["sim", "--evaluations", "2", "--engine", engine, "--out", str(out)]
    process = start(argv, tmp_path)
    _, err = process.communicate(timeout=120)
    assert process.returncode == 1
    assert err.strip().splitlines() == [f"surprise-master: {out}: Not a directory"]


def test_sim_into_an_unwritable_directory_is_one_clear_line(tmp_path: Path):
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    prefix = obeying_modes(tmp_path)
    try:
        argv = ["sim", "--evaluations", "2", "--out", str(locked / "run")]
        process = start(argv, tmp_path, prefix)
        _, err = process.communicate(timeout=120)
    finally:
        locked.chmod(0o700)
    assert process.returncode == 1
    assert err.strip().splitlines() == [f"surprise-master: {locked / 'run'}: Permission denied"]
