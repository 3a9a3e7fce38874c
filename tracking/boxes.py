"""The boxes on the floor: blobs found in one frame, and the start's matched to the end's for d_B.

Boxes carry no markers, so they are found as what they are: small blobs that differ from the
floor around them. The floor's look varies (a carpet on a brighter floor, light falling off to
the corners), so "around them" is the median of a window four boxes wide: boxes, fewer than half
of any window's pixels, vanish from it, and the floor's larger shapes (the carpet's straight
edge) keep their place. What differs from it by more than
``contrast`` of the floor's brightness, off the robots and the corner markers and inside the
floor, is a box's. When the boxes' colour (the median blob's) is far from every floor colour, the
boxes are found again by their colour alone, so that a clump wider than the median's window is
found whole. A blob of k boxes' area is split into k by k-means on its pixels. A blob's
centre is found at half a box's height (the camera sees its top and, off the nadir, a side).

d_B (:func:`simulator.metrics.box_displacement`) is the mean distance between each box's start
and end. Without identities, :func:`match_boxes` pairs the start's boxes with the end's so that
the sum of the distances is least (the Hungarian assignment): the boxes that did not move pair
with themselves, and a pushed box with where it went, as long as it did not end nearer another
box's start than its own.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import cv2
import numpy as np

from tracking.camera import CameraModel, Floor

__all__ = ["find_boxes", "match_boxes", "robot_outline"]

#: Blobs smaller than this share of one box's area are noise or a box's cut-off corner.
_SMALLEST = 0.35
#: A blob whose chromaticity (r, g, b shares) is farther than this (sum of the differences) from
#: the typical blob's is not a box.
_CHROMA = 0.08
#: The chromaticity's noise on a mid-grey pixel of a blurred frame: colours closer than twice it
#: are not told apart.
_CHROMA_NOISE = 0.02
#: Blobs larger than this many boxes are not boxes (a shadow, a bag on the floor).
_LARGEST = 60


def robot_outline() -> tuple[np.ndarray, np.ndarray]:
    """A Thymio II from above in its own frame (metres, x forward from the wheel axis, y left):
    its body, 5.3 cm tall, and its pushing blade, 2 cm tall: what hides the floor around it."""
    side = math.asin(0.055 / 0.08)
    arc = [(0.08 * math.cos(a), 0.08 * math.sin(a)) for a in np.linspace(-side, side, 9)]
    body = np.array([*arc, (-0.032, 0.058), (-0.032, -0.058)])
    blade = np.array([(0.082, -0.062), (0.097, -0.062), (0.097, 0.062), (0.082, 0.062)])
    return body, blade


#: The blade's height above the floor (metres): it hides less than the body.
_BLADE_HEIGHT = 0.02


def find_boxes(
    frame: np.ndarray,
    camera: CameraModel,
    floor: Floor,
    robots: Sequence[tuple[float, float, float]],
    *,
    box_size: float,
    contrast: float,
    robot_height: float,
) -> np.ndarray:
    """The centres (B, 2) in metres of the boxes in ``frame`` (BGR), the robots at ``robots``
    ((x, y, heading) each) and the corner markers left out."""
    height, width = frame.shape[:2]
    pixels_per_metre = _scale(camera)
    box_px = box_size * pixels_per_metre
    radius = max(2, round(2 * box_px))
    # Sensor noise blurred away first, then the floor around each pixel as the median of a
    # window four boxes wide: boxes (fewer than half of any window's pixels) vanish from it, the
    # carpet's straight edge stays where it is.
    smooth = cv2.GaussianBlur(frame, (3, 3), 0)
    background = cv2.medianBlur(smooth, 2 * radius + 1)
    difference = cv2.absdiff(smooth, background).max(axis=2).astype(np.float32)
    floor_light = background.max(axis=2).astype(np.float32)
    allowed = _floor_mask(camera, floor, robots, robot_height, (width, height))
    objects = (difference > contrast * np.maximum(floor_light, 20.0)).astype(np.uint8) & allowed
    thin = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (max(3, round(box_px / 2)) | 1,) * 2)
    # Opened with a disc half a box wide: slivers along the carpet's edge (where the median
    # wavers) go, and so do the thin bridges between two boxes nearly touching.
    objects = cv2.morphologyEx(objects, cv2.MORPH_OPEN, thin)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(objects, connectivity=8)
    like, colour = _like_most(smooth, labels, count)
    by_colour = _by_colour(smooth, colour, allowed, objects)
    if by_colour is not None:
        # The boxes' colour tells them from the floor: a clump of boxes, more than half of the
        # median's window, is then found whole.
        objects = cv2.morphologyEx(by_colour, cv2.MORPH_OPEN, thin)
        count, labels, stats, _ = cv2.connectedComponentsWithStats(objects, connectivity=8)
        like = np.ones(count - 1, dtype=bool)
    areas = stats[1:, cv2.CC_STAT_AREA].astype(float)
    # One box's blob: its top and, off the nadir, a side, blurred: larger than box_px^2. Most
    # blobs are single boxes, so their median area is it (the nominal area bounds the guess).
    nominal = box_px**2
    plausible = areas[(areas > 0.5 * nominal) & (areas < 2.5 * nominal)]
    area = float(np.median(plausible)) if len(plausible) >= 5 else 1.3 * nominal
    centres: list[np.ndarray] = []
    for label in range(1, count):
        boxes = areas[label - 1] / area
        if boxes < _SMALLEST or boxes > _LARGEST or not like[label - 1]:
            continue
        k = max(1, round(boxes))
        if k == 1:
            ys, xs = np.nonzero(labels[_box(stats[label])] == label)
            top = stats[label]
            centres.append(np.array([xs.mean() + top[0], ys.mean() + top[1]]))
            continue
        ys, xs = np.nonzero(labels[_box(stats[label])] == label)
        top = stats[label]
        points = np.column_stack([xs + top[0], ys + top[1]]).astype(np.float32)
        criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.1)
        cv2.setRNGSeed(0)  # k-means' first guesses: the same frame gives the same boxes
        _, _, split = cv2.kmeans(
            points, k, np.zeros((len(points), 1), np.int32), criteria, 3, cv2.KMEANS_PP_CENTERS
        )
        centres.extend(split)
    if not centres:
        return np.zeros((0, 2))
    return camera.to_floor(np.array(centres), box_size / 2)


def _box(stats: np.ndarray) -> tuple[slice, slice]:
    # A blob's bounding box as the slices of the image's rows and columns.
    x, y, w, h = (int(v) for v in stats[:4])
    return slice(y, y + h), slice(x, x + w)


def _by_colour(
    image: np.ndarray, colour: np.ndarray | None, allowed: np.ndarray, objects: np.ndarray
) -> np.ndarray | None:
    # The pixels of the boxes' chromaticity ``colour``, if it is far enough from every floor
    # pixel's to tell them apart (else None: the floor has the boxes' colour, so to speak).
    if colour is None:
        return None
    pixels = image.astype(np.float32)
    total = pixels.sum(axis=2)
    distance = np.abs(pixels / np.maximum(total, 1.0)[..., None] - colour).sum(axis=2)
    floor = distance[(allowed > 0) & (objects == 0) & (total > 60)]
    if floor.size < 100:
        return None
    # The floor's colour nearest the boxes', over the floor's pixels less a tenth (the boxes'
    # blurred rims, which the median's test left out, have colours between).
    nearest = float(np.percentile(floor, 10))
    if nearest < 2 * _CHROMA_NOISE:
        return None
    return ((distance < nearest / 2) & (total > 60) & (allowed > 0)).astype(np.uint8)


def _like_most(
    image: np.ndarray, labels: np.ndarray, count: int
) -> tuple[np.ndarray, np.ndarray | None]:
    # Whether each blob (labels 1 .. count - 1) has the colour most blobs have: the boxes are
    # alike and the most of the blobs, while the floor's own slivers (where the median wavers at
    # the carpet's edge) have the floor's colour. Compared as chromaticity, the colour with the
    # brightness divided out, as the light falls off towards the corners.
    if count <= 1:
        return np.zeros(0, dtype=bool), None
    flat = labels.ravel()
    sums = np.stack(
        [np.bincount(flat, weights=image[..., c].ravel(), minlength=count) for c in range(3)],
        axis=1,
    )[1:]
    chroma = sums / np.maximum(sums.sum(axis=1, keepdims=True), 1.0)
    typical = np.median(chroma, axis=0)
    like = np.abs(chroma - typical).sum(axis=1) < _CHROMA
    return like, (typical if count > 10 else None)


def match_boxes(
    start: np.ndarray, end: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pair the boxes found at the start (S, 2) with those found at the end (E, 2), the sum of
    the pairs' distances least: (start, end) of the pairs, each (min(S, E), 2), in pair order,
    then the start's and the end's boxes left without a pair."""
    from scipy.optimize import linear_sum_assignment

    start = np.asarray(start, dtype=float).reshape(-1, 2)
    end = np.asarray(end, dtype=float).reshape(-1, 2)
    if not len(start) or not len(end):
        return np.zeros((0, 2)), np.zeros((0, 2)), start, end
    cost = np.hypot(start[:, None, 0] - end[None, :, 0], start[:, None, 1] - end[None, :, 1])
    rows, cols = linear_sum_assignment(cost)
    left_start = np.setdiff1d(np.arange(len(start)), rows)
    left_end = np.setdiff1d(np.arange(len(end)), cols)
    return start[rows], end[cols], start[left_start], end[left_end]


