"""A battery running low pauses the run between evaluations, checkpoint written and motors
stopped, naming the robot to swap; after the swap and `surprise-master continue` the run goes on
to the result an uninterrupted run reaches. Real agents on simulated robots, over loopback TCP."""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path

import msgspec
import pytest

from master_service.cli import main
from master_service.experiments.simulate import SimulatedSwarm, simulation_experiment
from master_service.pause import read_pause
from master_service.rundir import RunDir
from runfiles.schema import PauseFile
from simulator.battery import SimBattery

pytestmark = pytest.mark.slow

PAUSE = PauseFile.FILE

EVALUATIONS = 12
STEPS = 30
#: Seconds to wait for the run to pause: lockstep runs at CPU speed, a few evaluations take well
#: under a second; a loaded CI machine gets ample room.
PAUSE_TIMEOUT = 60.0
#: Columns that depend on the wall clock or the robots' batteries, not on the evolution.
NOT_EVOLUTION = ("duration_s", "battery_v_")


def experiment():
    base = simulation_experiment("basic", setting="paper", robots=2, seed=3)
    return msgspec.structs.replace(
        base,
        evolution=msgspec.structs.replace(base.evolution, evaluations=EVALUATIONS),
        evaluation_steps=STEPS,
        post_evaluation_steps=40,
    )


def evolution_rows(run: Path) -> list[dict[str, str]]:
    return [
        {k: v for k, v in row.items() if not k.startswith(NOT_EVOLUTION)}
        for row in RunDir(run).read_rows()
    ]


async def wait_for_pause(run: Path, task: asyncio.Task) -> PauseFile:
    deadline = time.monotonic() + PAUSE_TIMEOUT
    while (pause := read_pause(RunDir(run))) is None:
        assert not task.done(), "the run ended without pausing"
        assert time.monotonic() < deadline, "the run never paused"
        await asyncio.sleep(0.02)
    return pause


async def test_a_low_battery_pauses_the_run_which_goes_on_to_the_same_result(tmp_path, capsys):
    plain = tmp_path / "plain"
    await SimulatedSwarm(experiment()).run(plain)

    # sim-1's battery crosses 3.6 V during its 5th evaluation: 0.6 V over 4.x evaluations.
    drain = 0.6 / (4.5 * STEPS)
    batteries = [SimBattery(), SimBattery(drain_v_per_step=drain)]
    paused = tmp_path / "paused"
    swarm = SimulatedSwarm(experiment(), batteries=batteries)
    task = asyncio.create_task(swarm.run(paused))
    pause = await wait_for_pause(paused, task)

    assert pause.kind == "battery" and pause.robots == ["sim-1"]
    assert "swap the battery of sim-1 (3.5" in pause.reason
    # Paused after the 5th evaluation, with that evaluation on disk and the motors stopped.
    rows = RunDir(paused).read_rows()
    assert len(rows) == 5
    assert json.loads((paused / "checkpoint.json").read_text())["csv_rows"] == 5
    assert float(rows[-1]["battery_v_sim-1"]) < 3.6 <= float(rows[-2]["battery_v_sim-1"])
    assert float(rows[-1]["battery_v_sim-0"]) == 4.2  # no drain: a full battery throughout
    assert (rows[-1]["overruns_sim-0"], rows[-1]["read_failures_sim-1"]) == ("0", "0")
    assert not swarm.world.commands.any()
    # It stays paused: no evaluation goes out while a person swaps the battery.
    await asyncio.sleep(0.5)
    assert len(RunDir(paused).read_rows()) == 5 and not task.done()
    assert "paused: battery below 3.60 V" in (paused / "master.log").read_text()

    batteries[1].swap()
    batteries[1].drain_v_per_step = drain / 4  # a fresh battery lasts the rest of the run
    assert main(["continue", str(paused)]) == 0
    assert "continuing" in capsys.readouterr().out
    await asyncio.wait_for(task, PAUSE_TIMEOUT)

    assert not (paused / PAUSE).exists()
    assert evolution_rows(paused) == evolution_rows(plain)
    # The report tells the batteries' story in a line.
    assert main(["report", str(paused)]) == 0
    out = capsys.readouterr().out
    assert (
        "batteries: sim-0 4.20 -> 4.20 V (lowest 4.20), sim-1 4.07 -> 3.97 V (lowest 3.53)" in out
    )
    stats = json.loads((paused / "metrics.json").read_text())["robot_stats"]
    assert stats["sim-1"]["battery_min_v"] < 3.6 and stats["sim-0"]["overruns"] == 0
    for name in ("best_genome.json", "post_evaluation.json"):
        a = json.loads((plain / name).read_text())
        b = json.loads((paused / name).read_text())
        for data in (a, b):
            data.pop("written_at", None)
            data.pop("started_at", None)  # the wall clock at which the robots flashed
            for robot in data.get("robots", {}).values():
                robot["stats"].pop("battery_v")  # full batteries against none
        assert a == b, name


def test_continue_without_a_master_waiting_says_to_resume_and_keeps_the_pause(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    (run / PAUSE).write_text('{"kind": "battery", "reason": "swap r1", "robots": ["r1"]}')
    (run / "live.json").write_text('{"running": false, "pid": 1, "updated_at": 0}')
    assert main(["continue", str(run)]) == 2
    assert f"no master is running {run}: continue it with `surprise-master resume" in (
        capsys.readouterr().err
    )
    assert (run / PAUSE).exists()


async def test_pause_before_post_waits_with_the_evolution_on_disk(tmp_path, capsys):
    plain = tmp_path / "plain"
    await SimulatedSwarm(experiment()).run(plain)
    run = tmp_path / "run"
    swarm = SimulatedSwarm(experiment(), pause_before_post=True)
    task = asyncio.create_task(swarm.run(run))
    pause = await wait_for_pause(run, task)

    assert pause.kind == "before-post-evaluation" and pause.robots == []
    checkpoint = json.loads((run / "checkpoint.json").read_text())
    assert (checkpoint["phase"], checkpoint["csv_rows"]) == ("post-evaluation", EVALUATIONS)
    assert not (run / "post_evaluation.json").exists()
    assert not swarm.world.commands.any()
    assert main(["status", str(run)]) == 0
    assert "paused: the evolution is done: place the robots" in capsys.readouterr().out

    assert main(["continue", str(run)]) == 0
    await asyncio.wait_for(task, PAUSE_TIMEOUT)
    a, b = (json.loads((r / "post_evaluation.json").read_text()) for r in (plain, run))
    for data in (a, b):  # when it was written, and when the robots flashed: wall clocks
        data.pop("written_at", None), data.pop("started_at", None)
    assert a == b
