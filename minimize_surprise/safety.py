"""The safety layer: the last step before the motors (docs/safety.md).

It is a pure function of (sensor values, intended command, safety state): it returns the command
to apply, the next state and why it intervened, and does no I/O, reads no clock and holds no
mutable state. Even its randomness (the direction and length of an escape turn) is a small
counter-based generator carried in the state, so a step can be replayed exactly from its inputs.

The rules are one kernel, :func:`safety_step` (compiled by numba where available), which the
robot's agent runs for its one robot through :class:`SafetyLayer` and the simulator's engine runs
for every robot of every run; the two cannot drift apart. Every number and every condition is a
field of :class:`SafetyConfig`, so the real robots' rules (the ``lab`` setting, the authors'
real-robot code) and the paper's Webots rules (the ``paper`` setting) are two configurations.
Why one file of over 600 lines: the rules, their every parameter and their one kernel are read
together when a rule changes, and the robot and the engine must share exactly this code::

    layer = SafetyLayer(body.sensors, config.safety)
    state = layer.initial_state(seed)
    ...
    decision = layer.step(state, frame.values, intended, age=clock.now() - frame.timestamp)
    state = decision.state
    await body.drive(*decision.command)

Two profiles, chosen by :attr:`SafetyConfig.profile`:

``stop`` (basic behaviours, paper Sec. V-B)
    Stateless. Only while the command drives roughly straight (``|(l + r) / (r - l)| >= ratio``,
    ``r == l`` straight; with ``stop_both_wheels`` only when both wheels turn that way): driving
    forward, stop if a front IR is above ``stop_ir_threshold`` or a ground sensor sees the
    boundary; driving backward, the same with the rear IR (and the ground if
    ``stop_ground_when_reversing``). Turning commands pass, which is what lets the robots evolve
    their own obstacle avoidance.

``escape`` (object manipulation, paper Sec. V-C)
    A front obstacle starts an escape: reverse at ``escape_speed`` for ``escape_drive_steps``,
    then turn on the spot in a random direction for a random ``turn_steps_min..turn_steps_max``
    steps. A rear obstacle does the same driving forward. Force above ``force_threshold`` or the
    boundary under a ground sensor starts the turn at once (with ``boundary_turn_ratio``, only if
    the command is not already a sharp turn). A running manoeuvre ignores the network. More than
    ``backward_limit_steps`` consecutive backward commands stop the robot until the network
    commands otherwise. With ``escape_looks_ahead`` (ours, the lab's default) a drive phase that
    meets an obstacle in its own direction turns at once, and an escape never drives into a
    known obstacle. The experimenter may start the front obstacle's escape by hand
    (``escape_now``, paper Sec. V-C: forcing a robot back into the arena); it starts the same
    bounded manoeuvre and cannot command the motors otherwise. Call :meth:`SafetyLayer.reset`
    when a new genome arrives.

Always, in both profiles: a non-finite command (NaN, inf) becomes a stop, commands are clamped to
[-1, 1], stale or non-finite sensor data stop the robot, and a rule whose sensors the layout lacks
is simply off (see :attr:`SafetyLayer.active_rules`).
"""

from __future__ import annotations

import math
import zlib
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from functools import lru_cache
from typing import Annotated, Literal, NamedTuple

import msgspec
import numpy as np

from minimize_surprise.config import NonNegativeFloat, PositiveInt, Probability, Strict
from minimize_surprise.jit import kernel
from minimize_surprise.rng import next_state, unit
from minimize_surprise.sensors import FORCE_SENSORS, GROUND_SENSORS, IR_SENSORS, check_sensor_names

