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

Why one file of over 600 lines: :func:`compile_plan` copies :func:`evaluate`'s calls argument by
argument, so that a first run compiles the kernels it calls side by side (docs/simulation.md,
"The first run"); next to each other, a change to one shows in the other.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal, NamedTuple

import numpy as np

from minimize_surprise.fitness import step_score
from minimize_surprise.jit import borrow, kernel, typed_list, typed_list_plan
from minimize_surprise.network import (
    GenomeLayout,
    LaneWeights,
    NetworkSpec,
    lane_weights,
    network_step_lanes,
    network_weights,
)
from minimize_surprise.precompile import ListOf, Plan, signature
from minimize_surprise.safety import (
    REASON_OF_CODE,
    REASONS,
    SafetyConfig,
    SafetyInput,
    SafetyLayer,
    SafetyParams,
    SafetySensors,
    intervention_share,
    safety_seed,
    safety_step,
)
from simulator import physics
from simulator.physics import Geometry, SenseWork, Sensing
from simulator.scenarios import WorldConfig
from simulator.world import World, box_frame_steps, box_frames

__all__ = [
    "Arenas",
    "CompilePlan",
    "EvaluationRecord",
    "Recording",
    "SafetyLayers",
    "Scratch",
    "Swarm",
    "compile_plan",
    "evaluate",
    "evaluate_swarms",
    "new_scratch",
    "robot_ids",
]

#: The networks' lanes come in multiples of this: the vector loops the compiler makes of
#: network_step_lanes run eight doubles at a time (AVX-512, or AVX2 unrolled twice) and leave a
#: remainder to slow scalar code, so padded robots cost less than a remainder (docs/simulation.md,
#: "Figures behind the code's choices").
_LANES = 8


def robot_ids(count: int) -> list[str]:
    """The simulated robots' ids: ``sim-0`` .. ``sim-<count-1>``."""
    return [f"sim-{i}" for i in range(count)]


class SafetyLayers(NamedTuple):
    """The robots' safety layers: their rules, the positions of each group of sensors in the
    world's sensors (empty: that rule is off; see :func:`~minimize_surprise.safety.safety_step`)
    and ``state`` (B, N, 5) int64, each robot's state in each arena, updated in place."""

    params: SafetyParams
    sensors: SafetySensors
    state: np.ndarray


class Arenas(NamedTuple):
    """B worlds of N robots each as the kernel takes them: per world its constants (lists of B)
    and its live arrays, stacked (``pose`` (B, N, 3), ``cmd`` (B, N, 2), ``force`` (B, N),
    ``clock`` (B) the worlds' step counts) or, for the boxes, of which each world has its own
    number, one after the other (world b's in rows ``box_start[b]`` to ``box_start[b + 1] - 1`` of
    ``boxes`` and ``pending``); all updated in place. A batch without any box has None for
    ``boxes`` and ``pending``, and the kernel is compiled without the box physics."""

    geometry: Sequence[Geometry]
    sensing: Sequence[Sensing]
    pose: np.ndarray
    cmd: np.ndarray
    force: np.ndarray
    boxes: np.ndarray | None
    pending: np.ndarray | None
    box_start: np.ndarray
    clock: np.ndarray


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


class Scratch(NamedTuple):
    """The working arrays of one :func:`evaluate` call (:func:`new_scratch`), allocated by
    its caller so that the kernel may borrow them: ``values`` (B, N, world's sensors) the
    readings, ``sensing`` each world's :class:`~simulator.physics.SenseWork` stacked (B, N,
    ...); the networks' lanes (``work``, ``acc``, ``previous`` a(t-1) starting as the initial
    action, ``hidden`` h(t-1) starting as the initial hidden state, ``action``,
    ``predictions``); ``total`` (B, N) the summed scores; ``need_force`` (B) each world's flag,
    read from its Sensing once."""

    values: np.ndarray
    sensing: SenseWork
    work: np.ndarray
    acc: np.ndarray
    previous: np.ndarray
    hidden: np.ndarray
    action: np.ndarray
    predictions: np.ndarray
    total: np.ndarray
    need_force: np.ndarray


