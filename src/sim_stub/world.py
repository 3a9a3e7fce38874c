"""The kinematic arena: Thymio II robots on a carpet, walls, boxes, a lamp, and their sensors.

Everything is vectorised over robots and boxes with numpy; one :meth:`World.step` advances all
robots by ``dt`` with the wheel commands last set, then pushes apart whatever overlaps. The world
knows nothing of asyncio; :mod:`sim_stub.body` drives it in lockstep or in real time.

Models (every number is a field of :class:`~sim_stub.scenarios.WorldConfig`):

* Motion: exact differential-drive arcs for constant wheel speeds over one step.
* Bodies: a circle per robot (see ``WorldConfig``) for the IR and robot-robot contacts. Robots
  with a force sensor also carry a blade, a bar across their front that robots' bodies meet too;
  for boxes such a robot is one convex outline, a rectangle with rounded corners from its flat
  rear to the blade's face. Boxes are discs of diameter ``box_size``.
* Contacts, each step: robots push each other apart (half each) and are kept inside the walls;
  then robots push boxes and boxes push boxes, the box farther down a pushing chain giving way.
  A box held by a wall, or wedged between a robot and other boxes, cannot give way: the box or
  robot pushing it is moved back instead (boxes weigh a few grams; they never push a robot
  otherwise). A robot still wedged among boxes after that stays where it was before the step
  and the boxes settle around it. Robots moved by boxes are parted again (a few rounds at most).
  Overlaps shallower than 10 um are left alone; in dense jams of many bladed robots a box may
  stay a few millimetres inside a robot for a step. Blades are not kept apart from each other.
* Horizontal IR: the nearest distance ``d`` within a cone of half angle ``ir_aperture`` around each
  sensor's axis to another robot's body or to an IR-visible wall gives ``c / (d^2 + c)`` when
  ``d < ir_range``, else 0: about 1 at contact and 0.27 at 14 cm, as the Thymio's 0..4500 scale
  reads (REFERENCE section 4). Boxes are too low to be seen.
* Ground: ``ground_carpet`` over the carpet, ``ground_outside`` beyond its edge.
* Force: ``force_per_box`` times the number of boxes the robot's blade moved this step, directly
  or through a chain of boxes, capped at 1. A robot that stands still or backs off feels nothing.
* Light: with a lamp, inverse-square fall-off from ``light_centre`` under it to ``light_corner``
  at the carpet's corners; otherwise ``light_uniform`` everywhere.
* Noise: Gaussian, drawn once per step for every robot (so the values do not depend on who reads
  them when), added and clipped to [0, 1].

Determinism: every random draw comes from generators seeded by ``seed``; the same seed and the
same commands give the same trajectories bit for bit.
"""

from __future__ import annotations

import math

import numpy as np

from drivers.body import clamp_unit
from sim_stub.scenarios import WorldConfig
from surprise.errors import ConfigError
from surprise.sensors import ALL_SENSORS

# Thymio II sensor geometry (REFERENCE section 5, Enki's model), metres and radians, robot frame:
# x forward, y left, origin between the wheels.
IR_POSITIONS = np.array(
    [
        [0.062, 0.0485],
        [0.075, 0.0255],
        [0.0795, 0.0],
        [0.075, -0.0255],
        [0.062, -0.0485],
        [-0.0295, 0.0295],
        [-0.0295, -0.0295],
    ]
)
IR_HEADINGS = np.radians([40.0, 20.0, 0.0, -20.0, -40.0, 180.0, 180.0])
GROUND_POSITIONS = np.array([[0.072, 0.012], [0.072, -0.012]])

_IR = slice(0, 7)
_GROUND = slice(7, 9)
_FORCE = 9
_LIGHT = slice(10, 12)
assert ALL_SENSORS[_FORCE] == "force" and ALL_SENSORS[_LIGHT] == ("light.0", "light.1")

_TWO_PI = 2.0 * math.pi
# The Thymio II's flat rear is 3 cm behind its wheel axis (REFERENCE section 5).
_REAR = 0.03
# Overlaps shallower than this (metres) are left alone: resolving them exactly would take many
# more passes for nothing anyone could measure (boxes and robots are a few centimetres).
_SLOP = 1e-5
# At most this many passes of robot-robot separation per step (most steps need none or one;
# pile-ups of several robots against a wall need more).
_ROBOT_PASSES = 8
# Rounds of settling boxes around robots wedged among them (see World._push_boxes).
_SETTLE_ROUNDS = 3
# Rounds of robot separation and box pushing per step (see World.step).
_CONTACT_ROUNDS = 3
# Placement draws candidate positions in batches of _BATCH, gives up on one robot after
# _MAX_TRIES candidates and on the arena after _PLACEMENT_RESTARTS fresh starts.
_BATCH = 64
_MAX_TRIES = 4_096
_PLACEMENT_RESTARTS = 20