def _scale(camera: CameraModel) -> float:
    # Pixels per metre on the floor at the image of the floor's centre.
    points = camera.to_image(np.array([[0.0, 0.0], [0.1, 0.0], [0.0, 0.1]]))
    return float((np.hypot(*(points[1] - points[0])) + np.hypot(*(points[2] - points[0]))) * 5)


def _floor_mask(
    camera: CameraModel,
    floor: Floor,
    robots: Sequence[tuple[float, float, float]],
    robot_height: float,
    size: tuple[int, int],
) -> np.ndarray:
    # 1 where a box may be seen: inside the floor, off the corner markers and the robots.
    mask = np.zeros((size[1], size[0]), np.uint8)
    w, h = floor.width / 2, floor.height / 2
    outline = camera.to_image(np.array([[-w, -h], [w, -h], [w, h], [-w, h]]))
    cv2.fillConvexPoly(mask, np.round(outline).astype(np.int32), 1)
    for corners in floor.corner_points().values():
        grown = corners.mean(axis=0) + (corners - corners.mean(axis=0)) * 1.3
        cv2.fillConvexPoly(mask, np.round(camera.to_image(grown)).astype(np.int32), 0)
    body, blade = robot_outline()
    for x, y, heading in robots:
        c, s = math.cos(heading), math.sin(heading)
        for shape, top in ((body, robot_height), (blade, _BLADE_HEIGHT)):
            placed = np.column_stack(
                [x + c * shape[:, 0] - s * shape[:, 1], y + s * shape[:, 0] + c * shape[:, 1]]
            )
            seen = np.vstack([camera.to_image(placed), camera.to_image(placed, top)])
            hull = cv2.convexHull(seen.astype(np.float32))
            cv2.fillConvexPoly(mask, np.round(hull).astype(np.int32), 0)
    # The robots' edges blur into the floor: keep a few pixels off them.
    return cv2.erode(mask, np.ones((5, 5), np.uint8))
