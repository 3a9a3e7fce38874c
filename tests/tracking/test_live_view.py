"""The camera's live view: ``surprise-master track --live`` writes where it sees the robots into
the run's ``camera.json``, and the dashboard shows them, for a real run without trajectories too,
while the file is fresh."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from bokeh.document import Document
from filmed_run import MARKERS, ROBOTS, Filmed, as_real, scene

from master_service.cli import main
from reporting.dashboard import _Page, _Poller
from reporting.dashboard_data import RunReader
from runfiles import schema
from runfiles.schema import STALE_AFTER, CameraView
from standins.overhead_camera import OverheadVideo
from tracking.live import CameraWriter


def _tracked_live(filmed: Filmed, tmp_path: Path) -> Path:
    boxes = filmed.video.boxes
    assert boxes is not None
    video = OverheadVideo(
        scene(marker_offset=(0.0, 0.0)),
        filmed.poses[:20],
        boxes[: 20 // filmed.video.box_every + 1],
        box_every=filmed.video.box_every,
        pre_roll=0.5,
        seed=4,
    )
    path = video.write(tmp_path / "live.mp4")
    real = as_real(filmed.run, tmp_path)
    markers = ",".join(f"{r}={m}" for r, m in zip(ROBOTS, MARKERS, strict=True))
    args = ["track", str(path), "--run", str(real), "--markers", markers, "--live"]
    assert main([*args, "--camera-height", "2", "--duration", "1.5"]) == 0
    return real


def test_the_camera_view_is_written_and_shown_while_fresh(filmed, tmp_path, capsys):
    real = _tracked_live(filmed, tmp_path)
    capsys.readouterr()
    view = schema.read(real, CameraView)
    assert view is not None and sorted(view.robots) == sorted(ROBOTS)
    assert view.floor == (1.3, 1.3)  # the boxes arena's walls, from the run
    # The last view written is of a frame the robots stood in as the film shows them.
    step = min(max(round((view.video_time - 0.5) / 0.1), 0), 19)  # standing before the start
    for i, robot in enumerate(ROBOTS):
        pose = view.robots[robot]
        assert math.dist((pose.x, pose.y), filmed.poses[step, i, :2]) < 0.01

    reader = RunReader(real, clock=lambda: view.updated_at + 1.0)
    snapshot = reader.read()
    assert snapshot.camera == view and snapshot.trajectories is None  # a real run's traces
    page = _Page(Document(), _Poller(reader), real, None)
    page.refresh()
    assert page.paths_plot.visible
    assert sorted(page.seen.data["robot"]) == sorted(ROBOTS)
    assert page.arena.data["side"] == [1.3] and page.arena.data["height"] == [1.3]

    stale = RunReader(real, clock=lambda: view.updated_at + STALE_AFTER + 1.0).read()
    assert stale.camera is None  # the tracker stopped: its last view is not shown as now


def test_the_writer_writes_at_most_every_interval(tmp_path: Path) -> None:
    from tracking.tracker import RobotPose, TrackedFrame

    now = [100.0]
    writer = CameraWriter(tmp_path, "camera 0", (1.3, 1.3), clock=lambda: now[0])
    pose = RobotPose(x=0.1, y=0.2, heading=0.3, flash=0.0, corners=np.zeros((4, 2)))
    frame = TrackedFrame(time=1.0, robots={"a": pose}, unknown=(), corners=(), camera=None)
    writer(frame)
    assert writer.writes == 0  # no camera yet: the corner markers place it first
    placed = TrackedFrame(
        time=1.0, robots={"a": pose}, unknown=(), corners=(0, 1, 2, 3), camera=object()
    )  # type: ignore[arg-type]
    for _ in range(3):
        writer(placed)
        now[0] += 0.05
    assert writer.writes == 1
    now[0] += 0.2
    writer(placed)
    assert writer.writes == 2
    view = schema.read(tmp_path, CameraView)
    assert view is not None and view.robots["a"].x == pytest.approx(0.1)


def test_live_needs_a_run(tmp_path: Path, capsys) -> None:
    assert main(["track", "v.mp4", "--out", str(tmp_path / "p.csv"), "--live"]) == 2
    assert "--live" in capsys.readouterr().err
