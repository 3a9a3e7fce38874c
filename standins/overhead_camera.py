"""A synthetic overhead camera: the video a lab's camera would take of a simulated post-evaluation.

It stands in for the camera over the arena (``surprise-master track`` reads its frames as it reads
a webcam's): the floor with the four corner markers, the boxes, and each robot's body with its
ArUco marker on top, seen by a pinhole camera a little off the vertical and turned, with what
makes a real picture hard: motion blur along each robot's motion, sensor noise, light falling
off towards the corners, one robot's marker hidden for a while (a cable, a hand), and the robots'
top LEDs flashing a colour when the post-evaluation starts. Every random draw is seeded.

The poses and boxes are a simulator's: the trace's ``poses`` (steps, N, 3), pose k at
``k * dt`` seconds after the start, and the boxes' positions (frames, B, 2), one frame every
``box_every`` steps, with the last entry the boxes after the last step. Before the start the
robots stand at their first pose for ``pre_roll`` seconds; after the end at their last.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

__all__ = ["OverheadScene", "OverheadVideo", "camera_matrix"]

#: Colours (BGR) of the floor outside the carpet, the carpet, beyond the floor and the boxes.
_MARGIN = (196, 200, 202)
_CARPET = (122, 143, 156)
_BEYOND = (70, 72, 75)
_BOX_TOP = (80, 150, 205)
_BOX_SIDE = (55, 105, 150)
_BODY_TOP = (232, 234, 236)
_BODY_SIDE = (170, 172, 176)
_BLADE = (60, 60, 60)
_FLASH = (40, 40, 250)
_HIDER = (90, 110, 95)
#: The Thymio II's outline in its own frame (metres, x forward from the wheel axis): a front arc
#: of 8 cm radius around the axle, a flat rear 3 cm behind it, 11 cm wide.
_SIDE_ANGLE = math.asin(0.055 / 0.08)
_OUTLINE = np.array(
    [(0.08 * math.cos(a), 0.08 * math.sin(a)) for a in np.linspace(-_SIDE_ANGLE, _SIDE_ANGLE, 13)]
    + [(-0.03, 0.055), (-0.03, -0.055)]
)


@dataclass(frozen=True)
class OverheadScene:
    """What the camera looks at and how it hangs (metres and degrees unless said).

    ``floor`` is the rectangle between the corner markers' black squares' outer corners (centred
    on the origin; each sheet's white margin lies around its square),
    ``carpet`` the carpet the robots drive on, its side or its (width, height); ``robots`` the
    robot ids in the poses' order and ``markers`` their marker ids. The camera stands ``height``
    above the point ``nadir``, its optical axis aimed at ``aim`` on the floor and turned ``roll``
    about it.
    """

    floor: tuple[float, float] = (1.3, 1.3)
    carpet: float | tuple[float, float] = 1.1
    robots: tuple[str, ...] = ()
    markers: tuple[int, ...] = ()
    corner_ids: tuple[int, int, int, int] = (0, 1, 2, 3)
    corner_size: float = 0.10
    marker_size: float = 0.06
    marker_height: float = 0.055
    marker_offset: tuple[float, float] = (0.02, 0.0)
    box_size: float = 0.025
    blade_x: float | None = 0.09
    image_size: tuple[int, int] = (1280, 720)
    height: float = 2.0
    nadir: tuple[float, float] = (0.06, -0.10)
    aim: tuple[float, float] = (0.0, 0.0)
    roll: float = 1.5
    #: camera frames per second
    fps: float = 10.0
    #: the share of a frame's period the shutter is open (motion blur)
    exposure: float = 0.5
    #: the sensor noise's standard deviation in grey levels
    noise: float = 3.0
    #: how much darker the floor's corners are than its centre (0: even light)
    vignette: float = 0.35
    dictionary: int = cv2.aruco.DICT_4X4_50


def camera_matrix(scene: OverheadScene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The scene's pinhole camera: intrinsics K (3, 3), rotation R world-to-camera (3, 3) and
    centre C (3,), the principal point at the image's centre, the floor filling the image."""
    centre = np.array([scene.nadir[0], scene.nadir[1], scene.height])
    z = np.array([scene.aim[0], scene.aim[1], 0.0]) - centre
    z /= np.linalg.norm(z)
    x = np.array([1.0, 0.0, 0.0]) - z[0] * z
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    roll = math.radians(scene.roll)
    x, y = math.cos(roll) * x + math.sin(roll) * y, -math.sin(roll) * x + math.cos(roll) * y
    rotation = np.vstack([x, y, z])
    width, height = scene.image_size
    # The floor and a 6 % border fill the shorter way of the image.
    reach = 1.06 * max(abs(c) / 2 + abs(o) for c, o in zip(scene.floor, scene.nadir, strict=True))
    focal = min(width, height) / 2 * (scene.height - scene.marker_height) / reach
    k = np.array([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1.0]])
    return k, rotation, centre