def new_scratch(
    sensings: Sequence[Sensing], robots: int, net: LaneWeights, sensors: int,
    initial_action: float,
) -> Scratch:  # fmt: skip
    """Fresh working arrays for :func:`evaluate` on worlds with these ``sensings`` of ``robots``
    robots each, networks ``net`` reading ``sensors`` of the world's sensors."""
    count, lanes = len(sensings), net.p_init.shape[1]
    inputs = net.a_in.shape[0]
    one = physics.sense_work(robots)
    # The networks' arrays hold a robot in each column (network_step_lanes): readings s(t) in
    # the first R rows of ``work``, a(t-1), h(t-1), p(t+1) as the robots' columns; the lanes
    # beyond the last arena's robots (padding to whole vectors) compute on zeros, unread.
    return Scratch(
        values=np.empty((count, robots, len(sensings[0].columns))),
        sensing=SenseWork(*(np.stack([part] * count) for part in one)),
        work=np.zeros((sensors + 3 + inputs, lanes)),
        acc=np.empty((max(inputs, net.p_in.shape[0], sensors, 2), lanes)),
        previous=np.full((2, lanes), initial_action),
        hidden=net.p_init.copy(),
        action=np.empty((2, lanes)),
        predictions=np.empty((sensors, lanes)),
        total=np.zeros((count, robots)),
        need_force=np.array([sn.need_force for sn in sensings], dtype=np.bool_),
    )


@kernel
def evaluate(
    arenas: Arenas,
    safety: SafetyLayers,
    net: LaneWeights,
    scratch: Scratch,
    columns: np.ndarray,
    steps: int,
    fitness: np.ndarray,
    interventions: np.ndarray,
    record: bool,
    recs: Sequence[Recording],
    grid: bool | None,
) -> None:
    """One evaluation on each of B arenas of N robots at once, each arena with its own genome
    (lanes of ``net``: arena b's robots in lanes b N .. b N + N - 1), from each world's step
    count on. Each robot's safety state is reset for the new genome (its generator kept);
    ``fitness`` (B, N) receives the fitnesses, ``interventions`` (B, N, reasons) the safety
    counts and, with ``record``, ``recs[b]`` arena b's trace. ``columns``: the network's sensors
    among the world's. An arena's results do not depend on the others in the batch: each of its
    numbers is computed as in a batch of one. ``grid``: None for arenas of fewer robots than their
    ``grid_robots`` (:func:`~simulator.physics.grid_choice`), so that no grid is compiled."""
    # Everything borrowed (jit.borrow): the robots' loops below take views of these arrays at
    # every step, and an owned view costs a reference count taken and dropped, atomically.
    arenas, safety, net, scratch = borrow(arenas), borrow(safety), borrow(net), borrow(scratch)
    columns, fitness, interventions = borrow(columns), borrow(fitness), borrow(interventions)
    # Every field into a local once, by name (a field read in the loop costs more than a local).
    geometries, sensings, poses, cmds = arenas.geometry, arenas.sensing, arenas.pose, arenas.cmd
    forces, boxes, pending, clock = arenas.force, arenas.boxes, arenas.pending, arenas.clock
    box_start = arenas.box_start
    sp, groups, states = safety.params, safety.sensors, safety.state
    a_in, a_out, p_in, p_self, p_out = net.a_in, net.a_out, net.p_in, net.p_self, net.p_out
    free, fixed = net.free, net.fixed
    values, work, acc = scratch.values, scratch.work, scratch.acc
    full, bodies, cos_sin, candidates, near = scratch.sensing
    previous, hidden, action = scratch.previous, scratch.hidden, scratch.action
    predictions, total, need_force = scratch.predictions, scratch.total, scratch.need_force
    b_count, n = fitness.shape[0], fitness.shape[1]
    r = columns.shape[0]
    # A new genome: no manoeuvre carries over; the generator of escape turns does.
    states[:, :, :4] = 0
    interventions[:, :, :] = 0
    for t in range(steps):
        for b in range(b_count):
            if record and t % recs[b].box_every == 0 and box_start[b + 1] > box_start[b]:
                frame = t // recs[b].box_every
                _record_boxes(recs[b], frame, boxes, box_start[b], box_start[b + 1])
            sensing = borrow(sensings[b])  # its list, an argument, holds it
            arrays = SenseWork(full[b], bodies[b], cos_sin[b], candidates[b], near[b])
            physics.sense(sensing, poses[b], forces[b], clock[b], values[b], arrays, grid)
            for i in range(n):
                lane = b * n + i
                for k in range(r):
                    work[k, lane] = values[b, i, columns[k]]
                if t > 0:
                    total[b, i] += step_score(predictions[:, lane], work[:r, lane])
        network_step_lanes(
            a_in, a_out, p_in, p_self, p_out, free, fixed, work, previous, hidden, acc, action,
            predictions,
        )  # fmt: skip
        for b in range(b_count):
            cmd, state, counts = cmds[b], states[b], interventions[b]
            # Poses only (record="poses"): no reasons to write.
            reasons = record and recs[b].reasons.shape[0] > 0
            for i in range(n):
                lane = b * n + i
                inputs = SafetyInput(
                    values=values[b, i],
                    left=action[0, lane],
                    right=action[1, lane],
                    fresh=True,
                    age=0.0,
                    escape_now=False,  # no experimenter reaches into a compiled run
                )
                left, right, code = safety_step(sp, groups, inputs, state[i])
                counts[i, code] += 1
                cmd[i, 0] = left
                cmd[i, 1] = right
                if reasons:
                    recs[b].reasons[t, i] = code
            if record:
                _record(recs[b], t, b * n, poses[b], work, predictions, action, cmd)
            physics.step_world(
                geometries[b], poses[b], cmd, forces[b], boxes, pending, box_start[b],
                box_start[b + 1], need_force[b], grid,
            )  # fmt: skip
            clock[b] += 1
    # Every robot stops; the lockstep counts that as everybody's command for one more step.
    cmds[:, :, :] = 0.0
    for b in range(b_count):
        physics.step_world(
            geometries[b], poses[b], cmds[b], forces[b], boxes, pending, box_start[b],
            box_start[b + 1], need_force[b], grid,
        )  # fmt: skip
        clock[b] += 1
    scored = steps - 1
    for b in range(b_count):
        for i in range(n):
            fitness[b, i] = total[b, i] / scored if scored > 0 else 0.0


