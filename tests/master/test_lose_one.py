"""Lose one, go on: a robot whose agent stops for good pauses the run naming it; a spare swapped
in with `surprise-master swap` takes its place, or, where the experiment's `min_robots` allows,
the run goes on without it. Either way every evaluation is counted once, the checkpoint holds
the new swarm and a resumed run keeps it. Real agents on simulated robots, over loopback TCP."""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path

import msgspec
import pytest

from master_service import swap
from master_service.cli import main
from master_service.experiments.simulate import SimulatedSwarm, simulation_experiment
from master_service.pause import read_pause
from master_service.rundir import RunDir
from runfiles import schema
from runfiles.schema import EVENT_SWARM_CHANGE, Checkpoint, PauseFile

pytestmark = pytest.mark.slow

EVALUATIONS = 14
STEPS = 30
#: Seconds a stopped robot may be away before it is gone for good: far below the default's
#: minutes, far above the moment a simulated agent takes to reconnect.
GONE_AFTER = 0.5
#: Seconds to wait for the run to reach a state: lockstep runs at CPU speed, a few evaluations
#: take well under a second; a loaded CI machine gets ample room.
WAIT = 60.0


def experiment(**changes):
    base = simulation_experiment("basic", setting="paper", robots=4, seed=5)
    return msgspec.structs.replace(
        base,
        evolution=msgspec.structs.replace(base.evolution, evaluations=EVALUATIONS),
        evaluation_steps=STEPS,
        post_evaluation_steps=40,
        **changes,
    )


async def until(check, task: asyncio.Task, what: str):
    deadline = time.monotonic() + WAIT
    while not (found := check()):
        assert not task.done(), f"the run ended before {what}"
        assert time.monotonic() < deadline, f"never {what}"
        await asyncio.sleep(0.02)
    return found


def counted(run: Path) -> list[int]:
    return [int(row["evaluation"]) for row in RunDir(run).read_rows()]


def checkpoint(run: Path) -> Checkpoint:
    found = schema.read(run, Checkpoint)
    assert found is not None
    return found


async def swap_command(*args: str) -> int:
    # The command waits for the master's answer: in a thread, so the master's loop runs.
    return await asyncio.to_thread(main, ["swap", *args])


