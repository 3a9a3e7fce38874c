"""The vectorised engine: whole evaluations of a simulated swarm in one compiled loop.

``surprise-master sim --engine agents`` runs the real system: the master and one agent per robot
over loopback TCP, the world stepped in lockstep. This engine runs the same experiment without
any of that machinery: :func:`evaluate` runs every step of one evaluation of one swarm inside
numba, calling the very kernels the agents call (the network pair, the surprise score, the safety
rules) and the world's own physics and sensors. Per evaluation it does exactly what the agents'
lockstep does:

1. every robot reads the world as it is (``sense``), scores the prediction it made on the step
   before, runs its network, and passes the intended command through its safety layer;
2. the world steps once with every robot's command;
3. after the last step every robot stops, and the world steps once more with zero commands (the
   agents' final stop, which the lockstep counts as everybody's command for a step).

So for the same seed the engine and the agents give the same trajectories and fitnesses, bit for
bit (a test checks it). :class:`Swarm` holds one simulated swarm (world state, safety states,
robot ids) and evaluates genomes on it; the evolution around it is the master's own
:class:`~minimize_surprise.evolution.OnePlusOne` (see ``master_service.experiments.engine_run``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from minimize_surprise.fitness import step_score
from minimize_surprise.jit import kernel
from minimize_surprise.network import GenomeLayout, NetworkSpec, network_step, network_weights
from minimize_surprise.safety import (
    REASON_OF_CODE,
    SafetyConfig,
    SafetyLayer,
    SafetyParams,
    intervention_share,
    safety_seed,
    safety_step,
)
from minimize_surprise.sensors import ALL_SENSORS
from sim_stub import physics
from sim_stub.physics import Geometry, Sensing
from sim_stub.scenarios import WorldConfig
from sim_stub.world import World, box_frame_steps, box_frames

__all__ = ["EvaluationRecord", "Swarm", "evaluate", "robot_ids"]

#: Sensors in the world's full frame, every sensor it simulates (as ``World`` allocates it).
_FULL_WIDTH = len(ALL_SENSORS)


def robot_ids(count: int) -> list[str]:
    """The simulated robots' ids: ``sim-0`` .. ``sim-<count-1>``."""
    return [f"sim-{i}" for i in range(count)]