@kernel
def _record_boxes(
    rec: Recording, frame: int, boxes: np.ndarray | None, first: int, last: int
) -> None:
    # The boxes of one arena into frame ``frame`` of its trace, element by element: a slice
    # assignment would compile numba's shape checks and their messages.
    if boxes is None:
        return
    for j in range(last - first):
        rec.boxes[frame, j, 0] = boxes[first + j, 0]
        rec.boxes[frame, j, 1] = boxes[first + j, 1]


@kernel
def _record(
    rec: Recording, t: int, first: int, pose: np.ndarray, work: np.ndarray,
    predictions: np.ndarray, action: np.ndarray, cmd: np.ndarray,
) -> None:  # fmt: skip
    # Step t of one arena's trace (all but the safety reasons): its robots are the lanes from
    # ``first`` on, its commands those of the step, its poses those before it.
    r = predictions.shape[0]
    if rec.sensors.shape[0] == 0:  # poses only (record="poses")
        for i in range(pose.shape[0]):
            rec.poses[t, i, 0] = pose[i, 0]
            rec.poses[t, i, 1] = pose[i, 1]
            rec.poses[t, i, 2] = pose[i, 2]
        return
    for i in range(pose.shape[0]):
        lane = first + i
        for k in range(r):  # element by element: see _record_boxes
            rec.sensors[t, i, k] = work[k, lane]
            rec.predictions[t, i, k] = predictions[k, lane]
        rec.actions[t, i, 0] = action[0, lane]
        rec.actions[t, i, 1] = action[1, lane]
        rec.commands[t, i, 0] = cmd[i, 0]
        rec.commands[t, i, 1] = cmd[i, 1]
        rec.poses[t, i, 0] = pose[i, 0]
        rec.poses[t, i, 1] = pose[i, 1]
        rec.poses[t, i, 2] = pose[i, 2]


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
    #: the boxes' positions every :func:`~simulator.world.box_frame_steps` steps, (frames, boxes,
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
        self._issued = len(self.ids)
        layer = SafetyLayer(world_config.sensors, safety)
        self.layer = layer
        self.safety = np.zeros((world_config.robots, 5), dtype=np.int64)
        for i, robot_id in enumerate(self.ids):
            self.safety[i] = layer.initial_state(safety_seed(robot_id)).to_array()
        missing = [name for name in spec.sensors if name not in world_config.sensors]
        if missing:
            raise ValueError(f"the world's robots do not carry {', '.join(missing)}")
        self._columns = np.array(
            [world_config.sensors.index(name) for name in spec.sensors], dtype=np.int64
        )

    def resize(self, keep: Sequence[int], joined: int) -> tuple[list[str], list[str]]:
        """After the world's robots changed (``simulator.events``): robots ``keep`` stayed, in
        order, ``joined`` new ones came after them with fresh safety layers and new ids; the
        ids that left and those that joined."""
        ids = [self.ids[k] for k in keep]
        left = [robot for robot in self.ids if robot not in ids]
        # A robot that joins never takes the id of one that left: the CSV keeps their columns.
        new = [f"sim-{self._issued + i}" for i in range(joined)]
        self._issued += joined
        fresh = [self.layer.initial_state(safety_seed(robot)).to_array() for robot in new]
        self.safety = np.concatenate(
            [self.safety[list(keep)], np.array(fresh, dtype=np.int64).reshape(-1, 5)]
        )
        self.ids = ids + new
        return left, new

    def snapshot(self) -> dict[str, object]:
        """The swarm's state (world and safety layers) as plain data; see :meth:`restore`."""
        return {"world": self.world.snapshot(), "safety": self.safety.tolist()}

    def restore(self, snapshot: dict[str, object]) -> None:
        """Return to the state of :meth:`snapshot`."""
        self.world.restore(snapshot["world"])  # type: ignore[arg-type]
        self.safety = np.array(snapshot["safety"], dtype=np.int64).reshape(-1, 5)

    def evaluate(self, genome: np.ndarray, steps: int, *, record: bool = False) -> EvaluationRecord:
        """Run ``genome`` on every robot for ``steps`` steps from where the swarm stands."""
        (result,) = evaluate_swarms([self], [genome], steps, record=record)
        return result

    def check_batch(self, other: Swarm) -> None:
        """Raise ValueError unless ``other`` can be evaluated in one batch with this swarm: the
        same network shape, number of robots, world sensors and safety rules."""
        mine = (self.spec, len(self.ids), self.world.config.sensors, self.layer.config)
        theirs = (other.spec, len(other.ids), other.world.config.sensors, other.layer.config)
        if mine != theirs:
            raise ValueError(
                "swarms of one batch need the same network shape, robots, sensors and safety "
                f"rules: {mine} against {theirs}"
            )

    def _recording(self, steps: int, record: bool | str) -> Recording:
        world = self.world
        n, r = world.n_robots, len(self.spec.sensors)
        shape = (steps, n) if record is True else (0, n)
        every = box_frame_steps(world.config.dt)
        frames = box_frames(steps, every) if record else 0
        return Recording(
            on=bool(record),
            sensors=np.empty((*shape, r)),
            predictions=np.empty((*shape, r)),
            actions=np.empty((*shape, 2)),
            commands=np.empty((*shape, 2)),
            reasons=np.empty(shape, dtype=np.int64),
            poses=np.empty((steps, n, 3) if record else (0, n, 3)),
            box_every=every,
            boxes=np.empty((frames, len(world.box_positions), 2)),
        )


