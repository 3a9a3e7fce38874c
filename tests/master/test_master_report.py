"""Reports, status and the progress display."""

from __future__ import annotations

import asyncio
import io
import json
import os
import time

import pytest
from master_helpers import SECRET, close, experiment, make_robots, master_config, run_with

from master_service import Master, Progress
from master_service.cli import main
from master_service.progress import ProgressDisplay, describe
from minimize_surprise import __version__
from minimize_surprise.provenance import software_commit
from reporting.report import compute_metrics, write_report
from reporting.status import status_text
from runfiles import schema
from runfiles.schema import Software, SoftwareRecord
from standins.scripted_robots import ScriptedRobot


@pytest.fixture
async def finished_run(tmp_path):
    """A finished run of 3 robots whose traces hold poses, as in simulation."""
    run = tmp_path / "run"
    async with Master(master_config(experiment(evaluations=8)), run, secret=SECRET) as master:
        robots = make_robots(master.port, 3, poses=True)
        await run_with(master, robots)
        await close(robots)
    return run


def test_report_writes_metrics_and_plots(finished_run, capsys):
    assert main(["report", str(finished_run)]) == 0
    out = capsys.readouterr().out
    assert "8 evaluations, best fitness" in out and "8 pictures" in out
    assert "safety layer drove: 25 % of the post-evaluation steps" in out
    assert "behaviour: stopped, grouped" in out
    assert "warning: in the last tenth of the evolution the safety layer overrode 100 %" in out
    metrics = json.loads((finished_run / "metrics.json").read_text())
    assert metrics["evaluations"] == metrics["evaluations_planned"] == 8
    assert metrics["robots"] == ["r0", "r1", "r2"]
    assert metrics["offspring"] + metrics["reevaluations"] == 7
    assert metrics["attempts"] == 8 and metrics["failed_attempts"] == 0
    assert set(metrics["robot_fitness"]) == {"r0", "r1", "r2"}
    post = metrics["post_evaluation"]
    assert post["steps"] == 4 and set(post["robots"]) == {"r0", "r1", "r2"}
    # Scripted traces: robot i predicts 0.1 (i + 1) for every sensor; readings add 0.01 (t % 10)
    # and 0.001 per sensor index. Predictions at t = 0..2 are scored against readings t = 1..3.
    ir = post["sensors"]["ir.f0"]
    assert ir["mean_predicted"] == pytest.approx(0.2)
    assert ir["mean_real"] == pytest.approx(0.2 + 0.02)
    assert post["sensors"]["ground.1"]["mean_real"] == pytest.approx(0.2 + 0.02 + 0.008)
    assert post["robots"]["r0"]["safety_steps"] == 1  # the scripted trace stops every 5th step
    behaviour = post["behaviour"]
    # Robots drive 1 cm and turn 0.1 rad per step, 11 cm apart: all within one cluster. Rotation
    # covers the second half of the 3 steps (2 steps), as the paper measures the end of a run.
    assert behaviour["distance_covered"] == pytest.approx(0.03)
    assert behaviour["mean_cluster_size"] == pytest.approx(3.0)
    assert behaviour["rotation"] == pytest.approx(0.2)
    assert behaviour["motion"] == "stopped" and behaviour["grouping"] == "grouped"
    assert behaviour["box_displacement"] is None and post["robots"]["r0"]["path_length"] == 0.03
    # The scripted robots' safety stops every fifth step from the first: one of the
    # post-evaluation's 4 steps, and the whole of every 1-step evaluation, which is warned of.
    safety = metrics["safety"]
    assert safety["post_evaluation_share"] == pytest.approx(0.25)
    assert safety["post_evaluation_reasons"] == {"front": 3}
    assert safety["evolution_mean_share"] == safety["last_tenth_share"] == 1.0
    assert metrics["warnings"] == safety["warnings"]
    [warning] = safety["warnings"]
    assert warning.startswith("in the last tenth of the evolution the safety layer overrode 100 %")
    plots = {p.name for p in (finished_run / "plots").iterdir()}
    names = ("fitness", "robot_fitness", "predictions", "trajectories")
    assert plots == {f"{name}.{fmt}" for name in names for fmt in ("png", "pdf")}
    assert sorted(metrics["pictures"]) == sorted(f"plots/{name}" for name in plots)
    for name in plots:
        magic = b"\x89PNG" if name.endswith(".png") else b"%PDF"
        assert (finished_run / "plots" / name).read_bytes()[:4] == magic


def test_status_of_a_finished_run(finished_run, capsys):
    assert main(["status", str(finished_run)]) == 0
    text = capsys.readouterr().out
    assert "phase: done, 8/8 evaluations counted" in text
    assert "the run is complete" in text and "post-evaluation: done" in text


async def test_status_and_metrics_while_running(tmp_path):
    run = tmp_path / "run"
    async with Master(master_config(experiment(evaluations=5)), run, secret=SECRET) as master:
        robots = make_robots(master.port, 2)
        for robot in robots:
            await robot.connect()
        async with asyncio.timeout(5):
            # live.json is refreshed by the master's own task within a fraction of a second.
            while "robots connected 2/3" not in (text := status_text(run)):
                await asyncio.sleep(0.02)
        assert "phase: not started" in text
        assert f"master: running (pid {os.getpid()}" in text
        assert compute_metrics(run)["evaluations"] == 0
        await close(robots)
    assert "not running; continue with `surprise-master resume" in status_text(run)


