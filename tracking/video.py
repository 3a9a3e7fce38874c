"""A whole post-evaluation from a video or a camera: poses of every frame, time zero at the LED
flash, the boxes at the start and the end, and the files ``surprise-master report`` reads.

:func:`track_video` runs the :class:`~tracking.tracker.Tracker` over every frame of a video file
(or a V4L2 camera, through OpenCV's capture), finds the first frame in which most robots' tops
flash a saturated colour (the post-evaluation's start, time zero) unless a start is given, and
finds the boxes in that frame and in the first frame at or after the end. A robot whose marker
was not read in a frame takes the pose interpolated between the frames around it (or, before its
first and after its last sighting, the nearest one), and its row says so (``seen`` 0).

:func:`write_positions` writes the CSV file ``reporting.tracker`` reads (``time`` from the
flash, seconds; ``robot``; ``x``, ``y`` metres; ``heading`` radians; ``seen``);
:func:`write_boxes` the boxes' file (``runfiles.schema.TrackedBoxes``) beside it.
"""

from __future__ import annotations

import math
import time as clock
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Final

import cv2
import numpy as np

from runfiles import schema
from runfiles.schema import BoxesMoved, TrackedBoxes
from tracking.boxes import match_boxes
from tracking.camera import CameraModel, TrackingError
from tracking.config import TrackingConfig
from tracking.tracker import TrackedFrame, Tracker

__all__ = [
    "POSITION_COLUMNS",
    "RobotSummary",
    "TrackResult",
    "frames_of",
    "track_frames",
    "track_video",
    "write_boxes",
    "write_positions",
]

#: The positions file's header.
POSITION_COLUMNS: Final = ("time", "robot", "x", "y", "heading", "seen")
#: Frames within which the four corner markers must have been seen.
CORNER_DEADLINE: Final = 100
#: A marker that is neither a corner's nor a robot's, seen in more than this share of the frames,
#: is a robot left out of the markers (a stray false detection is seen in a frame or two).
UNKNOWN_SHARE: Final = 0.1
_CORNER_NAMES: Final = ("bottom-left", "bottom-right", "top-right", "top-left")


@dataclass(frozen=True)
class RobotSummary:
    """How well one robot was followed over the post-evaluation: ``frames`` in it, ``seen``
    the frames its marker was read in, ``longest_gap_s`` the longest time it was not."""

    marker: int
    frames: int
    seen: int
    longest_gap_s: float


@dataclass(frozen=True)
class TrackResult:
    """What :func:`track_video` found: ``times`` (F,) the post-evaluation's frames, seconds from
    its start; ``poses`` per robot (F, 3) and ``seen`` (F,) bools; ``start`` the start's time on
    the video's clock, ``flash`` whether the flash gave it; ``boxes`` (None without boxes)."""

    source: str
    times: np.ndarray
    poses: dict[str, np.ndarray]
    seen: dict[str, np.ndarray]
    robots: dict[str, RobotSummary]
    start: float
    flash: bool
    end_reached: bool
    camera: CameraModel
    boxes: TrackedBoxes | None
    frames: int
    unknown: dict[int, int]


def frames_of(source: str | int) -> Iterator[tuple[float, np.ndarray]]:
    """The frames of a video file (times from its frame rate) or of the camera with that index
    (times from this machine's clock), each with its time in seconds."""
    name = f"camera {source}" if isinstance(source, int) else str(source)
    if isinstance(source, str) and not Path(source).is_file():
        raise TrackingError("no such video file", source=name)
    capture = cv2.VideoCapture(source)
    try:
        if not capture.isOpened():
            raise TrackingError("OpenCV cannot open it as a video", source=name)
        fps = capture.get(cv2.CAP_PROP_FPS) if isinstance(source, str) else 0.0
        began = clock.monotonic()
        index = 0
        while True:
            ok, frame = capture.read()
            if not ok:
                if index == 0:
                    raise TrackingError("OpenCV reads no frame from it", source=name)
                return
            if fps > 0:
                t = index / fps
            elif isinstance(source, str):
                t = capture.get(cv2.CAP_PROP_POS_MSEC) / 1000
            else:
                t = clock.monotonic() - began
            yield t, frame
            index += 1
    finally:
        capture.release()