# Why the layer changed the command. Short and stable: the evaluation runner counts interventions
# by these strings and the traces store them. ``None`` means the command passed unchanged.
REASON_CLAMP = "clamp"  #: a finite command value was outside [-1, 1]
REASON_INVALID = "invalid"  #: a command value was NaN or infinite: both wheels stop
REASON_STALE = "stale"  #: the sensor frame is not fresh (caller said so, or it is too old)
REASON_SENSOR = "sensor"  #: a sensor value the layer uses is NaN or infinite
REASON_FRONT = "front"  #: a front IR saw an obstacle (stop, or start of an escape)
REASON_REAR = "rear"  #: a rear IR saw an obstacle (stop, or start of an escape)
REASON_GROUND = "ground"  #: a ground sensor saw the arena boundary
REASON_FORCE = "force"  #: the pushing force is above the limit
REASON_ESCAPE = "escape"  #: a step of an escape manoeuvre that began on an earlier step
REASON_BACKWARD_LIMIT = "backward-limit"  #: driven backward for too long
REASON_EXPERIMENTER = "experimenter"  #: the experimenter started an escape (paper Sec. V-C)

#: Every reason, for the evaluation runner's counters. When several apply in one step the first
#: that decides the applied command is reported: stale data, then the experimenter's escape, the
#: sensor rules and escapes, then the backward limit, then the repair of the command itself. A
#: reason's position here is its code in the kernels (0: none); the experimenter's comes last only
#: because it came last.
REASONS: tuple[str, ...] = (
    REASON_STALE,
    REASON_SENSOR,
    REASON_FRONT,
    REASON_REAR,
    REASON_FORCE,
    REASON_GROUND,
    REASON_ESCAPE,
    REASON_BACKWARD_LIMIT,
    REASON_INVALID,
    REASON_CLAMP,
    REASON_EXPERIMENTER,
)
# Appended last, so every older reason keeps its code (and a recorded engine run its meaning).
_NONE, _STALE, _SENSOR, _FRONT, _REAR, _FORCE, _GROUND, _ESCAPE, _BACKWARD, _INVALID, _CLAMP = (
    range(11)
)
_EXPERIMENTER = 11
#: The reason of each kernel code (code 0 is no intervention).
REASON_OF_CODE: tuple[str | None, ...] = (None, *REASONS)

STOP: tuple[float, float] = (0.0, 0.0)

_FRONT_IR = IR_SENSORS[:5]
_REAR_IR = IR_SENSORS[5:]
# Kernel state: [phase, steps_left, direction, backward_steps, rng]; phases:
_IDLE, _DRIVE, _TURN = 0, 1, 2
#: In the kernel, no new manoeuvre begins (a running one goes on).
_KEEP = _IDLE
_PHASES: tuple[str, ...] = ("idle", "drive", "turn")

Speed = Annotated[float, msgspec.Meta(gt=0.0, le=1.0)]