async def test_a_robot_gone_for_good_pauses_the_run_until_a_spare_takes_its_place(
    tmp_path, capsys, monkeypatch
):
    run = tmp_path / "run"
    swarm = SimulatedSwarm(experiment(), spares=["spare-0"], robot_gone_after=GONE_AFTER)
    task = asyncio.create_task(swarm.run(run))
    await until(lambda: len(counted(run)) >= 4, task, "counted four evaluations")
    await swarm.stop_agent("sim-2")
    pause = await until(lambda: read_pause(RunDir(run)), task, "paused")
    assert pause.kind == "robot-gone" and pause.robots == ["sim-2"]
    assert f"bring in a spare with `surprise-master swap {run} sim-2 SPARE`" in pause.reason
    assert pause.reason.startswith("sim-2 gone for")
    before = counted(run)
    assert main(["status", str(run)]) == 0
    assert "paused: sim-2 gone for" in capsys.readouterr().out

    # Each refusal is one line and leaves the swarm as it was.
    for args, line in [
        (("nobody", "spare-0"), "nobody is not in this run's swarm (its robots: sim-0, sim-1, "),
        (("sim-2", "sim-1"), "sim-1 is in the swarm already"),
        (("sim-2", "stranger"), "stranger is unknown: not among the master file's allowed_robots"),
        (("sim-0", "spare-0"), "sim-0 is connected: a swap replaces a robot that is gone"),
    ]:
        assert await swap_command(str(run), *args) == 1
        err = capsys.readouterr().err
        assert line in err and err.count("\n") == 1, err
    monkeypatch.setattr(swap, "SPARE_WAIT", 0.3)
    assert await swap_command(str(run), "sim-2", "spare-0") == 1
    assert "spare-0 did not connect within 0.3 s" in capsys.readouterr().err
    # A malformed request costs nothing but itself.
    (run / "requests" / "swap-request-bad.json").write_text('{"gone": 3}')
    await asyncio.sleep(0.5)
    assert checkpoint(run).roster == ["sim-0", "sim-1", "sim-2", "sim-3"]
    assert read_pause(RunDir(run)) is not None and counted(run) == before

    await swarm.start_spare("spare-0", replacing="sim-2")
    assert await swap_command(str(run), "sim-2", "spare-0") == 0
    out = capsys.readouterr().out
    first = len(before) + 1
    assert f"spare-0 takes the place of sim-2 from evaluation {first} on" in out

    # Stopped two evaluations after the change and resumed: the swarm stays the new one.
    await until(lambda: len(counted(run)) >= first + 1, task, "counted with the spare")
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)
    assert checkpoint(run).roster == ["sim-0", "sim-1", "spare-0", "sim-3"]
    resumed = SimulatedSwarm(experiment(), spares=["spare-0"], robot_gone_after=GONE_AFTER)
    await asyncio.wait_for(resumed.run(run, resume=True), WAIT)

    assert counted(run) == list(range(1, EVALUATIONS + 1))
    final = checkpoint(run)
    assert final.roster == ["sim-0", "sim-1", "spare-0", "sim-3"]
    assert final.swarms is not None and len(final.swarms) == 1
    change = final.swarms[0]
    assert (change.from_evaluation, change.left, change.joined) == (first, "sim-2", "spare-0")
    rows = RunDir(run).read_rows()
    assert [row["swarm"] for row in rows] == ["0"] * (first - 1) + ["1"] * (EVALUATIONS - first + 1)
    for row in rows:
        in_first = row["swarm"] == "0"
        assert bool(row["fitness_sim-2"]) == in_first and bool(row["overruns_sim-2"]) == in_first
        assert bool(row["fitness_spare-0"]) != in_first
    post = json.loads((run / "post_evaluation.json").read_text())
    assert sorted(post["robots"]) == ["sim-0", "sim-1", "sim-3", "spare-0"]
    events = [e for e in schema.read_events(run) if e.kind == EVENT_SWARM_CHANGE]
    assert [e.accepted for e in events] == [False] * 5 + [True]
    assert events[-1].evaluation_id == first and events[-1].joined == "spare-0"
    # The report copes with a robot that left and one that joined.
    assert main(["report", str(run)]) == 0
    metrics = json.loads((run / "metrics.json").read_text())
    assert set(metrics["robot_fitness"]) == {"sim-0", "sim-1", "sim-2", "sim-3", "spare-0"}
    assert main(["status", str(run)]) == 0
    assert f"swarm changed from evaluation {first}: sim-2 gone, spare-0 in its place" in (
        capsys.readouterr().out
    )


async def test_with_min_robots_the_run_goes_on_without_the_gone_robot(tmp_path):
    run = tmp_path / "run"
    swarm = SimulatedSwarm(experiment(min_robots=3), robot_gone_after=GONE_AFTER)
    task = asyncio.create_task(swarm.run(run))
    await until(lambda: len(counted(run)) >= 4, task, "counted four evaluations")
    await swarm.stop_agent("sim-1")
    await asyncio.wait_for(task, WAIT)

    assert not (run / PauseFile.FILE).exists()
    assert counted(run) == list(range(1, EVALUATIONS + 1))
    final = checkpoint(run)
    assert final.roster == ["sim-0", "sim-2", "sim-3"]
    assert final.swarms is not None and final.swarms[0].joined is None
    first = final.swarms[0].from_evaluation
    rows = RunDir(run).read_rows()
    assert all(bool(r["fitness_sim-1"]) == (int(r["evaluation"]) < first) for r in rows)
    log = (run / "master.log").read_text()
    assert "robot sim-1 gone for" in log and f"without it from evaluation {first}" in log


def test_swap_without_a_running_master_says_so(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / "live.json").write_text('{"running": false, "pid": 1, "updated_at": 0}')
    assert main(["swap", str(run), "sim-2", "spare-0"]) == 2
    err = capsys.readouterr().err
    assert f"no master is running {run}: a swap changes a running run's swarm" in err
    assert err.count("\n") == 1
