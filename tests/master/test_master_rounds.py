"""Evolution rounds against scripted robots over loopback TCP, with and without faults.

In every scenario the run must end with exactly the reference rows (nothing lost, nothing counted
twice) and the master must keep serving.
"""

from __future__ import annotations

import asyncio
import json
import struct

import numpy as np
import pytest
from master_helpers import (
    SECRET,
    ProgressLog,
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
from minimize_surprise.wire import MAX_FRAME_SIZE, Evaluate
from standins.scripted_robots import (
    DISCONNECT,
    DUPLICATE,
    FAIL,
    IGNORE,
    LATE,
    REPLY,
    ScriptedRobot,
    deterministic_fitness,
)


def on(count: int, action: str):
    """A behaviour doing ``action`` on the robot's ``count``-th Evaluate, REPLY otherwise."""
    return lambda n, msg: action if n == count else REPLY


def all_ids(robots: list[ScriptedRobot]) -> list[int]:
    return sorted({m.evaluation_id for r in robots for m in r.evaluations})


async def test_all_robots_reply(tmp_path):
    exp = experiment(evaluations=15)
    progress = ProgressLog()
    async with Master(master_config(exp), tmp_path / "run", secret=SECRET) as master:
        master.add_progress_listener(progress)
        robots = make_robots(master.port, 3)
        summary = await run_with(master, robots)
        await close(robots)
    run = tmp_path / "run"
    assert_matches_reference(run, exp, robot_ids(3))
    rows = read_csv(run / "evaluations.csv")
    assert rows[0]["kind"] == "initial"
    assert {r["kind"] for r in rows[1:]} <= {"offspring", "reevaluation"}
    assert all(r["attempts"] == "1" for r in rows)
    assert summary.evaluations == 15 and summary.failed_attempts == 0
    assert summary.best_fitness == float(rows[-1]["best_fitness"])
    # Every robot got the same evaluations, one id per attempt: 15 rounds + the post-evaluation.
    ids = [[m.evaluation_id for m in r.evaluations] for r in robots]
    assert ids[0] == ids[1] == ids[2] == list(range(16))
    assert [m.record for m in robots[0].evaluations] == [False] * 15 + [True]
    # The best genome file is bit-exact and is what the post-evaluation ran.
    best = json.loads((run / "best_genome.json").read_text())
    assert np.array_equal(np.array(best["genome"]), summary.best_genome)
    assert robots[0].evaluations[-1].genome == np.asarray(best["genome"]).astype("<f8").tobytes()
    checkpoint = json.loads((run / "checkpoint.json").read_text())
    assert checkpoint["phase"] == "done" and checkpoint["csv_rows"] == 15
    post = json.loads((run / "post_evaluation.json").read_text())
    assert set(post["robots"]) == set(robot_ids(3))
    for rid in robot_ids(3):
        with np.load(run / "traces" / f"{rid}.npz") as trace:
            assert trace["sensors"].shape == (4, 9) and trace["predictions"].shape == (4, 9)
    assert progress.updates[-1].phase == "done" and progress.updates[-1].evaluations == 15
    assert "evaluation 15/15" in (run / "master.log").read_text()


async def test_one_robot_times_out_and_the_same_genome_goes_out_again(tmp_path):
    exp = experiment()
    async with Master(master_config(exp), tmp_path / "run", secret=SECRET) as master:
        robots = make_robots(master.port, 3)
        robots[1].behaviour = on(3, IGNORE)
        summary = await run_with(master, robots)
        await close(robots)
    assert_matches_reference(tmp_path / "run", exp, robot_ids(3))
    rows = read_csv(tmp_path / "run" / "evaluations.csv")
    assert [r["attempts"] for r in rows] == ["1", "1", "2"] + ["1"] * 9
    assert summary.failed_attempts == 1
    for robot in robots:
        # The failed attempt (id 2) was aborted everywhere, and its genome sent again as id 3.
        assert [a.evaluation_id for a in robot.aborts] == [2]
        assert robot.evaluations[2].genome == robot.evaluations[3].genome
        assert robot.evaluations[2].evaluation_id == 2 and robot.evaluations[3].evaluation_id == 3


async def test_a_robot_that_disconnects_pauses_the_run_until_it_is_back(tmp_path):
    exp = experiment()
    progress = ProgressLog()
    async with Master(master_config(exp), tmp_path / "run", secret=SECRET) as master:
        master.add_progress_listener(progress)
        robots = make_robots(master.port, 3)
        robots[2].behaviour = on(4, DISCONNECT)
        run = asyncio.create_task(master.run())
        await connect(robots)
        await robots[2].closed.wait()
        # (Not the wait at the start, when robots were still connecting.)
        paused = await progress.wait(lambda p: p.waiting and p.evaluations > 0)
        assert paused.robots_connected == 2
        assert paused.evaluations == 3
        # While the robot is away nothing goes out: the others saw the aborted attempt only.
        sent = len(robots[0].evaluations)
        await robots[0].wait_until(lambda: len(robots[0].aborts) == 1)
        assert len(robots[0].evaluations) == sent
        await robots[2].connect()
        await asyncio.wait_for(run, 15)
        await close(robots)
    assert_matches_reference(tmp_path / "run", exp, robot_ids(3))
    rows = read_csv(tmp_path / "run" / "evaluations.csv")
    assert rows[3]["attempts"] == "2"
    log = (tmp_path / "run" / "master.log").read_text()
    assert "robot r2 left" in log and "waiting for robots" in log and "missing r2" in log


@pytest.mark.parametrize("action", [LATE, DUPLICATE, FAIL])
async def test_late_duplicate_and_failed_replies(tmp_path, action):
    exp = experiment()
    async with Master(master_config(exp), tmp_path / "run", secret=SECRET) as master:
        robots = make_robots(master.port, 3)
        # LATE: the answer to attempt 2 arrives after its abort; DUPLICATE: every answer of
        # r0 arrives twice; FAIL: r1 cannot complete attempt 5.
        robots[0].behaviour = {
            LATE: on(2, LATE),
            DUPLICATE: lambda n, m: DUPLICATE,
            FAIL: on(5, FAIL),
        }[action]
        if action == FAIL:
            robots[0].behaviour, robots[1].behaviour = None, on(5, FAIL)
        summary = await run_with(master, robots)
        await close(robots)
    assert_matches_reference(tmp_path / "run", exp, robot_ids(3))
    log = (tmp_path / "run" / "master.log").read_text()
    if action == LATE:
        assert summary.failed_attempts == 1 and "ignored a late Result for evaluation 1" in log
    elif action == DUPLICATE:
        assert summary.failed_attempts == 0 and "ignored a duplicate answer" in log
    else:
        assert summary.failed_attempts == 1 and "could not evaluate: scripted" in log


async def test_a_genome_failing_again_and_again_is_retried_with_a_pause(tmp_path):
    exp = experiment(evaluations=3)
    async with Master(master_config(exp), tmp_path / "run", secret=SECRET) as master:
        robots = make_robots(master.port, 3)
        robots[2].behaviour = lambda n, msg: FAIL if n in (2, 3) else REPLY
        summary = await run_with(master, robots)
        await close(robots)
    assert_matches_reference(tmp_path / "run", exp, robot_ids(3))
    rows = read_csv(tmp_path / "run" / "evaluations.csv")
    assert [r["attempts"] for r in rows] == ["1", "3", "1"] and summary.failed_attempts == 2
    log = (tmp_path / "run" / "master.log").read_text()
    assert "attempt 1 (id 1) does not count" in log and "attempt 2 (id 2)" in log
    assert "goes out again in 0.5 s" in log


@pytest.mark.parametrize(
    "data, words",
    [
        # Untagged bytes in a session: whoever sent them, they are not the robot's.
        pytest.param(b"\x00\x00\x00\x07garbage", "robot r1: frame 2 is too short", id="garbage"),
        pytest.param(
            b"\x00\x00\x00\x17" + bytes(23), "robot r1: frame 2 fails authentication", id="forged"
        ),
        pytest.param(
            struct.pack(">I", MAX_FRAME_SIZE + 1),
            "malformed input from robot r1: frame of",
            id="oversized",
        ),
    ],
)
async def test_malformed_input_from_a_robot_costs_its_connection_only(tmp_path, data, words):
    exp = experiment()
    async with Master(master_config(exp), tmp_path / "run", secret=SECRET) as master:
        robots = make_robots(master.port, 3)

        def garbage(n: int, msg: Evaluate) -> str:
            if n == 3:
                robots[1].send_raw(data)
                return IGNORE
            return REPLY

        robots[1].behaviour = garbage
        run = asyncio.create_task(master.run())
        await connect(robots)
        await robots[1].closed.wait()
        await robots[1].connect()
        await asyncio.wait_for(run, 15)
        await close(robots)
    assert_matches_reference(tmp_path / "run", exp, robot_ids(3))
    log = (tmp_path / "run" / "master.log").read_text()
    assert words in log


async def test_a_robot_dropping_out_of_the_post_evaluation_is_waited_for(tmp_path):
    exp = experiment(evaluations=3)
    async with Master(master_config(exp), tmp_path / "run", secret=SECRET) as master:
        robots = make_robots(master.port, 3)
        robots[0].behaviour = on(4, DISCONNECT)
        run = asyncio.create_task(master.run())
        await connect(robots)
        await robots[0].closed.wait()
        await robots[0].connect()
        summary = await asyncio.wait_for(run, 15)
        await close(robots)
    assert summary.failed_attempts == 1 and summary.post_evaluation_fitness is not None
    assert (tmp_path / "run" / "traces" / "r0.npz").exists()
    assert json.loads((tmp_path / "run" / "post_evaluation.json").read_text())["evaluation_id"] == 4


async def test_no_post_evaluation_when_its_length_is_zero(tmp_path):
    exp = experiment(evaluations=4, post_evaluation_steps=0)
    async with Master(master_config(exp), tmp_path / "run", secret=SECRET) as master:
        robots = make_robots(master.port, 3)
        summary = await run_with(master, robots)
        await close(robots)
    assert summary.post_evaluation_fitness is None
    assert not (tmp_path / "run" / "traces").exists()
    assert all(not m.record for m in robots[0].evaluations)
    assert json.loads((tmp_path / "run" / "checkpoint.json").read_text())["phase"] == "done"


async def test_the_swarm_is_fixed_by_the_allow_list_order_independent(tmp_path):
    exp = experiment(evaluations=3)
    config = master_config(exp, allowed_robots=["r2", "r0", "r1"])
    async with Master(config, tmp_path / "run", secret=SECRET) as master:
        robots = make_robots(master.port, 3)
        await run_with(master, robots)
        await close(robots)
    header = (tmp_path / "run" / "evaluations.csv").read_text().splitlines()[0]
    assert "fitness_r0,fitness_r1,fitness_r2,battery_v_r0,battery_v_r1,battery_v_r2" in header
    assert_matches_reference(tmp_path / "run", exp, robot_ids(3))


@pytest.mark.parametrize("hostile", [1e300, -0.5, 1.0 + 1e-9])
async def test_a_fitness_outside_zero_to_one_closes_that_session_and_the_round_repeats(
    tmp_path, hostile
):
    # One result of 1e300 once made the best fitness 2.5e299 and froze the evolution for the rest
    # of the run. A fitness outside [0, 1] is a protocol error: that robot's session closes, the
    # round does not count, and it is repeated with the same genome once the robot is back.
    exp = experiment(evaluations=3)
    pending = [hostile]

    def fitness(genome, index):
        if index == 1 and pending:
            return pending.pop()
        return deterministic_fitness(genome, index)

    async with Master(master_config(exp), tmp_path / "run", secret=SECRET) as master:
        robots = make_robots(master.port, 3, fitness=fitness)
        run = asyncio.create_task(master.run())
        await connect(robots)
        await asyncio.wait_for(robots[1].closed.wait(), 5)
        await robots[1].connect()
        summary = await asyncio.wait_for(run, 15)
        await close(robots)
    assert summary.failed_attempts == 1
    assert_matches_reference(tmp_path / "run", exp, robot_ids(3))
    log = (tmp_path / "run" / "master.log").read_text()
    assert "malformed input from robot r1" in log and "fitness" in log


async def test_the_round_deadline_follows_the_experiments_step_period(tmp_path):
    # Robots at 0.5 s per step answer 2 steps after 0.7 s: far past a deadline of 2 * 0.1 s +
    # margin, well inside 2 * 0.5 s + margin. Every Evaluate carries the period.
    exp = experiment(evaluations=2, evaluation_steps=2, post_evaluation_steps=0, step_period=0.5)
    async with Master(master_config(exp), tmp_path / "run", secret=SECRET) as master:
        assert master.rounds.deadline(2, exp.step_period) == pytest.approx(1.0 + 0.3)
        robots = make_robots(master.port, 3, delay=0.7)
        summary = await run_with(master, robots)
        await close(robots)
    assert summary.failed_attempts == 0
    assert {m.step_period for r in robots for m in r.evaluations} == {0.5}


def test_scripted_robots_answer_a_fitness_in_range_however_large_the_swarm():
    # The benchmarks run a thousand of them: their fitness must be one the master accepts.
    for genome in (np.full(10, -50.0), np.zeros(10), np.full(10, 50.0)):
        values = [deterministic_fitness(genome, index) for index in range(1000)]
        assert min(values) >= 0.0 and max(values) <= 1.0