class SafetyConfig(Strict, frozen=True):
    """Thresholds, timings and conditions of the safety layer (docs/safety.md).

    Sensor thresholds are on normalised values in [0, 1]; steps are control steps; speeds are
    normalised wheel speeds. The defaults are the real robots' (the authors' real-robot code and
    the paper's Sec. V); the ``paper`` setting replaces them with the authors' Webots rules.
    """

    #: ``stop`` for the basic behaviours, ``escape`` for object manipulation (paper Sec. V-B, V-C)
    profile: Literal["stop", "escape"] = "stop"
    #: a frame older than this (seconds) is stale; ``None`` trusts the caller's ``fresh`` flag only.
    #: Ours: 0.25 s is 2.5 periods of the 10 Hz loop, about 2.7 cm at the real robots' top speed.
    max_frame_age: NonNegativeFloat | None = 0.25
    #: which ground values mean "the arena boundary": ``above`` the threshold (a bright floor
    #: beyond the carpet, the real robots) or ``below`` it (nothing beyond the carpet: Webots's
    #: ground sensors read 0 there)
    ground_boundary: Literal["above", "below"] = "above"
    #: the ground threshold (above: at least this; below: less than this). The authors' code.
    ground_threshold: Probability = 0.55

    # --- stop profile
    #: IR value above which a robot ahead (or behind, when reversing) stops a straight drive
    #: (the authors' real-robot code: 0.75; Webots: 0.9)
    stop_ir_threshold: Probability = 0.75
    #: a command is "straight" when |(l + r) / (r - l)| >= this ratio (the authors' code)
    straight_ratio: NonNegativeFloat = 1.0
    #: check forward (backward) driving only when both wheels turn forward (backward); the
    #: authors' Webots code. Off: the sign of l + r decides.
    stop_both_wheels: bool = False
    #: apply the ground rule to straight backward driving too. Off on the real robots, as in the
    #: paper: the ground sensors sit at the front, so a robot reversing away from the edge still
    #: sees it and the rule would hold it there for good; the arena's walls keep reversing robots
    #: in. The authors' Webots code checks it (there, nothing beyond the carpet reads 0, which a
    #: robot reversing off it sees only when almost out, paper Sec. V-B).
    stop_ground_when_reversing: bool = False

    # --- escape profile
    #: a front IR above this starts an escape backward (the authors used 0.35 to 0.4)
    escape_front_threshold: Probability = 0.4
    #: a rear IR above this starts an escape forward (the authors' code)
    escape_rear_threshold: Probability = 0.4
    #: force above this turns the robot away from the boxes. The authors' real-robot code used
    #: 0.45; the paper states P > 0.25 (about 10 boxes) for its own normalisation.
    force_threshold: Probability = 0.45
    #: steps of the straight part of an escape (0: turn at once; the authors' code: 30)
    escape_drive_steps: Annotated[int, msgspec.Meta(ge=0)] = 30
    #: wheel speed of the straight part of an escape (the authors' code: full speed)
    escape_speed: Speed = 1.0
    #: the fewest steps of a turn on the spot: its length is drawn uniformly from
    #: [turn_steps_min, turn_steps_max] (the authors' code: 25 to 44)
    turn_steps_min: PositiveInt = 25
    #: the most steps of a turn on the spot
    turn_steps_max: PositiveInt = 44
    #: wheel speed of the turn on the spot (the sources give none; full speed, like the reverse)
    turn_speed: Speed = 1.0
    #: probability that a turn is clockwise (left wheel forward); the authors' Webots code: 49/99
    turn_clockwise_probability: Probability = 0.5
    #: force and boundary turn the robot only if the command is not already a sharp turn,
    #: |(l + r) / (r - l)| > this ratio (the authors' Webots code: 1/3); ``None``: always
    boundary_turn_ratio: NonNegativeFloat | None = None
    #: ours: a drive phase that meets an obstacle in its own direction turns at once, an escape
    #: never drives into a known obstacle, and a boxed-in robot only turns (turning on the spot
    #: moves the robot least). The authors' code does none of this.
    escape_looks_ahead: bool = True
    #: a (0, 0) command is left alone: no rule is checked and the backward count stays (the
    #: authors' Webots code); otherwise an obstacle next to a standing robot starts an escape
    skip_rules_when_still: bool = False
    #: more consecutive backward steps than this stop the robot (paper: 9 s; 90 steps at 10 Hz);
    #: ``None`` switches the rule off
    backward_limit_steps: PositiveInt | None = 90
    #: the authors' Webots counting: a backward step needs both wheels backward, any other moving
    #: command resets the count, and nothing is counted during a manoeuvre; otherwise a step with
    #: no wheel forward and one backward counts, also during a manoeuvre, and only a wheel forward
    #: resets it (the paper: "positive motor values")
    backward_needs_both_wheels: bool = False

    def __post_init__(self) -> None:
        if self.turn_steps_max < self.turn_steps_min:
            raise ValueError(
                f"`turn_steps_max`: must be at least turn_steps_min ({self.turn_steps_min})"
            )


