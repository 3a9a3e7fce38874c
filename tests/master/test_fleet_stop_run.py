"""``surprise-master fleet stop --run DIR`` during a run: real agents on simulated bodies over
loopback TCP, the stop goes through the run's master (a request in ``requests/``). Every robot's
motors stop, the running attempt does not count, the run pauses with a line naming the stop, and
after ``continue`` it finishes with every evaluation counted once (docs/fleet.md)."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import pytest
from master_helpers import read_csv

import master_service.stopall as stopall_module
from master_service.cli import main
from master_service.experiments.simulate import SimulatedSwarm, simulation_experiment
from master_service.stopall import STOP_PAUSE_TEXT
from runfiles import schema
from runfiles.schema import EVENT_FLEET_STOP, PauseFile

#: Long enough that the command's round trip (a thread, a file, the master's poll, a message)
#: lands inside an evaluation on a loaded machine; a lockstep world runs it in a second or two.
STEPS = 3000


async def _when(condition, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        await asyncio.sleep(0.001)  # lockstep: the world moves between our looks


async def test_a_stop_through_the_master_pauses_the_run_and_loses_no_evaluation(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
):
    monkeypatch.setattr(stopall_module, "POLL_INTERVAL", 0.01)
    experiment = simulation_experiment(
        "basic",
        robots=2,
        evaluations=2,
        seed=5,
        data={"setting": "lab", "evaluation_steps": STEPS, "post_evaluation_steps": 10},
    )
    run = tmp_path / "run"
    sim = SimulatedSwarm(experiment)
    seen: dict[str, object] = {}

    def evaluating() -> bool:
        master = sim.master
        return master is not None and master.rounds.current is not None

    async def experimenter() -> None:
        await _when(evaluating)
        seen["stop"] = await asyncio.to_thread(main, ["fleet", "stop", "--run", str(run)])
        await _when(lambda: (run / PauseFile.FILE).exists())
        seen["pause"] = schema.read(run, PauseFile)
        assert sim.swarm is not None
        seen["commands"] = sim.swarm.world.commands.tolist()
        seen["continue"] = await asyncio.to_thread(main, ["continue", str(run)])

    hand = asyncio.create_task(experimenter())
    result = await sim.run(run)
    await hand
    printed = capsys.readouterr().out
    assert seen["stop"] == 0, printed
    assert "stopped (confirmed): sim-0, sim-1" in printed and "did not answer: none" in printed
    pause = seen["pause"]
    assert isinstance(pause, PauseFile)
    assert pause.kind == "fleet-stop" and pause.reason == STOP_PAUSE_TEXT
    assert seen["commands"] == [[0.0, 0.0], [0.0, 0.0]]  # held while the run waited
    assert seen["continue"] == 0

    (event,) = [e for e in schema.read_events(run) if e.kind == EVENT_FLEET_STOP]
    assert event.accepted and event.confirmed == ["sim-0", "sim-1"] and event.unanswered == []
    log = (run / "master.log").read_text()
    assert f"paused: {STOP_PAUSE_TEXT}" in log
    # The stopped attempt did not count; every evaluation is in the CSV once.
    rows = read_csv(run / "evaluations.csv")
    assert [int(row["evaluation"]) for row in rows] == [1, 2]
    assert result.summary.failed_attempts == 1
    assert sorted(row["attempts"] for row in rows) == ["1", "2"]
