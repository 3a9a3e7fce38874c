"""Where the camera is, from the four corner markers: floor pixels to metres, with parallax.

The four markers lying at the floor's corners give sixteen image points of known floor
coordinates, hence the homography from the floor to the image (no calibration step). A robot's
marker does not lie on the floor but ``h`` above it: seen from a camera at height ``H`` its image
falls where the floor point ``(H / (H - h))`` times as far from the camera's nadir would, which
at 0.65 m from the nadir, a 2 m camera and a 5.5 cm marker is 1.8 cm outwards. So the camera's
nadir is needed too: the homography is split into a pinhole camera (principal point at the
image's centre, square pixels, no distortion) whose focal length makes its height the measured
one; its centre gives the nadir. A point of the image at height ``z`` is then

    P = N + (P0 - N) * (H - z) / H,

where ``P0`` is the floor point the homography gives and ``N`` the nadir: exact for a pinhole
camera, and the nadir's error ``e`` moves ``P`` by ``e * z / H`` only (1 mm per 4 cm at 2 m).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import cv2
import numpy as np

__all__ = ["CameraModel", "Floor", "TrackingError"]

from minimize_surprise.errors import ConfigError


class TrackingError(ConfigError):
    """A video, camera or tracking input that cannot be used; the message names it and what was
    wrong, in one line."""

    def __init__(self, reason: str, *, source: str | None = None, key: str | None = None) -> None:
        super().__init__(reason, file=source, key=key)


@dataclass(frozen=True)
class Floor:
    """The floor between the corner markers: ``width`` along x, ``height`` along y (metres),
    centred on the origin; ``corner_ids`` at bottom-left, bottom-right, top-right, top-left,
    each marker ``corner_size`` wide, inside the floor at its corner, top edge towards +y."""

    width: float
    height: float
    corner_ids: tuple[int, int, int, int]
    corner_size: float

    def corner_points(self) -> dict[int, np.ndarray]:
        """Each corner marker's four corners in floor metres (4, 2), in ArUco's order (top-left,
        top-right, bottom-right, bottom-left of the marker as printed)."""
        w, h, s = self.width / 2, self.height / 2, self.corner_size
        # The marker's bottom-left corner for each of the floor's corners.
        origins = [(-w, -h), (w - s, -h), (w - s, h - s), (-w, h - s)]
        points = {}
        for marker, (x, y) in zip(self.corner_ids, origins, strict=True):
            points[marker] = np.array([[x, y + s], [x + s, y + s], [x + s, y], [x, y]])
        return points


@dataclass(frozen=True)
class CameraModel:
    """The camera over the floor: ``homography`` maps floor metres (x, y, 1) to pixels;
    ``nadir`` is the floor point under the lens, ``height`` the lens's height (metres);
    ``tilt`` the angle between the optical axis and the vertical (radians, a check of the
    set-up); ``residual_px`` the corner markers' RMS reprojection error."""

    homography: np.ndarray
    inverse: np.ndarray
    nadir: np.ndarray
    height: float
    tilt: float
    residual_px: float

    @classmethod
    def from_corners(
        cls,
        floor: Floor,
        found: Mapping[int, np.ndarray],
        image_size: tuple[int, int],
        height: float,
    ) -> CameraModel:
        """The camera of the corner markers ``found`` (marker id: (4, 2) pixels, all four of
        ``floor.corner_ids``) in an image of ``image_size`` (width, height) pixels, with its
        lens ``height`` metres above the floor."""
        known = floor.corner_points()
        world = np.concatenate([known[m] for m in floor.corner_ids])
        image = np.concatenate([np.asarray(found[m], dtype=float) for m in floor.corner_ids])
        homography, _ = cv2.findHomography(world, image, 0)
        if homography is None:
            raise TrackingError("the corner markers give no homography (are they in a line?)")
        mapped = cv2.perspectiveTransform(world[None], homography)[0]
        residual = float(np.sqrt(((mapped - image) ** 2).sum(axis=1).mean()))
        nadir, tilt = _nadir(homography, image_size, height)
        return cls(
            homography=homography,
            inverse=np.linalg.inv(homography),
            nadir=nadir,
            height=height,
            tilt=tilt,
            residual_px=residual,
        )

    def to_floor(self, pixels: np.ndarray, z: float = 0.0) -> np.ndarray:
        """Image ``pixels`` (n, 2) of points ``z`` metres above the floor, in floor metres."""
        p = np.asarray(pixels, dtype=np.float64).reshape(1, -1, 2)
        on_floor = cv2.perspectiveTransform(p, self.inverse)[0]
        if z == 0.0:
            return on_floor
        return self.nadir + (on_floor - self.nadir) * ((self.height - z) / self.height)

    def to_image(self, points: np.ndarray, z: float = 0.0) -> np.ndarray:
        """Floor points (n, 2) at ``z`` metres above the floor, in pixels (n, 2)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        if z != 0.0:
            p = self.nadir + (p - self.nadir) * (self.height / (self.height - z))
        return cv2.perspectiveTransform(p.reshape(1, -1, 2), self.homography)[0]


def _pose(homography: np.ndarray, centre: np.ndarray, focal: float) -> tuple[np.ndarray, float]:
    # The pinhole camera of focal length ``focal`` (pixels) that the homography is: its centre
    # in floor coordinates (x, y, z) and the tilt of its optical axis from the vertical.
    k_inv = np.array(
        [[1 / focal, 0, -centre[0] / focal], [0, 1 / focal, -centre[1] / focal], [0, 0, 1]]
    )
    a = k_inv @ homography
    scale = math.sqrt(np.linalg.norm(a[:, 0]) * np.linalg.norm(a[:, 1]))
    a = a / scale
    if a[2, 2] < 0:  # the floor lies in front of the camera
        a = -a
    r1, r2, t = a[:, 0], a[:, 1], a[:, 2]
    u, _, vt = np.linalg.svd(np.column_stack([r1, r2, np.cross(r1, r2)]))
    rotation = u @ vt
    position = -rotation.T @ t
    tilt = math.acos(min(1.0, abs(float(rotation[2, 2]))))
    return position, tilt


def _nadir(
    homography: np.ndarray, image_size: tuple[int, int], height: float
) -> tuple[np.ndarray, float]:
    # The focal length whose camera stands ``height`` above the floor, by bisection (the height
    # grows with the focal length: a longer lens sees the same floor from farther away).
    centre = np.array([image_size[0] / 2, image_size[1] / 2])
    low, high = math.log(0.05 * image_size[0]), math.log(50.0 * image_size[0])
    for _ in range(60):
        middle = (low + high) / 2
        position, _ = _pose(homography, centre, math.exp(middle))
        if abs(position[2]) < height:
            low = middle
        else:
            high = middle
    position, tilt = _pose(homography, centre, math.exp((low + high) / 2))
    return position[:2].copy(), tilt