def evaluate_swarms(
    swarms: Sequence[Swarm],
    genomes: Sequence[np.ndarray],
    steps: int,
    *,
    record: bool | Literal["poses"] = False,
) -> list[EvaluationRecord]:
    """Run ``genomes[b]`` on every robot of ``swarms[b]`` for ``steps`` steps, every swarm in one
    compiled call (their robots' networks side by side as lanes); each swarm's result is the one
    it has when evaluated alone, to the last bit. The swarms must be compatible
    (:meth:`Swarm.check_batch`). ``record="poses"`` records only the poses and boxes (a
    behaviour's measures need no more; writing the whole trace doubles a step's cost)."""
    if not swarms or len(swarms) != len(genomes):
        raise ValueError(f"{len(swarms)} swarms and {len(genomes)} genomes: need one each")
    first = swarms[0]
    for swarm in swarms[1:]:
        first.check_batch(swarm)
    n = len(first.ids)
    lanes = _lane_count(len(swarms), n)
    net = lane_weights(
        [network_weights(swarm.layout, g) for swarm, g in zip(swarms, genomes, strict=True)],
        n, lanes,
    )  # fmt: skip
    worlds = [swarm.world for swarm in swarms]
    # The worlds' arrays of one shape stacked (copied back below), the others listed.
    states = [world.kernel_state for world in worlds]
    geometry, sensing, empty = _world_lists(swarms)
    box_start = np.cumsum([0] + [len(state[3]) for state in states])
    arenas = Arenas(
        geometry=geometry,
        sensing=sensing,
        pose=np.stack([state[0] for state in states]),
        cmd=np.stack([state[1] for state in states]),
        force=np.stack([state[2] for state in states]),
        boxes=np.concatenate([state[3] for state in states]) if box_start[-1] else None,
        pending=np.concatenate([state[4] for state in states]) if box_start[-1] else None,
        box_start=box_start,
        clock=np.array([world.steps for world in worlds], dtype=np.int64),
    )
    layer = first.layer
    safety = SafetyLayers(
        params=layer.params,
        sensors=layer.groups,
        state=np.stack([swarm.safety for swarm in swarms]),
    )
    recs = [swarm._recording(steps, record) for swarm in swarms] if record else empty
    fitness = np.empty((len(swarms), n))
    interventions = np.zeros((len(swarms), n, len(REASON_OF_CODE)), dtype=np.int64)
    arrays = new_scratch(
        [world.kernel_constants[1] for world in worlds], n, net, len(first._columns),
        first.spec.initial_action,
    )  # fmt: skip
    # Below every world's grid_robots, None: the kernel is compiled without the grid (each world
    # still decides at every step where it is compiled with it).
    # (Read from the worlds, not from the typed lists: indexing those from Python compiles.)
    limits = [limit for world in worlds for limit in _grid_limits(world)]
    grid = physics.grid_choice(n, min(limits))
    evaluate(
        arenas, safety, net, arrays, first._columns, steps, fitness, interventions, bool(record),
        recs if not record else typed_list(recs), grid,
    )  # fmt: skip
    results = []
    for b, (swarm, world, state) in enumerate(zip(swarms, worlds, states, strict=True)):
        state[0][:] = arenas.pose[b]
        state[1][:] = arenas.cmd[b]
        state[2][:] = arenas.force[b]
        if arenas.boxes is not None and arenas.pending is not None:
            state[3][:] = arenas.boxes[box_start[b] : box_start[b + 1]]
            state[4][:] = arenas.pending[box_start[b] : box_start[b + 1]]
        swarm.safety[:] = safety.state[b]
        world.advance_to(int(arenas.clock[b]))
        counts = [
            {REASONS[c - 1]: int(k) for c, k in enumerate(row) if c and k}
            for row in interventions[b]
        ]
        if not record:
            results.append(EvaluationRecord(fitness[b].copy(), counts))
            continue
        rec = recs[b]
        if record == "poses":
            results.append(
                EvaluationRecord(fitness[b].copy(), counts, poses=rec.poses, boxes=rec.boxes)
            )
            continue
        trace = (rec.sensors, rec.predictions, rec.actions, rec.commands, rec.reasons, rec.poses)
        results.append(EvaluationRecord(fitness[b].copy(), counts, *trace, boxes=rec.boxes))
    return results


