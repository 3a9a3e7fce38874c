"""The experimenter's hand, end to end: ``surprise-master escape RUN ROBOT`` on a running
``sim --engine agents`` run (real agents over loopback TCP on simulated bodies) reaches the robot's
safety layer, which escapes at its next step; the escape shows in the robot's step statistics and
trace, in ``events.jsonl`` and in ``master.log``. The command's one-line errors: no master, a
robot not in the run, not connected, an agent that predates the message, a paused run. And the
post-evaluation's start: its time in the run directory, every simulated robot's top LED lit for
its first five steps."""

from __future__ import annotations

import asyncio
import contextlib
import json
import time
from pathlib import Path

import numpy as np
import pytest
from master_helpers import SECRET, experiment, master_config

import master_service.escape as escape_module
from master_service import Master
from master_service.cli import main
from master_service.experiments.simulate import SimulatedSwarm, simulation_experiment
from master_service.pause import Pause
from minimize_surprise.safety import REASON_ESCAPE, REASON_EXPERIMENTER
from runfiles import schema
from runfiles.schema import EVENT_ESCAPE, EVENT_POST_EVALUATION, Live, PostEvaluation
from standins.scripted_robots import ScriptedRobot

#: Long enough that the command's round trip (a thread, a file, the master's poll, a message)
#: lands inside it on a loaded machine; a lockstep world runs it in a second or two.
POST_STEPS = 3000


def _experiment(profile: str = "escape", post_steps: int = POST_STEPS):
    return simulation_experiment(
        "basic",
        robots=2,
        evaluations=2,
        seed=5,
        data={
            "setting": "lab",
            "evaluation_steps": 10,
            "post_evaluation_steps": post_steps,
            "safety": {"profile": profile},
        },
    )


async def _when(condition, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, "timed out"
        await asyncio.sleep(0)  # lockstep: the world moves between our looks


def _evaluating(sim: SimulatedSwarm, robot: str) -> bool:
    master = sim.master
    return (
        master is not None
        and master.state is not None
        and master.state.phase == "post-evaluation"
        and master._evaluating(robot)
    )


async def test_the_command_makes_a_simulated_robot_escape_during_the_post_evaluation(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
):
    # The master looks into requests/ more often than a person needs, so that the lockstep
    # world, which runs far faster than 10 Hz, is still in its post-evaluation.
    monkeypatch.setattr(escape_module, "POLL_INTERVAL", 0.01)
    run = tmp_path / "run"
    sim = SimulatedSwarm(_experiment())
    codes: list[int] = []

    async def experimenter() -> None:
        await _when(lambda: _evaluating(sim, "sim-0"))
        codes.append(await asyncio.to_thread(main, ["escape", str(run), "sim-0"]))

    hand = asyncio.create_task(experimenter())
    result = await sim.run(run)
    await hand
    assert codes == [0], capsys.readouterr().err
    printed = capsys.readouterr().out
    assert "sim-0 escapes now" in printed and "events.jsonl" in printed

    post = schema.read(run, PostEvaluation)
    assert post is not None and result.summary.post_evaluation_fitness == post.swarm_fitness
    counts = post.robots["sim-0"].stats.interventions
    assert counts.get(REASON_EXPERIMENTER) == 1, counts
    assert REASON_EXPERIMENTER not in post.robots["sim-1"].stats.interventions
    with np.load(run / "traces" / "sim-0.npz") as trace:
        safety = list(trace["safety"])
        commands = trace["commands"]
    start = safety.index(REASON_EXPERIMENTER)
    # The front obstacle's escape: a reverse at full speed (cut short only by something behind).
    assert commands[start].tolist() == [-1.0, -1.0]
    assert set(safety[start + 1 : start + 5]) <= {REASON_ESCAPE, "rear"}

    events = schema.read_events(run)
    (escape,) = [e for e in events if e.kind == EVENT_ESCAPE]
    assert escape.robot == "sim-0" and escape.accepted
    assert escape.evaluation_id == post.evaluation_id
    assert "the experimenter's escape: robot sim-0 escapes now" in (run / "master.log").read_text()
    assert not list((run / "requests").iterdir())  # taken

    # The post-evaluation's start: when it went out, and every robot's LED lit for 0.5 s.
    starts = [e for e in events if e.kind == EVENT_POST_EVALUATION]
    assert [e.evaluation_id for e in starts] == [post.evaluation_id]
    assert post.started_at == starts[0].time and escape.time >= post.started_at
    assert sim.swarm is not None
    assert [sim.swarm.lit_steps(i) for i in range(2)] == [[(0, 5)], [(0, 5)]]


async def test_the_stop_profile_s_robot_refuses_with_a_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
):
    monkeypatch.setattr(escape_module, "POLL_INTERVAL", 0.01)
    run = tmp_path / "run"
    sim = SimulatedSwarm(_experiment("stop"))
    codes: list[int] = []

    async def experimenter() -> None:
        await _when(lambda: _evaluating(sim, "sim-1"))
        codes.append(await asyncio.to_thread(main, ["escape", str(run), "sim-1"]))

    hand = asyncio.create_task(experimenter())
    await sim.run(run)
    await hand
    assert codes == [1]
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith("surprise-master: escape of sim-1: sim-1 refused: profile: ")
    assert "'stop' profile, which has no escape behaviour" in line
    post = schema.read(run, PostEvaluation)
    assert post is not None
    assert all(REASON_EXPERIMENTER not in r.stats.interventions for r in post.robots.values())
    (event,) = [e for e in schema.read_events(run) if e.kind == EVENT_ESCAPE]
    assert event.accepted is False and "profile" in event.detail