async def test_status_shows_the_software_each_robot_joined_with(tmp_path):
    """software.json records the master's and each robot's version, commit and firmware as it
    joins; ``status`` shows them and marks a robot on other software."""
    run = tmp_path / "run"
    commit = software_commit()
    assert commit is not None, "the tests run from a git checkout"
    old = "0123456789abcdef0123456789abcdef01234567"
    async with Master(master_config(experiment(evaluations=5)), run, secret=SECRET) as master:
        robots = [
            ScriptedRobot("r0", SECRET, master.port, software=(__version__, commit, 14)),
            ScriptedRobot("r1", SECRET, master.port, software=(__version__, old, 11)),
        ]
        for robot in robots:
            await robot.connect()
        await robots[1].close()
        # The same robot back with another build: recorded, and the master log says so.
        robots[1] = ScriptedRobot("r1", SECRET, master.port, software=("0.0.9", None, None))
        await robots[1].connect()
        await close(robots)
    record = schema.read(run, SoftwareRecord)
    assert record is not None
    assert record.master == Software(version=__version__, commit=commit)
    assert record.robots == {
        "r0": Software(version=__version__, commit=commit, firmware=14),
        "r1": Software(version="0.0.9", commit=None),
    }
    assert set(record.joined_at) == {"r0", "r1"}
    assert "robot r1 joined with other software than before" in (run / "master.log").read_text()
    lines = status_text(run).splitlines()
    short = commit.removesuffix("-dirty")[:10]
    start = lines.index(next(line for line in lines if line.startswith("software: master")))
    assert lines[start].startswith(f"software: master {__version__} {short}")
    assert lines[start + 1].startswith(f"  r0: {__version__} {short}")
    assert lines[start + 1].endswith(", firmware 14")
    assert lines[start + 2] == (
        "  r1: 0.0.9, commit unknown, firmware ? (other software than the master's)"
    )


async def test_report_of_real_robots_says_why_there_is_no_behaviour(tmp_path, capsys):
    run = tmp_path / "run"
    async with Master(master_config(experiment(evaluations=2)), run, secret=SECRET) as master:
        robots = make_robots(master.port, 3)  # as real robots: traces without positions
        await run_with(master, robots)
        await close(robots)
    assert main(["report", str(run)]) == 0
    out = capsys.readouterr().out
    assert "behaviour: none: the post-evaluation's traces hold no positions" in out
    metrics = json.loads((run / "metrics.json").read_text())
    assert "behaviour" not in metrics["post_evaluation"]
    assert "no positions" in metrics["post_evaluation"]["behaviour_missing"]


def test_report_of_a_run_without_rows(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text("experiment: {}\n")
    metrics = write_report(run)
    assert metrics["evaluations"] == 0 and metrics["post_evaluation"] is None
    assert list((run / "plots").iterdir()) == []


def sample_progress(**overrides) -> Progress:
    values = {
        "run_id": "run",
        "phase": "evolution",
        "waiting": False,
        "evaluations": 12,
        "total": 350,
        "best_fitness": 0.87654,
        "last_fitness": 0.8,
        "robots_connected": 3,
        "robots_expected": 4,
        "failed_attempts": 1,
        "elapsed_s": 125.0,
        "time_left_s": 3480.0,
    }
    values.update(overrides)
    return Progress(**values)


def test_describe_has_every_figure():
    text = describe(sample_progress(waiting=True, safety_share=0.62))
    assert "safety drove 62 %" in text
    assert "waiting for robots" in text and "evaluations 12/350" in text
    assert "best 0.8765" in text and "robots 3/4" in text and "left ~58m00s" in text


def test_without_a_terminal_the_display_is_plain_log_lines():
    stream = io.StringIO()
    with ProgressDisplay(stream) as display:
        assert not display.live
        display.update(sample_progress())
        import logging

        logging.getLogger("master_service.run.x").info("evaluation 1/2")
    assert stream.getvalue().rstrip().endswith("INFO evaluation 1/2")
    assert "\x1b[" not in stream.getvalue()


def test_the_live_panel_renders():
    stream = io.StringIO()
    with ProgressDisplay(stream, live=True) as display:
        display.update(sample_progress(time_left_s=None, best_fitness=None))
        display.update(sample_progress())
        time.sleep(0)  # the panel refreshes on its own thread; stop() draws the last state
    assert "evaluations" in stream.getvalue() and "12/350" in stream.getvalue()


def test_the_live_panel_says_when_the_safety_layer_does_the_driving():
    stream = io.StringIO()
    with ProgressDisplay(stream, live=True) as display:
        display.update(sample_progress(safety_share=0.2))
    assert "20 % of steps" in stream.getvalue()
    assert "does most of the driving" not in stream.getvalue()
    stream = io.StringIO()
    with ProgressDisplay(stream, live=True) as display:
        display.update(sample_progress(safety_share=0.97))
    assert "97 % of steps" in stream.getvalue()
    assert "the safety layer does most of the driving" in stream.getvalue()


async def test_report_and_status_of_a_crashed_run_ignore_a_torn_last_row(tmp_path):
    # kill -9 in the middle of a commit leaves a torn row past the checkpoint's count; the report
    # of that run (before any resume) must count the checkpointed rows and not crash on it.
    run = tmp_path / "run"
    async with Master(master_config(experiment(evaluations=4)), run, secret=SECRET) as master:
        robots = make_robots(master.port, 3)
        await run_with(master, robots)
        await close(robots)
    with open(run / "evaluations.csv", "a") as file:
        file.write("5,offspring,0.5,0.")
    metrics = write_report(run)
    assert metrics["evaluations"] == 4
    assert "4/4 evaluations counted" in status_text(run)
