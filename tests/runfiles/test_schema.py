"""The run directory's schema: every file round-trips, is pinned by its bytes, reads the files of
the version before formats were written down, and refuses a newer format by name; one rule says
whether a master is alive."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import msgspec
import pytest

from minimize_surprise.config import ExperimentConfig
from minimize_surprise.network import NetworkSpec
from minimize_surprise.wire import EvaluationStats
from runfiles import schema
from runfiles.schema import (
    STALE_AFTER,
    BestGenome,
    BoxesMoved,
    CameraPose,
    CameraView,
    Checkpoint,
    EscapeRequest,
    Event,
    Live,
    MarkRequest,
    PauseFile,
    PauseNote,
    PostEvaluation,
    PostRobot,
    QDElite,
    QDSummary,
    Replay,
    RunDirError,
    RunFile,
    SimulatedWorld,
    Simulation,
    Software,
    SoftwareRecord,
    StopRequest,
    SwapRequest,
    SwarmChange,
    TrackedBoxes,
    master_alive,
)

STATS = EvaluationStats(steps_run=100, overruns=1, interventions={"front": 3}, battery_v=3.9)

#: One filled example of every file, and its bytes as this version writes them. A renamed,
#: retyped or dropped field changes the bytes: then the file format changed, and its FORMAT must
#: go up with a reader for the old one (docs/runs.md).
GOLDEN: dict[type[RunFile], tuple[RunFile, str]] = {
    Checkpoint: (
        Checkpoint(
            run_id="r1",
            phase="evolution",
            next_evaluation_id=4,
            attempts=1,
            failed_attempts=2,
            csv_rows=3,
            roster=["a", "b"],
            elapsed_s=1.5,
            written_at=1700000000.25,
            optimizer={"evaluations": 3, "best_fitness": 0.75},
            simulation=None,
        ),
        '{"format": 1, "run_id": "r1", "phase": "evolution", "next_evaluation_id": 4, '
        '"attempts": 1, "failed_attempts": 2, "csv_rows": 3, "roster": ["a", "b"], '
        '"elapsed_s": 1.5, "written_at": 1700000000.25, '
        '"optimizer": {"evaluations": 3, "best_fitness": 0.75}, "simulation": null}',
    ),
    Live: (
        Live(
            pid=123,
            running=True,
            host="0.0.0.0",
            port=7474,
            robots=["a"],
            phase="post-evaluation",
            waiting=False,
            evaluations=10,
            time_left_s=30.0,
            paused=PauseNote(kind="battery", reason="swap a", robots=["a"]),
            robot_state={"a": {"battery_v": 3.7, "overruns": 0, "read_failures": 0}},
            updated_at=1700000001.0,
        ),
        '{"format": 1, "pid": 123, "running": true, "host": "0.0.0.0", "port": 7474, '
        '"robots": ["a"], "phase": "post-evaluation", "waiting": false, "evaluations": 10, '
        '"time_left_s": 30.0, "paused": {"kind": "battery", "reason": "swap a", '
        '"robots": ["a"]}, "robot_state": {"a": {"battery_v": 3.7, "overruns": 0, '
        '"read_failures": 0}}, "updated_at": 1700000001.0}',
    ),
    PauseFile: (
        PauseFile(kind="before-post-evaluation", reason="place the robots", robots=[], since=5.0),
        '{"format": 1, "kind": "before-post-evaluation", "reason": "place the robots", '
        '"robots": [], "since": 5.0}',
    ),
    BestGenome: (
        BestGenome(
            evaluation=7,
            fitness=0.5,
            genome=[0.1, -0.2],
            spec=NetworkSpec(sensors=("ir.f0", "ground.0"), actor_hidden=1, predictor_hidden=1),
        ),
        '{"format": 1, "evaluation": 7, "fitness": 0.5, "genome": [0.1, -0.2], '
        '"spec": {"sensors": ["ir.f0", "ground.0"], "actor_hidden": 1, "predictor_hidden": 1, '
        '"predefined": {}, "initial_action": 0.0}}',
    ),
    PostEvaluation: (
        PostEvaluation(
            evaluation_id=12,
            steps=100,
            genome_fitness=0.5,
            swarm_fitness=0.625,
            robots={"a": PostRobot(fitness=0.625, stats=STATS, trace="traces/a.npz")},
            started_at=1700000002.5,
        ),
        '{\n  "format": 1,\n  "evaluation_id": 12,\n  "steps": 100,\n  "genome_fitness": 0.5,\n'
        '  "swarm_fitness": 0.625,\n  "robots": {\n    "a": {\n      "fitness": 0.625,\n'
        '      "stats": {\n        "steps_run": 100,\n        "overruns": 1,\n'
        '        "interventions": {\n          "front": 3\n        },\n'
        '        "read_failures": 0,\n        "battery_v": 3.9\n      },\n'
        '      "trace": "traces/a.npz"\n    }\n  },\n  "started_at": 1700000002.5\n}',
    ),
    EscapeRequest: (
        EscapeRequest(robot="thymio-3", token="0f1e2d3c4b5a6978", requested_at=1700000003.25),
        '{"format": 1, "robot": "thymio-3", "token": "0f1e2d3c4b5a6978", '
        '"requested_at": 1700000003.25}',
    ),
    SwapRequest: (
        SwapRequest(
            gone="thymio-3", spare="thymio-9", token="1a2b3c4d5e6f7081", requested_at=1700000006.5
        ),
        '{"format": 1, "gone": "thymio-3", "spare": "thymio-9", "token": "1a2b3c4d5e6f7081", '
        '"requested_at": 1700000006.5}',
    ),
    MarkRequest: (
        MarkRequest(text="moved the light", token="3c4d5e6f70819203", requested_at=1700000008.5),
        '{"format": 1, "text": "moved the light", "token": "3c4d5e6f70819203", '
        '"requested_at": 1700000008.5}',
    ),
    StopRequest: (
        StopRequest(token="2b3c4d5e6f708192", requested_at=1700000007.5),
        '{"format": 1, "token": "2b3c4d5e6f708192", "requested_at": 1700000007.5}',
    ),
    Simulation: (
        Simulation(
            scenario="boxes",
            setting="paper",
            engine="fast",
            realtime=False,
            world=SimulatedWorld(arena_side=1.1, robots=4, boxes=2),
            post_evaluation_boxes=BoxesMoved(start=[[0.0, 0.1]], end=[[0.2, 0.1]]),
            post_evaluation_safety=[[0, 1]],
        ),
        '{"format": 1, "scenario": "boxes", "setting": "paper", "engine": "fast", '
        '"realtime": false, "world": {"arena_side": 1.1, "robots": 4, "boxes": 2}, '
        '"post_evaluation_boxes": {"start": [[0.0, 0.1]], "end": [[0.2, 0.1]]}, '
        '"post_evaluation_safety": [[0, 1]]}',
    ),
    Replay: (
        Replay(source="/runs/a", source_run="/runs/a", genome_fitness=None),
        '{\n  "format": 1,\n  "source": "/runs/a",\n  "source_run": "/runs/a",\n'
        '  "genome_fitness": null\n}',
    ),
    SoftwareRecord: (
        SoftwareRecord(
            master=Software(version="0.1.0", commit="3f2a9c4e1b7d8a6f5e4c3b2a1908f7e6d5c4b3a2"),
            robots={
                "thymio-1": Software(
                    version="0.1.0",
                    commit="3f2a9c4e1b7d8a6f5e4c3b2a1908f7e6d5c4b3a2-dirty",
                    firmware=14,
                ),
                "thymio-2": Software(version="0.0.9", commit=None),
            },
            joined_at={"thymio-1": 1700000001.5, "thymio-2": 1700000002.0},
        ),
        '{"format": 1, "master": {"version": "0.1.0", "commit": '
        '"3f2a9c4e1b7d8a6f5e4c3b2a1908f7e6d5c4b3a2", "firmware": null}, "robots": {"thymio-1": '
        '{"version": "0.1.0", "commit": "3f2a9c4e1b7d8a6f5e4c3b2a1908f7e6d5c4b3a2-dirty", '
        '"firmware": 14}, "thymio-2": {"version": "0.0.9", "commit": null, "firmware": null}}, '
        '"joined_at": {"thymio-1": 1700000001.5, "thymio-2": 1700000002.0}}',
    ),
    CameraView: (
        CameraView(
            source="camera 0",
            floor=(1.3, 1.3),
            video_time=12.5,
            robots={"thymio-1": CameraPose(x=0.1, y=-0.2, heading=1.5)},
            updated_at=1700000004.5,
        ),
        '{"format": 1, "source": "camera 0", "floor": [1.3, 1.3], "video_time": 12.5, '
        '"robots": {"thymio-1": {"x": 0.1, "y": -0.2, "heading": 1.5}}, '
        '"updated_at": 1700000004.5}',
    ),
    TrackedBoxes: (
        TrackedBoxes(
            source="post.mp4",
            start_time_s=0.0,
            end_time_s=100.0,
            boxes=BoxesMoved(start=[[0.0, 0.1]], end=[[0.2, 0.1]]),
            unpaired_end=[[0.3, 0.3]],
        ),
        '{\n  "format": 1,\n  "source": "post.mp4",\n  "start_time_s": 0.0,\n'
        '  "end_time_s": 100.0,\n  "boxes": {\n    "start": [\n      [\n        0.0,\n'
        '        0.1\n      ]\n    ],\n    "end": [\n      [\n        0.2,\n        0.1\n'
        '      ]\n    ]\n  },\n  "unpaired_start": [],\n  "unpaired_end": [\n    [\n'
        "      0.3,\n      0.3\n    ]\n  ]\n}",
    ),
    QDSummary: (
        QDSummary(
            experiment=ExperimentConfig(),
            done=True,
            evaluations=40,
            cells=3,
            coverage=0.5,
            qd_score=2.5,
            seconds=1.5,
            classes={
                "stopped/grouped": QDElite(
                    fitness=0.9,
                    measures={"rotation": 1.0},
                    directory="elites/stopped-grouped",
                    post_fitness=0.8,
                    post_class="stopped/dispersed",
                )
            },
        ),
        '{\n  "format": 1,\n  "experiment": {\n    "setting": "lab",\n    "sensors": [\n   '
        '   "ir.f0",\n      "ir.f1",\n      "ir.f2",\n      "ir.f3",\n      "ir.f4",\n     '
        ' "ir.b0",\n      "ir.b1",\n      "ground.0",\n      "ground.1"\n    ],\n    "netwo'
        'rk": {\n      "actor_hidden": 8,\n      "predictor_hidden": null,\n      "initial_'
        'action": 0.0\n    },\n    "evolution": {\n      "evaluations": 350,\n      "reeval'
        'uation_probability": 0.2,\n      "reevaluation_weight": 0.2,\n      "mutation_prob'
        'ability": 0.1,\n      "mutation_range": 0.4,\n      "initial_range": 0.5,\n      "'
        'first_genome": "random"\n    },\n    "predefined": {},\n    "evaluation_steps": 10'
        '0,\n    "post_evaluation_steps": 1000,\n    "step_period": 0.1,\n    "scenario": "'
        'basic",\n    "arena": null,\n    "robots": 10,\n    "min_robots": null,\n    "seed'
        '": 0,\n    "simulation": {},\n    "safety": {},\n    "optimizer": null,\n'
        '    "events": []\n  },\n  "d'
        'one": true,\n  "evaluations": 40,\n  "cells": 3,\n  "coverage": 0.5,\n  "qd_score"'
        ': 2.5,\n  "seconds": 1.5,\n  "classes": {\n    "stopped/grouped": {\n      "fitnes'
        's": 0.9,\n      "measures": {\n        "rotation": 1.0\n      },\n      "directory'
        '": "elites/stopped-grouped",\n      "post_fitness": 0.8,\n      "post_class": "sto'
        'pped/dispersed"\n    }\n  }\n}',
    ),
}


def _files() -> set[type[RunFile]]:
    found: set[type[RunFile]] = set()
    todo = list(RunFile.__subclasses__())
    while todo:
        kind = todo.pop()
        todo += kind.__subclasses__()
        if kind is not PauseNote:  # live.json's part; its file is PauseFile
            found.add(kind)
    return found


def test_every_file_of_the_schema_has_a_golden_example() -> None:
    assert _files() == set(GOLDEN)


@pytest.mark.parametrize("kind", list(GOLDEN), ids=lambda k: k.FILE)
def test_every_file_is_pinned_by_its_bytes_and_reads_back(kind: type[RunFile], tmp_path) -> None:
    example, golden = GOLDEN[kind]
    assert schema.encode(example).decode() == golden
    schema.write(tmp_path, example)
    assert (tmp_path / kind.FILE).read_text() == golden
    assert schema.read(tmp_path, kind) == example


def test_a_post_evaluation_written_before_its_start_time_reads_without_one(tmp_path) -> None:
    example, golden = GOLDEN[PostEvaluation]
    older = golden.replace(',\n  "started_at": 1700000002.5', "")
    assert "started_at" not in older
    (tmp_path / PostEvaluation.FILE).write_text(older)
    assert schema.read(tmp_path, PostEvaluation) == msgspec.structs.replace(
        example, started_at=None
    )
    # And written so again when there is none (a run of the compiled engine: no robots flash).
    assert schema.encode(msgspec.structs.replace(example, started_at=None)).decode() == older


def test_a_checkpoint_keeps_the_swarms_changes_and_reads_one_without_them(tmp_path) -> None:
    example, golden = GOLDEN[Checkpoint]
    assert "swarms" not in golden  # a swarm that never changed: written as before swaps existed
    changed = msgspec.structs.replace(
        example,
        roster=["a", "c"],
        swarms=[SwarmChange(from_evaluation=3, robots=["a", "c"], left="b", joined="c", time=7.5)],
    )
    text = schema.encode(changed).decode()
    assert text == golden.replace('"roster": ["a", "b"]', '"roster": ["a", "c"]').replace(
        '"simulation": null}',
        '"simulation": null, "swarms": [{"from_evaluation": 3, "robots": ["a", "c"], '
        '"left": "b", "joined": "c", "time": 7.5}]}',
    )
    (tmp_path / Checkpoint.FILE).write_text(text)
    assert schema.read(tmp_path, Checkpoint) == changed


def test_rows_are_written_by_their_columns_and_a_header_widens_for_a_spare() -> None:
    cells = schema.row_cells(
        4, "offspring", 0.5, 0.5, True, 1, 2.0, 0.25, ["a", "c"], [0.25, 0.75], [STATS] * 2,
        swarm=1,
    )  # fmt: skip
    header = schema.evaluation_header(["a", "b"], robot_stats=True)
    wider = schema.widen_header(header, ["a", "c"], robot_stats=True)
    assert wider == [*header, "fitness_c", "battery_v_c", "overruns_c", "read_failures_c", "swarm"]
    assert schema.widen_header(wider, ["a", "c"], robot_stats=True) == wider
    assert schema.render_row(cells, wider) == (
        "4,offspring,0.5,0.5,true,1,2.000,0.2500,0.25,,3.900,,1,,0,,0.75,3.900,1,0,1\n"
    )


#: Two events as the master appends them: each a line of its own, unset fields left out.
EVENTS = [
    Event(time=1700000004.5, kind="post-evaluation-start", evaluation_id=41),
    Event(
        time=1700000005.75,
        kind="escape",
        robot="thymio-3",
        request="0f1e2d3c4b5a6978",
        accepted=False,
        detail="thymio-3 is not connected",
    ),
    Event(
        time=1700000006.25,
        kind="swarm-change",
        robot="thymio-3",
        joined="thymio-9",
        request="1a2b3c4d5e6f7081",
        accepted=True,
        evaluation_id=212,
    ),
    Event(
        time=1700000007.75,
        kind="fleet-stop",
        request="2b3c4d5e6f708192",
        accepted=False,
        confirmed=["thymio-1", "thymio-2"],
        unanswered=["thymio-3"],
        detail="thymio-3 is not connected",
    ),
]
EVENT_LINES = (
    '{"format": 1, "time": 1700000004.5, "kind": "post-evaluation-start", "evaluation_id": 41, '
    '"detail": ""}\n'
    '{"format": 1, "time": 1700000005.75, "kind": "escape", "robot": "thymio-3", '
    '"request": "0f1e2d3c4b5a6978", "accepted": false, "detail": "thymio-3 is not connected"}\n'
    '{"format": 1, "time": 1700000006.25, "kind": "swarm-change", "robot": "thymio-3", '
    '"request": "1a2b3c4d5e6f7081", "accepted": true, "evaluation_id": 212, "detail": "", '
    '"joined": "thymio-9"}\n'
    '{"format": 1, "time": 1700000007.75, "kind": "fleet-stop", "request": "2b3c4d5e6f708192", '
    '"accepted": false, "detail": "thymio-3 is not connected", "confirmed": ["thymio-1", '
    '"thymio-2"], "unanswered": ["thymio-3"]}\n'
)


def test_events_are_lines_pinned_by_their_bytes_and_read_back(tmp_path: Path) -> None:
    assert schema.read_events(tmp_path) == []
    for event in EVENTS:
        schema.append_event(tmp_path, event)
    assert (tmp_path / schema.EVENTS).read_text() == EVENT_LINES
    assert schema.read_events(tmp_path) == EVENTS


def test_an_event_line_this_version_cannot_read_is_skipped(tmp_path: Path) -> None:
    newer = '{"format": 2, "time": 1.0, "kind": "escape"}\n'
    torn = '{"format": 1, "time": 2.0, "ki'
    (tmp_path / schema.EVENTS).write_text(EVENT_LINES + newer + '{"time": 3}\n' + torn)
    assert schema.read_events(tmp_path) == EVENTS


def test_an_absent_file_is_none_and_a_damaged_one_is_named(tmp_path: Path) -> None:
    assert schema.read(tmp_path, Live) is None
    (tmp_path / "live.json").write_text('{"pid": 1, "runn')
    with pytest.raises(RunDirError, match=r"live\.json is not valid JSON"):
        schema.read(tmp_path, Live)


def test_files_written_before_formats_existed_are_read_as_format_1(tmp_path: Path) -> None:
    # As the previous version wrote them: json.dumps of plain dicts, no "format" key.
    (tmp_path / "simulation.json").write_text(
        json.dumps(
            {
                "scenario": "basic",
                "setting": "paper",
                "realtime": False,
                "world": {"arena_side": 1.0, "robots": 10, "boxes": 0},
            }
        )
    )
    simulation = schema.read(tmp_path, Simulation)
    assert simulation is not None and simulation.engine == "agents"  # older runs: agents
    assert simulation.post_evaluation_boxes is None
    (tmp_path / "pause.json").write_text(
        json.dumps({"kind": "battery", "reason": "swap b", "robots": ["b"], "since": 2.0})
    )
    assert schema.read(tmp_path, PauseFile) == PauseFile(
        kind="battery", reason="swap b", robots=["b"], since=2.0
    )


def test_a_newer_format_is_refused_naming_both_versions(tmp_path: Path) -> None:
    golden = GOLDEN[Checkpoint][1]
    (tmp_path / "checkpoint.json").write_text(golden.replace('"format": 1', '"format": 2'))
    with pytest.raises(RunDirError) as refused:
        schema.read(tmp_path, Checkpoint)
    message = str(refused.value)
    assert "checkpoint.json is format 2" in message and "up to format 1" in message
    # A reader that only shows what it finds passes over it.
    assert schema.read_if_readable(tmp_path, Checkpoint) is None


def test_a_missing_or_mistyped_key_is_named(tmp_path: Path) -> None:
    (tmp_path / "live.json").write_text(json.dumps({"format": 1, "pid": "7"}))
    with pytest.raises(RunDirError, match=r"live\.json cannot be read \(format 1\).*\$\.pid"):
        schema.read(tmp_path, Live)


def test_unknown_keys_of_a_later_minor_change_are_ignored(tmp_path: Path) -> None:
    example, golden = GOLDEN[Replay]
    data = json.loads(golden) | {"note": "added later"}
    (tmp_path / "replay.json").write_text(json.dumps(data))
    assert schema.read(tmp_path, Replay) == example


def test_the_config_snapshot_gives_readers_the_experiment_and_the_swarm(tmp_path: Path) -> None:
    (tmp_path / "config.yaml").write_text(
        "experiment:\n  robots: 4\n  evolution:\n    evaluations: 30\nport: 7474\n"
    )
    config = schema.read_config(tmp_path)
    assert isinstance(config.experiment, ExperimentConfig)
    assert config.experiment.evolution.evaluations == 30 and config.robot_count == 4
    with pytest.raises(RunDirError, match="not a run directory"):
        schema.read_config(tmp_path / "elsewhere")


def _live(**fields) -> Live:
    example, _ = GOLDEN[Live]
    data = schema.decode(Live, schema.encode(example))
    return Live(**{f: getattr(data, f) for f in Live.__struct_fields__} | fields)


def test_a_master_is_alive_while_running_fresh_and_its_process_exists() -> None:
    now = 1000.0
    assert master_alive(_live(pid=os.getpid(), updated_at=now - 1), now)
    assert not master_alive(_live(pid=os.getpid(), updated_at=now - 1, running=False), now)
    assert not master_alive(_live(pid=os.getpid(), updated_at=now - STALE_AFTER - 1), now)
    assert not master_alive(None, now)
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    assert not master_alive(_live(pid=gone.pid, updated_at=now), now)


@pytest.mark.parametrize("pid", [0, -1])
def test_a_pid_that_names_no_process_is_not_asked_about(pid: int) -> None:
    # os.kill(0 or -1, 0) asks about process groups, which always answer: only the file's age
    # decides then.
    now = time.time()
    assert master_alive(_live(pid=pid, updated_at=now), now)
    assert not master_alive(_live(pid=pid, updated_at=now - STALE_AFTER - 1), now)