# --------------------------------------------------------------------------- the command's errors


def test_without_a_running_master_the_command_says_so_in_a_line(tmp_path, capsys):
    run = tmp_path / "run"
    run.mkdir()
    assert main(["escape", str(run), "sim-0"]) == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith("surprise-master: no master is running") and "during a run" in line
    # A master that stopped (live.json says so) is no master either; nothing is left behind.
    schema.write(run, Live(pid=1, running=False, host="h", port=1, robots=[], phase="done",
                           waiting=False, evaluations=0, time_left_s=None, paused=None,
                           robot_state={}, updated_at=time.time()))  # fmt: skip
    assert main(["escape", str(run), "sim-0"]) == 2
    assert "no master is running" in capsys.readouterr().err
    assert not (run / "requests").exists()


async def _command(run: Path, robot: str, capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    code = await asyncio.to_thread(main, ["escape", str(run), robot, "--timeout", "20"])
    captured = capsys.readouterr()
    return code, (captured.err or captured.out).strip()


async def test_the_master_refuses_with_one_line_what_it_cannot_pass_on(tmp_path, capsys):
    exp = experiment(evaluations=1, robots=2)
    config = master_config(exp, allowed_robots=["sim-0", "sim-1"])
    run = tmp_path / "run"
    async with Master(config, run, secret=SECRET) as master, contextlib.AsyncExitStack() as stack:
        code, line = await _command(run, "thymio-9", capsys)
        assert code == 1 and line == (
            "surprise-master: escape of thymio-9: thymio-9 is not in this run (its robots: "
            "sim-0, sim-1)"
        )
        code, line = await _command(run, "sim-0", capsys)
        assert code == 1 and line.endswith("sim-0: sim-0 is not connected")
        # A robot whose agent predates the message offers no feature: it is never sent one.
        old = ScriptedRobot("sim-1", SECRET, master.port)
        await old.connect()
        stack.push_async_callback(old.close)
        code, line = await _command(run, "sim-1", capsys)
        assert code == 1 and line.endswith(
            "sim-1's agent (software scripted) does not know the experimenter's escape: update it"
        )
        master.evolution.pauses.current = Pause("battery", "swap the battery of sim-1")
        code, line = await _command(run, "sim-1", capsys)
        assert code == 1 and line.endswith(
            "the run is paused (swap the battery of sim-1): its robots stand still"
        )
        master.evolution.pauses.current = None
    events = [e for e in schema.read_events(run) if e.kind == EVENT_ESCAPE]
    assert [(e.robot, e.accepted) for e in events] == [
        ("thymio-9", False), ("sim-0", False), ("sim-1", False), ("sim-1", False)
    ]  # fmt: skip
    log = (run / "master.log").read_text()
    assert log.count("the experimenter's escape for robot") == 4
    assert json.loads((run / "live.json").read_text())["running"] is False