class _Chains:
    """Book-keeping of one step's box pushing (see World._relax)."""

    __slots__ = ("backoffs", "gave", "held", "owner", "pushed", "pusher", "rank")

    def __init__(self, boxes: int, robots: int) -> None:
        # Who gives way when two boxes overlap: the one of higher rank. A box a robot touches
        # ranks 1 + (its distance from that robot) / 10, a box pushed by a box one more than
        # its pusher (plus its own distance / 10): the chain's far end gives way and ties are
        # rare, so a chain settles in about as many passes as it has links.
        self.rank = np.full(boxes, np.inf)
        self.pusher = np.full(boxes, -1, dtype=np.intp)  # the robot that started the push
        self.owner = np.full(boxes, -1, dtype=np.intp)  # the robot whose blade did (force)
        self.held = np.zeros(boxes, dtype=bool)  # cannot give way (wall, held box, robot)
        self.pushed = np.zeros((boxes, robots), dtype=bool)  # robots that pushed it
        self.gave = np.zeros(boxes, dtype=bool)  # it gave way all of an overlap with a box
        self.backoffs = np.zeros(robots, dtype=np.intp)  # times a robot backed off a held box


def wrap_angle(theta: np.ndarray | float) -> np.ndarray | float:
    """Angles wrapped to [-pi, pi)."""
    return (theta + math.pi) % _TWO_PI - math.pi


