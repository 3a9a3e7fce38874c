"""Runs whose arena changes: each event happens once, at its evaluation, on either engine, is
logged in events.jsonl, and survives a stop and resume of an endless run without happening
twice; a person's mark lands in events.jsonl through the master's desk."""

from __future__ import annotations

import asyncio
import csv
import logging
from pathlib import Path

import pytest

from master_service.console import Console
from master_service.experiments.engine_run import FastRun
from master_service.experiments.simulate import SimulatedSwarm, simulation_experiment
from master_service.mark import MarkDesk, hand_console, request_mark
from master_service.rundir import RunDir, RunState
from minimize_surprise.evolution import OnePlusOne
from runfiles.schema import EVENT_ARENA, EVENT_MARK, Event, read_events

EVENTS = [
    {"kind": "light-moves", "evaluation": 4, "position": [0.3, -0.2]},
    {"kind": "boxes-removed", "evaluation": 6, "count": 20},
    {"kind": "robots-leave", "evaluation": 9, "count": 1},
    {"kind": "wall-appears", "evaluation": 14, "start": [-0.3, 0.1], "end": [0.3, 0.1]},
    {"kind": "robots-join", "evaluation": 16, "count": 2},
]


def changing(evaluations: int | None, events=EVENTS, scenario: str = "gradient", **more):
    return simulation_experiment(
        data={
            "setting": "paper",
            "scenario": scenario,
            "robots": 3,
            "seed": 4,
            "evolution": {"evaluations": evaluations},
            "evaluation_steps": 40,
            "post_evaluation_steps": 50,
            "events": events,
            **more,
        }
    )


def arena_lines(run: Path) -> list[tuple[int | None, int | None]]:
    return [(e.index, e.evaluation) for e in read_events(run) if e.kind == EVENT_ARENA]


def rows(run: Path) -> list[dict[str, str]]:
    with open(run / "evaluations.csv", newline="") as file:
        return list(csv.DictReader(file))


def test_a_fast_run_makes_each_event_happen_once_at_its_evaluation(tmp_path: Path):
    run = tmp_path / "run"
    result = FastRun(changing(20)).run(run, plots=False)
    assert result is not None and result.summary.evaluations == 20
    # Before evaluation N: N - 1 counted evaluations done.
    assert arena_lines(run) == [(0, 3), (1, 5), (2, 8), (3, 13), (4, 15)]
    details = [e.detail for e in read_events(run) if e.kind == EVENT_ARENA]
    assert details[0] == "the light moves to (0.3, -0.2)" and details[2] == "1 robot leaves"
    table = rows(run)
    # sim-2 left before evaluation 9; sim-3 and sim-4 joined before evaluation 16.
    assert table[7]["fitness_sim-2"] and not table[8]["fitness_sim-2"]
    assert not table[14]["fitness_sim-3"] and table[15]["fitness_sim-3"]
    assert table[15]["fitness_sim-4"] and table[19]["fitness_sim-0"]
    state = RunDir(run).read_state(RunDir(run).load_config())
    assert state is not None and state.events_applied == [0, 1, 2, 3, 4]
    assert state.roster == ["sim-0", "sim-1", "sim-3", "sim-4"]


def test_a_stopped_run_with_events_resumes_to_the_uninterrupted_result(tmp_path: Path):
    whole, stopped = tmp_path / "whole", tmp_path / "stopped"
    FastRun(changing(20)).run(whole, plots=False)
    counted: list[int] = []
    first = FastRun(changing(20), on_progress=lambda p: counted.append(p.evaluations))
    assert first.run(stopped, plots=False, should_stop=lambda: counted[-1:] == [12]) is None
    assert FastRun(changing(20)).run(stopped, plots=False, resume=True) is not None
    assert arena_lines(stopped) == arena_lines(whole)
    drop = {"duration_s", "attempts"}
    strip = [{k: v for k, v in r.items() if k not in drop} for r in rows(stopped)]
    assert strip == [{k: v for k, v in r.items() if k not in drop} for r in rows(whole)]


def test_an_endless_run_stopped_and_resumed_makes_no_event_happen_twice(tmp_path: Path):
    run = tmp_path / "endless"
    endless = changing(None)
    assert endless.evolution.evaluations is None
    for stop_at in (7, 15, 24):  # stops before, between and after the events
        counted: list[int] = []
        fast = FastRun(endless, on_progress=lambda p, c=counted: c.append(p.evaluations))
        stop = lambda c=counted, n=stop_at: bool(c) and c[-1] >= n  # noqa: E731
        assert fast.run(run, plots=False, resume=stop_at != 7, should_stop=stop) is None
    state = RunDir(run).read_state(RunDir(run).load_config())
    assert state is not None and state.phase == "evolution"
    assert state.optimizer.evaluations == 24 and state.events_applied == [0, 1, 2, 3, 4]
    assert arena_lines(run) == [(0, 3), (1, 5), (2, 8), (3, 13), (4, 15)]
    assert len(rows(run)) == 24


