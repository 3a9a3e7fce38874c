"""The kinematic arena: Thymio II robots on a carpet, walls, boxes, a lamp, and their sensors.

:class:`World` holds the state of one arena and steps it with the compiled kernels of
:mod:`simulator.physics` (where the models are described); it knows nothing of asyncio, and
:mod:`simulator.body` drives it in lockstep or in real time. At a reset it places robots and boxes
(:mod:`simulator.placement`) with numpy generators seeded by ``seed``; sensor noise comes from the
kernels' counter-based generator, keyed by the same seed. The same seed and the same commands
give the same trajectories bit for bit.
"""

from __future__ import annotations

import math

import numpy as np

from drivers.body import clamp_unit
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
from simulator.placement import (
    REAR,
    TooManyRobotsError,
    body_reach,
    place_boxes,
    place_robots,
    wrap_angle,
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


def box_frame_steps(dt: float) -> int:
    """Steps between two recorded frames of the boxes for a step of ``dt`` seconds."""
    return max(1, round(BOX_FRAME_PERIOD / dt))


def box_frames(steps: int, every: int) -> int:
    """Frames of the boxes recorded over ``steps`` steps, one before every ``every``-th step."""
    return (steps + every - 1) // every


def compile_world(config: WorldConfig, seed: int) -> tuple[Geometry, Sensing]:
    """The constants of ``config`` as the kernels take them (noise keyed by ``seed``)."""
    rr = config.blade_thickness / 2
    hw = config.blade_width / 2
    reach = config.body_offset + config.robot_radius
    if config.has_blade:
        hx = np.array([-REAR, config.blade_x + rr])
        reach = max(reach, float(np.hypot(hx, max(hw - rr, 0.0) + rr).max()))
    rb = config.box_size / 2
    geometry = Geometry(
        dt=config.dt,
        half_vmax=0.5 * config.max_speed,
        vmax_over_base=config.max_speed / config.wheel_base,
        robot_radius=config.robot_radius,
        body_offset=config.body_offset,
        wall_half=config.wall_half,
        wall_hx=config.wall_hx,
        wall_hy=config.wall_hy,
        blade=config.has_blade,
        blade_x=config.blade_x,
        blade_width=config.blade_width,
        hw=hw,
        tb=rr,
        hull_x0=rr - REAR,
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
        if config.arena_height is None:
            corner2 = 2 * (config.arena_side / 2) ** 2
        else:
            corner2 = (config.carpet_width / 2) ** 2 + (config.carpet_height / 2) ** 2
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
        wall_hx=config.wall_hx,
        wall_hy=config.wall_hy,
        robot_radius=config.robot_radius,
        body_offset=config.body_offset,
        arena_hx=config.carpet_width / 2,
        arena_hy=config.carpet_height / 2,
        ground_carpet=config.ground_carpet,
        ground_outside=config.ground_outside,
        ground_noise=config.ground_noise,
        light=config.light,
        light_centre=config.light_centre,
        light_x=config.light_position[0],
        light_y=config.light_position[1],
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
        place_robots(self.config, np.random.default_rng(start_ss), self._pose)
        self._boxes = place_boxes(self.config, np.random.default_rng(box_ss), self._pose)
        self._box_start = self._boxes.copy()
        self._box_start.flags.writeable = False
        self._pending = np.zeros(len(self._boxes), dtype=bool)
        self._cache: np.ndarray | None = None
        if self._recording is not None:
            self._recording = [self._pose.copy()]
            self._box_recording = [self._boxes.copy()]

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

    # --- changes of the arena (simulator.events) ---------------------------------------------

    def reconfigure(self, config: WorldConfig) -> None:
        """Go on in ``config`` (a moved lamp, another number of robots) from the current state:
        the kernels' constants are compiled anew with the same seed."""
        self.config = config
        self._body_reach = body_reach(config)
        self._geometry, self._sensing = compile_world(config, self.seed)
        self._cache = None

    def add_boxes(self, positions: np.ndarray) -> None:
        """Add boxes at ``positions`` (K, 2); the box physics separates any they overlap."""
        new = np.array(positions, dtype=float).reshape(-1, 2)
        self._boxes = np.concatenate([self._boxes, new])
        start = np.concatenate([self._box_start, new])
        start.flags.writeable = False
        self._box_start = start
        self._pending = np.concatenate([self._pending, np.ones(len(new), dtype=bool)])
        self._cache = None

    def remove_boxes(self, count: int) -> None:
        """Take the last ``count`` boxes away."""
        keep = max(0, len(self._boxes) - count)
        self._boxes = self._boxes[:keep].copy()
        self._box_start = self._box_start[:keep].copy()
        self._box_start.flags.writeable = False
        self._pending = self._pending[:keep].copy()
        self._cache = None

    def resize_swarm(self, keep: np.ndarray, poses: np.ndarray, config: WorldConfig) -> None:
        """The robots ``keep`` (indexes, in order) stay, robots at ``poses`` (K, 3) join after
        them, idle; ``config`` the world's with the new number of robots. Boxes a new robot
        stands on are pushed off it by the next step's box physics."""
        self._pose = np.concatenate([self._pose[keep], np.asarray(poses, float).reshape(-1, 3)])
        self._cmd = np.concatenate([self._cmd[keep], np.zeros((len(poses), 2))])
        self._force = np.concatenate([self._force[keep], np.zeros(len(poses))])
        self._n = len(self._pose)
        self._sense_work = sense_work(self._n)
        if len(poses):
            self._pending[:] = True
        self.reconfigure(config)

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
        dx, dy = x - self.config.light_position[0], y - self.config.light_position[1]
        return (
            self.config.light_centre * (h2 / (h2 + dx * dx + dy * dy)) ** self.config.light_exponent
        )
