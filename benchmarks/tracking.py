"""The overhead camera's tracker: frames a second on one core, against ArUco detection alone.

Renders ``--frames`` synthetic 1280x720 frames of the overhead camera (``standins.overhead_camera``:
corner markers, 289 boxes, robots driving circles, noise, blur, uneven light) before timing, then
times, on one core (``cv2.setNumThreads(1)``), the same frames through

- ``tracking``: :meth:`tracking.tracker.Tracker.process` (grey conversion, ArUco detection, the
  poses with parallax, the flash samples of every robot);
- ``aruco_detect``: the peer, ``cv2.aruco.ArucoDetector.detectMarkers`` on the grey frame with
  the tracker's detector parameters, which is most of the tracker's work;
- ``boxes``: one call of the boxes' finder (done twice a post-evaluation, not per frame).

Prints one figure a line as ``name: value unit``. Goal: tracking >= 30 frames/s at 1280x720.
Run: ``python benchmarks/tracking.py [--frames 150] [--robots 4]``
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import cv2
import numpy as np

# This file bears the package's name: run as a script, its directory comes first on the path and
# ``import tracking`` would find this file instead of the package.
_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _HERE]


def _poses(robots: int, steps: int) -> np.ndarray:
    # Robots driving circles of 15 cm radius around centres on a ring, at 8 cm/s.
    t = np.arange(steps)[:, None] * 0.1
    phase = 2 * math.pi * np.arange(robots)[None, :] / robots
    cx, cy = 0.3 * np.cos(phase), 0.3 * np.sin(phase)
    angle = phase + 0.08 / 0.15 * t
    poses = np.empty((steps, robots, 3))
    poses[..., 0] = cx + 0.15 * np.cos(angle)
    poses[..., 1] = cy + 0.15 * np.sin(angle)
    poses[..., 2] = (angle + math.pi / 2 + math.pi) % (2 * math.pi) - math.pi
    return poses


def main() -> None:
    """Run the benchmark and print its figures."""
    from standins.overhead_camera import OverheadScene, OverheadVideo
    from tracking.config import CameraSettings, RobotMarkers, TrackingConfig
    from tracking.tracker import Tracker

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=150)
    parser.add_argument("--robots", type=int, default=4)
    args = parser.parse_args()
    cv2.setNumThreads(1)
    robots = tuple(f"robot-{i}" for i in range(args.robots))
    markers = tuple(10 + i for i in range(args.robots))
    size = (1280, 720)
    scene = OverheadScene(robots=robots, markers=markers, image_size=size, fps=10.0)
    rng = np.random.default_rng(0)
    # Boxes on a jittered 6.5 cm grid, none touching another (about the boxes scenario's 14 %).
    grid = np.arange(-0.52, 0.53, 0.065)
    centres = np.stack(np.meshgrid(grid, grid), axis=-1).reshape(-1, 2)
    centres += rng.uniform(-0.015, 0.015, centres.shape)
    boxes = centres[None]
    poses = _poses(args.robots, args.frames)
    video = OverheadVideo(scene, poses, boxes, pre_roll=0.0, post_roll=0.0, flash=0.0)
    began = time.perf_counter()
    frames = [video.render(i) for i in range(args.frames)]
    render = time.perf_counter() - began
    config = TrackingConfig(
        floor=scene.floor,
        robots=RobotMarkers(ids=dict(zip(robots, markers, strict=True))),
        camera=CameraSettings(height=scene.height),
    )
    tracker = Tracker(config)
    tracker.process(frames[0], 0.0)  # the camera fixed, as after the first frames of a video
    began = time.perf_counter()
    seen = 0
    for i, frame in enumerate(frames):
        seen += len(tracker.process(frame, i * 0.1).robots)
    tracking = time.perf_counter() - began
    detector = tracker._detector  # the same parameters: the peer differs only by the tracker's work
    greys = [cv2.cvtColor(f, cv2.COLOR_BGR2GRAY) for f in frames]
    began = time.perf_counter()
    for grey in greys:
        detector.detectMarkers(grey)
    detect = time.perf_counter() - began
    standing = {
        r: (float(p[0]), float(p[1]), float(p[2])) for r, p in zip(robots, poses[0], strict=True)
    }
    began = time.perf_counter()
    repeats = 5
    for _ in range(repeats):
        found = tracker.boxes(frames[0], standing)
    boxes_s = (time.perf_counter() - began) / repeats
    n = len(frames)
    label = f"{size[0]}x{size[1]}"
    print(f"tracking_fps_{label}: {n / tracking:.1f} frames/s")
    print(f"aruco_detect_fps_{label}: {n / detect:.1f} frames/s")
    print(f"tracking_over_detection_time: {tracking / detect:.2f} ratio")
    print(f"robots_seen_share: {seen / (n * args.robots):.3f} share")
    print(f"boxes_found_{label}: {len(found)} of {boxes.shape[1]} boxes")
    print(f"boxes_time_{label}: {1000 * boxes_s:.1f} ms")
    print(f"synthetic_render_fps_{label}: {n / render:.1f} frames/s")


if __name__ == "__main__":
    main()