class SafetyParams(NamedTuple):
    """:class:`SafetyConfig` as the kernel takes it (a tuple of numbers and flags)."""

    escape: bool
    max_frame_age: float  # negative: no limit
    ground_below: bool
    ground_threshold: float
    stop_ir_threshold: float
    straight_ratio: float
    stop_both_wheels: bool
    stop_ground_when_reversing: bool
    escape_front_threshold: float
    escape_rear_threshold: float
    force_threshold: float
    escape_drive_steps: int
    escape_speed: float
    turn_steps_min: int
    turn_steps_max: int
    turn_speed: float
    turn_clockwise_probability: float
    boundary_turn_ratio: float  # negative: always
    escape_looks_ahead: bool
    skip_rules_when_still: bool
    backward_limit_steps: int  # negative: off
    backward_needs_both_wheels: bool


class SafetySensors(NamedTuple):
    """Where each group of sensors the rules read sits in the sensor values, as the kernel takes
    it: int64 positions in ``values`` (empty: that group's rule is off). Fixed per sensor layout
    (:class:`SafetyLayer` makes it once); built with every field named, which a test checks."""

    front: np.ndarray  # the front IRs: the stop profile's forward rule, escapes backward
    rear: np.ndarray  # the rear IRs: the stop profile's backward rule, escapes forward
    ground: np.ndarray  # the ground sensors: the boundary rule
    force: np.ndarray  # the force sensor: the escape profile's pushing rule


class SafetyInput(NamedTuple):
    """One step's input to the kernel: the reading and the intended command. Built with every
    field named, which a test checks (a swapped pair of positional floats would compile and
    run)."""

    values: np.ndarray  # the normalised sensor values, float64, in the layout's order
    left: float  # the intended left wheel command (not trusted: NaN, inf, out of range)
    right: float  # the intended right wheel command
    fresh: bool  # False: the values are not a new reading (a failed or timed-out read)
    age: float  # the reading's age in seconds; -inf: unknown (only ``fresh`` counts)
    # The experimenter asked for an escape now (``surprise-master escape``); the escape profile
    # starts its own manoeuvre, the stop profile has none and ignores it.
    escape_now: bool = False


def safety_params(config: SafetyConfig) -> SafetyParams:
    """The kernel's form of ``config``."""
    return SafetyParams(
        escape=config.profile == "escape",
        max_frame_age=-1.0 if config.max_frame_age is None else float(config.max_frame_age),
        ground_below=config.ground_boundary == "below",
        ground_threshold=config.ground_threshold,
        stop_ir_threshold=config.stop_ir_threshold,
        straight_ratio=config.straight_ratio,
        stop_both_wheels=config.stop_both_wheels,
        stop_ground_when_reversing=config.stop_ground_when_reversing,
        escape_front_threshold=config.escape_front_threshold,
        escape_rear_threshold=config.escape_rear_threshold,
        force_threshold=config.force_threshold,
        escape_drive_steps=config.escape_drive_steps,
        escape_speed=config.escape_speed,
        turn_steps_min=config.turn_steps_min,
        turn_steps_max=config.turn_steps_max,
        turn_speed=config.turn_speed,
        turn_clockwise_probability=config.turn_clockwise_probability,
        boundary_turn_ratio=-1.0
        if config.boundary_turn_ratio is None
        else float(config.boundary_turn_ratio),
        escape_looks_ahead=config.escape_looks_ahead,
        skip_rules_when_still=config.skip_rules_when_still,
        backward_limit_steps=-1
        if config.backward_limit_steps is None
        else config.backward_limit_steps,
        backward_needs_both_wheels=config.backward_needs_both_wheels,
    )


