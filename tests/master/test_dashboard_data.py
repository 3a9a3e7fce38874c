"""The dashboard's reading of a run directory (reporting.dashboard_data) and the
HTML it makes of it, without Bokeh or a browser: files missing, half written, cut back on resume,
columns the master adds later, a master that runs, pauses or died."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from run_files import write_checkpoint, write_live

from minimize_surprise.wire import EvaluationStats
from reporting.dashboard import robots_html, status_html
from reporting.dashboard_data import (
    MAX_TRACE_POINTS,
    RunReader,
    parse_value,
    robot_keys,
)
from runfiles import schema
from runfiles.schema import (
    STALE_AFTER,
    Phase,
    PostEvaluation,
    PostRobot,
    SimulatedWorld,
    Simulation,
)

FIXED = "evaluation,kind,fitness,best_fitness,accepted,attempts,duration_s,safety_share"


def _row(evaluation: int, fitness: float, *cells: str) -> str:
    best = max(fitness, 0.5)
    return f"{evaluation},offspring,{fitness!r},{best!r},true,1,0.100,0.2500," + ",".join(cells)


def _run(tmp_path: Path, robots: tuple[str, ...] = ("a", "b"), planned: int = 10) -> Path:
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text(f"experiment:\n  evolution:\n    evaluations: {planned}\n")
    return run


def _checkpoint(run: Path, rows: int, phase: Phase = "evolution", written_at: float = 0.0) -> None:
    write_checkpoint(run, rows, phase, written_at)


def _csv(run: Path, text: str, mode: str = "w") -> None:
    with open(run / "evaluations.csv", mode, encoding="utf-8") as file:
        file.write(text)


def _live(run: Path, **fields: Any) -> None:
    write_live(run, **fields)


def test_values_are_parsed_where_they_are_numbers() -> None:
    assert parse_value("") is None
    assert parse_value("3") == 3
    assert parse_value("0.25") == 0.25
    assert parse_value("true") == "true"


def test_per_robot_columns_are_discovered_with_ids_that_hold_underscores() -> None:
    header = [
        *FIXED.split(","),
        "fitness_lab_1",
        "fitness_lab_11",
        "battery_v_lab_1",
        "battery_v_lab_11",
        "overruns_lab_11",
        "temperature_c_lab_1",
    ]
    robots, keys = robot_keys(header)
    assert robots == ["lab_1", "lab_11"]
    assert keys == ["fitness", "battery_v", "overruns", "temperature_c"]


def test_an_empty_directory_is_a_run_not_started(tmp_path: Path) -> None:
    snapshot = RunReader(tmp_path).read()
    assert (snapshot.state, snapshot.phase, snapshot.evaluations) == (
        "not started",
        "not started",
        0,
    )
    assert snapshot.robots == [] and snapshot.problems == [] and snapshot.trajectories is None
    assert "no robots yet" in robots_html(snapshot)
    assert 'data-key="evaluations" data-value="0"' in status_html(snapshot)


def test_a_half_written_line_waits_until_it_is_complete(tmp_path: Path) -> None:
    run = _run(tmp_path)
    reader = RunReader(run)
    _csv(run, f"{FIXED},fitness_a,fitness_b\n" + _row(1, 0.5, "0.4", "0.6") + "\n")
    _checkpoint(run, 1)
    assert reader.read().evaluations == 1
    _csv(run, _row(2, 0.7, "0.6", "0."), mode="a")  # the writer is in the middle of the line
    snapshot = reader.read()
    assert snapshot.last_row is not None and snapshot.last_row["evaluation"] == "1"
    assert snapshot.curve.evaluation == [1]
    _csv(run, "8\n", mode="a")
    _checkpoint(run, 2)
    snapshot = reader.read()
    assert snapshot.last_row is not None and snapshot.last_row["evaluation"] == "2"
    assert [r.values["fitness"] for r in snapshot.robots] == ["0.6", "0.8"]
    assert snapshot.curve.evaluation == [1, 2] and snapshot.curve.best_fitness == [0.5, 0.7]
    assert snapshot.best_fitness == "0.7"


def test_rows_past_the_checkpoint_are_not_counted_yet(tmp_path: Path) -> None:
    run = _run(tmp_path)
    _csv(run, f"{FIXED},fitness_a\n" + _row(1, 0.5, "0.5") + "\n" + _row(2, 0.6, "0.6") + "\n")
    _checkpoint(run, 1)
    snapshot = RunReader(run).read()
    assert snapshot.evaluations == 1 and snapshot.curve.evaluation == [1]
    assert snapshot.robots[0].values["fitness"] == "0.5"


def test_a_file_cut_back_and_written_again_is_read_again(tmp_path: Path) -> None:
    run = _run(tmp_path)
    reader = RunReader(run)
    header = f"{FIXED},fitness_a\n"
    _csv(run, header + _row(1, 0.5, "0.5") + "\n" + _row(2, 0.6, "0.6") + "\n")
    first = reader.read()
    # A resume cuts the uncounted row 2 and the run writes another row 2, longer than the first.
    _csv(run, header + _row(1, 0.5, "0.5") + "\n" + _row(2, 0.71, "0.71") + "\n")
    _csv(run, _row(3, 0.72, "0.72") + "\n", mode="a")
    second = reader.read()
    assert second.curve.generation != first.curve.generation
    assert second.curve.fitness == [0.5, 0.71, 0.72]


def test_robot_columns_added_by_the_master_show_without_a_change(tmp_path: Path) -> None:
    run = _run(tmp_path)
    header = (
        f"{FIXED},fitness_a,fitness_b,battery_v_a,battery_v_b,overruns_a,overruns_b,"
        "read_failures_a,read_failures_b\n"
    )
    _csv(run, header + _row(1, 0.5, "0.4", "0.6", "3.912", "", "0", "2", "1", "0") + "\n")
    _checkpoint(run, 1)
    snapshot = RunReader(run).read()
    assert snapshot.keys == ["fitness", "battery_v", "overruns", "read_failures"]
    a, b = snapshot.robots
    assert a.numbers == {"fitness": 0.4, "battery_v": 3.912, "overruns": 0, "read_failures": 1}
    assert b.numbers["battery_v"] is None and b.numbers["overruns"] == 2
    table = robots_html(snapshot)
    assert "battery (V)" in table and "read failures" in table
    assert 'data-key="battery_v" data-value="3.912">3.91<' in table
    assert 'data-key="battery_v" data-value="">–<' in table


def test_a_running_master_tells_connections_time_left_and_a_pause(tmp_path: Path) -> None:
    run = _run(tmp_path, planned=20)
    _csv(run, f"{FIXED},fitness_a,fitness_b\n" + _row(1, 0.5, "0.4", "0.6") + "\n")
    _checkpoint(run, 1)
    reader = RunReader(run)
    _live(run, robots=["a"], time_left_s=125.0, paused=None)
    snapshot = reader.read()
    assert snapshot.state == "running" and snapshot.time_left_s == 125.0
    assert [r.connected for r in snapshot.robots] == [True, False]
    assert "~2 min 05 s" in status_html(snapshot)
    _live(
        run,
        robots=["a", "b"],
        paused={"kind": "battery", "reason": "battery <low> on b", "robots": ["b"]},
        robot_state={"b": {"battery_v": 3.41, "overruns": 0}},
    )
    snapshot = reader.read()
    assert snapshot.state == "paused" and snapshot.pause is not None
    assert snapshot.pause.robots == ("b",)
    assert snapshot.robots[1].numbers == {"fitness": 0.6, "battery_v": 3.41, "overruns": 0}
    assert snapshot.keys == ["fitness", "battery_v", "overruns"]
    page = status_html(snapshot)
    assert "battery &lt;low&gt; on b" in page and "(robots: b)" in page


def test_pause_json_says_why_even_without_live_json(tmp_path: Path) -> None:
    run = _run(tmp_path)
    _checkpoint(run, 0)
    (run / "pause.json").write_text(
        json.dumps({"kind": "battery", "reason": "swap the batteries", "robots": [], "since": 1.0})
    )
    snapshot = RunReader(run).read()
    assert snapshot.state == "paused" and snapshot.pause is not None
    assert snapshot.pause.reason == "swap the batteries"


def test_a_master_that_died_is_stopped_and_has_no_robot_connected(tmp_path: Path) -> None:
    run = _run(tmp_path)
    _csv(run, f"{FIXED},fitness_a\n" + _row(1, 0.5, "0.5") + "\n")
    _checkpoint(run, 1)
    _live(run, robots=["a"], updated_at=time.time() - STALE_AFTER - 1, time_left_s=5.0)
    snapshot = RunReader(run).read()
    assert snapshot.state == "stopped" and snapshot.time_left_s is None
    assert snapshot.robots[0].connected is False


def test_without_live_json_a_recent_checkpoint_is_a_running_run(tmp_path: Path) -> None:
    run = _run(tmp_path)
    _csv(run, f"{FIXED},fitness_a\n" + _row(1, 0.5, "0.5") + "\n")
    _checkpoint(run, 1, written_at=time.time())
    snapshot = RunReader(run).read()
    assert snapshot.state == "running" and snapshot.robots[0].connected is None
    _checkpoint(run, 1, phase="done", written_at=time.time())
    assert RunReader(run).read().state == "finished"


def test_a_damaged_json_file_keeps_the_last_good_value_and_is_named(tmp_path: Path) -> None:
    run = _run(tmp_path)
    _checkpoint(run, 0, phase="post-evaluation")
    reader = RunReader(run)
    assert reader.read().phase == "post-evaluation"
    (run / "checkpoint.json").write_text('{"phase": "do')
    snapshot = reader.read()
    assert snapshot.phase == "post-evaluation"
    assert [p.split(":")[0] for p in snapshot.problems] == ["checkpoint.json"]
    _checkpoint(run, 0, phase="done")
    snapshot = reader.read()
    assert (snapshot.phase, snapshot.problems) == ("done", [])


def test_trajectories_are_thinned_and_traces_without_poses_left_out(tmp_path: Path) -> None:
    run = _run(tmp_path)
    traces = run / "traces"
    traces.mkdir()
    steps = 3 * MAX_TRACE_POINTS + 7
    poses = np.column_stack([np.linspace(0, 1, steps), np.linspace(0, -1, steps), np.zeros(steps)])
    np.savez_compressed(traces / "a.npz", poses=poses, sensors=np.zeros((steps, 2)))
    np.savez_compressed(traces / "real.npz", sensors=np.zeros((steps, 2)))
    world = SimulatedWorld(arena_side=1.5, robots=1, boxes=0)
    schema.write(run, Simulation(scenario="basic", setting="paper", world=world))
    stats = EvaluationStats(steps_run=10, overruns=0, interventions={"x": 3})
    robots = {"a": PostRobot(fitness=0.75, stats=stats, trace="traces/a.npz")}
    post = PostEvaluation(
        evaluation_id=1, steps=10, genome_fitness=0.7, swarm_fitness=0.75, robots=robots
    )
    schema.write(run, post)
    reader = RunReader(run)
    snapshot = reader.read()
    trajectories = snapshot.trajectories
    assert trajectories is not None and list(trajectories.xs) == ["a"]
    assert trajectories.steps == steps and trajectories.arena_side == 1.5
    assert len(trajectories.xs["a"]) <= MAX_TRACE_POINTS + 1
    assert (trajectories.xs["a"][-1], trajectories.ys["a"][-1]) == (1.0, -1.0)
    assert snapshot.post_fitness == 0.75
    assert snapshot.post_robots["a"] == {"fitness": 0.75, "safety_share": 0.3}
    assert reader.read().trajectories is trajectories  # unchanged files are not read again


@pytest.mark.parametrize("files", [("evaluations.csv",), ("config.yaml", "checkpoint.json")])
def test_reading_writes_nothing(tmp_path: Path, files: tuple[str, ...]) -> None:
    run = _run(tmp_path)
    _csv(run, f"{FIXED},fitness_a\n" + _row(1, 0.5, "0.5") + "\n")
    _checkpoint(run, 1)
    for name in files:
        (run / name).chmod(0o444)
    before = {p: p.stat().st_mtime_ns for p in run.rglob("*")}
    reader = RunReader(run)
    for _ in range(3):
        reader.read()
    assert {p: p.stat().st_mtime_ns for p in run.rglob("*")} == before


def test_a_damaged_trace_is_named_not_raised(tmp_path: Path) -> None:
    run = _run(tmp_path)
    (run / "traces").mkdir()
    (run / "traces" / "a.npz").write_bytes(b"PK\x03\x04 cut short")
    snapshot = RunReader(run).read()
    assert snapshot.trajectories is None
    assert [p.split(":")[0] for p in snapshot.problems] == ["traces"]
