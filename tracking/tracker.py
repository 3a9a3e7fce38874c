"""Frames in, poses out: :class:`Tracker` finds the robots' markers in one frame of the overhead
camera and gives each robot's pose in the floor's metres.

The four corner markers fix the camera (:mod:`tracking.camera`); from then on each frame costs
one ArUco detection and a little arithmetic per robot, so the same object serves a video file
(:mod:`tracking.video`) and, later, a live view. A robot's pose is the point between its wheels:
the marker's centre, found at the marker's height, minus the marker's offset on the robot; its
heading the direction the marker's top edge faces. Each robot's top is also sampled around the
marker for the LED flash that starts the post-evaluation (:attr:`RobotPose.flash`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import cv2
import numpy as np

from tracking.boxes import find_boxes
from tracking.camera import CameraModel, Floor, TrackingError
from tracking.config import TrackingConfig

__all__ = ["CORNER_FRAMES", "RobotPose", "TrackedFrame", "Tracker"]

#: The corner markers of this many frames are averaged before the camera is fixed: they do not
#: move, and their mean's noise is a fifth of one frame's.
CORNER_FRAMES = 25


@dataclass(frozen=True)
class RobotPose:
    """One robot in one frame: ``x``, ``y`` (metres) of the point between its wheels, ``heading``
    (radians, counter-clockwise from x, in [-pi, pi)), ``flash`` the share of its top's samples
    lit by a saturated colour, ``corners`` its marker's four corners in pixels (4, 2)."""

    x: float
    y: float
    heading: float
    flash: float
    corners: np.ndarray


@dataclass(frozen=True)
class TrackedFrame:
    """What one frame showed: its ``time`` (seconds), every robot whose marker was read, the
    ``unknown`` marker ids seen that are neither a corner's nor a robot's, and ``flashing``:
    whether most robots seen showed the LED flash. ``camera`` is None until the four corner
    markers were seen; ``corners`` the corner markers this frame showed."""

    time: float
    robots: dict[str, RobotPose]
    unknown: tuple[int, ...]
    corners: tuple[int, ...]
    camera: CameraModel | None
    flashing: bool = False


@dataclass
class _Corners:
    # The running sum of the corner markers' pixels over the frames that showed all four.
    sums: dict[int, np.ndarray] = field(default_factory=dict)
    frames: int = 0


