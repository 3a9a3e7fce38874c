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
from typing import NamedTuple

import numpy as np

from minimize_surprise.fitness import step_score
from minimize_surprise.jit import kernel
from minimize_surprise.network import (
    GenomeLayout,
    NetworkSpec,
    Weights,
    network_step_lanes,
    network_weights,
)
from minimize_surprise.safety import (
    REASON_OF_CODE,
    REASONS,
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

__all__ = [
    "Controller",
    "EvaluationRecord",
    "Outcome",
    "Recording",
    "SafetyLayers",
    "Swarm",
    "WorldState",
    "evaluate",
    "robot_ids",
]

#: Sensors in the world's full frame, every sensor it simulates (as ``World`` allocates it).
_FULL_WIDTH = len(ALL_SENSORS)
#: The networks' lanes come in multiples of this: the vector loops the compiler makes of
#: network_step_lanes run eight doubles at a time (AVX-512, or AVX2 unrolled twice) and leave a
#: remainder to slow scalar code; ten robots padded to 16 cost less than ten (measured).
_LANES = 8


def robot_ids(count: int) -> list[str]:
    """The simulated robots' ids: ``sim-0`` .. ``sim-<count-1>``."""
    return [f"sim-{i}" for i in range(count)]


class Controller(NamedTuple):
    """What every robot runs for one genome: its network's weights, the action a(-1) before the
    first step, and ``columns``, the network's sensors among the world's (int64)."""

    weights: Weights
    initial_action: float
    columns: np.ndarray


class SafetyLayers(NamedTuple):
    """Every robot's safety layer: its rules, the positions of each group of sensors in the
    world's sensors (empty: that rule is off; see :func:`~minimize_surprise.safety.safety_step`)
    and ``state`` (N, 5) int64, each robot's state, updated in place."""

    params: SafetyParams
    front: np.ndarray
    rear: np.ndarray
    ground: np.ndarray
    force: np.ndarray
    state: np.ndarray


class WorldState(NamedTuple):
    """The world's live arrays, updated in place (see :attr:`World.kernel_state
    <sim_stub.world.World.kernel_state>`)."""

    pose: np.ndarray
    cmd: np.ndarray
    force: np.ndarray
    boxes: np.ndarray
    pending: np.ndarray


class Outcome(NamedTuple):
    """What one evaluation gives per robot: ``fitness`` (N) and ``interventions`` (N,
    len(REASON_OF_CODE)) int64, the count of each safety reason code."""

    fitness: np.ndarray
    interventions: np.ndarray


class Recording(NamedTuple):
    """With ``on``, the trace the agents send with a recorded result, arrays (steps, N, ...), and
    ``boxes``, the boxes' positions every ``box_every`` steps (frames, boxes, 2); without, the
    arrays are empty and untouched."""

    on: bool
    sensors: np.ndarray
    predictions: np.ndarray
    actions: np.ndarray
    commands: np.ndarray
    reasons: np.ndarray  # int64
    poses: np.ndarray
    box_every: int
    boxes: np.ndarray


@kernel
def evaluate(
    g: Geometry,
    sn: Sensing,
    net: Controller,
    safety: SafetyLayers,
    world: WorldState,
    world_step: int,
    steps: int,
    out: Outcome,
    rec: Recording,
) -> int:
    """One evaluation of one genome on every robot of one arena, from the world's step
    ``world_step``; returns the world's new step count. Each robot's safety state is reset for
    the new genome (its generator kept); ``out`` receives the fitnesses and safety counts, ``rec``
    the trace if it is on."""
    # Every field into a local once, by name: numba counts a reference each time an array is
    # read from a tuple, which in the loop below would cost a tenth of the speed (measured).
    pose, cmd, force, boxes = world.pose, world.cmd, world.force, world.boxes
    pending = world.pending
    w = net.weights
    a_in, a_out, p_in, p_self, p_out = w.a_in, w.a_out, w.p_in, w.p_self, w.p_out
    free, fixed, p_init = w.free, w.fixed, w.p_init
    initial_action, columns = net.initial_action, net.columns
    sp, front, rear, ground = safety.params, safety.front, safety.rear, safety.ground
    force_idx, state = safety.force, safety.state
    fitness, interventions = out.fitness, out.interventions
    record, box_every, rec_boxes = rec.on, rec.box_every, rec.boxes
    rec_sensors, rec_predictions, rec_actions = rec.sensors, rec.predictions, rec.actions
    rec_commands, rec_reasons, rec_poses = rec.commands, rec.reasons, rec.poses
    n = pose.shape[0]
    r = columns.shape[0]
    values = np.empty((n, sn.columns.shape[0]))
    full = np.zeros((n, _FULL_WIDTH))
    # The networks' arrays hold a robot in each column (network_step_lanes): readings s(t) in
    # the first R rows of ``work``, a(t-1), h(t-1), p(t+1) as the robots' columns. Columns are
    # padded to whole vectors (_LANES), so the compiler's vector loop covers every robot; the
    # padding lanes compute on zeros, and nothing reads them.
    lanes = -(-n // _LANES) * _LANES
    work = np.zeros((r + 3 + a_in.shape[0], lanes))
    units = max(a_in.shape[0], p_init.shape[0], r, 2)
    acc = np.empty((units, lanes))
    previous = np.full((2, lanes), initial_action)
    hidden = np.empty((p_init.shape[0], lanes))
    action = np.empty((2, lanes))
    predictions = np.empty((r, lanes))
    for i in range(lanes):
        hidden[:, i] = p_init
    for i in range(n):
        # A new genome: no manoeuvre carries over; the generator of escape turns does.
        state[i, 0] = 0
        state[i, 1] = 0
        state[i, 2] = 0
        state[i, 3] = 0
    total = np.zeros(n)
    interventions[:, :] = 0
    for t in range(steps):
        if record and boxes.shape[0] and t % box_every == 0:
            rec_boxes[t // box_every, :, :] = boxes
        physics.sense(sn, pose, force, world_step, values, full)
        for i in range(n):
            for k in range(r):
                work[k, i] = values[i, columns[k]]
            if t > 0:
                total[i] += step_score(predictions[:, i], work[:r, i])
        network_step_lanes(
            a_in, a_out, p_in, p_self, p_out, free, fixed, work, previous, hidden, acc, action,
            predictions,
        )  # fmt: skip
        for i in range(n):
            left, right, code = safety_step(
                sp, front, rear, ground, force_idx, values[i], action[0, i], action[1, i], True,
                0.0, state[i],
            )  # fmt: skip
            interventions[i, code] += 1
            cmd[i, 0] = left
            cmd[i, 1] = right
            if record:
                rec_sensors[t, i, :] = work[:r, i]
                rec_predictions[t, i, :] = predictions[:, i]
                rec_actions[t, i, 0] = action[0, i]
                rec_actions[t, i, 1] = action[1, i]
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
        self.safety = np.zeros((world_config.robots, 5), dtype=np.int64)
        for i, robot_id in enumerate(self.ids):
            self.safety[i] = layer.initial_state(safety_seed(robot_id)).to_array()
        # The kernel's view of the safety layers; ``restore`` keeps ``self.safety`` in place.
        self._layers = SafetyLayers(
            layer.params, layer.front, layer.rear, layer.ground, layer.force, self.safety
        )
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
        net = Controller(
            network_weights(self.layout, genome), self.spec.initial_action, self._columns
        )
        r = len(self.spec.sensors)
        out = Outcome(np.empty(n), np.zeros((n, self._reasons), dtype=np.int64))
        shape = (steps, n) if record else (0, n)
        every = box_frame_steps(world.config.dt)
        frames = box_frames(steps, every) if record else 0
        rec = Recording(
            on=record,
            sensors=np.empty((*shape, r)),
            predictions=np.empty((*shape, r)),
            actions=np.empty((*shape, 2)),
            commands=np.empty((*shape, 2)),
            reasons=np.empty(shape, dtype=np.int64),
            poses=np.empty((*shape, 3)),
            box_every=every,
            boxes=np.empty((frames, len(world.box_positions), 2)),
        )
        geometry, sensing = world.kernel_constants
        steps_after = evaluate(
            geometry, sensing, net, self._layers, WorldState(*world.kernel_state), world.steps,
            steps, out, rec,
        )  # fmt: skip
        world.advance_to(steps_after)
        interventions = [
            {REASONS[c - 1]: int(k) for c, k in enumerate(row) if c and k}
            for row in out.interventions
        ]
        if not record:
            return EvaluationRecord(out.fitness, interventions)
        return EvaluationRecord(
            out.fitness, interventions, rec.sensors, rec.predictions, rec.actions, rec.commands,
            rec.reasons, rec.poses, boxes=rec.boxes,
        )  # fmt: skip
