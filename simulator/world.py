"""The kinematic arena: Thymio II robots on a carpet, walls, boxes, a lamp, and their sensors.

:class:`World` holds the state of one arena and steps it with the compiled kernels of
:mod:`simulator.physics` (where the models are described); it knows nothing of asyncio, and
:mod:`simulator.body` drives it in lockstep or in real time. Placing robots and boxes at a reset is
done here, with numpy generators seeded by ``seed``; sensor noise comes from the kernels'
counter-based generator, keyed by the same seed. The same seed and the same commands give the
same trajectories bit for bit.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from drivers.body import clamp_unit
from minimize_surprise.errors import ConfigError
from minimize_surprise.sensors import ALL_SENSORS
from simulator import physics
from simulator.physics import (
    GROUND_POSITIONS,
    IR_HEADINGS,
    IR_POSITIONS,
    Geometry,
    Sensing,
    ir_reach,
    sense_work,
)
from simulator.scenarios import WorldConfig

__all__ = [
    "BOX_FRAME_PERIOD",
    "GROUND_POSITIONS",
    "IR_HEADINGS",
    "IR_POSITIONS",
    "TooManyRobotsError",
    "World",
    "box_frame_steps",
    "box_frames",
    "compile_world",
    "wrap_angle",
]

#: Simulated seconds between two recorded frames of the boxes: an animation needs no more, and
#: every step of the paper's 100 Hz would hold a post-evaluation's 220 boxes in 35 MB.
BOX_FRAME_PERIOD = 0.1

_TWO_PI = 2.0 * math.pi
# The Thymio II's flat rear is 3 cm behind its wheel axis (docs/simulation.md).
_REAR = 0.03
# Placement draws candidate positions in batches of _BATCH, gives up on one robot after
# _MAX_TRIES candidates and on the arena after _PLACEMENT_RESTARTS fresh starts.
_BATCH = 64
_MAX_TRIES = 4_096
_PLACEMENT_RESTARTS = 20


class TooManyRobotsError(ConfigError):
    """More robots than fit at the start: ``robots`` were asked for, at most ``fit`` fit
    ``where`` (e.g. "on a 1.0 m carpet"; ``approximate`` when the random start found that many,
    not a formula); ``larger`` is the world parameter that makes room (``arena_side`` or
    ``start_ring``)."""

    def __init__(self, robots: int, fit: int, where: str, *, larger: str, approximate: bool):
        self.robots = robots
        self.fit = fit
        self.where = where
        self.larger = larger
        self.approximate = approximate
        about = "about " if approximate else ""
        super().__init__(
            f"at most {about}{fit} robots fit {where} ({robots} asked for)",
            key="simulation.robots",
        )


def box_frame_steps(dt: float) -> int:
    """Steps between two recorded frames of the boxes for a step of ``dt`` seconds."""
    return max(1, round(BOX_FRAME_PERIOD / dt))


def box_frames(steps: int, every: int) -> int:
    """Frames of the boxes recorded over ``steps`` steps, one before every ``every``-th step."""
    return (steps + every - 1) // every


def wrap_angle(theta: np.ndarray | float) -> np.ndarray | float:
    """Angles wrapped to [-pi, pi)."""
    return (theta + math.pi) % _TWO_PI - math.pi


def _ring(gap: float, n: int) -> float:
    # Radius of the ring on which n points stand gap apart from their neighbours.
    return 0.0 if n == 1 else gap / (2 * math.sin(math.pi / n))


def _chord(radius: float, n: int) -> float:
    # Distance between neighbours of n points evenly spread on a ring of that radius.
    return math.inf if n == 1 else 2 * radius * math.sin(math.pi / n)


def _ring_capacity(n: int, fits: Callable[[int], bool]) -> int:
    # The most robots, up to n, that a ring takes; fits(m) is monotone (m robots fit, fewer do).
    return next((m for m in range(n, 0, -1) if fits(m)), 0)


def body_reach(config: WorldConfig) -> float:
    """How far a robot's shapes (body, blade) reach from its body's centre."""
    reach = config.robot_radius
    if config.has_blade:
        rr = config.blade_thickness / 2
        hy = max(config.blade_width / 2 - rr, 0.0) + rr
        off = np.array([-_REAR, config.blade_x + rr]) - config.body_offset
        reach = max(reach, float(np.hypot(off, hy).max()))
    return reach


def compile_world(config: WorldConfig, seed: int) -> tuple[Geometry, Sensing]:
    """The constants of ``config`` as the kernels take them (noise keyed by ``seed``)."""
    rr = config.blade_thickness / 2
    hw = config.blade_width / 2
    reach = config.body_offset + config.robot_radius
    if config.has_blade:
        hx = np.array([-_REAR, config.blade_x + rr])
        reach = max(reach, float(np.hypot(hx, max(hw - rr, 0.0) + rr).max()))
    rb = config.box_size / 2
    geometry = Geometry(
        dt=config.dt,
        half_vmax=0.5 * config.max_speed,
        vmax_over_base=config.max_speed / config.wheel_base,
        robot_radius=config.robot_radius,
        body_offset=config.body_offset,
        wall_half=config.wall_half,
        blade=config.has_blade,
        blade_x=config.blade_x,
        blade_width=config.blade_width,
        hw=hw,
        tb=rr,
        hull_x0=rr - _REAR,
        hull_x1=config.blade_x,
        hull_hy=max(hw - rr, 0.0),
        hull_rr=rr,
        rb=rb,
        box_size=config.box_size,
        box_iterations=config.box_iterations,
        box_reach2=(reach + rb + 2 * config.max_speed * config.dt + 0.01) ** 2,
        force_per_box=config.force_per_box,
    )
    names = set(config.sensors)
    aperture = math.radians(config.ir_aperture)
    lamp_h2 = 0.0
    if config.light:
        corner2 = 2 * (config.arena_side / 2) ** 2
        q = (config.light_corner / config.light_centre) ** (1.0 / config.light_exponent)
        lamp_h2 = corner2 * q / (1.0 - q)
    table = np.array(config.ir_table, dtype=float).reshape(-1, 2)
    sensing = Sensing(
        need_ir=any(n.startswith("ir.") for n in names),
        need_ground=any(n.startswith("ground.") for n in names),
        need_force="force" in names,
        need_light=any(n.startswith("light.") for n in names),
        ir_model=physics.IR_RAY if config.ir_model == "ray" else physics.IR_CONE,
        ir_range=config.ir_range,
        ir_ca=math.cos(aperture),
        ir_sa=math.sin(aperture),
        ir_c=config.ir_response_c,
        ir_table_d=np.ascontiguousarray(table[:, 0]),
        ir_table_v=np.ascontiguousarray(table[:, 1]),
        ir_noise=config.ir_noise,
        ir_robot_reflectance=config.ir_robot_reflectance,
        ir_wall_reflectance=config.ir_wall_reflectance,
        walls_visible=config.walls_visible_to_ir,
        wall_half=config.wall_half,
        robot_radius=config.robot_radius,
        body_offset=config.body_offset,
        arena_half=config.arena_side / 2,
        ground_carpet=config.ground_carpet,
        ground_outside=config.ground_outside,
        ground_noise=config.ground_noise,
        light=config.light,
        light_centre=config.light_centre,
        light_exponent=config.light_exponent,
        lamp_h2=lamp_h2,
        light_uniform=config.light_uniform,
        light_offsets=np.array(config.light_sensor_offsets, dtype=float),
        noise=config.noise,
        columns=np.array([ALL_SENSORS.index(n) for n in config.sensors], dtype=np.int64),
        seed=int(seed) & 0xFFFFFFFF,
        ir_reach=ir_reach(config.robot_radius, config.body_offset, config.ir_range),
    )
    return geometry, sensing


class World:
    """A shared arena of ``config.robots`` robots (and boxes), seeded by ``seed``.

    ``record=True`` keeps the poses of every step (see :meth:`recorded_poses`).
    """

    def __init__(self, config: WorldConfig, seed: int = 0, *, record: bool = False) -> None:
        self.config = config
        n = config.robots
        self._n = n
        self._need_force = "force" in config.sensors
        self._body_reach = body_reach(config)
        self._pose = np.zeros((n, 3))
        self._cmd = np.zeros((n, 2))
        self._force = np.zeros(n)
        self._boxes = np.zeros((0, 2))
        self._sense_work = sense_work(n)
        self._recording: list[np.ndarray] | None = [] if record else None
        self._box_recording: list[np.ndarray] = []
        self._box_every = box_frame_steps(config.dt)
        self.reset(seed)

    # --- set-up --------------------------------------------------------------------------------

    def reset(self, seed: int | None = None) -> None:
        """Place robots and boxes anew (as at construction, with ``seed`` if given) at time 0.

        Commands are set to zero; a recording restarts from the new poses.
        """
        if seed is not None:
            self.seed = int(seed)
        start_ss, box_ss = np.random.SeedSequence(self.seed).spawn(2)
        self._geometry, self._sensing = compile_world(self.config, self.seed)
        self._cmd[:] = 0.0
        self._force[:] = 0.0
        self._steps = 0
        self._place_robots(np.random.default_rng(start_ss))
        self._boxes = self._place_boxes(np.random.default_rng(box_ss))
        self._box_start = self._boxes.copy()
        self._box_start.flags.writeable = False
        self._pending = np.zeros(len(self._boxes), dtype=bool)
        self._cache: np.ndarray | None = None
        if self._recording is not None:
            self._recording = [self._pose.copy()]
            self._box_recording = [self._boxes.copy()]

    def _place_robots(self, rng: np.random.Generator) -> None:
        cfg = self.config
        n = self._n
        rp = self._body_reach
        half = cfg.arena_side / 2
        if cfg.start == "centre":
            # A fixed ring around the centre, each robot facing outwards; without a given ring,
            # neighbours just apart.
            phi = _TWO_PI * np.arange(n) / n + math.radians(cfg.start_ring_phase)
            if cfg.start_ring is not None:
                axle = cfg.start_ring
                if axle + cfg.body_offset + rp > half:
                    raise ConfigError(
                        "the start ring does not fit in the arena", key="simulation.start_ring"
                    )
                # Bodies must not overlap; blades may reach past each other's circle, as in the
                # authors' layout, since they point outwards.
                body = cfg.robot_radius
                fit = _ring_capacity(n, lambda m: _chord(axle + cfg.body_offset, m) >= 2 * body)
                if fit < n:
                    raise TooManyRobotsError(
                        n,
                        fit,
                        f"on the start ring {axle} m around the centre",
                        larger="start_ring",
                        approximate=False,
                    )
            else:
                gap = 2 * rp + cfg.start_clearance
                fit = _ring_capacity(n, lambda m: _ring(gap, m) + rp <= half)
                if fit == 0:
                    raise ConfigError(
                        "the arena is too small for a robot", key="simulation.arena_side"
                    )
                if fit < n:
                    raise TooManyRobotsError(
                        n,
                        fit,
                        f"around the centre of a {cfg.arena_side} m carpet",
                        larger="arena_side",
                        approximate=False,
                    )
                axle = _ring(gap, n) - cfg.body_offset
            self._pose[:, 0] = axle * np.cos(phi)
            self._pose[:, 1] = axle * np.sin(phi)
            self._pose[:, 2] = wrap_angle(phi)
            return
        # Random: bodies wholly on the carpet, apart by the clearance, in seeded order. Robots
        # placed one by one can box themselves in on a crowded carpet; then all start afresh.
        lim = half - rp
        if lim <= 0:
            raise ConfigError("the arena is too small for a robot", key="simulation.arena_side")
        min_d2 = (2 * rp + cfg.start_clearance) ** 2
        most = 0
        for _ in range(_PLACEMENT_RESTARTS):
            centres, placed = self._random_centres(rng, n, lim, min_d2)
            if placed == n:
                break
            most = max(most, placed)
        else:
            # The most any start placed: with this seed that many would have been placed (a
            # start draws the same candidates whatever the number asked for), with another
            # seed about as many.
            raise TooManyRobotsError(
                n, most, f"on a {cfg.arena_side} m carpet", larger="arena_side", approximate=True
            )
        theta = rng.uniform(-math.pi, math.pi, size=n)
        self._pose[:, 0] = centres[:, 0] - cfg.body_offset * np.cos(theta)
        self._pose[:, 1] = centres[:, 1] - cfg.body_offset * np.sin(theta)
        self._pose[:, 2] = theta

    @staticmethod
    def _random_centres(
        rng: np.random.Generator, n: int, lim: float, min_d2: float
    ) -> tuple[np.ndarray, int]:
        # Body centres in [-lim, lim]^2, pairwise at least sqrt(min_d2) apart, and how many
        # were placed before one found no room (n when all were).
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
                return placed, i
        return placed, n

    def _place_boxes(self, rng: np.random.Generator) -> np.ndarray:
        cfg = self.config
        if not cfg.boxes:
            return np.zeros((0, 2))
        if cfg.box_layout == "grid":
            return self._grid_boxes(rng)
        count = cfg.box_count
        if count == 0:
            return np.zeros((0, 2))
        rb = cfg.box_size / 2
        lim = cfg.arena_side / 2 - rb
        rp = self._body_reach
        th = self._pose[:, 2]
        rcx = self._pose[:, 0] + cfg.body_offset * np.cos(th)
        rcy = self._pose[:, 1] + cfg.body_offset * np.sin(th)
        away2 = (rp + rb + cfg.start_clearance) ** 2
        apart2 = (cfg.box_size + 0.001) ** 2
        clear = cfg.box_clear_centre / 2
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
            keep = (d2 >= away2).all(axis=1) & ~(np.abs(cand) < clear).all(axis=1)
            cand = cand[keep]
            # Accept in order, each against every box accepted so far (a one-off cost at set-up).
            for c in cand:
                if k and (((out[:k] - c) ** 2).sum(axis=1) < apart2).any():
                    continue
                out[k] = c
                k += 1
                if k == count:
                    break
        return out

    def _grid_boxes(self, rng: np.random.Generator) -> np.ndarray:
        # The authors' Webots layout: rows box_grid_pitch apart; along a row each box
        # pitch .. pitch + jitter after the last, up to jitter above the row; every coordinate
        # rounded to 1 cm; none in the central clear square. About 270 boxes on 1.1 m.
        cfg = self.config
        pitch, jitter = cfg.box_grid_pitch, cfg.box_grid_jitter
        edge = cfg.arena_side / 2 - cfg.box_size * 0.72  # 1.8 cm in from the carpet's edge
        clear = cfg.box_clear_centre / 2
        boxes = []
        row = -edge
        x = -edge
        while row <= edge:
            while x <= edge:
                y = round(rng.uniform(row, row + jitter), 2)
                if not (abs(x) < clear and abs(y) < clear) and abs(y) <= edge:
                    boxes.append((x, y))
                x = round(rng.uniform(x + pitch, x + pitch + jitter), 2)
            row += pitch
            x = round(rng.uniform(-edge, -edge + pitch), 2)
        return np.array(boxes, dtype=float).reshape(-1, 2)

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
        physics.clamp_commands(np.asarray(commands, dtype=np.float64), self._cmd)

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

    # --- snapshots ------------------------------------------------------------------------------

    def snapshot(self) -> dict[str, object]:
        """The whole state as plain data (JSON keeps every float exactly): with
        :meth:`restore`, a stopped simulated run goes on as if it had never stopped."""
        return {
            "seed": self.seed,
            "steps": self._steps,
            "pose": self._pose.tolist(),
            "cmd": self._cmd.tolist(),
            "force": self._force.tolist(),
            "boxes": self._boxes.tolist(),
            "box_start": self._box_start.tolist(),
            "pending": self._pending.tolist(),
        }

    def restore(self, snapshot: dict[str, object]) -> None:
        """Return to the state of :meth:`snapshot` (of a world of the same configuration)."""
        n = self._n
        self.seed = int(snapshot["seed"])  # type: ignore[call-overload]
        self._geometry, self._sensing = compile_world(self.config, self.seed)
        self._pose[:] = np.array(snapshot["pose"], dtype=float).reshape(n, 3)
        self._cmd[:] = np.array(snapshot["cmd"], dtype=float).reshape(n, 2)
        self._force[:] = np.array(snapshot["force"], dtype=float).reshape(n)
        self._boxes = np.array(snapshot["boxes"], dtype=float).reshape(-1, 2)
        self._box_start = np.array(snapshot["box_start"], dtype=float).reshape(-1, 2)
        self._box_start.flags.writeable = False
        self._pending = np.array(snapshot["pending"], dtype=bool).reshape(-1)
        self._steps = int(snapshot["steps"])  # type: ignore[call-overload]
        self._cache = None

    # --- the engine's access ------------------------------------------------------------------

    @property
    def kernel_constants(self) -> tuple[Geometry, Sensing]:
        """The constants the kernels take (see :func:`compile_world`)."""
        return self._geometry, self._sensing

    @property
    def kernel_state(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The live state arrays the kernels update in place: pose, commands, forces, boxes and
        the boxes that may still overlap something (for :mod:`simulator.engine`)."""
        return self._pose, self._cmd, self._force, self._boxes, self._pending

    def advance_to(self, steps: int) -> None:
        """Record that kernels stepped the state in place up to ``steps`` steps since the reset."""
        self._steps = int(steps)
        self._cache = None

    # --- recording -----------------------------------------------------------------------------

    def start_recording(self) -> None:
        """Record the poses of every following step, starting with the current ones, and the
        boxes' positions every :func:`box_frame_steps` steps (see :meth:`recorded_boxes`)."""
        self._recording = [self._pose.copy()]
        self._box_recording = [self._boxes.copy()]

    def stop_recording(self) -> np.ndarray:
        """Stop recording and return what was recorded (see :meth:`recorded_poses`)."""
        poses = self.recorded_poses()
        self._recording = None
        return poses

    def recorded_boxes(self, steps: int | None = None) -> np.ndarray:
        """The boxes' positions recorded so far, one frame every :func:`box_frame_steps` steps
        from the start of the recording, shape (frames, boxes, 2); with ``steps`` the frames
        of the first ``steps`` steps only (as :class:`~simulator.engine.Swarm` records them)."""
        frames = self._box_recording
        if steps is not None:
            frames = frames[: box_frames(steps, self._box_every)]
        if not frames:
            return np.zeros((0, len(self._boxes), 2))
        return np.stack(frames)

    def recorded_poses(self) -> np.ndarray:
        """Poses recorded so far, shape (steps + 1, N, 3); empty if nothing is being recorded."""
        if not self._recording:
            return np.zeros((0, self._n, 3))
        return np.stack(self._recording)

    # --- stepping ------------------------------------------------------------------------------

    def step(self) -> None:
        """Advance the world by one step of ``dt`` with the current commands."""
        g, boxes, pending = self._geometry, self._boxes, self._pending
        some = len(boxes) > 0  # none: no box physics compiled (step_world)
        physics.step_world(
            g, self._pose, self._cmd, self._force, boxes if some else None,
            pending if some else None, 0, len(boxes), self._need_force,
            physics.grid_choice(self._n, g.grid_robots),
        )  # fmt: skip
        self._steps += 1
        self._cache = None
        if self._recording is not None:
            self._recording.append(self._pose.copy())
            if (len(self._recording) - 1) % self._box_every == 0:
                self._box_recording.append(self._boxes.copy())

    # --- sensors -------------------------------------------------------------------------------

    def sensor_matrix(self) -> np.ndarray:
        """Read-only (N, R) sensor values of every robot for the current step, in ``sensors``
        order; computed once per step for all robots."""
        if self._cache is None:
            out = np.empty((self._n, len(self.config.sensors)))
            grid = physics.grid_choice(self._n, self._sensing.grid_robots)
            physics.sense(
                self._sensing, self._pose, self._force, self._steps, out, self._sense_work, grid
            )
            out.flags.writeable = False
            self._cache = out
        return self._cache

    def sensor_values(self, index: int) -> np.ndarray:
        """Robot ``index``'s sensor values for the current step (a fresh array, ``sensors``
        order, normalised to [0, 1])."""
        return self.sensor_matrix()[index].copy()

    def light_at(self, x: np.ndarray | float, y: np.ndarray | float) -> np.ndarray:
        """Light value at points (x, y) of the floor: the lamp's inverse-square fall-off, or
        the uniform value without a lamp."""
        x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
        if not self.config.light:
            return np.full(np.broadcast(x, y).shape, self.config.light_uniform)
        h2 = self._sensing.lamp_h2
        return self.config.light_centre * (h2 / (h2 + x * x + y * y)) ** self.config.light_exponent