class CompilePlan(NamedTuple):
    """What a first run compiles for the engine (:func:`compile_plan`), for
    :func:`~minimize_surprise.precompile.compile_ahead`: the ``kernels`` :func:`evaluate` calls, the
    typed ``lists`` it is given, and ``loop``, :func:`evaluate` itself."""

    kernels: Plan
    lists: Plan
    loop: Plan


def compile_plan(swarm: Swarm, *, batch: int = 1) -> CompilePlan:
    """What :func:`evaluate` is and calls for batches of ``batch`` swarms like ``swarm``, each
    kernel with the signature of its call: :func:`~minimize_surprise.precompile.compile_ahead`
    compiles the kernels side by side, then the loop against them while the lists compile. The
    calls copy ``evaluate``'s, arena 0 and robot 0 standing for every one
    (``tests/sim/test_compile_ahead.py`` checks that the run compiles nothing more); the largest
    compile comes first."""
    world = swarm.world
    geometry, sensing = world.kernel_constants
    pose, cmd, force, box_rows, pending_rows = world.kernel_state
    n, r = len(swarm.ids), len(swarm._columns)
    layout = swarm.layout
    net = lane_weights([network_weights(layout, np.zeros(layout.size))], n, _lane_count(1, n))
    scratch = new_scratch([sensing], n, net, r, swarm.spec.initial_action)
    rec = swarm._recording(0, False)
    grid = physics.grid_choice(n, min(_grid_limits(world)))
    # Shaped as evaluate_swarms shapes them: each world's arrays stacked, boxes in one array.
    poses, cmds, forces = np.stack([pose]), np.stack([cmd]), np.stack([force])
    box_start = np.cumsum([0, len(box_rows)])
    boxes, pending = (box_rows, pending_rows) if box_start[-1] else (None, None)
    clock = np.zeros(1, dtype=np.int64)
    states = np.stack([swarm.safety])
    work, predictions, action = scratch.work, scratch.predictions, scratch.action
    inputs = SafetyInput(
        values=scratch.values[0, 0], left=0.0, right=0.0, fresh=True, age=0.0, escape_now=False
    )
    net_arrays = (net.a_in, net.a_out, net.p_in, net.p_self, net.p_out, net.free, net.fixed)
    calls: list[tuple[Any, tuple[Any, ...]]] = [
        (
            physics.sense,
            (
                sensing, poses[0], forces[0], clock[0], scratch.values[0],
                SenseWork(*(part[0] for part in scratch.sensing)), grid,
            ),
        ),
        (
            network_step_lanes,
            (
                *net_arrays, work, scratch.previous, scratch.hidden, scratch.acc, action,
                predictions,
            ),
        ),
        (
            physics.step_world,
            (
                geometry, poses[0], cmds[0], forces[0], boxes, pending, box_start[0],
                box_start[1], scratch.need_force[0], grid,
            ),
        ),
        (safety_step, (swarm.layer.params, swarm.layer.groups, inputs, states[0][0])),
        (_record, (rec, 0, 0, poses[0], work, predictions, action, cmds[0])),
        (_record_boxes, (rec, 0, boxes, box_start[0], box_start[1])),
        (step_score, (predictions[:, 0], work[:r, 0])),
    ]  # fmt: skip
    lists = [
        entry
        for item in (geometry, sensing, rec)
        for entry in typed_list_plan(item, appended=batch > 1)
    ]
    unbuilt: Any = ListOf  # typed lists' types, without building them (which compiles)
    arenas = Arenas(
        geometry=unbuilt(geometry), sensing=unbuilt(sensing), pose=poses, cmd=cmds, force=forces,
        boxes=boxes, pending=pending, box_start=box_start, clock=clock,
    )  # fmt: skip
    layers = SafetyLayers(params=swarm.layer.params, sensors=swarm.layer.groups, state=states)
    loop = (
        arenas, layers, net, scratch, swarm._columns, 1, np.empty((1, n)),
        np.zeros((1, n, len(REASON_OF_CODE)), dtype=np.int64), False, ListOf(rec), grid,
    )  # fmt: skip
    return CompilePlan(
        kernels=[(function, signature(function, *args)) for function, args in calls],
        lists=lists,
        loop=[(evaluate, signature(evaluate, *loop))],
    )