class World:
    """A shared arena of ``config.robots`` robots (and boxes), seeded by ``seed``.

    ``record=True`` keeps the poses of every step (see :meth:`recorded_poses`).
    """

    def __init__(self, config: WorldConfig, seed: int = 0, *, record: bool = False) -> None:
        self.config = config
        n = config.robots
        self._n = n
        self._columns = np.array([ALL_SENSORS.index(s) for s in config.sensors], dtype=np.intp)
        names = set(config.sensors)
        self._need_ir = any(s.startswith("ir.") for s in names)
        self._need_ground = any(s.startswith("ground.") for s in names)
        self._need_force = "force" in names
        self._need_light = any(s.startswith("light.") for s in names)

        # Constants of the step, computed once.
        self._half_vmax = 0.5 * config.max_speed
        self._vmax_over_base = config.max_speed / config.wheel_base
        self._blade = config.has_blade
        self._rb = config.box_size / 2
        self._tb = config.blade_thickness / 2
        self._hw = config.blade_width / 2
        # Outline that boxes meet on a robot with a blade: rectangle core x0..x1, -hy..hy in the
        # robot's frame grown by rr; the flat Thymio rear is _REAR behind the wheels.
        rr = self._tb
        self._hull = (rr - _REAR, config.blade_x, max(self._hw - rr, 0.0), rr)
        # How far a robot's shapes reach from its wheel axis and from its body centre.
        self._reach = config.body_offset + config.robot_radius
        self._body_reach = config.robot_radius
        if self._blade:
            hx = np.array([-_REAR, config.blade_x + rr])
            hy = self._hull[2] + rr
            self._reach = max(self._reach, float(np.hypot(hx, hy).max()))
            off = hx - config.body_offset
            self._body_reach = max(self._body_reach, float(np.hypot(off, hy).max()))
        # Boxes farther than this from a robot's wheel axis cannot touch it during a step.
        self._box_reach2 = (self._reach + self._rb + 2 * config.max_speed * config.dt + 0.01) ** 2
        # Added to pair distances, it keeps each robot out of its own collision and IR tests.
        self._self_far = np.where(np.eye(n, dtype=bool), 1e6, 0.0)
        self._not_self = ~np.eye(n, dtype=bool)
        self._pair_sign = np.where(np.arange(n)[:, None] > np.arange(n)[None, :], 1.0, -1.0)
        ap = math.radians(config.ir_aperture)
        self._ca, self._sa = math.cos(ap), math.sin(ap)
        corner2 = 2 * (config.arena_side / 2) ** 2
        if config.light:
            fall = config.light_centre - config.light_corner
            self._lamp_h2 = config.light_corner * corner2 / fall
        self._light_xy = np.array(config.light_sensor_offsets, dtype=float)
        self._full = np.zeros((n, len(ALL_SENSORS)))
        if not config.light:
            self._full[:, _LIGHT] = config.light_uniform

        self._pose = np.zeros((n, 3))
        self._cmd = np.zeros((n, 2))
        self._force = np.zeros(n)
        self._boxes = np.zeros((0, 2))
        self._recording: list[np.ndarray] | None = [] if record else None
        self.reset(seed)

    # --- set-up --------------------------------------------------------------------------------

    def reset(self, seed: int | None = None) -> None:
        """Place robots and boxes anew (as at construction, with ``seed`` if given) at time 0.

        Commands are set to zero; a recording restarts from the new poses.
        """
        if seed is not None:
            self.seed = int(seed)
        start_ss, box_ss, noise_ss = np.random.SeedSequence(self.seed).spawn(3)
        self._noise_rng = np.random.default_rng(noise_ss)
        self._cmd[:] = 0.0
        self._force[:] = 0.0
        self._steps = 0
        self._place_robots(np.random.default_rng(start_ss))
        self._boxes = self._place_boxes(np.random.default_rng(box_ss))
        self._box_start = self._boxes.copy()
        self._box_start.flags.writeable = False
        self._pending = np.zeros(len(self._boxes), dtype=bool)
        self._cache: np.ndarray | None = None
        self._draw_noise()
        if self._recording is not None:
            self._recording = [self._pose.copy()]

    def _place_robots(self, rng: np.random.Generator) -> None:
        cfg = self.config
        n = self._n
        rp = self._body_reach
        half = cfg.arena_side / 2
        if cfg.start == "centre":
            # A fixed ring around the centre, each robot facing outwards, neighbours just apart.
            gap = 2 * rp + cfg.start_clearance
            ring = 0.0 if n == 1 else gap / (2 * math.sin(math.pi / n))
            if ring + rp > half:
                raise ConfigError(
                    f"{n} robots do not fit around the centre of the arena",
                    key="simulation.robots",
                )
            phi = _TWO_PI * np.arange(n) / n + math.pi / 4
            centre = ring - cfg.body_offset
            self._pose[:, 0] = centre * np.cos(phi)
            self._pose[:, 1] = centre * np.sin(phi)
            self._pose[:, 2] = wrap_angle(phi)
            return
        # Random: bodies wholly on the carpet, apart by the clearance, in seeded order. Robots
        # placed one by one can box themselves in on a crowded carpet; then all start afresh.
        lim = half - rp
        if lim <= 0:
            raise ConfigError("the arena is too small for a robot", key="simulation.arena_side")
        min_d2 = (2 * rp + cfg.start_clearance) ** 2
        for _ in range(_PLACEMENT_RESTARTS):
            centres = self._random_centres(rng, n, lim, min_d2)
            if centres is not None:
                break
        else:
            raise ConfigError(
                f"cannot place {n} robots apart on a {cfg.arena_side} m carpet",
                key="simulation.robots",
            )
        theta = rng.uniform(-math.pi, math.pi, size=n)
        self._pose[:, 0] = centres[:, 0] - cfg.body_offset * np.cos(theta)
        self._pose[:, 1] = centres[:, 1] - cfg.body_offset * np.sin(theta)
        self._pose[:, 2] = theta

    @staticmethod
    def _random_centres(
        rng: np.random.Generator, n: int, lim: float, min_d2: float
    ) -> np.ndarray | None:
        # Body centres in [-lim, lim]^2, pairwise at least sqrt(min_d2) apart, or None.
        placed = np.empty((n, 2))
        for i in range(n):
            for _ in range(_MAX_TRIES // _BATCH):
                cand = rng.uniform(-lim, lim, size=(_BATCH, 2))
                d2 = ((cand[:, None, :] - placed[None, :i, :]) ** 2).sum(axis=2)
                ok = np.flatnonzero((d2 >= min_d2).all(axis=1))
                if ok.size:
                    placed[i] = cand[ok[0]]
                    break
            else:
                return None
        return placed

    def _place_boxes(self, rng: np.random.Generator) -> np.ndarray:
        cfg = self.config
        count = cfg.box_count
        if count == 0:
            return np.zeros((0, 2))
        rb = self._rb
        lim = cfg.arena_side / 2 - rb
        rp = self._body_reach
        th = self._pose[:, 2]
        rcx = self._pose[:, 0] + cfg.body_offset * np.cos(th)
        rcy = self._pose[:, 1] + cfg.body_offset * np.sin(th)
        away2 = (rp + rb + cfg.start_clearance) ** 2
        apart2 = (cfg.box_size + 0.001) ** 2
        out = np.empty((count, 2))
        k = 0
        tries = 0
        while k < count:
            if tries >= 50 * count + _MAX_TRIES:
                raise ConfigError(
                    f"cannot place {count} boxes apart on the carpet", key="simulation.box_coverage"
                )
            cand = rng.uniform(-lim, lim, size=(4 * _BATCH, 2))
            tries += len(cand)
            d2 = (cand[:, 0, None] - rcx) ** 2 + (cand[:, 1, None] - rcy) ** 2
            cand = cand[(d2 >= away2).all(axis=1)]
            # Accept in order, each against every box accepted so far (a one-off cost at set-up).
            for c in cand:
                if k and (((out[:k] - c) ** 2).sum(axis=1) < apart2).any():
                    continue
                out[k] = c
                k += 1
                if k == count:
                    break
        return out

    # --- state ---------------------------------------------------------------------------------

    @property
    def n_robots(self) -> int:
        """Number of robots."""
        return self._n

    @property
    def sensors(self) -> tuple[str, ...]:
        """Names of the values :meth:`sensor_values` returns, in that order."""
        return self.config.sensors

    @property
    def poses(self) -> np.ndarray:
        """Read-only (N, 3) view of every robot's ``x, y, theta`` (metres, radians in [-pi, pi))."""
        view = self._pose.view()
        view.flags.writeable = False
        return view

    @property
    def commands(self) -> np.ndarray:
        """Read-only (N, 2) view of the normalised wheel commands ``left, right``."""
        view = self._cmd.view()
        view.flags.writeable = False
        return view

    @property
    def box_positions(self) -> np.ndarray:
        """Read-only (B, 2) view of the box centres."""
        view = self._boxes.view()
        view.flags.writeable = False
        return view

    @property
    def box_start_positions(self) -> np.ndarray:
        """The box centres at the last :meth:`reset` (for the box displacement d_B)."""
        return self._box_start

    @property
    def forces(self) -> np.ndarray:
        """Force value of each robot for the last step (0 without blade or boxes)."""
        return self._force.copy()

    @property
    def steps(self) -> int:
        """Steps taken since the last reset."""
        return self._steps

    @property
    def time(self) -> float:
        """World time in seconds: ``steps * dt`` (computed, so it never drifts)."""
        return self._steps * self.config.dt

    def set_command(self, index: int, left: float, right: float) -> None:
        """Set robot ``index``'s wheel speeds, normalised to [-1, 1] (clamped; NaN is 0).

        The command holds for every following step until it is set again, as on a real robot.
        """
        self._cmd[index, 0] = clamp_unit(left)
        self._cmd[index, 1] = clamp_unit(right)

    def set_commands(self, commands: np.ndarray) -> None:
        """Set every robot's command at once from an (N, 2) array (clamped; NaN is 0)."""
        cmd = np.nan_to_num(np.asarray(commands, dtype=float), nan=0.0)
        np.clip(cmd, -1.0, 1.0, out=self._cmd)

    def set_pose(self, index: int, x: float, y: float, theta: float) -> None:
        """Put robot ``index`` at a pose (no overlap check: for tests and tools)."""
        self._pose[index] = (x, y, wrap_angle(theta))
        self._cache = None

    def set_box_positions(self, positions: np.ndarray) -> None:
        """Replace the boxes (and their start positions) by ``positions`` (B, 2); for tests."""
        self._boxes = np.array(positions, dtype=float).reshape(-1, 2)
        self._box_start = self._boxes.copy()
        self._box_start.flags.writeable = False
        self._pending = np.zeros(len(self._boxes), dtype=bool)
        self._cache = None

    # --- recording -----------------------------------------------------------------------------

    def start_recording(self) -> None:
        """Record the poses of every following step, starting with the current ones."""
        self._recording = [self._pose.copy()]

    def stop_recording(self) -> np.ndarray:
        """Stop recording and return what was recorded (see :meth:`recorded_poses`)."""
        poses = self.recorded_poses()
        self._recording = None
        return poses

    def recorded_poses(self) -> np.ndarray:
        """Poses recorded so far, shape (steps + 1, N, 3); empty if nothing is being recorded."""
        if not self._recording:
            return np.zeros((0, self._n, 3))
        return np.stack(self._recording)

    # --- stepping ------------------------------------------------------------------------------

    def step(self) -> None:
        """Advance the world by one step of ``dt`` with the current commands."""
        cfg = self.config
        dt = cfg.dt
        pose = self._pose
        start = pose.copy()
        x, y, th = pose[:, 0], pose[:, 1], pose[:, 2]
        left, right = self._cmd[:, 0], self._cmd[:, 1]
        v = (left + right) * self._half_vmax
        dth = (right - left) * (self._vmax_over_base * dt)
        # Exact arc for constant wheel speeds: a chord of length v dt sinc(dth / 2) along the mean
        # heading; np.sinc(x) is sin(pi x) / (pi x) and needs no special case for straight lines.
        chord = v * dt * np.sinc(dth * (0.5 / math.pi))
        mid = th + 0.5 * dth
        x += chord * np.cos(mid)
        y += chord * np.sin(mid)
        th[:] = wrap_angle(th + dth)

        self._force[:] = 0.0
        for round_ in range(_CONTACT_ROUNDS):
            # Robots part first, then boxes give way to them; a robot the boxes moved (backed
            # off or sent back) may touch another robot again, hence another round.
            parted = self._separate_robots()
            if (round_ and not parted) or not len(self._boxes):
                break
            before = pose.copy()
            self._push_boxes(start)
            if np.array_equal(before, pose):
                break
        self._steps += 1
        self._cache = None
        self._draw_noise()
        if self._recording is not None:
            self._recording.append(pose.copy())

    def _blade_ends(
        self, c: np.ndarray, s: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        # World coordinates of the blade's left (a) and right (b) end points.
        x, y = self._pose[:, 0], self._pose[:, 1]
        bx, hw = self.config.blade_x, self._hw
        ax = x + bx * c - hw * s
        ay = y + bx * s + hw * c
        return ax, ay, ax + 2 * hw * s, ay - 2 * hw * c

    def _wall_shift(self, c: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # Translation that brings every robot's body (and blade) back inside the walls.
        cfg = self.config
        wall = cfg.wall_half
        r = cfg.robot_radius
        cx = self._pose[:, 0] + cfg.body_offset * c
        cy = self._pose[:, 1] + cfg.body_offset * s
        if not self._blade:
            return np.clip(cx, r - wall, wall - r) - cx, np.clip(cy, r - wall, wall - r) - cy
        ax, ay, bx, by = self._blade_ends(c, s)
        tb = self._tb
        lo_x = np.maximum.reduce([r - wall - cx, tb - wall - ax, tb - wall - bx])
        hi_x = np.maximum.reduce([cx - (wall - r), ax - (wall - tb), bx - (wall - tb)])
        lo_y = np.maximum.reduce([r - wall - cy, tb - wall - ay, tb - wall - by])
        hi_y = np.maximum.reduce([cy - (wall - r), ay - (wall - tb), by - (wall - tb)])
        return np.maximum(lo_x, 0) - np.maximum(hi_x, 0), np.maximum(lo_y, 0) - np.maximum(hi_y, 0)

    def _keep_inside_walls(self) -> None:
        th = self._pose[:, 2]
        sx, sy = self._wall_shift(np.cos(th), np.sin(th))
        self._pose[:, 0] += sx
        self._pose[:, 1] += sy

    def _separate_robots(self) -> bool:
        # Whether any robot moved.
        cfg = self.config
        moved = False
        pose = self._pose
        th = pose[:, 2]
        c, s = np.cos(th), np.sin(th)
        r2 = 2 * cfg.robot_radius
        for _ in range(_ROBOT_PASSES):
            shift_x = np.zeros(self._n)
            shift_y = np.zeros(self._n)
            if self._n > 1:
                cx = pose[:, 0] + cfg.body_offset * c
                cy = pose[:, 1] + cfg.body_offset * s
                dx = cx[:, None] - cx[None, :]
                dy = cy[:, None] - cy[None, :]
                d2 = dx * dx + dy * dy + self._self_far
                hit = d2 < (r2 - _SLOP) ** 2
                if hit.any():
                    d2h, dxh, dyh = self._safe_directions(hit, d2, dx, dy)
                    d = np.sqrt(d2h)
                    # Each of two touching robots gives way by half the overlap.
                    k = np.where(hit, 0.5 * (r2 - d) / d, 0.0)
                    shift_x += (k * dxh).sum(axis=1)
                    shift_y += (k * dyh).sum(axis=1)
                if self._blade:
                    self._blade_body_push(c, s, cx, cy, shift_x, shift_y)
            pose[:, 0] += shift_x
            pose[:, 1] += shift_y
            sx, sy = self._wall_shift(c, s)
            pose[:, 0] += sx
            pose[:, 1] += sy
            if not (shift_x.any() or shift_y.any() or sx.any() or sy.any()):
                return moved
            moved = True
        return moved

    def _safe_directions(
        self, hit: np.ndarray, d2: np.ndarray, dx: np.ndarray, dy: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        # Two robots on the same spot have no direction between them: part them along x.
        same = hit & (d2 < 1e-18)
        if not same.any():
            return d2, dx, dy
        return np.where(same, 1.0, d2), np.where(same, self._pair_sign, dx), np.where(same, 0.0, dy)

    def _blade_body_push(
        self,
        c: np.ndarray,
        s: np.ndarray,
        cx: np.ndarray,
        cy: np.ndarray,
        shift_x: np.ndarray,
        shift_y: np.ndarray,
    ) -> None:
        # Robot i's blade (rows) against robot j's body (columns); both give way by half. Blades
        # against blades are not separated: the bodies keep them apart nearly always.
        ax, ay, bx, by = self._blade_ends(c, s)
        ux, uy = (bx - ax)[:, None], (by - ay)[:, None]
        wx = cx[None, :] - ax[:, None]
        wy = cy[None, :] - ay[:, None]
        t = np.clip((wx * ux + wy * uy) / (self.config.blade_width**2), 0.0, 1.0)
        dx = wx - t * ux
        dy = wy - t * uy
        d2 = dx * dx + dy * dy
        reach = self.config.robot_radius + self._tb
        hit = (d2 < (reach - _SLOP) ** 2) & self._not_self
        if not hit.any():
            return
        d = np.sqrt(np.maximum(d2, 1e-18))
        k = np.where(hit, 0.5 * (reach - d) / d, 0.0)
        px, py = k * dx, k * dy
        # Row i is pushed back, column j forward.
        shift_x += px.sum(axis=0) - px.sum(axis=1)
        shift_y += py.sum(axis=0) - py.sum(axis=1)

    def _robot_box_pushes(
        self, idx: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None:
        # Push (x, y) that moves each box of ``idx`` (rows) out of each robot (columns), the
        # depth of that overlap, and whether the blade's front did it; None if nothing
        # overlaps. The robots' headings are those cached by _push_boxes.
        pose = self._pose
        c, s = self._cs
        qx = self._boxes[idx, 0][:, None]
        qy = self._boxes[idx, 1][:, None]
        if not self._blade:
            cfg = self.config
            reach = cfg.robot_radius + self._rb
            dx = qx - (pose[:, 0] + cfg.body_offset * c)
            dy = qy - (pose[:, 1] + cfg.body_offset * s)
            d2 = dx * dx + dy * dy
            hit = d2 < (reach - _SLOP) ** 2
            if not hit.any():
                return None
            d = np.sqrt(np.maximum(d2, 1e-18))
            depth = np.where(hit, reach - d, 0.0)
            return depth * dx / d, depth * dy / d, depth, np.zeros(depth.shape, dtype=bool)
        # With a blade, boxes meet one convex outline: a rectangle with rounded corners from the
        # flat rear to the blade's front face, as wide as the blade. (A circle plus a bar would
        # leave pockets at the bar's ends where a box gets wedged between two shapes.)
        x0, x1, hy, rr = self._hull
        dx = qx - pose[:, 0]
        dy = qy - pose[:, 1]
        lx = dx * c + dy * s
        ly = dy * c - dx * s
        ex = lx - np.minimum(np.maximum(lx, x0), x1)
        ey = ly - np.minimum(np.maximum(ly, -hy), hy)
        e2 = ex * ex + ey * ey
        reach = rr + self._rb
        hit = e2 < (reach - _SLOP) ** 2
        if not hit.any():
            return None
        depth = np.where(hit, reach - np.sqrt(e2), 0.0)
        inside = e2 < 1e-18
        if inside.any():
            # A box centre inside the core (a deep sweep by a turning robot) leaves by the
            # nearest face.
            faces = np.stack([x1 - lx, lx - x0, hy - ly, ly + hy])
            face = np.argmin(faces, axis=0)
            gap = np.min(faces, axis=0)
            nx = np.choose(face, [1.0, -1.0, 0.0, 0.0])
            ny = np.choose(face, [0.0, 0.0, 1.0, -1.0])
            depth = np.where(inside, gap + reach, depth)
            ex = np.where(inside, nx, ex)
            ey = np.where(inside, ny, ey)
            e2 = np.where(inside, 1.0, e2)
        k = depth / np.sqrt(np.maximum(e2, 1e-18))
        kx = k * ex
        ky = k * ey
        front = (lx > x1) & (np.abs(ly) <= hy + reach) & hit
        return kx * c - ky * s, kx * s + ky * c, depth, front

    def _push_boxes(self, start: np.ndarray) -> None:
        # ``start``: the poses before this step's motion.
        boxes = self._boxes
        pose = self._pose
        # Headings do not change while robots and boxes push each other.
        self._cs = (np.cos(pose[:, 2]), np.sin(pose[:, 2]))
        dx = boxes[:, 0, None] - pose[None, :, 0]
        dy = boxes[:, 1, None] - pose[None, :, 1]
        near = ((dx * dx + dy * dy) < self._box_reach2).any(axis=1)
        # Boxes that overlap something must be looked at: those near robots, those left
        # overlapping by the last step, and each box moved during this one.
        near |= self._pending
        chains = _Chains(len(boxes), self._n)
        active = self._relax(near, self._pending.copy(), chains, robots_yield=True)

        # A robot still in a box is wedged between boxes that cannot give way: it stays where it
        # was before this step, and the boxes settle around the robots, which no longer move.
        # Should a box held by a wall still be inside a robot, the robot backs off it, and the
        # boxes settle again.
        cand = np.flatnonzero(near)
        for round_ in range(_SETTLE_ROUNDS if cand.size else 0):
            pushes = self._robot_box_pushes(cand)
            if pushes is None:
                break
            px, py, depth, _ = pushes
            stuck = depth.max(axis=0) > 0.0
            if round_ == 0:
                pose[stuck] = start[stuck]
                self._cs = (np.cos(pose[:, 2]), np.sin(pose[:, 2]))
            else:
                deepest = np.argmax(depth, axis=0)
                cols = np.flatnonzero(stuck)
                pose[cols, 0] -= px[deepest[cols], cols]
                pose[cols, 1] -= py[deepest[cols], cols]
                self._keep_inside_walls()
            active = self._relax(near, active, _Chains(len(boxes), self._n), robots_yield=False)
        self._pending = active
        if self._need_force:
            owner = chains.owner
            counted = owner[owner >= 0]
            if counted.size:
                counts = np.bincount(counted, minlength=self._n)
                # The strongest push of this step's contact rounds.
                force = np.minimum(counts * self.config.force_per_box, 1.0)
                np.maximum(self._force, force, out=self._force)

    def _relax(
        self, near: np.ndarray, active: np.ndarray, ch: _Chains, *, robots_yield: bool
    ) -> np.ndarray:
        # Passes of robots pushing boxes, boxes pushing boxes and walls holding boxes, until
        # nothing moves or the passes run out; returns the boxes moved by the last pass (those
        # that may still overlap). ``near`` (updated) marks the boxes that may touch a robot.
        # With ``robots_yield`` a robot backs off a box that cannot give way; without, robots
        # stand like walls and every box they touch leaves them and is held.
        cfg = self.config
        boxes = self._boxes
        nb = len(boxes)
        pose = self._pose
        lo, hi = self._rb - cfg.wall_half, cfg.wall_half - self._rb
        rank, held = ch.rank, ch.held
        for _ in range(cfg.box_iterations):
            moved = np.zeros(nb, dtype=bool)
            robots_moved = False
            cand = np.flatnonzero(near)
            pushes = self._robot_box_pushes(cand) if cand.size else None
            if pushes is not None:
                px, py, depth, blade = pushes
                touched = depth > 0.0
                if robots_yield:
                    # A box pushed back into a robot that pushed it before in this step is
                    # wedged between that robot and something else: the robot backs off
                    # instead of the two pushing it to and fro (passes that would barely
                    # converge).
                    again = (touched & ch.pushed[cand]).any(axis=1)
                    held[cand[again]] = True
                    ch.pushed[cand] |= touched
                    free = ~held[cand]
                else:
                    rows = touched.any(axis=1)
                    free = rows
                    held[cand[rows]] = True
                fr = touched & free[:, None]
                if fr.any():
                    rows = np.flatnonzero(fr.any(axis=1))
                    ids = cand[rows]
                    frr = fr[rows]
                    boxes[ids, 0] += np.where(frr, px[rows], 0.0).sum(axis=1)
                    boxes[ids, 1] += np.where(frr, py[rows], 0.0).sum(axis=1)
                    moved[ids] = True
                    who = np.argmax(np.where(frr, depth[rows], 0.0), axis=1)
                    ch.pusher[ids] = who
                    far = np.hypot(boxes[ids, 0] - pose[who, 0], boxes[ids, 1] - pose[who, 1])
                    np.minimum(rank[ids], 1.0 + 0.1 * far, out=far)
                    rank[ids] = far
                    by_blade = blade[rows] & frr
                    has = by_blade.any(axis=1)
                    ch.owner[ids[has]] = np.argmax(by_blade[has], axis=1)
                stuck = touched & ~free[:, None]
                if stuck.any():
                    # A held box does not give way: the robot backs off by its deepest
                    # overlap with a held box (a robot that had to twice is wedged: it is
                    # left to the clean-up rather than rocked to and fro).
                    robots_moved = bool(ch.backoffs.max() < 2)
                    dep = np.where(stuck, depth, 0.0)
                    deepest = np.argmax(dep, axis=0)
                    cols = np.flatnonzero(dep.max(axis=0) > 0.0)
                    pose[cols, 0] -= px[deepest[cols], cols]
                    pose[cols, 1] -= py[deepest[cols], cols]
                    ch.backoffs[cols] += 1
                    self._keep_inside_walls()
                    # The robot's blade still pushes the held chain: it feels the force.
                    by_blade = stuck & blade
                    hb = by_blade.any(axis=1)
                    ch.owner[cand[hb]] = np.argmax(by_blade[hb], axis=1)
            check = active | moved
            if check.any():
                self._box_box(np.flatnonzero(check), check, ch, moved)
            # Walls hold boxes: a clamped box cannot give way any more this step.
            mv = np.flatnonzero(moved)
            if mv.size:
                bx, by = boxes[mv, 0], boxes[mv, 1]
                cx, cy = np.clip(bx, lo, hi), np.clip(by, lo, hi)
                clamped = (cx != bx) | (cy != by)
                if clamped.any():
                    boxes[mv, 0] = cx
                    boxes[mv, 1] = cy
                    held[mv[clamped]] = True
            near |= moved
            active = moved
            if not (mv.size or robots_moved):
                break
        return active

    def _box_box(
        self, act: np.ndarray, act_mask: np.ndarray, ch: _Chains, moved: np.ndarray
    ) -> None:
        # Separate every overlapping pair that involves a box of ``act``.
        boxes = self._boxes
        size = self.config.box_size
        dx = boxes[act, 0, None] - boxes[None, :, 0]
        dy = boxes[act, 1, None] - boxes[None, :, 1]
        d2 = dx * dx + dy * dy
        d2[np.arange(act.size), act] = np.inf
        ia, j = np.nonzero(d2 < (size - _SLOP) ** 2)
        if ia.size == 0:
            return
        i = act[ia]
        # A pair of two active boxes appears twice; keep it once.
        keep = ~(act_mask[j] & (j < i))
        ia, i, j = ia[keep], i[keep], j[keep]
        ddx, ddy, dd2 = dx[ia, j], dy[ia, j], d2[ia, j]
        same = dd2 < 1e-18
        if same.any():
            ddx = np.where(same, 1.0, ddx)
            ddy = np.where(same, 0.0, ddy)
            dd2 = np.where(same, 1.0, dd2)
        d = np.sqrt(dd2)
        k = (size - d) / d
        rank, held, gave = ch.rank, ch.held, ch.gave
        hi_, hj = held[i], held[j]
        ri, rj = rank[i], rank[j]
        # Share of the overlap each box gives way by: a held box none; else the box of higher
        # rank all of it; boxes of equal rank (both untouched) half each.
        by_rank = np.where(ri < rj, 0.0, np.where(ri > rj, 1.0, 0.5))
        # A box that gave way before in this step and must again is wedged between boxes
        # nearer the pusher: it shares the overlap with them, so the jam spreads back along
        # the chain (and to the robot) instead of the box sliding to and fro pass after pass.
        wedged = np.where(by_rank == 1.0, gave[i], np.where(by_rank == 0.0, gave[j], False))
        by_rank = np.where(wedged, 0.5, by_rank)
        wi = np.where(hi_ & hj, 0.5, np.where(hi_, 0.0, np.where(hj, 1.0, by_rank)))
        wj = np.where(hi_ & hj, 0.5, 1.0 - wi)
        nb = len(boxes)
        mx = np.bincount(i, weights=wi * k * ddx, minlength=nb)
        mx -= np.bincount(j, weights=wj * k * ddx, minlength=nb)
        my = np.bincount(i, weights=wi * k * ddy, minlength=nb)
        my -= np.bincount(j, weights=wj * k * ddy, minlength=nb)
        boxes[:, 0] += mx
        boxes[:, 1] += my
        moved[i[wi > 0]] = True
        moved[j[wj > 0]] = True
        gave[i[wi == 1.0]] = True
        gave[j[wj == 1.0]] = True
        # The box that gave way all of it joins its pusher's chain, one link farther.
        self._join_chain(i[wi == 1.0], j[wi == 1.0], ch)
        self._join_chain(j[wj == 1.0], i[wj == 1.0], ch)
        # A box that gave way to a held box is itself held now.
        held[i[hj & ~hi_]] = True
        held[j[hi_ & ~hj]] = True

    def _join_chain(self, yielded: np.ndarray, by: np.ndarray, ch: _Chains) -> None:
        # Boxes ``yielded`` gave way to boxes ``by``: they take the chain's robot and rank.
        rank, pusher, owner = ch.rank, ch.pusher, ch.owner
        chained = pusher[by] >= 0
        if not chained.any():
            return
        yielded, by = yielded[chained], by[chained]
        who = pusher[by]
        boxes, pose = self._boxes, self._pose
        far = np.hypot(boxes[yielded, 0] - pose[who, 0], boxes[yielded, 1] - pose[who, 1])
        new = np.floor(rank[by]) + 1.0 + 0.1 * far
        better = new < rank[yielded]
        yielded, by, new = yielded[better], by[better], new[better]
        rank[yielded] = new
        pusher[yielded] = pusher[by]
        owner[yielded] = owner[by]

    # --- sensors -------------------------------------------------------------------------------

    def _draw_noise(self) -> None:
        if self.config.noise > 0.0:
            self._noise = self._noise_rng.normal(
                0.0, self.config.noise, size=(self._n, len(self.config.sensors))
            )

    def sensor_matrix(self) -> np.ndarray:
        """Read-only (N, R) sensor values of every robot for the current step, in ``sensors``
        order; computed once per step for all robots."""
        if self._cache is None:
            self._cache = self._compute_sensors()
        return self._cache

    def sensor_values(self, index: int) -> np.ndarray:
        """Robot ``index``'s sensor values for the current step (a fresh array, ``sensors``
        order, normalised to [0, 1])."""
        return self.sensor_matrix()[index].copy()

    def _compute_sensors(self) -> np.ndarray:
        full = self._full
        th = self._pose[:, 2]
        c, s = np.cos(th), np.sin(th)
        if self._need_ir:
            full[:, _IR] = self._ir(c, s)
        if self._need_ground:
            gx, gy = self._local_to_world(GROUND_POSITIONS, c, s)
            half = self.config.arena_side / 2
            on = (np.abs(gx) <= half) & (np.abs(gy) <= half)
            full[:, _GROUND] = np.where(on, self.config.ground_carpet, self.config.ground_outside)
        if self._need_force:
            full[:, _FORCE] = self._force
        if self._need_light and self.config.light:
            full[:, _LIGHT] = self.light_at(*self._local_to_world(self._light_xy, c, s))
        out = full[:, self._columns]
        if self.config.noise > 0.0:
            out += self._noise
            np.clip(out, 0.0, 1.0, out=out)
        out.flags.writeable = False
        return out

    def light_at(self, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray:
        """Light value at points (x, y) of the floor: the lamp's inverse-square fall-off, or
        the uniform value without a lamp."""
        x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
        if not self.config.light:
            return np.full(np.broadcast(x, y).shape, self.config.light_uniform)
        h2 = self._lamp_h2
        return self.config.light_centre * h2 / (h2 + x * x + y * y)

    def _local_to_world(
        self, points: np.ndarray, c: np.ndarray, s: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        # (N, P) world coordinates of points given in the robots' frame.
        px, py = points[:, 0], points[:, 1]
        x = self._pose[:, 0, None] + c[:, None] * px - s[:, None] * py
        y = self._pose[:, 1, None] + s[:, None] * px + c[:, None] * py
        return x, y

    def _ir(self, c: np.ndarray, s: np.ndarray) -> np.ndarray:
        cfg = self.config
        sx, sy = self._local_to_world(IR_POSITIONS, c, s)
        psi = self._pose[:, 2, None] + IR_HEADINGS
        cp, sp = np.cos(psi), np.sin(psi)
        ca, sa = self._ca, self._sa
        dist = np.full(sx.shape, np.inf)
        if self._n > 1:
            r = cfg.robot_radius
            cx = self._pose[:, 0] + cfg.body_offset * c
            cy = self._pose[:, 1] + cfg.body_offset * s
            # (robot, sensor, other robot); a robot's own body is moved far away.
            wx = cx[None, None, :] - sx[:, :, None] + self._self_far[:, None, :]
            wy = cy[None, None, :] - sy[:, :, None]
            cp3, sp3 = cp[:, :, None], sp[:, :, None]
            dot = wx * cp3 + wy * sp3
            cross = np.abs(wx * sp3 - wy * cp3)
            # Nearest ray of the cone to the other body's centre: the axis if the centre is
            # inside the cone, else the cone's edge; perp and along are the centre's distances
            # from and along that ray (angle-difference formulas, no trigonometry needed).
            perp = cross * ca - dot * sa
            inside = perp <= 0.0
            centre = np.sqrt(wx * wx + wy * wy)
            along = np.where(inside, centre, dot * ca + cross * sa)
            perp = np.maximum(perp, 0.0)
            chord2 = r * r - perp * perp
            hit = (chord2 > 0.0) & (along > 0.0)
            d = np.where(hit, along - np.sqrt(np.maximum(chord2, 0.0)), np.inf)
            d = np.where(centre < r, 0.0, d)
            dist = d.min(axis=2)
        if cfg.walls_visible_to_ir:
            wall = cfg.wall_half
            # Walls at +x, -x, +y, -y: the ray of the cone closest to the wall's normal.
            cosn = np.stack([cp, -cp, sp, -sp])
            sinn = np.abs(np.stack([sp, sp, cp, cp]))
            eff = np.where(cosn >= ca, 1.0, cosn * ca + sinn * sa)
            gap = np.maximum(np.stack([wall - sx, wall + sx, wall - sy, wall + sy]), 0.0)
            with np.errstate(divide="ignore"):
                dw = np.where(eff > 1e-9, gap / np.maximum(eff, 1e-9), np.inf).min(axis=0)
            dist = np.minimum(dist, dw)
        k = cfg.ir_response_c
        return np.where(dist < cfg.ir_range, k / (dist * dist + k), 0.0)