@dataclass
class OverheadVideo:
    """The frames of ``scene`` seeing ``poses`` (steps, N, 3) and ``boxes`` (frames, B, 2).

    ``dt``: seconds per step; ``box_every``: steps between box frames. ``pre_roll`` and
    ``post_roll``: seconds before the start and after the end. ``flash``: seconds the LEDs
    stay lit from the start. ``hidden``: (robot index, from, to) seconds after the start when
    that robot's marker is covered. ``seed``: every random draw's.
    """

    scene: OverheadScene
    poses: np.ndarray
    boxes: np.ndarray | None = None
    dt: float = 0.1
    box_every: int = 1
    pre_roll: float = 1.0
    post_roll: float = 0.5
    flash: float = 0.3
    hidden: Sequence[tuple[int, float, float]] = ()
    seed: int = 0
    _background: np.ndarray = field(init=False, repr=False)
    _light: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.k, self.rotation, self.centre = camera_matrix(self.scene)
        self._rng = np.random.default_rng(self.seed)
        self._background = self._floor()
        self._light = self._lighting()
        self._noise = self._noise_bank(6)
        dictionary = cv2.aruco.getPredefinedDictionary(self.scene.dictionary)
        self._marker_images = {
            m: _bordered(cv2.aruco.generateImageMarker(dictionary, m, 60))
            for m in self.scene.markers
        }

    # --- geometry ------------------------------------------------------------------------------

    @property
    def duration(self) -> float:
        """Seconds from the start (the flash) to the end of the poses."""
        return len(self.poses) * self.dt

    @property
    def frame_count(self) -> int:
        """Frames in the whole video, pre- and post-roll included."""
        total = self.pre_roll + self.duration + self.post_roll
        return math.floor(total * self.scene.fps + 1e-9)

    def frame_time(self, index: int) -> float:
        """Seconds after the start of frame ``index`` (negative before the start)."""
        return index / self.scene.fps - self.pre_roll

    def project(self, points: np.ndarray, z: float | np.ndarray = 0.0) -> np.ndarray:
        """Floor points (n, 2) at height ``z``, in pixels (n, 2)."""
        p = np.asarray(points, dtype=float).reshape(-1, 2)
        world = np.column_stack([p, np.broadcast_to(z, (len(p),))])
        cam = (world - self.centre) @ self.rotation.T
        uv = cam[:, :2] / cam[:, 2:3]
        return uv * self.k[0, 0] + self.k[:2, 2]

    def poses_at(self, t: float) -> np.ndarray:
        """The robots' poses (N, 3) ``t`` seconds after the start: the first before it, the last
        after the end, linear between steps (the heading the short way round)."""
        k = t / self.dt
        if k <= 0:
            return self.poses[0].copy()
        last = len(self.poses) - 1
        if k >= last:
            return self.poses[last].copy()
        i = math.floor(k)
        w = k - i
        a, b = self.poses[i], self.poses[i + 1]
        turn = (b[:, 2] - a[:, 2] + math.pi) % (2 * math.pi) - math.pi
        out = a + w * (b - a)
        out[:, 2] = a[:, 2] + w * turn
        return out

    def boxes_at(self, t: float) -> np.ndarray:
        """The boxes' positions (B, 2) ``t`` seconds after the start."""
        assert self.boxes is not None
        k = min(max(t / (self.dt * self.box_every), 0.0), len(self.boxes) - 1)
        i = min(math.floor(k), len(self.boxes) - 2) if len(self.boxes) > 1 else 0
        if len(self.boxes) == 1:
            return self.boxes[0]
        w = k - i
        return self.boxes[i] + w * (self.boxes[i + 1] - self.boxes[i])

    # --- the still parts -----------------------------------------------------------------------

    def _floor(self) -> np.ndarray:
        # The floor, carpet and corner markers, drawn in floor metres at 1 mm and warped into
        # the image at twice its resolution, then shrunk by area: no aliasing on the markers.
        s = self.scene
        res = 0.001
        half_w, half_h = s.floor[0] / 2 + 0.3, s.floor[1] / 2 + 0.3
        cols, rows = round(2 * half_w / res), round(2 * half_h / res)
        texture = np.empty((rows, cols, 3), np.uint8)
        texture[:] = _BEYOND

        def box(x0: float, y0: float, x1: float, y1: float) -> tuple[slice, slice]:
            return (
                slice(round((half_h - y1) / res), round((half_h - y0) / res)),
                slice(round((x0 + half_w) / res), round((x1 + half_w) / res)),
            )

        texture[box(-s.floor[0] / 2, -s.floor[1] / 2, s.floor[0] / 2, s.floor[1] / 2)] = _MARGIN
        cw, ch = s.carpet if isinstance(s.carpet, tuple) else (s.carpet, s.carpet)
        texture[box(-cw / 2, -ch / 2, cw / 2, ch / 2)] = _CARPET
        dictionary = cv2.aruco.getPredefinedDictionary(s.dictionary)
        side = round(s.corner_size / res)
        w, h, c = s.floor[0] / 2, s.floor[1] / 2, s.corner_size
        for marker, (x, y) in zip(
            s.corner_ids, [(-w, -h), (w - c, -h), (w - c, h - c), (-w, h - c)], strict=True
        ):
            image = cv2.aruco.generateImageMarker(dictionary, marker, side)
            # The printed sheet's white margin, a cell wide, around the black square.
            texture[box(x - c / 6, y - c / 6, x + 7 * c / 6, y + 7 * c / 6)] = 255
            region = box(x, y, x + c, y + c)
            texture[region] = cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)[
                : region[0].stop - region[0].start, : region[1].stop - region[1].start
            ]
        to_floor = np.array([[res, 0, -half_w], [0, -res, half_h], [0, 0, 1.0]])
        big = 2
        scale = np.diag([big, big, 1.0])
        size = (s.image_size[0] * big, s.image_size[1] * big)
        warped = cv2.warpPerspective(
            texture, scale @ self._homography() @ to_floor, size, flags=cv2.INTER_LINEAR
        )
        return cv2.resize(warped, s.image_size, interpolation=cv2.INTER_AREA)

    def _homography(self) -> np.ndarray:
        # Floor (x, y, 1) to pixels.
        r, c = self.rotation, self.centre
        m = self.k @ np.column_stack([r[:, 0], r[:, 1], -r @ c])
        return m / m[2, 2]

    def _lighting(self) -> np.ndarray:
        # Light falling off from a point near the centre, as 0-255 gains for cv2.multiply.
        width, height = self.scene.image_size
        u, v = np.meshgrid(np.arange(width), np.arange(height))
        cx, cy = 0.45 * width, 0.55 * height
        r2 = ((u - cx) ** 2 + (v - cy) ** 2) / (0.5 * width) ** 2
        gain = 1.0 - self.scene.vignette * np.clip(r2, 0, 1.5) / 1.5
        return cv2.merge([np.clip(gain * 255, 0, 255).astype(np.uint8)] * 3)

    def _noise_bank(self, count: int) -> list[tuple[np.ndarray, np.ndarray]]:
        # A few seeded noise frames, split into what is added and what is taken away, so a frame
        # costs two saturating additions (cycled: a viewer sees no pattern in a few frames).
        width, height = self.scene.image_size
        bank = []
        for _ in range(count):
            n = self._rng.normal(0.0, self.scene.noise, (height, width, 3))
            bank.append((np.clip(n, 0, 255).astype(np.uint8), np.clip(-n, 0, 255).astype(np.uint8)))
        return bank

    # --- one frame -----------------------------------------------------------------------------

    def frames(self) -> Iterator[tuple[float, np.ndarray]]:
        """Every frame of the video with its time on the video's clock (seconds from the first
        frame, as a video file's are; :meth:`frame_time` is the time after the start)."""
        for index in range(self.frame_count):
            yield index / self.scene.fps, self.render(index)

    def render(self, index: int) -> np.ndarray:
        """Frame ``index`` (BGR, uint8)."""
        t = self.frame_time(index)
        frame = self._background.copy()
        if self.boxes is not None and len(self.boxes[0]):
            self._draw_boxes(frame, self.boxes_at(t))
        poses = self.poses_at(t)
        period = self.scene.exposure / self.scene.fps
        before = self.poses_at(t - period / 2)
        after = self.poses_at(t + period / 2)
        lit = 0.0 <= t < self.flash
        for i in range(len(poses)):
            covered = any(r == i and t0 <= t < t1 for r, t0, t1 in self.hidden)
            self._draw_robot(frame, i, poses[i], before[i], after[i], lit=lit, covered=covered)
        frame = cv2.multiply(frame, self._light, scale=1 / 255)
        add, take = self._noise[index % len(self._noise)]
        return cv2.subtract(cv2.add(frame, add), take)

    def _draw_boxes(self, frame: np.ndarray, centres: np.ndarray) -> None:
        half = self.scene.box_size / 2
        square = np.array([(-half, -half), (half, -half), (half, half), (-half, half)])
        corners = centres[:, None, :] + square[None]
        flat = corners.reshape(-1, 2)
        bottom = self.project(flat, 0.0).reshape(-1, 4, 2)
        top = self.project(flat, self.scene.box_size).reshape(-1, 4, 2)
        shift = 4  # sub-pixel vertices: 1/16 pixel
        for b, t in zip(bottom, top, strict=True):
            hull = cv2.convexHull(np.vstack([b, t]).astype(np.float32))
            cv2.fillConvexPoly(frame, _fixed(hull, shift), _BOX_SIDE, cv2.LINE_AA, shift)
            cv2.fillConvexPoly(frame, _fixed(t, shift), _BOX_TOP, cv2.LINE_AA, shift)

    def _draw_robot(
        self,
        frame: np.ndarray,
        index: int,
        pose: np.ndarray,
        before: np.ndarray,
        after: np.ndarray,
        *,
        lit: bool,
        covered: bool,
    ) -> None:
        s = self.scene
        top_h = s.marker_height - 0.002
        outline = _place(_OUTLINE, pose)
        reach = self.project(outline, top_h)
        x0, y0 = np.floor(reach.min(axis=0)).astype(int) - 12
        x1, y1 = np.ceil(reach.max(axis=0)).astype(int) + 12
        height, width = frame.shape[:2]
        x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, width), min(y1, height)
        if x1 <= x0 or y1 <= y0:
            return
        patch = frame[y0:y1, x0:x1].copy()
        origin = np.array([x0, y0], dtype=float)
        shift = 4
        body = np.vstack([self.project(outline, 0.0), reach]) - origin
        cv2.fillConvexPoly(
            patch, _fixed(cv2.convexHull(body.astype(np.float32)), shift), _BODY_SIDE,
            cv2.LINE_AA, shift,
        )  # fmt: skip
        if s.blade_x is not None:
            bar = np.array([(s.blade_x - 0.005, -0.06), (s.blade_x + 0.005, -0.06),
                            (s.blade_x + 0.005, 0.06), (s.blade_x - 0.005, 0.06)])  # fmt: skip
            blade = self.project(_place(bar, pose), 0.02) - origin
            cv2.fillConvexPoly(patch, _fixed(blade, shift), _BLADE, cv2.LINE_AA, shift)
        top_colour = _FLASH if lit else _BODY_TOP
        cv2.fillPoly(patch, [_fixed(reach - origin, shift)], top_colour, cv2.LINE_AA, shift)
        # The marker with its white margin, warped onto the top.
        half = s.marker_size / 2 * (8 / 6)  # the image holds 6 cells and a cell of white margin
        cx, cy = s.marker_offset
        square = np.array([(cx + half, cy + half), (cx + half, cy - half),
                           (cx - half, cy - half), (cx - half, cy + half)])  # fmt: skip
        # In the robot's frame x is forward: the marker's top edge (image row 0) is the front.
        image_corners = self.project(_place(square, pose), s.marker_height) - origin
        marker = self._marker_images[s.markers[index]]
        size = marker.shape[0]
        source = np.array([[0, 0], [size, 0], [size, size], [0, size]], dtype=np.float32)
        # Image corners in order: front-left, front-right, rear-right, rear-left.
        target = image_corners[[0, 1, 2, 3]].astype(np.float32)
        warp = cv2.getPerspectiveTransform(source, target)
        big = 4
        up = np.diag([big, big, 1.0]).astype(np.float64)
        shape = (patch.shape[1] * big, patch.shape[0] * big)
        ink = cv2.warpPerspective(marker, up @ warp, shape, flags=cv2.INTER_LINEAR)
        mask = cv2.warpPerspective(np.full_like(marker, 255), up @ warp, shape)
        ink = cv2.resize(ink, patch.shape[1::-1], interpolation=cv2.INTER_AREA)
        mask = cv2.resize(mask, patch.shape[1::-1], interpolation=cv2.INTER_AREA)
        alpha = (mask.astype(np.float32) / 255)[..., None]
        patch[:] = (patch * (1 - alpha) + cv2.cvtColor(ink, cv2.COLOR_GRAY2BGR) * alpha).astype(
            np.uint8
        )
        if covered:
            # Something lying across the marker: a cable's bend, a hand.
            blot = self.project(_place(square * 0.9, pose), s.marker_height + 0.01) - origin
            cv2.fillConvexPoly(patch, _fixed(blot, shift), _HIDER, cv2.LINE_AA, shift)
        patch = self._blur(patch, before, after)
        frame[y0:y1, x0:x1] = patch

    def _blur(self, patch: np.ndarray, before: np.ndarray, after: np.ndarray) -> np.ndarray:
        # The shutter open while the robot moved from ``before`` to ``after``: a line kernel along
        # that motion in the image (rotation blurs little at these speeds; it is left out).
        a, b = self.project(np.vstack([before[:2], after[:2]]), self.scene.marker_height)
        length = float(np.hypot(*(b - a)))
        if length < 0.5:
            return patch
        size = math.ceil(length) | 1
        kernel = np.zeros((size + 2, size + 2), np.float32)
        centre = (size + 1) / 2
        direction = (b - a) / length
        for s in np.linspace(-length / 2, length / 2, 4 * size + 1):
            x, y = centre + s * direction
            kernel[round(y), round(x)] += 1
        kernel /= kernel.sum()
        return cv2.filter2D(patch, -1, kernel, borderType=cv2.BORDER_REPLICATE)

    def write(self, path: str | Path, fourcc: str = "mp4v") -> Path:
        """Write the video to ``path`` (``fourcc``: the codec, ``mp4v`` for an .mp4 file)."""
        path = Path(path)
        writer = cv2.VideoWriter(
            str(path), cv2.VideoWriter.fourcc(*fourcc), self.scene.fps, self.scene.image_size
        )
        if not writer.isOpened():
            raise OSError(f"{path}: OpenCV cannot write a {fourcc} video")
        try:
            for _, frame in self.frames():
                writer.write(frame)
        finally:
            writer.release()
        return path


def _place(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    # Points of a robot's frame (x forward, y left) on the floor at ``pose``.
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.column_stack(
        [
            pose[0] + c * points[:, 0] - s * points[:, 1],
            pose[1] + s * points[:, 0] + c * points[:, 1],
        ]
    )


def _fixed(points: np.ndarray, shift: int) -> np.ndarray:
    # Pixel coordinates as the fixed-point integers cv2's polygon fills take with ``shift``.
    return np.round(np.asarray(points).reshape(-1, 2) * (1 << shift)).astype(np.int32)


def _bordered(marker: np.ndarray) -> np.ndarray:
    # A printed marker: a white margin of one cell around the black square.
    cell = marker.shape[0] // 6
    return cv2.copyMakeBorder(marker, cell, cell, cell, cell, cv2.BORDER_CONSTANT, value=255)