class SafetyState(msgspec.Struct, frozen=True, kw_only=True):
    """What the layer remembers between steps (immutable; each step returns a new one).

    ``phase`` is the escape manoeuvre in progress, ``steps_left`` its remaining steps including
    the next one, ``direction`` its sign (drive: +1 forward, -1 backward; turn: +1 clockwise, i.e.
    left wheel forward, -1 counter-clockwise). ``backward_steps`` counts consecutive backward
    steps. ``rng`` is the state of the generator that draws escape turns. The ``stop`` profile
    leaves the state as it is.
    """

    phase: Literal["idle", "drive", "turn"] = "idle"
    steps_left: int = 0
    direction: int = 0
    backward_steps: int = 0
    rng: int = 0

    def to_array(self) -> np.ndarray:
        """The kernel's form: ``[phase, steps_left, direction, backward_steps, rng]``."""
        return np.array(
            [_PHASES.index(self.phase), self.steps_left, self.direction, self.backward_steps,
             self.rng],
            dtype=np.int64,
        )  # fmt: skip

    @classmethod
    def from_array(cls, state: np.ndarray) -> SafetyState:
        """The state the kernel left in ``state``."""
        return cls(
            phase=_PHASES[int(state[0])],  # type: ignore[arg-type]
            steps_left=int(state[1]),
            direction=int(state[2]),
            backward_steps=int(state[3]),
            rng=int(state[4]),
        )


class Decision(NamedTuple):
    """One step's outcome: the command to send, the next state and why (``None``: unchanged)."""

    command: tuple[float, float]
    state: SafetyState
    reason: str | None

    @property
    def intervened(self) -> bool:
        """Whether the layer changed or repaired the command, or found the sensor data unusable."""
        return self.reason is not None


# --------------------------------------------------------------------------- the kernel


@kernel(inline=True)
def _finite(values: np.ndarray, idx: np.ndarray) -> bool:
    # Whether the sensors at ``idx`` all read a number (a tuple of the four groups to loop over
    # would take and drop a reference to each array at every step). A loop: numba compiles no
    # generator expressions.
    for k in range(idx.shape[0]):  # noqa: SIM110
        if not math.isfinite(values[idx[k]]):
            return False
    return True


@kernel(inline=True)
def _peak(values: np.ndarray, idx: np.ndarray) -> float:
    # A rule whose sensors are absent never fires: -inf is below every threshold.
    best = -math.inf
    for k in range(idx.shape[0]):
        if values[idx[k]] > best:
            best = values[idx[k]]
    return best


@kernel(inline=True)
def _boundary(p: SafetyParams, values: np.ndarray, ground: np.ndarray) -> bool:
    for k in range(ground.shape[0]):
        g = values[ground[k]]
        if p.ground_below:
            if g < p.ground_threshold:
                return True
        elif g >= p.ground_threshold:
            return True
    return False


@kernel(inline=True)
def _draw_turn(p: SafetyParams, state: np.ndarray) -> None:
    # Direction first, then the length, from the generator in the state.
    rng = next_state(state[4])
    direction = 1 if unit(rng) < p.turn_clockwise_probability else -1
    rng = next_state(rng)
    span = p.turn_steps_max - p.turn_steps_min + 1
    state[0] = _TURN
    state[1] = p.turn_steps_min + int(unit(rng) * span)
    state[2] = direction
    state[4] = rng


@kernel(inline=True)
def _manoeuvre(p: SafetyParams, state: np.ndarray) -> tuple[float, float]:
    # One step of the running manoeuvre; the state moves on.
    direction = state[2]
    if state[0] == _DRIVE:
        speed = direction * p.escape_speed
        state[1] -= 1
        if state[1] <= 0:
            _draw_turn(p, state)
        return speed, speed
    speed = direction * p.turn_speed
    state[1] -= 1
    if state[1] <= 0:
        state[0] = _IDLE
        state[1] = 0
        state[2] = 0
    return speed, -speed


