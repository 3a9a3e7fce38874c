"""The tracker against the synthetic overhead camera: the simulator's poses, boxes and classes
recovered from pictures, a hidden marker filled in, the flash found at its frame.

Bounds. A pixel is 2.3 mm on the floor (1280x720, a 1.3 m floor); ArUco's sub-pixel corners put
a 6 cm marker's centre within a fraction of that: poses within 5 mm RMS and headings within
0.03 rad RMS of the simulator's. The boxes' d_B within 1 cm: boxes the simulator lets overlap
merge into one blob, which loses a few of the moved ones (the error is below, never above)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from filmed_run import HIDDEN, PRE_ROLL, ROBOTS, STEPS, Filmed, scene, tracking_config

from simulator import metrics
from standins.overhead_camera import OverheadVideo
from tracking.camera import CameraModel, Floor
from tracking.video import track_frames


def _errors(filmed: Filmed) -> tuple[np.ndarray, np.ndarray]:
    # Position (metres) and heading (radians) errors of every robot in every frame it was seen.
    distance, turn = [], []
    for i, robot in enumerate(ROBOTS):
        seen = filmed.result.seen[robot][:STEPS]
        got = filmed.result.poses[robot][:STEPS][seen]
        want = filmed.poses[:, i][seen]
        distance.append(np.hypot(*(got[:, :2] - want[:, :2]).T))
        turn.append((got[:, 2] - want[:, 2] + math.pi) % (2 * math.pi) - math.pi)
    return np.concatenate(distance), np.concatenate(turn)


def test_the_poses_are_the_simulators_within_5_mm_and_0_03_rad(filmed):
    distance, turn = _errors(filmed)
    assert np.sqrt(np.mean(distance**2)) < 0.005
    assert np.sqrt(np.mean(turn**2)) < 0.03
    assert distance.max() < 0.015
    assert filmed.result.times[:STEPS] == pytest.approx(np.arange(STEPS) * 0.1)


def test_the_flash_is_time_zero(filmed):
    # The LEDs light at the start, after 1 s of standing: frame 10 of the video.
    assert filmed.result.flash and filmed.result.start == pytest.approx(PRE_ROLL)
    assert filmed.result.times[0] == 0.0


@pytest.mark.parametrize(("fps", "pre_roll"), [(30.0, 0.5), (25.0, 1.2)])
def test_the_flash_is_found_at_its_frame_at_other_rates(filmed, fps, pre_roll):
    video = OverheadVideo(
        scene(fps=fps, image_size=(960, 540)),
        filmed.poses[:10],
        pre_roll=pre_roll,
        flash=0.2,
        seed=5,
    )
    result = track_frames(video.frames(), tracking_config(), name="short", duration=0.1)
    frame = round(pre_roll * fps)
    assert result.start == pytest.approx(frame / fps)


def test_a_hidden_marker_is_filled_in_and_reported(filmed):
    robot, t0, t1 = ROBOTS[HIDDEN[0]], HIDDEN[1], HIDDEN[2]
    times = filmed.result.times
    hidden = (times >= t0 - 1e-9) & (times < t1 - 1e-9)
    assert not filmed.result.seen[robot][hidden].any()
    assert filmed.result.seen[robot][~hidden].all()
    summary = filmed.result.robots[robot]
    assert summary.seen == summary.frames - hidden.sum()
    assert summary.longest_gap_s == pytest.approx(t1 - t0 + 0.1)
    # Interpolated straight across 2 s of driving: near the path, not on it.
    steps = np.flatnonzero(hidden)
    got = filmed.result.poses[robot][steps]
    want = filmed.poses[steps, HIDDEN[0]]
    assert np.hypot(*(got[:, :2] - want[:, :2]).T).max() < 0.05
    assert all(filmed.result.robots[r].seen == len(times) for r in ROBOTS if r != robot)


def test_the_boxes_give_d_b_within_1_cm_and_the_same_classes(filmed):
    boxes = filmed.result.boxes
    assert boxes is not None
    start, end = np.array(boxes.boxes.start), np.array(boxes.boxes.end)
    assert len(start) >= 0.95 * len(filmed.boxes_start)
    tracked_d_b = metrics.box_displacement(start, end)
    true_d_b = metrics.box_displacement(filmed.boxes_start, filmed.boxes_end)
    assert tracked_d_b == pytest.approx(true_d_b, abs=0.01)
    stacked = np.stack([filmed.result.poses[r][:STEPS] for r in ROBOTS], axis=1)
    mine = metrics.behaviour_metrics(stacked, start, end)
    theirs = metrics.behaviour_metrics(filmed.poses, filmed.boxes_start, filmed.boxes_end)
    # Far from the thresholds, so that equal classes are no luck.
    assert 10 < theirs.rotation < 45 and theirs.mean_cluster_size < 1.2
    assert theirs.box_displacement is not None and theirs.box_displacement < 0.05
    for field in ("motion", "grouping", "pushing", "manipulation"):
        assert getattr(mine, field) == getattr(theirs, field), field
    assert mine.rotation == pytest.approx(theirs.rotation, abs=0.5)


def test_the_camera_is_placed_from_the_corner_markers_alone(filmed):
    camera = filmed.result.camera
    truth = filmed.video.scene
    assert camera.nadir == pytest.approx(np.array(truth.nadir), abs=0.01)
    assert camera.residual_px < 0.5
    assert math.degrees(camera.tilt) == pytest.approx(3.3, abs=0.5)
    # A point at a marker's height maps back to itself, and lies farther out on the floor.
    point = np.array([[0.5, -0.4]])
    pixel = camera.to_image(point, 0.055)
    assert camera.to_floor(pixel, 0.055) == pytest.approx(point, abs=1e-9)
    on_floor = camera.to_floor(pixel)
    assert np.hypot(*(on_floor - camera.nadir).T) > np.hypot(*(point - camera.nadir).T)


def test_floor_corner_points_are_in_arucos_order():
    floor = Floor(width=2.0, height=1.0, corner_ids=(4, 5, 6, 7), corner_size=0.1)
    points = floor.corner_points()
    assert points[4].tolist() == [[-1.0, -0.4], [-0.9, -0.4], [-0.9, -0.5], [-1.0, -0.5]]
    assert points[6][1].tolist() == [1.0, 0.5]  # the top-right marker's top-right corner
    assert isinstance(CameraModel, type)
