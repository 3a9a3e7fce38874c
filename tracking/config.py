"""The tracking configuration: the arena's markers, the robots' markers and the camera.

A small YAML file (``surprise-master track --config tracking.yaml``) decoded into
:class:`TrackingConfig`; the command's options (``--floor``, ``--markers``, ``--camera-height``)
replace its keys. Lengths are metres, angles radians, the frame the simulator's (origin at the
centre of the floor, x to the right, y up). docs/tracking.md shows a file.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated, Final

import msgspec

from minimize_surprise.config import Strict, decode, read_yaml
from minimize_surprise.errors import ConfigError

__all__ = [
    "DICTIONARIES",
    "BoxSettings",
    "CameraSettings",
    "CornerMarkers",
    "FlashSettings",
    "RobotMarkers",
    "TrackingConfig",
    "load_tracking_config",
    "parse_floor",
    "parse_markers",
]

Positive = Annotated[float, msgspec.Meta(gt=0.0)]
Share = Annotated[float, msgspec.Meta(gt=0.0, le=1.0)]
MarkerId = Annotated[int, msgspec.Meta(ge=0, le=999)]

#: The ArUco dictionaries a file may name (OpenCV's names). 4x4 cells read from the farthest:
#: the fewest bits per marker, so the largest cells for a given printed size.
DICTIONARIES: Final = ("DICT_4X4_50", "DICT_4X4_100", "DICT_5X5_50", "DICT_6X6_50")


class CornerMarkers(Strict, frozen=True):
    """The four markers lying flat at the floor's corners, each inside the floor with its outer
    corner on the floor's corner and its top edge towards +y (the far side)."""

    #: marker ids at the corners: bottom-left, bottom-right, top-right, top-left (seen from above,
    #: x to the right, y up)
    ids: tuple[MarkerId, MarkerId, MarkerId, MarkerId] = (0, 1, 2, 3)
    #: side of each corner marker's black square, as printed
    size: Positive = 0.10


class RobotMarkers(Strict, frozen=True):
    """The marker on each robot's top: its size, height and where it sits on the robot."""

    #: side of a robot marker's black square, as printed
    size: Positive = 0.06
    #: height of the marker's face above the floor (a Thymio II's top: 5.3 cm, plus the card)
    height: Annotated[float, msgspec.Meta(ge=0.0)] = 0.055
    #: where the marker's centre sits in the robot's frame (forward, left) from the point between
    #: the wheels; the marker's top edge points the robot's way
    offset: tuple[float, float] = (0.0, 0.0)
    #: robot id (as in the run) to its marker's id
    ids: dict[str, MarkerId] = msgspec.field(default_factory=dict)


class CameraSettings(Strict, frozen=True):
    """What the corner markers cannot tell of the camera."""

    #: height of the camera's lens above the floor, measured; with the corner markers it places
    #: the camera, whose parallax shifts a robot's marker outwards (``null``: give
    #: ``--camera-height``)
    height: Positive | None = None


class BoxSettings(Strict, frozen=True):
    """The boxes on the floor (found as blobs that differ from the floor, no identities)."""

    #: side of a (cubic) box
    size: Positive = 0.025
    #: a pixel differs from the floor when its colour is this far from the floor's around it, as
    #: a share of the floor's brightness there
    contrast: Share = 0.18


class FlashSettings(Strict, frozen=True):
    """The robots' top LEDs flashing when the post-evaluation starts."""

    #: a pixel of a robot's top is lit when its saturation (0-1) is at least this
    saturation: Share = 0.45
    #: ... and its value (brightness, 0-1) at least this
    value: Share = 0.35
    #: a robot flashes when at least this share of its top's samples are lit
    share: Share = 0.3


class TrackingConfig(Strict, frozen=True):
    """Everything ``surprise-master track`` needs to know of the arena and the robots."""

    #: the floor's width (along x) and height (along y) between its outer corners
    floor: tuple[Positive, Positive] | None = None
    #: the ArUco dictionary of every marker (one of DICTIONARIES)
    dictionary: str = "DICT_4X4_50"
    #: the markers at the floor's corners
    corners: CornerMarkers = CornerMarkers()
    #: the markers on the robots' tops
    robots: RobotMarkers = RobotMarkers()
    #: the camera
    camera: CameraSettings = CameraSettings()
    #: the boxes
    boxes: BoxSettings = BoxSettings()
    #: the LED flash that starts the post-evaluation
    flash: FlashSettings = FlashSettings()

    def __post_init__(self) -> None:
        if self.dictionary not in DICTIONARIES:
            raise ValueError(f"`dictionary`: expected one of {', '.join(DICTIONARIES)}")
        if len(set(self.corners.ids)) != 4:
            raise ValueError("`corners.ids`: four different marker ids are needed")
        taken = {m: "a corner" for m in self.corners.ids}
        for robot, marker in self.robots.ids.items():
            if marker in taken:
                raise ValueError(
                    f"`robots.ids.{robot}`: marker {marker} is already {taken[marker]}'s"
                )
            taken[marker] = f"robot {robot}"


def load_tracking_config(path: str | Path | None) -> TrackingConfig:
    """The tracking configuration of the YAML file ``path`` (the defaults without one), or a
    :class:`ConfigError` naming the file and key."""
    if path is None:
        return TrackingConfig()
    return decode(read_yaml(path), TrackingConfig, file=path)


_FLOOR = re.compile(r"^\s*([0-9.]+)\s*[xX×]\s*([0-9.]+)\s*$")


def parse_floor(text: str) -> tuple[float, float]:
    """``"2.2x2.9"`` as (2.2, 2.9) metres, or a :class:`ConfigError` naming ``--floor``."""
    found = _FLOOR.match(text)
    try:
        width, height = (float(found[1]), float(found[2])) if found else (0.0, 0.0)
    except ValueError:
        width = height = 0.0
    if not (width > 0 and height > 0):
        raise ConfigError(
            f"expected WIDTHxHEIGHT in metres, e.g. 2.2x2.9, got '{text}'", key="--floor"
        )
    return width, height


def parse_markers(text: str) -> dict[str, int]:
    """``"thymio-1=10,thymio-2=11"`` as a robot-to-marker mapping, or a :class:`ConfigError`
    naming ``--markers`` and the pair at fault."""
    markers: dict[str, int] = {}
    for pair in text.split(","):
        robot, sep, marker = pair.partition("=")
        robot, marker = robot.strip(), marker.strip()
        if not sep or not robot or not marker.isdigit():
            raise ConfigError(
                f"expected ROBOT=MARKER pairs separated by commas (thymio-1=10,thymio-2=11), "
                f"got '{pair}'",
                key="--markers",
            )
        if robot in markers:
            raise ConfigError(f"robot '{robot}' is given twice", key="--markers")
        markers[robot] = int(marker)
    return markers