@kernel(inline=True)
def safety_step(
    p: SafetyParams, sensors: SafetySensors, inputs: SafetyInput, state: np.ndarray
) -> tuple[float, float, int]:
    """One step of the rules for one robot: ``(left, right, reason code)`` to apply.

    ``sensors`` are the positions in ``inputs.values`` of each group of sensors (empty: that
    rule is off); ``inputs`` are the reading and the intended command, ``inputs.age`` the
    reading's age in seconds (-inf: unknown, only ``fresh`` counts; NaN: stale); ``state``
    (int64 ``[phase, steps_left, direction, backward_steps, rng]``) is updated in place. Four
    arguments of four kinds with every input named in them: two of them swapped fail (numba
    does not compile the call, Python raises AttributeError). Reason codes index
    :data:`REASON_OF_CODE`.
    """
    front, rear, ground, force = sensors.front, sensors.rear, sensors.ground, sensors.force
    values, left, right = inputs.values, inputs.left, inputs.right
    fresh, age = inputs.fresh, inputs.age
    max_age = p.max_frame_age
    # -inf: the age is unknown, only ``fresh`` counts; a NaN age is stale.
    if not fresh or (max_age >= 0.0 and age != -math.inf and not age <= max_age):
        return 0.0, 0.0, _STALE
    if not (
        _finite(values, front)
        and _finite(values, rear)
        and _finite(values, ground)
        and _finite(values, force)
    ):
        return 0.0, 0.0, _SENSOR
    if not (math.isfinite(left) and math.isfinite(right)):
        return 0.0, 0.0, _INVALID
    reason = _NONE
    cl = min(max(left, -1.0), 1.0)
    cr = min(max(right, -1.0), 1.0)
    if cl != left or cr != right:
        reason = _CLAMP
    left, right = cl, cr

    if not p.escape:
        # |(l + r) / (r - l)| >= k without the division, so r == l is straight (0 >= 0).
        straight = abs(left + right) >= p.straight_ratio * abs(right - left)
        if p.stop_both_wheels:
            forward = left > 0.0 and right > 0.0
            backward = left < 0.0 and right < 0.0
        else:
            forward = left + right > 0.0
            backward = left + right < 0.0
        if straight and (forward or backward):
            ir = _peak(values, front if forward else rear)
            if ir > p.stop_ir_threshold:
                return 0.0, 0.0, _FRONT if forward else _REAR
            if (forward or p.stop_ground_when_reversing) and _boundary(p, values, ground):
                return 0.0, 0.0, _GROUND
        return left, right, reason

    still = left == 0.0 and right == 0.0
    # The backward limit counts the network's intent, not what the layer applies: it limits an
    # evolved reversing behaviour, while the layer's own escapes are short by construction. The
    # authors' Webots counting skips manoeuvres, like every rule there.
    counting = not (still and p.skip_rules_when_still)
    if p.backward_needs_both_wheels and state[0] != _IDLE:
        counting = False
    if counting:
        if p.backward_needs_both_wheels:
            if left < 0.0 and right < 0.0:
                state[3] += 1
            elif not still:
                state[3] = 0
        elif left > 0.0 or right > 0.0:
            state[3] = 0
        elif left < 0.0 or right < 0.0:
            state[3] += 1

    obstacle_front = _peak(values, front) > p.escape_front_threshold
    obstacle_rear = _peak(values, rear) > p.escape_rear_threshold
    pushing = _peak(values, force) > p.force_threshold
    boundary = _boundary(p, values, ground)
    # What makes a straight drive ahead unsafe; the first hit names the reason.
    ahead = _FRONT if obstacle_front else (_FORCE if pushing else (_GROUND if boundary else 0))

    # Which manoeuvre this step runs, decided first and run once below: each helper then has
    # one call site, so one inlined copy of it (every copy is code to optimise and emit in each
    # kernel that inlines the layer, and the engine's first run on a machine waits for it).
    code = -1  # no manoeuvre: the network's command, checked against the limit below
    begin = _KEEP
    direction = 0
    if inputs.escape_now:
        # The experimenter's hand (paper Sec. V-C): the escape a front obstacle starts, reverse
        # then turn, whatever runs now; the same manoeuvre, bounded as the layer's own. A robot
        # that left the arena drove out forward, so reversing brings it back in.
        code, direction = _EXPERIMENTER, -1
        begin = _TURN if p.escape_looks_ahead and obstacle_rear else _DRIVE
    elif state[0] != _IDLE:
        code = _ESCAPE
        if p.escape_looks_ahead and state[0] == _DRIVE:
            blocked = ahead if state[2] > 0 else (_REAR if obstacle_rear else 0)
            if blocked:
                code, begin = blocked, _TURN
    elif still and p.skip_rules_when_still:
        return left, right, reason
    elif obstacle_front:
        # Boxed in front and back (looking ahead): either straight move would hit something,
        # so only turn.
        code, direction = _FRONT, -1
        begin = _TURN if p.escape_looks_ahead and obstacle_rear else _DRIVE
    elif obstacle_rear:
        # Escape forward unless the way ahead is unsafe too (front is already known clear).
        code, direction = _REAR, 1
        begin = _TURN if p.escape_looks_ahead and ahead else _DRIVE
    elif ahead:  # force or the boundary: turn on the spot, unless already turning sharply
        ratio = p.boundary_turn_ratio
        if ratio < 0.0 or left == right or abs(left + right) > ratio * abs(right - left):
            code, begin = ahead, _TURN
    if code >= 0:
        if begin == _DRIVE and p.escape_drive_steps == 0:
            begin = _TURN  # no drive phase: the turn at once
        if begin == _TURN:
            _draw_turn(p, state)
        elif begin == _DRIVE:
            state[0] = _DRIVE
            state[1] = p.escape_drive_steps
            state[2] = direction
        sl, sr = _manoeuvre(p, state)
        return sl, sr, code
    limit = p.backward_limit_steps
    # An intended stop is already what the limit wants: it passes and counts as no intervention.
    if limit >= 0 and state[3] > limit and not still:
        return 0.0, 0.0, _BACKWARD
    return left, right, reason


