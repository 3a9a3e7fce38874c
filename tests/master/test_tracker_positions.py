"""``surprise-master report RUN --positions TRACKER.csv``: a real run's behaviour from a tracker.

A simulated run stands in for a real one: its traces' poses are written as an overhead tracker
would write them (its own clock, 25 Hz instead of the robots' 10 Hz, jittered time stamps, rows
shuffled, headings in [0, 2 pi), extra columns), then taken out of the traces as a real robot's
never had them. The report from the tracker's file must find the behaviour the poses gave.

Tolerances. The tracker samples the simulated path (straight between the 10 Hz poses) at other
instants; resampled onto the steps, a pose that falls between two samples lies on their chord,
which cuts the corner the path turns at that step. A Thymio II drives at most 10.6 cm/s and turns
at most 2.3 rad/s (0.23 rad per 0.1 s step); over the 0.04 s between samples the chord misses the
corner by less than 0.3 mm and the heading by less than 0.05 rad. So: the path lengths (d_R)
agree within 1 % (a cut corner shortens a step by at most 1 - cos(0.23 / 2) < 0.7 %); c_o, the
swarm's net turn over the window, within 0.1 rad (two ends, 0.05 rad each); the mean cluster size
within 0.05 (a pair within 0.6 mm of the 15.75 cm cluster distance may change sides at an
instant). The run's values lie far from the class thresholds (c_o 5 and 55 rad, size 1.43), so the
classes must be equal.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import msgspec
import numpy as np
import pytest

from master_service.cli import main
from master_service.experiments.engine_run import FastRun
from master_service.experiments.simulation_setup import simulation_experiment
from minimize_surprise.errors import ConfigError
from reporting.report import compute_metrics, write_report
from reporting.tracker import (
    MIN_COVERAGE,
    TrackerError,
    read_tracker,
    resample,
    tracked_poses,
)

ROBOTS = [f"sim-{i}" for i in range(5)]
#: The tracker's clock when the post-evaluation's first step was taken.
CLOCK = 1234.56
STEP = 0.1
STEPS = 1200


@pytest.fixture(scope="module")
def simulated(tmp_path_factory) -> Path:
    """A lab-setting run of 5 robots whose 120 s post-evaluation is diverse and grouped."""
    experiment = simulation_experiment("basic", setting="lab", robots=5, evaluations=3, seed=0)
    experiment = msgspec.structs.replace(
        experiment, evaluation_steps=20, post_evaluation_steps=STEPS
    )
    assert experiment.step_period == STEP
    run = tmp_path_factory.mktemp("tracker") / "simulated"
    FastRun(experiment).run(run, plots=False)
    return run


@pytest.fixture(scope="module")
def poses(simulated) -> dict[str, np.ndarray]:
    """The simulated poses (steps, 3) per robot."""
    out = {}
    for robot in ROBOTS:
        with np.load(simulated / "traces" / f"{robot}.npz") as data:
            out[robot] = data["poses"]
    return out


@pytest.fixture
def real(simulated, tmp_path) -> Path:
    """The simulated run as a real one looks: traces without poses, no simulation.json, and no
    report yet."""
    run = tmp_path / "real"
    shutil.copytree(simulated, run)
    for name in ("simulation.json", "box_track.npz", "metrics.json"):
        (run / name).unlink(missing_ok=True)
    shutil.rmtree(run / "plots", ignore_errors=True)
    for path in (run / "traces").iterdir():
        with np.load(path) as data:
            arrays = {key: data[key] for key in data.files if key != "poses"}
        np.savez_compressed(path, **arrays)
    return run


def tracker_rows(
    poses: dict[str, np.ndarray], *, rate: float, before: float, after: float, seed: int = 7
) -> list[list[str]]:
    """Rows ``time, robot, x, y, heading`` of a tracker following the simulated path at ``rate``
    Hz from ``before`` s ahead of the first step to ``after`` s past the last: standing still
    there, as robots do before the start and after the end."""
    rng = np.random.default_rng(seed)
    rows = []
    span = (STEPS - 1) * STEP
    count = math.floor((before + span + after) * rate) + 1
    for robot, path in poses.items():
        ticks = -before + np.arange(count) / rate
        # A camera's frames are not punctual; the first is, so that it is the clock's start.
        ticks[1:] += rng.uniform(-0.002, 0.002, count - 1)
        at = np.arange(STEPS) * STEP
        x = np.interp(ticks, at, path[:, 0])
        y = np.interp(ticks, at, path[:, 1])
        heading = np.interp(ticks, at, np.unwrap(path[:, 2])) % (2 * math.pi)
        for t, px, py, h in zip(ticks, x, y, heading, strict=True):
            rows.append([f"{CLOCK + t:.6f}", robot, num(px), num(py), num(h)])
    order = rng.permutation(len(rows))
    return [rows[i] for i in order]


def num(value: float) -> str:
    """A number as a tracker writes it, every digit kept."""
    return repr(float(value))


def write_csv(path: Path, rows: list[list[str]], header: str = "time,robot,x,y,heading") -> Path:
    path.write_text(header + "\n" + "".join(",".join(row) + "\n" for row in rows))
    return path


def assert_same_behaviour(tracked: dict, original: dict) -> None:
    got, want = tracked["behaviour"], original["behaviour"]
    assert got["motion"] == want["motion"] == "diverse"
    assert got["grouping"] == want["grouping"] == "grouped"
    assert got["window"] == want["window"] == 500
    assert got["box_displacement"] is None and got["pushing"] is None
    assert got["distance_covered"] == pytest.approx(want["distance_covered"], rel=0.01)
    assert got["rotation"] == pytest.approx(want["rotation"], abs=0.1)
    assert got["mean_cluster_size"] == pytest.approx(want["mean_cluster_size"], abs=0.05)
    for robot in ROBOTS:
        mine, theirs = tracked["robots"][robot], original["robots"][robot]
        assert mine["path_length"] == pytest.approx(theirs["path_length"], rel=0.01)
        assert mine["rotation"] == pytest.approx(theirs["rotation"], abs=0.1)


def test_the_tracker_gives_the_behaviour_the_poses_gave(simulated, poses, real, tmp_path, capsys):
    original = compute_metrics(simulated)["post_evaluation"]
    # Far from the thresholds: a class equal by luck near one would prove little.
    assert 10 < original["behaviour"]["rotation"] < 50
    assert original["behaviour"]["mean_cluster_size"] > 1.8
    # The tracker runs from 3 s before the start to 2 s after the end: the offset says when the
    # post-evaluation began on its clock. Columns in another order, one more the report ignores.
    rows = tracker_rows(poses, rate=25, before=3.0, after=2.0)
    rows = [[r[1], r[3], r[0], "0.98", r[4], r[2]] for r in rows]
    csv = write_csv(tmp_path / "tracker.csv", rows, "robot, y, time, quality, heading, x")
    status = main(["report", str(real), "--positions", str(csv), "--positions-offset", str(CLOCK)])
    assert status == 0
    out = capsys.readouterr().out
    assert f"behaviour: diverse, grouped (positions from {csv})" in out
    metrics = json.loads((real / "metrics.json").read_text())
    post = metrics["post_evaluation"]
    assert "behaviour_missing" not in post
    assert_same_behaviour(post, original)
    source = post["positions"]
    assert source["file"] == str(csv) and source["offset_s"] == CLOCK and source["offset_given"]
    assert len(source["sha256"]) == 64
    for robot in ROBOTS:
        entry = source["robots"][robot]
        assert entry["coverage"] == 1.0 and entry["held_steps"] == 0
        assert entry["largest_gap_s"] < 0.045
    assert {"plots/trajectories.png", "plots/trajectories.pdf"} <= set(metrics["pictures"])
    assert (real / "plots" / "trajectories.png").read_bytes()[:4] == b"\x89PNG"


def test_without_an_offset_the_first_tracker_time_is_the_first_step(
    poses, simulated, real, tmp_path
):
    original = compute_metrics(simulated)["post_evaluation"]
    rows = tracker_rows(poses, rate=25, before=0.0, after=0.1)
    csv = write_csv(tmp_path / "tracker.csv", rows)
    metrics = write_report(real, positions=csv, plots=False)
    post = metrics["post_evaluation"]
    assert post["positions"]["offset_s"] == pytest.approx(CLOCK, abs=1e-9)
    assert not post["positions"]["offset_given"]
    assert_same_behaviour(post, original)


def test_a_tracker_sampling_the_steps_gives_the_poses_exactly(poses, real, tmp_path):
    # At the robots' own instants, resampling is the identity: the same numbers, bit for bit
    # but for the heading's wrap and the clock's rounding.
    rows = [
        [num(CLOCK + k * STEP), robot, *map(num, path[k])]
        for robot, path in poses.items()
        for k in range(STEPS)
    ]
    csv = write_csv(tmp_path / "tracker.csv", rows)
    found = tracked_poses(csv, dict.fromkeys(ROBOTS, STEPS), STEP)
    for robot in ROBOTS:
        np.testing.assert_allclose(found.poses[robot], poses[robot], rtol=0, atol=1e-9)


def test_the_heading_is_interpolated_through_pi_the_short_way(tmp_path):
    # A robot turning at 1 rad/s through +-pi, tracked at 25 Hz: linear in time, so exact.
    ticks = np.arange(0, 4.001, 0.04)
    heading = (3.0 + ticks + math.pi) % (2 * math.pi) - math.pi
    rows = [[num(t), "a", num(t), "0", num(h)] for t, h in zip(ticks, heading, strict=True)]
    tracks, _ = read_tracker(write_csv(tmp_path / "t.csv", rows), ["a"])
    grid = np.arange(0, 4.0, 0.1)
    got = resample(tracks["a"], grid)
    want = (3.0 + grid + math.pi) % (2 * math.pi) - math.pi
    np.testing.assert_allclose(got[:, 0], grid, atol=1e-12)
    np.testing.assert_allclose(np.angle(np.exp(1j * (got[:, 2] - want))), 0, atol=1e-12)
    assert got[:, 2].min() >= -math.pi and got[:, 2].max() < math.pi


def test_a_frame_written_twice_is_one_sample(tmp_path):
    rows = [["0", "a", "0", "0", "0"], ["1", "a", "1", "0", "0"], ["1", "a", "1", "0", "0"]]
    tracks, _ = read_tracker(write_csv(tmp_path / "t.csv", rows), ["a"])
    assert tracks["a"].times.tolist() == [0.0, 1.0] and tracks["a"].lines.tolist() == [2, 3]


def test_a_tracker_short_of_the_post_evaluation_is_held_up_to_five_percent(tmp_path):
    steps = 100
    covered = round(MIN_COVERAGE * steps)  # steps 0..94 of 0..99
    rows = [["0", "a", "0", "0", "0"], [num((covered - 1) * STEP), "a", "1", "0", "0"]]
    csv = write_csv(tmp_path / "t.csv", rows)
    found = tracked_poses(csv, {"a": steps}, STEP)
    assert found.source["robots"]["a"]["held_steps"] == steps - covered
    assert found.poses["a"][-1, 0] == 1.0  # the last tracked pose, held
    with pytest.raises(TrackerError, match=r"robot 'a': .* covers 94\.1 % of its steps"):
        tracked_poses(csv, {"a": steps + 1}, STEP)


def valid_rows() -> list[list[str]]:
    """Two samples per robot spanning the post-evaluation: lines 2 to 11."""
    span = num(CLOCK + STEPS * STEP)
    return [
        row for r in ROBOTS for row in ([num(CLOCK), r, "0", "0", "0"], [span, r, "1", "0", "0"])
    ]


def with_row(line: int, row: list[str]) -> list[list[str]]:
    rows = valid_rows()
    rows[line - 2] = row
    return rows


CASES = {
    "missing column": (
        valid_rows(),
        "time,robot,x,y",
        r"tracker\.csv, line 1, column 'heading': the header",
    ),
    "not a number": (
        with_row(3, [num(CLOCK + 120), "sim-0", "0.1m", "0", "0"]),
        None,
        r"tracker\.csv, line 3, column 'x': '0\.1m' is not a number",
    ),
    "not finite": (
        with_row(4, [num(CLOCK), "sim-1", "0", "nan", "0"]),
        None,
        r"tracker\.csv, line 4, column 'y': 'nan' is not a finite number",
    ),
    "short row": (
        with_row(5, [num(CLOCK), "sim-1", "0"]),
        None,
        r"tracker\.csv, line 5, column 'y': the row has 3 fields",
    ),
    "unknown robot": (
        [*valid_rows(), ["1234.6", "sim-9", "0", "0", "0"]],
        None,
        r"tracker\.csv, line 12, column 'robot': no robot 'sim-9' in the run",
    ),
    "robot missing": (
        valid_rows()[:-2],
        None,
        r"tracker\.csv, robot 'sim-4': has no row; at least two",
    ),
    "one row": (
        valid_rows()[:-1],
        None,
        r"tracker\.csv, robot 'sim-4': has only line 10; at least two",
    ),
    "same time twice": (
        [*valid_rows(), [num(CLOCK), "sim-2", "0.5", "0", "0"]],
        None,
        r"tracker\.csv, line 12, column 'time', robot 'sim-2': lines 6 and 12 place it "
        r"differently at the same time",
    ),
    "too short": (
        with_row(11, [num(CLOCK + 60), "sim-4", "1", "0", "0"]),
        None,
        r"tracker\.csv, robot 'sim-4': tracked from 1234\.56 s to 1294\.56 s .* covers 50\.1 %",
    ),
}


@pytest.mark.parametrize("case", CASES)
def test_a_bad_tracker_file_names_the_line_and_column_and_writes_nothing(
    case, real, tmp_path, capsys
):
    rows, header, message = CASES[case]
    csv = write_csv(tmp_path / "tracker.csv", rows, *([header] if header else []))
    with pytest.raises(TrackerError, match=message) as caught:
        write_report(real, positions=csv)
    assert isinstance(caught.value, ConfigError) and isinstance(caught.value, ValueError)
    assert caught.value.file == str(csv)
    assert main(["report", str(real), "--positions", str(csv)]) == 2
    assert "surprise-master: " in capsys.readouterr().err
    assert not (real / "metrics.json").exists() and not (real / "plots").exists()


def test_an_offset_needs_the_tracker_file_and_a_missing_file_is_named(real, tmp_path, capsys):
    assert main(["report", str(real), "--positions-offset", "3"]) == 2
    assert "option '--positions-offset': needs --positions" in capsys.readouterr().err
    missing = tmp_path / "none.csv"
    assert main(["report", str(real), "--positions", str(missing)]) == 2
    assert f"{missing}: cannot read it" in capsys.readouterr().err
    assert not (real / "metrics.json").exists()


def test_without_positions_a_real_run_has_no_behaviour(real):
    post = write_report(real, plots=False)["post_evaluation"]
    assert "behaviour" not in post and "positions" not in post
    assert "no positions" in post["behaviour_missing"]