@pytest.mark.slow
def test_the_agents_engine_moves_the_light_and_lets_a_robot_leave(tmp_path: Path):
    events = [
        {"kind": "light-moves", "evaluation": 3, "position": [0.3, 0.3]},
        {"kind": "boxes-added", "evaluation": 4, "count": 5},
        {"kind": "robots-leave", "evaluation": 5, "count": 1},
    ]
    config = changing(6, events, min_robots=2)
    swarm = SimulatedSwarm(config)
    seen: list[tuple[int, tuple[float, float], int]] = []

    async def run() -> None:
        task = asyncio.create_task(swarm.run(tmp_path / "run"))
        while not task.done():
            if swarm.master is not None and swarm.master.state is not None:
                done = swarm.master.state.optimizer.evaluations
                seen.append(
                    (done, swarm.world.config.light_position, len(swarm.world.box_positions))
                )
            await asyncio.sleep(0.005)
        await task

    asyncio.run(run())
    boxes = min(b for d, _, b in seen)
    assert {(p, b) for d, p, b in seen if d == 1} == {((0.0, 0.0), boxes)}
    assert ((0.3, 0.3), boxes + 5) in {(p, b) for d, p, b in seen if d == 4}
    assert arena_lines(tmp_path / "run") == [(0, 2), (1, 3), (2, 4)]
    table = rows(tmp_path / "run")
    assert table[3]["fitness_sim-2"] and not table[4]["fitness_sim-2"]


def test_an_event_the_agents_engine_cannot_make_is_refused_by_key():
    config = changing(6, [{"kind": "robots-join", "evaluation": 3, "count": 1}])
    with pytest.raises(Exception, match=r"events\[0\]\.kind") as info:
        SimulatedSwarm(config)
    assert "--engine fast" in str(info.value)


def test_a_mark_lands_in_events_jsonl_with_the_evaluation_it_happened_at(tmp_path: Path):
    run = RunDir(tmp_path)
    log = logging.getLogger("test.mark")
    optimizer = OnePlusOne(changing(20).evolution, 4, 0)
    optimizer.evaluations = 17
    state = RunState(run_id="r", optimizer=optimizer)
    desk = MarkDesk(run, log, lambda: state, lambda: 42.5)
    console = hand_console(run, log)
    console.line("mark   moved the light   to the door")
    console.line("mark")  # a mark needs a text: the console says what it knows

    async def serve() -> None:
        task = asyncio.create_task(desk.run())
        for _ in range(50):
            if read_events(tmp_path):
                break
            await asyncio.sleep(0.05)
        task.cancel()

    asyncio.run(serve())
    (event,) = read_events(tmp_path)
    assert event.kind == EVENT_MARK and event.detail == "moved the light to the door"
    assert event.evaluation == 17 and event.seconds == 42.5 and event.request
    assert not list((tmp_path / "requests").iterdir())


def test_the_console_knows_the_mark_line():
    marked: list[str] = []
    console = Console(logging.getLogger("test.console"), mark=marked.append)
    console.line("mark boxes added by hand")
    assert marked == ["boxes added by hand"]


@pytest.mark.slow
def test_surprise_master_mark_reaches_an_endless_agents_run_through_its_desk(tmp_path: Path):
    config = changing(None, [], scenario="basic")
    swarm = SimulatedSwarm(config)
    run = tmp_path / "run"

    async def mark_then_stop() -> Event:
        task = asyncio.create_task(swarm.run(run))
        while (
            swarm.master is None
            or swarm.master.state is None
            or (swarm.master.state.optimizer.evaluations < 3)
        ):
            assert not task.done(), task.result()
            await asyncio.sleep(0.01)
        event = await asyncio.to_thread(request_mark, RunDir(run), "moved the light")
        await asyncio.sleep(0.2)
        task.cancel()  # Ctrl-C: an endless run ends only so
        with pytest.raises(asyncio.CancelledError):
            await task
        return event

    answer = asyncio.run(mark_then_stop())
    (event,) = [e for e in read_events(run) if e.kind == EVENT_MARK]
    assert event == answer and event.detail == "moved the light"
    state = RunDir(run).read_state(RunDir(run).load_config())
    assert state is not None and state.phase == "evolution"
    assert event.evaluation is not None and 3 <= event.evaluation <= state.optimizer.evaluations