def track_video(
    source: str | int,
    config: TrackingConfig,
    *,
    duration: float | None = None,
    start: float | None = None,
    boxes: bool = False,
    on_frame: Callable[[TrackedFrame], None] | None = None,
) -> TrackResult:
    """Track the post-evaluation in ``source`` (a video file, or a camera's index); see
    :func:`track_frames`."""
    name = f"camera {source}" if isinstance(source, int) else str(source)
    return track_frames(
        frames_of(source),
        config,
        name=name,
        duration=duration,
        start=start,
        boxes=boxes,
        on_frame=on_frame,
    )


def track_frames(
    frames: Iterator[tuple[float, np.ndarray]] | list[tuple[float, np.ndarray]],
    config: TrackingConfig,
    *,
    name: str,
    duration: float | None = None,
    start: float | None = None,
    boxes: bool = False,
    on_frame: Callable[[TrackedFrame], None] | None = None,
) -> TrackResult:
    """Track the post-evaluation in ``frames`` ((time, BGR frame) pairs) named ``name``.

    Its start is ``start`` (seconds on the frames' clock) or else the LED flash; it lasts
    ``duration`` seconds (None: to the last frame). With ``boxes`` the boxes are found at the
    start and the end. Raises :class:`TrackingError` naming ``name`` and what was wrong.
    """
    tracker = Tracker(config)
    tracked: list[TrackedFrame] = []
    unknown: dict[int, int] = {}
    first: tuple[TrackedFrame, np.ndarray] | None = None
    last: tuple[TrackedFrame, np.ndarray] | None = None
    zero = start
    end_reached = False
    count = 0
    for t, frame in frames:
        count += 1
        result = tracker.process(frame, t)
        if on_frame is not None:
            on_frame(result)
        for marker in result.unknown:
            unknown[marker] = unknown.get(marker, 0) + 1
        if result.camera is None:
            if count >= CORNER_DEADLINE:
                break
            continue
        if zero is None and result.flashing:
            zero = t
        if zero is None or t < zero - 1e-9:
            continue
        tracked.append(result)
        if first is None:
            first = (result, frame)
        last = (result, frame)
        if duration is not None and t >= zero + duration - 1e-9:
            end_reached = True
            break
    if tracker.camera is None:
        raise TrackingError(_corners_missing(config, count, tracked), source=name)
    if zero is None or first is None or last is None:
        raise TrackingError(
            f"no LED flash found in its {count} frames (the robots' tops never showed a "
            "saturated colour together); give the post-evaluation's start (--start SECONDS)",
            source=name,
        )
    _check_unknown(unknown, count, config, name)
    times = np.array([f.time - zero for f in tracked])
    poses, seen, robots = {}, {}, {}
    for robot, marker in config.robots.ids.items():
        got = np.array([robot in f.robots for f in tracked])
        if not got.any():
            raise TrackingError(
                f"robot '{robot}' (marker {marker}) was not seen in the post-evaluation's "
                f"{len(tracked)} frames: is the marker on its top, and the id right?",
                source=name,
                key="--markers",
            )
        raw = np.array(
            [
                (f.robots[robot].x, f.robots[robot].y, f.robots[robot].heading)
                if robot in f.robots
                else (math.nan,) * 3
                for f in tracked
            ]
        )
        poses[robot] = _fill(times, raw, got)
        seen[robot] = got
        robots[robot] = RobotSummary(
            marker=marker, frames=len(got), seen=int(got.sum()), longest_gap_s=_gap(times, got)
        )
    found = None
    if boxes:
        found = _boxes(tracker, first, last, times, poses, name)
    return TrackResult(
        source=name,
        times=times,
        poses=poses,
        seen=seen,
        robots=robots,
        start=zero,
        flash=start is None,
        end_reached=end_reached or duration is None,
        camera=tracker.camera,
        boxes=found,
        frames=count,
        unknown=unknown,
    )