def _lane_count(swarms: int, robots: int) -> int:
    # The networks' lanes for ``swarms`` of ``robots``: whole multiples of _LANES.
    return -(-swarms * robots // _LANES) * _LANES


def _grid_limits(world: World) -> tuple[int, int]:
    geometry, sensing = world.kernel_constants
    return geometry.grid_robots, sensing.grid_robots


#: The lists of the last batch evaluated (:func:`_world_lists`), by the identity of what is in
#: them. Building numba's lists costs more than an evaluation step (docs/simulation.md, "Figures
#: behind the code's choices").
_last_lists: list[tuple[tuple[int, ...], tuple[Any, ...]]] = []


def _world_lists(swarms: Sequence[Swarm]) -> tuple[Any, ...]:
    # The kernel's per-world lists: geometries, sensings, and recordings that record nothing. A
    # world's constants are replaced when it is reset or restored, so the same objects mean the
    # same lists; held here, they stay alive and their ids unique.
    parts = [swarm.world.kernel_constants for swarm in swarms]
    key = tuple(id(item) for part in parts for item in part)
    if _last_lists and _last_lists[0][0] == key:
        return _last_lists[0][1][:3]
    lists = tuple(typed_list([part[k] for part in parts]) for k in range(2))
    empty = typed_list([swarm._recording(0, False) for swarm in swarms])
    value = (*lists, empty, parts)
    _last_lists[:] = [(key, value)]
    return value[:3]