@kernel
def evaluate(
    g: Geometry,
    sn: Sensing,
    sp: SafetyParams,
    front: np.ndarray,
    rear: np.ndarray,
    ground: np.ndarray,
    force_idx: np.ndarray,
    a_in: np.ndarray,
    a_out: np.ndarray,
    p_in: np.ndarray,
    p_self: np.ndarray,
    p_out: np.ndarray,
    free: np.ndarray,
    fixed: np.ndarray,
    p_init: np.ndarray,
    initial_action: float,
    columns: np.ndarray,
    pose: np.ndarray,
    cmd: np.ndarray,
    force: np.ndarray,
    boxes: np.ndarray,
    pending: np.ndarray,
    world_step: int,
    steps: int,
    safety: np.ndarray,
    fitness: np.ndarray,
    interventions: np.ndarray,
    record: bool,
    rec_sensors: np.ndarray,
    rec_predictions: np.ndarray,
    rec_actions: np.ndarray,
    rec_commands: np.ndarray,
    rec_reasons: np.ndarray,
    rec_poses: np.ndarray,
    box_every: int,
    rec_boxes: np.ndarray,
) -> int:
    """One evaluation of one genome on every robot of one arena; returns the world's new step
    count. ``columns`` picks the network's sensors from the world's; ``safety`` (N, 5) holds
    each robot's safety state (reset here for the new genome, its generator kept);
    ``fitness`` (N) receives each robot's fitness and ``interventions`` (N, reasons + 1) the
    count of each safety reason code. With ``record`` the ``rec_*`` arrays (steps, N, ...)
    receive the trace the agents send with a recorded result, and ``rec_boxes`` the boxes'
    positions every ``box_every`` steps (frames, boxes, 2)."""
    n = pose.shape[0]
    r = columns.shape[0]
    values = np.empty((n, sn.columns.shape[0]))
    full = np.zeros((n, _FULL_WIDTH))
    s = np.empty(r)
    previous = np.full((n, 2), initial_action)
    hidden = np.empty((n, p_init.shape[0]))
    for i in range(n):
        hidden[i, :] = p_init
        # A new genome: no manoeuvre carries over; the generator of escape turns does.
        safety[i, 0] = 0
        safety[i, 1] = 0
        safety[i, 2] = 0
        safety[i, 3] = 0
    work = np.empty(r + 3 + a_in.shape[0])
    action = np.empty(2)
    predictions = np.empty((n, r))
    total = np.zeros(n)
    interventions[:, :] = 0
    for t in range(steps):
        if record and boxes.shape[0] and t % box_every == 0:
            rec_boxes[t // box_every, :, :] = boxes
        physics.sense(sn, pose, force, world_step, values, full)
        for i in range(n):
            for k in range(r):
                s[k] = values[i, columns[k]]
            if t > 0:
                total[i] += step_score(predictions[i], s)
            network_step(
                a_in, a_out, p_in, p_self, p_out, free, fixed, s, previous[i], hidden[i], work,
                action, predictions[i],
            )  # fmt: skip
            left, right, code = safety_step(
                sp, front, rear, ground, force_idx, values[i], action[0], action[1], True, 0.0,
                safety[i],
            )  # fmt: skip
            interventions[i, code] += 1
            cmd[i, 0] = left
            cmd[i, 1] = right
            if record:
                rec_sensors[t, i, :] = s
                rec_predictions[t, i, :] = predictions[i]
                rec_actions[t, i, 0] = action[0]
                rec_actions[t, i, 1] = action[1]
                rec_commands[t, i, 0] = left
                rec_commands[t, i, 1] = right
                rec_reasons[t, i] = code
                rec_poses[t, i, 0] = pose[i, 0]
                rec_poses[t, i, 1] = pose[i, 1]
                rec_poses[t, i, 2] = pose[i, 2]
        physics.step_world(g, pose, cmd, force, boxes, pending, sn.need_force)
        world_step += 1
    # Every robot stops; the lockstep counts that as everybody's command for one more step.
    cmd[:, :] = 0.0
    physics.step_world(g, pose, cmd, force, boxes, pending, sn.need_force)
    world_step += 1
    scored = steps - 1
    for i in range(n):
        fitness[i] = total[i] / scored if scored > 0 else 0.0
    return world_step


@dataclass(frozen=True)
class EvaluationRecord:
    """What one evaluation of a swarm produced: per-robot fitness and safety counts, and with
    ``record`` the trace arrays (steps, robots, ...) of the agents' recorded results."""

    fitness: np.ndarray
    interventions: list[dict[str, int]]
    sensors: np.ndarray | None = None
    predictions: np.ndarray | None = None
    actions: np.ndarray | None = None
    commands: np.ndarray | None = None
    reasons: np.ndarray | None = None
    poses: np.ndarray | None = None
    #: the boxes' positions every :func:`~sim_stub.world.box_frame_steps` steps, (frames, boxes,
    #: 2)
    boxes: np.ndarray | None = None

    def safety_share(self, steps: int) -> float:
        """The share of the robots' ``steps`` steps in which the safety layer changed the
        command (as the master computes it from the agents' counts)."""
        return intervention_share(self.interventions, steps * len(self.interventions))

    def safety_reasons(self, robot: int) -> list[str]:
        """Robot ``robot``'s safety reason of every recorded step ("" when none)."""
        assert self.reasons is not None
        return [REASON_OF_CODE[int(c)] or "" for c in self.reasons[:, robot]]


class Swarm:
    """One simulated swarm for the engine: a :class:`World`, and each robot's safety layer state.

    ``spec`` is the experiment's network shape (its sensors a subset of the world's); the safety
    layer sees every sensor of the world, as an agent's does of its body.
    """

    def __init__(
        self, world_config: WorldConfig, safety: SafetyConfig, spec: NetworkSpec, seed: int
    ) -> None:
        self.world = World(world_config, seed=seed)
        self.spec = spec
        self.layout = GenomeLayout(spec)
        self.ids = robot_ids(world_config.robots)
        layer = SafetyLayer(world_config.sensors, safety)
        self.layer = layer
        self._groups = (layer.front, layer.rear, layer.ground, layer.force)
        self.safety = np.zeros((world_config.robots, 5), dtype=np.int64)
        for i, robot_id in enumerate(self.ids):
            self.safety[i] = layer.initial_state(safety_seed(robot_id)).to_array()
        missing = [name for name in spec.sensors if name not in world_config.sensors]
        if missing:
            raise ValueError(f"the world's robots do not carry {', '.join(missing)}")
        self._columns = np.array(
            [world_config.sensors.index(name) for name in spec.sensors], dtype=np.int64
        )
        self._reasons = len(REASON_OF_CODE)

    def snapshot(self) -> dict[str, object]:
        """The swarm's state (world and safety layers) as plain data; see :meth:`restore`."""
        return {"world": self.world.snapshot(), "safety": self.safety.tolist()}

    def restore(self, snapshot: dict[str, object]) -> None:
        """Return to the state of :meth:`snapshot`."""
        self.world.restore(snapshot["world"])  # type: ignore[arg-type]
        self.safety[:] = np.array(snapshot["safety"], dtype=np.int64)

    def evaluate(self, genome: np.ndarray, steps: int, *, record: bool = False) -> EvaluationRecord:
        """Run ``genome`` on every robot for ``steps`` steps from where the swarm stands."""
        world = self.world
        n = world.n_robots
        weights = network_weights(self.layout, genome)
        r = len(self.spec.sensors)
        fitness = np.empty(n)
        counts = np.zeros((n, self._reasons), dtype=np.int64)
        shape = (steps, n) if record else (0, n)
        rec = (
            np.empty((*shape, r)),
            np.empty((*shape, r)),
            np.empty((*shape, 2)),
            np.empty((*shape, 2)),
            np.empty(shape, dtype=np.int64),
            np.empty((*shape, 3)),
        )
        every = box_frame_steps(world.config.dt)
        frames = box_frames(steps, every) if record else 0
        boxes = np.empty((frames, len(world.box_positions), 2))
        geometry, sensing = world.kernel_constants
        steps_after = evaluate(
            geometry, sensing, self.layer.params, *self._groups, *weights,
            self.spec.initial_action, self._columns, *world.kernel_state, world.steps, steps,
            self.safety, fitness, counts, record, *rec, every, boxes,
        )  # fmt: skip
        world.advance_to(steps_after)
        interventions = [
            {REASON_OF_CODE[c]: int(k) for c, k in enumerate(row) if c and k}  # type: ignore[misc]
            for row in counts
        ]
        if not record:
            return EvaluationRecord(fitness, interventions)
        return EvaluationRecord(fitness, interventions, *rec, boxes=boxes)
