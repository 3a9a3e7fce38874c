"""Draw docs/images/tracked-frame.png and print the tracker's errors on a filmed simulation.

Runs the boxes scenario (lab setting, seed 1, 3 evaluations, a 30 s post-evaluation) on the
compiled engine, films its post-evaluation with the synthetic overhead camera
(``standins.overhead_camera``: 1280x720, 10 frames a second, robot sim-1's marker covered from 3 s
to 5 s), tracks the film, prints the errors against the simulator's poses and boxes as
``name: value unit`` lines, and saves one frame with what the tracker found drawn on it: each
robot's pose (a dot between its wheels and an arrow along its heading), its marker's outline, and
the boxes found at the end (small circles).

Run: ``python docs/tools/tracked_frame.py [--out docs/images/tracked-frame.png] [--time 29.9]``
"""

from __future__ import annotations

import argparse
import math
import tempfile
from pathlib import Path

import cv2
import msgspec
import numpy as np

from master_service.experiments.engine_run import FastRun
from master_service.experiments.simulation_setup import simulation_experiment
from runfiles import schema
from runfiles.schema import BOX_TRACK, Simulation
from simulator import metrics
from standins.overhead_camera import OverheadScene, OverheadVideo
from tracking.config import CameraSettings, RobotMarkers, TrackingConfig
from tracking.video import TrackResult, track_frames

ROBOTS = ("sim-0", "sim-1", "sim-2", "sim-3")
MARKERS = (10, 11, 12, 13)
STEPS = 300
DEFAULT_OUTPUT = Path(__file__).resolve().parents[1] / "images" / "tracked-frame.png"


def main() -> None:
    """Film, track, print the errors and draw the frame."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=DEFAULT_OUTPUT)
    parser.add_argument("--time", type=float, default=29.9, help="the frame's time after the start")
    args = parser.parse_args()
    experiment = simulation_experiment("boxes", setting="lab", evaluations=3, seed=1)
    experiment = msgspec.structs.replace(
        experiment, evaluation_steps=20, post_evaluation_steps=STEPS
    )
    with tempfile.TemporaryDirectory() as where:
        run = Path(where) / "run"
        FastRun(experiment).run(run, plots=False)
        poses = np.stack([np.load(run / "traces" / f"{r}.npz")["poses"] for r in ROBOTS], axis=1)
        simulation = schema.read(run, Simulation)
        assert simulation is not None and simulation.post_evaluation_boxes is not None
        start = np.array(simulation.post_evaluation_boxes.start)
        end = np.array(simulation.post_evaluation_boxes.end)
        with np.load(run / BOX_TRACK) as track:
            frames, every = track["positions"], int(track["every"])
    scene = OverheadScene(robots=ROBOTS, markers=MARKERS, marker_offset=(0.02, 0.0))
    video = OverheadVideo(
        scene, poses, np.concatenate([frames, end[None]]), box_every=every, hidden=[(1, 3.0, 5.0)]
    )
    config = TrackingConfig(
        floor=scene.floor,
        robots=RobotMarkers(offset=(0.02, 0.0), ids=dict(zip(ROBOTS, MARKERS, strict=True))),
        camera=CameraSettings(height=scene.height),
    )
    result = track_frames(video.frames(), config, name="film", duration=STEPS * 0.1, boxes=True)
    _print_errors(result, poses, start, end)
    _draw(args.out, video, result, args.time)
    print(f"wrote {args.out}")


def _print_errors(
    result: TrackResult, poses: np.ndarray, start: np.ndarray, end: np.ndarray
) -> None:
    distance, turn = [], []
    for i, robot in enumerate(ROBOTS):
        seen = result.seen[robot][:STEPS]
        got, want = result.poses[robot][:STEPS][seen], poses[:, i][seen]
        distance.append(np.hypot(*(got[:, :2] - want[:, :2]).T))
        turn.append((got[:, 2] - want[:, 2] + math.pi) % (2 * math.pi) - math.pi)
    d, t = np.concatenate(distance), np.concatenate(turn)
    print(f"pose_error_rms: {1000 * np.sqrt(np.mean(d**2)):.2f} mm")
    print(f"pose_error_max: {1000 * d.max():.2f} mm")
    print(f"heading_error_rms: {np.sqrt(np.mean(t**2)):.4f} rad")
    print(f"flash_start: {result.start:.2f} s (the film's pre-roll: 1.00 s)")
    assert result.boxes is not None
    found = metrics.box_displacement(
        np.array(result.boxes.boxes.start), np.array(result.boxes.boxes.end)
    )
    true = metrics.box_displacement(start, end)
    print(f"d_B_tracked: {1000 * found:.1f} mm")
    print(f"d_B_simulator: {1000 * true:.1f} mm")
    print(f"d_B_error: {1000 * (found - true):.1f} mm")
    stacked = np.stack([result.poses[r][:STEPS] for r in ROBOTS], axis=1)
    mine = metrics.behaviour_metrics(
        stacked, np.array(result.boxes.boxes.start), np.array(result.boxes.boxes.end)
    )
    theirs = metrics.behaviour_metrics(poses, start, end)
    print(f"class_tracked: {metrics.behaviour_label(mine)}")
    print(f"class_simulator: {metrics.behaviour_label(theirs)}")


def _draw(out: Path, video: OverheadVideo, result: TrackResult, at: float) -> None:
    index = round((at + video.pre_roll) * video.scene.fps)
    frame = video.render(index)
    k = int(np.argmin(np.abs(result.times - at)))
    camera = result.camera
    height = 0.055
    for robot in ROBOTS:
        x, y, heading = result.poses[robot][k]
        ends = np.array([[x, y], [x + 0.1 * math.cos(heading), y + 0.1 * math.sin(heading)]])
        a, b = (tuple(round(v) for v in p) for p in camera.to_image(ends, height))
        colour = (0, 200, 0) if result.seen[robot][k] else (0, 140, 255)
        cv2.arrowedLine(frame, a, b, colour, 2, cv2.LINE_AA, tipLength=0.3)
        cv2.circle(frame, a, 3, colour, -1, cv2.LINE_AA)
        cv2.putText(frame, robot, (a[0] + 14, a[1] - 14), cv2.FONT_HERSHEY_SIMPLEX, 0.5, colour, 1,
                    cv2.LINE_AA)  # fmt: skip
    assert result.boxes is not None
    for box in camera.to_image(np.array(result.boxes.boxes.end), 0.0125):
        cv2.circle(frame, tuple(round(v) for v in box), 6, (255, 60, 0), 1, cv2.LINE_AA)
    floor = camera.to_image(np.array([[-0.7, -0.7], [0.7, 0.7]]))
    x0, x1 = sorted(int(v) for v in floor[:, 0])
    label = f"{result.times[k]:.1f} s after the flash; boxes found at the end: blue"
    cv2.putText(
        frame, label, (x0, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), frame[:, max(x0 - 20, 0) : x1 + 20])


if __name__ == "__main__":
    main()