class Tracker:
    """The robots of ``config`` (``robots.ids``: robot id to marker id), on the floor
    ``config.floor`` seen by a camera ``config.camera.height`` above it.

    :meth:`process` takes one BGR (or grey) frame and its time and returns a
    :class:`TrackedFrame`. Raises :class:`TrackingError` for a configuration it cannot track
    with (no floor size, no camera height, no robots).
    """

    def __init__(self, config: TrackingConfig) -> None:
        if config.floor is None:
            raise TrackingError("the floor's size is needed (WIDTHxHEIGHT)", key="--floor")
        if config.camera.height is None:
            raise TrackingError(
                "the camera's height above the floor is needed (metres, measured)",
                key="--camera-height",
            )
        if not config.robots.ids:
            raise TrackingError("no robot markers given (ROBOT=MARKER,...)", key="--markers")
        if config.camera.height <= config.robots.height:
            raise TrackingError(
                f"the camera ({config.camera.height} m) must hang above the robots' markers "
                f"({config.robots.height} m)",
                key="--camera-height",
            )
        self.config = config
        self.floor = Floor(
            width=config.floor[0],
            height=config.floor[1],
            corner_ids=config.corners.ids,
            corner_size=config.corners.size,
        )
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, config.dictionary))
        parameters = cv2.aruco.DetectorParameters()
        # Sub-pixel corners: a pixel is 2 mm on the floor, the poses are wanted to a few mm.
        parameters.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
        parameters.cornerRefinementWinSize = 3
        self._detector = cv2.aruco.ArucoDetector(dictionary, parameters)
        self._robot_of = {marker: robot for robot, marker in config.robots.ids.items()}
        self._corner_ids = set(config.corners.ids)
        self._corners = _Corners()
        self.camera: CameraModel | None = None
        self._samples = _top_samples(config.robots.size, config.robots.offset)

    def process(self, frame: np.ndarray, time: float) -> TrackedFrame:
        """The robots in ``frame`` (BGR or grey, uint8), taken at ``time`` seconds."""
        grey = frame if frame.ndim == 2 else cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
        found, ids, _ = self._detector.detectMarkers(grey)
        markers: dict[int, np.ndarray] = {}
        if ids is not None:
            for quad, marker in zip(found, ids.ravel(), strict=True):
                markers[int(marker)] = np.asarray(quad).reshape(4, 2).astype(np.float64)
        corners = tuple(sorted(m for m in markers if m in self._corner_ids))
        if len(corners) == 4 and self._corners.frames < CORNER_FRAMES:
            self._fit_camera(markers, grey.shape[1::-1])
        unknown = tuple(
            sorted(m for m in markers if m not in self._corner_ids and m not in self._robot_of)
        )
        robots: dict[str, RobotPose] = {}
        camera = self.camera
        if camera is not None:
            for seen, pixels in markers.items():
                robot = self._robot_of.get(seen)
                if robot is not None:
                    robots[robot] = self._pose(camera, pixels, frame)
        flashes = [pose.flash >= self.config.flash.share for pose in robots.values()]
        flashing = bool(flashes) and 2 * sum(flashes) > len(flashes)
        return TrackedFrame(time, robots, unknown, corners, camera, flashing)

    def boxes(
        self, frame: np.ndarray, robots: Mapping[str, tuple[float, float, float]]
    ) -> np.ndarray:
        """The boxes on the floor in ``frame`` (B, 2) in metres, with the robots standing at
        ``robots`` (robot: x, y, heading) masked out; see :func:`tracking.boxes.find_boxes`."""
        if self.camera is None:
            raise TrackingError("the corner markers were not seen yet: no camera to find boxes")
        return find_boxes(
            frame,
            self.camera,
            self.floor,
            list(robots.values()),
            box_size=self.config.boxes.size,
            contrast=self.config.boxes.contrast,
            robot_height=self.config.robots.height,
        )

    def _fit_camera(self, markers: Mapping[int, np.ndarray], size: tuple[int, int]) -> None:
        sums = self._corners.sums
        for marker in self._corner_ids:
            sums[marker] = sums.get(marker, 0) + markers[marker]
        self._corners.frames += 1
        mean = {m: s / self._corners.frames for m, s in sums.items()}
        assert self.config.camera.height is not None
        self.camera = CameraModel.from_corners(self.floor, mean, size, self.config.camera.height)

    def _pose(self, camera: CameraModel, pixels: np.ndarray, frame: np.ndarray) -> RobotPose:
        cfg = self.config.robots
        top = camera.to_floor(pixels, cfg.height)
        centre = top.mean(axis=0)
        # The top edge's direction and the side edges' turned a quarter left: both say which
        # way the marker faces; their sum halves the corners' noise.
        forward = (top[0] + top[1] - top[2] - top[3]) / 2
        right = (top[1] + top[2] - top[0] - top[3]) / 2
        fx, fy = forward[0] - right[1], forward[1] + right[0]
        heading = math.atan2(fy, fx)
        c, s = math.cos(heading), math.sin(heading)
        dx, dy = cfg.offset
        x = float(centre[0] - c * dx + s * dy)
        y = float(centre[1] - s * dx - c * dy)
        flash = self._flash(camera, frame, x, y, c, s) if frame.ndim == 3 else 0.0
        heading = (heading + math.pi) % (2 * math.pi) - math.pi
        return RobotPose(x=x, y=y, heading=heading, flash=flash, corners=pixels)

    def _flash(
        self, camera: CameraModel, frame: np.ndarray, x: float, y: float, c: float, s: float
    ) -> float:
        # The share of the robot's top around its marker that shows a bright saturated colour.
        local = self._samples
        points = np.column_stack(
            [x + c * local[:, 0] - s * local[:, 1], y + s * local[:, 0] + c * local[:, 1]]
        )
        pixels = np.round(camera.to_image(points, self.config.robots.height)).astype(int)
        height, width = frame.shape[:2]
        inside = (
            (pixels[:, 0] >= 0) & (pixels[:, 0] < width) & (pixels[:, 1] >= 0)
            & (pixels[:, 1] < height)
        )  # fmt: skip
        if not inside.any():
            return 0.0
        colours = frame[pixels[inside, 1], pixels[inside, 0]].reshape(1, -1, 3)
        hsv = cv2.cvtColor(colours, cv2.COLOR_BGR2HSV)[0]
        cfg = self.config.flash
        lit = (hsv[:, 1] >= 255 * cfg.saturation) & (hsv[:, 2] >= 255 * cfg.value)
        return float(lit.mean())


def _top_samples(marker_size: float, offset: tuple[float, float]) -> np.ndarray:
    # Points of a Thymio II's top in its own frame (x forward from the wheel axis, y left) that
    # the marker and its white margin do not cover: where the top LEDs' colour shows.
    xs, ys = np.meshgrid(np.arange(-0.025, 0.075, 0.006), np.arange(-0.05, 0.051, 0.006))
    points = np.column_stack([xs.ravel(), ys.ravel()])
    on_top = (np.hypot(points[:, 0], points[:, 1]) < 0.072) & (np.abs(points[:, 1]) < 0.049)
    reach = marker_size / 2 * (8 / 6) + 0.004
    off_marker = (np.abs(points[:, 0] - offset[0]) > reach) | (
        np.abs(points[:, 1] - offset[1]) > reach
    )
    return points[on_top & off_marker]