def _corners_missing(config: TrackingConfig, count: int, tracked: list[TrackedFrame]) -> str:
    named = zip(config.corners.ids, _CORNER_NAMES, strict=True)
    return (
        f"the four corner markers ({', '.join(f'{m} {n}' for m, n in named)}"
        f", {config.dictionary}) were never seen together in its first {count} frames: are "
        "they all in view, flat and printed from that dictionary?"
    )


def _check_unknown(unknown: dict[int, int], count: int, config: TrackingConfig, name: str) -> None:
    for marker, frames in sorted(unknown.items()):
        if frames > UNKNOWN_SHARE * count:
            mapped = ", ".join(f"{r}={m}" for r, m in config.robots.ids.items())
            raise TrackingError(
                f"marker {marker}, seen in {frames} of {count} frames, is neither a corner's "
                f"nor a robot's ({mapped}): a robot left out of --markers?",
                source=name,
                key="--markers",
            )


def _fill(times: np.ndarray, raw: np.ndarray, got: np.ndarray) -> np.ndarray:
    # The frames a robot was not seen in, interpolated between the frames around them (the
    # heading unwrapped, the short way round), held before the first and after the last.
    out = raw.copy()
    known = times[got]
    for axis in (0, 1):
        out[:, axis] = np.interp(times, known, raw[got, axis])
    out[:, 2] = np.interp(times, known, np.unwrap(raw[got, 2]))
    out[:, 2] = (out[:, 2] + math.pi) % (2 * math.pi) - math.pi
    return out


def _gap(times: np.ndarray, got: np.ndarray) -> float:
    # The longest span between two frames the robot was seen in (or the ends of the span).
    if got.all():
        return 0.0
    edges = np.concatenate([[times[0]], times[got], [times[-1]]])
    return float(np.diff(edges).max())


def _boxes(
    tracker: Tracker,
    first: tuple[TrackedFrame, np.ndarray],
    last: tuple[TrackedFrame, np.ndarray],
    times: np.ndarray,
    poses: dict[str, np.ndarray],
    name: str,
) -> TrackedBoxes:
    found = []
    # The robots where the first and the last frame show them, or their filled-in poses.
    for (_, frame), index in ((first, 0), (last, len(times) - 1)):
        standing = {robot: (p[index, 0], p[index, 1], p[index, 2]) for robot, p in poses.items()}
        found.append(tracker.boxes(frame, standing))
    start, end, alone_start, alone_end = match_boxes(found[0], found[1])
    if not len(start):
        raise TrackingError(
            f"no boxes found at the post-evaluation's {'start' if not len(found[0]) else 'end'}",
            source=name,
        )
    return TrackedBoxes(
        source=name,
        start_time_s=float(times[0]),
        end_time_s=float(times[-1]),
        boxes=BoxesMoved(start=start.tolist(), end=end.tolist()),
        unpaired_start=alone_start.tolist(),
        unpaired_end=alone_end.tolist(),
    )


def write_positions(path: str | Path, result: TrackResult) -> Path:
    """Write ``result``'s poses as the CSV file ``report --positions`` reads (time from the
    post-evaluation's start), atomically."""
    lines = [",".join(POSITION_COLUMNS)]
    for k, t in enumerate(result.times):
        for robot, poses in result.poses.items():
            x, y, heading = poses[k]
            seen = int(result.seen[robot][k])
            lines.append(f"{t:.4f},{robot},{x:.5f},{y:.5f},{heading:.5f},{seen}")
    path = Path(path)
    schema.write_atomic(path, ("\n".join(lines) + "\n").encode("utf-8"))
    return path


def write_boxes(positions: str | Path, result: TrackResult) -> Path | None:
    """Write ``result``'s boxes beside the positions file ``positions``
    (:func:`runfiles.schema.tracked_boxes_path`); None, and nothing written, without boxes."""
    if result.boxes is None:
        return None
    path = schema.tracked_boxes_path(positions)
    schema.write_atomic(path, schema.encode(result.boxes))
    return path