# --------------------------------------------------------------------------- the layer


def _sanitise(left: object, right: object) -> tuple[float, float, bool]:
    """Floats for the kernel, or False when a value is not a number at all."""
    try:
        return float(left), float(right), True  # type: ignore[arg-type]
    except (TypeError, ValueError, OverflowError):  # not a number, or an int beyond float
        return 0.0, 0.0, False


class SafetyLayer:
    """The rules for one sensor layout and configuration; see the module docstring.

    ``sensors`` are the names of the values passed to :meth:`step`, in that order (the body's
    :attr:`~drivers.body.Body.sensors`).
    """

    def __init__(self, sensors: Sequence[str], config: SafetyConfig | None = None) -> None:
        self.sensors = check_sensor_names(tuple(sensors))
        self.config = config if config is not None else SafetyConfig()
        self.params = safety_params(self.config)
        where = {name: i for i, name in enumerate(self.sensors)}

        def indices(group: Sequence[str]) -> np.ndarray:
            return np.array([where[n] for n in group if n in where], dtype=np.int64)

        force = indices(FORCE_SENSORS)
        #: the kernel's positions of each group of sensors in :attr:`sensors`
        self.groups = SafetySensors(
            front=indices(_FRONT_IR),
            rear=indices(_REAR_IR),
            ground=indices(GROUND_SENSORS),
            # the stop profile has no force rule
            force=force[:0] if self.config.profile == "stop" else force,
        )

    @property
    def front(self) -> np.ndarray:
        """The positions of the front IRs in :attr:`sensors`."""
        return self.groups.front

    @property
    def rear(self) -> np.ndarray:
        """The positions of the rear IRs in :attr:`sensors`."""
        return self.groups.rear

    @property
    def ground(self) -> np.ndarray:
        """The positions of the ground sensors in :attr:`sensors`."""
        return self.groups.ground

    @property
    def force(self) -> np.ndarray:
        """The positions of the force sensor in :attr:`sensors` (none in the stop profile)."""
        return self.groups.force

    @property
    def active_rules(self) -> tuple[str, ...]:
        """The sensor rules this layout supports (reason names); the others are off."""
        groups = (
            (REASON_FRONT, self.front),
            (REASON_REAR, self.rear),
            (REASON_FORCE, self.force),
            (REASON_GROUND, self.ground),
        )
        return tuple(reason for reason, idx in groups if idx.size)

    def initial_state(self, seed: int = 0) -> SafetyState:
        """The state at start-up; ``seed`` fixes the escape turns (use one seed per robot)."""
        return SafetyState(rng=seed & 0xFFFFFFFF)

    def reset(self, state: SafetyState) -> SafetyState:
        """The state for a new genome: no manoeuvre, backward count zero, random stream kept."""
        return SafetyState(rng=state.rng)

    def step(
        self,
        state: SafetyState,
        values: Sequence[float] | np.ndarray,
        command: Sequence[float] | np.ndarray,
        *,
        fresh: bool = True,
        age: float | None = None,
        escape_now: bool = False,
    ) -> Decision:
        """Decide the command to apply for one control step.

        ``values`` are the normalised sensor values in the order of :attr:`sensors`; ``command`` is
        the network's intended (left, right), not trusted in any way; ``fresh`` is False when the
        caller knows the values are not a new reading (a failed or timed-out read); ``age`` is how
        old the reading is in seconds (``None``: unknown, only ``fresh`` counts). ``escape_now``:
        the experimenter asked for an escape; in the ``escape`` profile this step starts the
        manoeuvre a front obstacle starts (reason ``experimenter``) unless the data is stale or
        broken (then the caller asks again next step), the ``stop`` profile ignores it. Raises
        ``ValueError`` if ``values`` does not match the sensor layout (a programming error).
        """
        v = np.asarray(values, dtype=np.float64)
        if v.shape != (len(self.sensors),):
            raise ValueError(f"expected {len(self.sensors)} sensor values, got shape {v.shape}")
        left, right = command
        left, right, numeric = _sanitise(left, right)
        if not numeric:
            left = right = math.nan
        array = state.to_array()
        inputs = SafetyInput(
            values=v,
            left=left,
            right=right,
            fresh=bool(fresh),
            age=-math.inf if age is None else float(age),
            escape_now=bool(escape_now),
        )
        sl, sr, code = safety_step(self.params, self.groups, inputs, array)
        changed = (array != state.to_array()).any()
        return Decision(
            (float(sl), float(sr)),
            SafetyState.from_array(array) if changed else state,
            REASON_OF_CODE[code],
        )


