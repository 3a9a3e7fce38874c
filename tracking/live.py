"""The camera's view while a run goes on: ``surprise-master track --live`` writes where it sees
the robots into the run's ``camera.json`` (:class:`~runfiles.schema.CameraView`), which the
dashboard shows (docs/tracking.md)."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path

from runfiles import schema
from runfiles.schema import CAMERA_INTERVAL, CameraPose, CameraView
from tracking.tracker import TrackedFrame

__all__ = ["CameraWriter"]


class CameraWriter:
    """Called with every tracked frame (``track_frames``' ``on_frame``); writes the robots seen
    in it to ``run_dir``'s ``camera.json`` at most every :data:`CAMERA_INTERVAL` seconds of
    ``clock`` (wall-clock time), not before the corner markers placed the camera."""

    def __init__(
        self,
        run_dir: str | Path,
        source: str,
        floor: tuple[float, float],
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.run_dir = Path(run_dir)
        self.source = source
        self.floor = floor
        self._clock = clock
        self._last = -float("inf")
        #: how many times the file was written
        self.writes = 0

    def __call__(self, frame: TrackedFrame) -> None:
        now = self._clock()
        if frame.camera is None or now - self._last < CAMERA_INTERVAL:
            return
        robots = {
            robot: CameraPose(x=pose.x, y=pose.y, heading=pose.heading)
            for robot, pose in frame.robots.items()
        }
        view = CameraView(
            source=self.source,
            floor=self.floor,
            video_time=frame.time,
            robots=robots,
            updated_at=now,
        )
        # Not durable: a view a moment old is replaced within CAMERA_INTERVAL anyway.
        schema.write(self.run_dir, view, durable=False)
        self._last = now
        self.writes += 1