@lru_cache(maxsize=8)
def _layer(sensors: tuple[str, ...], config: SafetyConfig) -> SafetyLayer:
    return SafetyLayer(sensors, config)


def apply_safety(
    values: Sequence[float] | np.ndarray,
    sensors: Sequence[str],
    command: Sequence[float] | np.ndarray,
    state: SafetyState,
    config: SafetyConfig,
    *,
    fresh: bool = True,
    age: float | None = None,
) -> Decision:
    """Functional form of :meth:`SafetyLayer.step` for one-off calls (layers are cached).

    The control loop should hold a :class:`SafetyLayer` instead.
    """
    return _layer(tuple(sensors), config).step(state, values, command, fresh=fresh, age=age)


# --- how much of a run the layer drove --------------------------------------------------------

#: Above this share of steps in which the layer changed the command, what a run shows is mostly
#: the safety layer's behaviour, not the networks': the progress, the log and the report say so.
SAFETY_DOMINATES = 0.5


def safety_seed(robot_id: str) -> int:
    """The seed of a robot's escape turns (:meth:`SafetyLayer.initial_state`): stable per robot,
    different between robots, so their escape turns do not agree. The robot's agent and the
    simulator's engine both derive it here, so the two give the same turns."""
    return zlib.crc32(robot_id.encode("utf-8"))


def intervention_share(counts: Iterable[Mapping[str, int]], steps: int) -> float:
    """The share of ``steps`` (all robots' steps together) in which the layer changed the
    command, from each robot's counts of interventions per reason."""
    if steps <= 0:
        return 0.0
    return min(1.0, sum(sum(c.values()) for c in counts) / steps)


def intervention_reasons(counts: Iterable[Mapping[str, int]]) -> Counter[str]:
    """Each robot's counts of interventions per reason summed over the robots (reasons in the
    order they first appear)."""
    total: Counter[str] = Counter()
    for c in counts:
        total.update(c)
    return total
