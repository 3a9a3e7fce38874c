"""The safety layer: the last step before the motors (docs/safety.md).

It is a pure function of (sensor values, intended command, safety state): it returns the command to
apply, the next state and why it intervened, and does no I/O, reads no clock and holds no mutable
state. Even its randomness (the direction and length of an escape turn) is a small counter-based
generator carried in :class:`SafetyState`, so a step can be replayed exactly from its inputs.

Build one :class:`SafetyLayer` per sensor layout (it resolves sensor names to indices once) and
call :meth:`SafetyLayer.step` every control step::

    layer = SafetyLayer(body.sensors, config.safety)
    state = layer.initial_state(seed)
    ...
    decision = layer.step(state, frame.values, intended, age=clock.now() - frame.timestamp)
    state = decision.state
    await body.drive(*decision.command)

Two profiles, chosen by :attr:`SafetyConfig.profile`:

``stop`` (basic behaviours, paper Sec. V-B)
    Stateless. Only while the command drives roughly straight, ``|(l + r) / (r - l)| >= ratio``
    (``r == l`` counts as straight): driving forward, stop if any front IR is above
    ``stop_ir_threshold`` or any ground value is at least ``ground_threshold``; driving backward,
    the same with the two rear IR instead of the front ones. Turning commands always pass, which is
    what lets the robots evolve their own obstacle avoidance.

``escape`` (object manipulation, paper Sec. V-C)
    A front obstacle starts an escape: reverse at ``escape_speed`` for ``escape_drive_steps``, then
    turn on the spot in a random direction for a random ``turn_steps_min..turn_steps_max`` steps. A
    rear obstacle does the same driving forward. Force above ``force_threshold`` or the arena
    boundary under a ground sensor starts the turn at once. A running manoeuvre ignores the network;
    a drive phase that meets an obstacle in its own direction of travel switches to the turn at once
    (our addition: the authors' code is silent, and turning on the spot moves the robot least).
    More than ``backward_limit_steps`` consecutive intended backward steps stop the robot until the
    network commands a positive motor value (the force sensor cannot feel boxes behind the robot).
    Call :meth:`SafetyLayer.reset` when a new genome arrives.

Always, in both profiles: a non-finite command (NaN, inf) becomes a stop, commands are clamped to
[-1, 1], stale or non-finite sensor data stop the robot, and a rule whose sensors the layout lacks
is simply off (see :attr:`SafetyLayer.active_rules`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import lru_cache
from typing import Annotated, Literal, NamedTuple

import msgspec
import numpy as np

from surprise.config import NonNegativeFloat, PositiveInt, Probability, Strict
from surprise.sensors import (
    FORCE_SENSORS,
    GROUND_SENSORS,
    IR_SENSORS,
    check_sensor_names,
)

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

#: Every reason, for the evaluation runner's counters. When several apply in one step the first
#: that decides the applied command is reported: stale data, then the sensor rules and escapes,
#: then the backward limit, then the repair of the command itself.
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
)

STOP: tuple[float, float] = (0.0, 0.0)

_FRONT_IR = IR_SENSORS[:5]
_REAR_IR = IR_SENSORS[5:]

Speed = Annotated[float, msgspec.Meta(gt=0.0, le=1.0)]


class SafetyConfig(Strict):
    """Thresholds and timings of the safety layer on the real robots (docs/safety.md).

    Sensor thresholds are on normalised values in [0, 1]; steps are control steps (0.1 s at 10 Hz);
    speeds are normalised wheel speeds. Each default says where it comes from: the paper's Sec. V
    (the rules), or the authors' code for their real Thymios (the numbers the paper leaves out).
    """

    #: ``stop`` for the basic behaviours, ``escape`` for object manipulation (paper Sec. V-B, V-C)
    profile: Literal["stop", "escape"] = "stop"
    #: a frame older than this (seconds) is stale; ``None`` trusts the caller's ``fresh`` flag only.
    #: Ours: 0.25 s is 2.5 periods of the 10 Hz loop, about 2.7 cm at the real robots' top speed.
    max_frame_age: NonNegativeFloat | None = 0.25
    #: a ground value at least this high is the arena boundary (both profiles; the authors' code)
    ground_threshold: Probability = 0.55

    # --- stop profile
    #: IR value above which a robot ahead (or behind, when reversing) stops a straight drive
    #: (the authors' code)
    stop_ir_threshold: Probability = 0.75
    #: a command is "straight" when |(l + r) / (r - l)| >= this ratio (the authors' code)
    straight_ratio: NonNegativeFloat = 1.0
    #: apply the ground rule to straight backward driving too. Off, as in the paper: the ground
    #: sensors sit at the front, so a robot reversing away from the edge still sees the boundary
    #: and the rule would hold it there for good; the arena's walls keep reversing robots in.
    stop_ground_when_reversing: bool = False

    # --- escape profile
    #: a front IR above this starts an escape backward (the authors used 0.35 to 0.4)
    escape_front_threshold: Probability = 0.4
    #: a rear IR above this starts an escape forward (the authors' code)
    escape_rear_threshold: Probability = 0.4
    #: force above this turns the robot away from the boxes. The authors' code used 0.45; the
    #: paper states P > 0.25 (about 10 boxes) for its own normalisation.
    force_threshold: Probability = 0.45
    #: steps of the straight part of an escape (0: turn at once; the authors' code: 30)
    escape_drive_steps: Annotated[int, msgspec.Meta(ge=0)] = 30
    #: wheel speed of the straight part of an escape (the authors' code: full speed)
    escape_speed: Speed = 1.0
    #: the turn on the spot lasts a uniformly drawn number of steps in [min, max] (the authors'
    #: code: 25 to 44)
    turn_steps_min: PositiveInt = 25
    turn_steps_max: PositiveInt = 44
    #: wheel speed of the turn on the spot (the sources give none; full speed, like the reverse)
    turn_speed: Speed = 1.0
    #: more consecutive intended backward steps than this stop the robot (paper: 9 s; 90 steps
    #: at 10 Hz); ``None`` switches the rule off
    backward_limit_steps: PositiveInt | None = 90

    def __post_init__(self) -> None:
        if self.turn_steps_max < self.turn_steps_min:
            raise ValueError(
                f"`turn_steps_max`: must be at least turn_steps_min ({self.turn_steps_min})"
            )


Phase = Literal["idle", "drive", "turn"]


class SafetyState(msgspec.Struct, frozen=True, kw_only=True):
    """What the layer remembers between steps (immutable; each step returns a new one).

    ``phase`` is the escape manoeuvre in progress, ``steps_left`` its remaining steps including
    the next one, ``direction`` its sign (drive: +1 forward, -1 backward; turn: +1 clockwise, i.e.
    left wheel forward, -1 counter-clockwise). ``backward_steps`` counts consecutive intended
    backward steps. ``rng`` is the state of the generator that draws escape turns. The ``stop``
    profile leaves the state as it is.
    """

    phase: Phase = "idle"
    steps_left: int = 0
    direction: int = 0
    backward_steps: int = 0
    rng: int = 0


class Decision(NamedTuple):
    """One step's outcome: the command to send, the next state and why (``None``: unchanged)."""

    command: tuple[float, float]
    state: SafetyState
    reason: str | None

    @property
    def intervened(self) -> bool:
        """Whether the layer changed or repaired the command, or found the sensor data unusable."""
        return self.reason is not None


_MASK64 = (1 << 64) - 1


def _splitmix64(state: int) -> tuple[int, int]:
    """One draw of SplitMix64: (64-bit output, next state). Tiny, pure and good enough for turns."""
    state = (state + 0x9E3779B97F4A7C15) & _MASK64
    z = state
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & _MASK64
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & _MASK64
    return z ^ (z >> 31), state


def _sanitise(left: float, right: float) -> tuple[float, float, str | None]:
    try:
        left, right = float(left), float(right)
    except (TypeError, ValueError, OverflowError):  # not a number at all, or an int beyond float
        return 0.0, 0.0, REASON_INVALID
    if not (math.isfinite(left) and math.isfinite(right)):
        # Both wheels, not only the broken one: one wheel alone would spin the robot on the spot.
        return 0.0, 0.0, REASON_INVALID
    cl = -1.0 if left < -1.0 else 1.0 if left > 1.0 else left
    cr = -1.0 if right < -1.0 else 1.0 if right > 1.0 else right
    return cl, cr, (REASON_CLAMP if (cl, cr) != (left, right) else None)


class SafetyLayer:
    """The safety layer for one sensor layout and configuration; :meth:`step` is pure.

    ``sensors`` are the names of the values passed to :meth:`step`, in that order (the body's
    :attr:`~drivers.body.Body.sensors`).
    """

    def __init__(self, sensors: Sequence[str], config: SafetyConfig | None = None) -> None:
        self.sensors = check_sensor_names(tuple(sensors))
        self.config = config if config is not None else SafetyConfig()
        where = {name: i for i, name in enumerate(self.sensors)}

        def indices(group: Sequence[str]) -> np.ndarray:
            return np.array([where[n] for n in group if n in where], dtype=np.intp)

        self._front = indices(_FRONT_IR)
        self._rear = indices(_REAR_IR)
        self._ground = indices(GROUND_SENSORS)
        self._force = indices(FORCE_SENSORS)
        if self.config.profile == "stop":
            self._force = self._force[:0]  # the stop profile has no force rule
        # Only the values a rule reads must be finite; a broken light sensor is not our business.
        self._used = np.concatenate([self._front, self._rear, self._ground, self._force])

    @property
    def active_rules(self) -> tuple[str, ...]:
        """The sensor rules this layout supports (reason names); the others are off."""
        groups = (
            (REASON_FRONT, self._front),
            (REASON_REAR, self._rear),
            (REASON_FORCE, self._force),
            (REASON_GROUND, self._ground),
        )
        return tuple(reason for reason, idx in groups if idx.size)

    def initial_state(self, seed: int = 0) -> SafetyState:
        """The state at start-up; ``seed`` fixes the escape turns (use one seed per robot)."""
        return SafetyState(rng=seed & _MASK64)

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
    ) -> Decision:
        """Decide the command to apply for one control step.

        ``values`` are the normalised sensor values in the order of :attr:`sensors`; ``command`` is
        the network's intended (left, right), not trusted in any way; ``fresh`` is False when the
        caller knows the values are not a new reading (a failed or timed-out read); ``age`` is how
        old the reading is in seconds (``None``: unknown, only ``fresh`` counts). Raises
        ``ValueError`` if ``values`` does not match the sensor layout (a programming error).
        """
        v = np.asarray(values, dtype=np.float64)
        if v.shape != (len(self.sensors),):
            raise ValueError(f"expected {len(self.sensors)} sensor values, got shape {v.shape}")
        max_age = self.config.max_frame_age
        # `not age <= max_age` also treats a NaN age as stale.
        if not fresh or (age is not None and max_age is not None and not age <= max_age):
            return Decision(STOP, state, REASON_STALE)
        if not np.isfinite(v[self._used]).all():
            return Decision(STOP, state, REASON_SENSOR)
        left, right = command
        left, right, reason = _sanitise(left, right)
        if self.config.profile == "stop":
            return self._stop_profile(v, left, right, state, reason)
        return self._escape_profile(v, left, right, state, reason)

    # ------------------------------------------------------------------ stop profile

    def _stop_profile(
        self, v: np.ndarray, left: float, right: float, state: SafetyState, reason: str | None
    ) -> Decision:
        c = self.config
        # |(l + r) / (r - l)| >= k without the division, so r == l is straight (0 >= 0).
        straight = abs(left + right) >= c.straight_ratio * abs(right - left)
        if straight and left + right != 0.0:
            forward = left + right > 0.0
            if _peak(v, self._front if forward else self._rear) > c.stop_ir_threshold:
                return Decision(STOP, state, REASON_FRONT if forward else REASON_REAR)
            if (forward or c.stop_ground_when_reversing) and _peak(
                v, self._ground
            ) >= c.ground_threshold:
                return Decision(STOP, state, REASON_GROUND)
        return Decision((left, right), state, reason)

    # ------------------------------------------------------------------ escape profile

    def _escape_profile(
        self, v: np.ndarray, left: float, right: float, state: SafetyState, reason: str | None
    ) -> Decision:
        c = self.config
        # The backward limit counts the network's intent, not what the layer applies: it limits an
        # evolved reversing behaviour, while the layer's own escapes are short by construction.
        if left > 0.0 or right > 0.0:
            backward = 0
        elif left < 0.0 or right < 0.0:
            backward = state.backward_steps + 1
        else:  # a stop is neither: it neither resets nor extends the run
            backward = state.backward_steps
        if backward != state.backward_steps:
            state = msgspec.structs.replace(state, backward_steps=backward)

        front = _peak(v, self._front) > c.escape_front_threshold
        rear = _peak(v, self._rear) > c.escape_rear_threshold
        force = _peak(v, self._force) > c.force_threshold
        ground = _peak(v, self._ground) >= c.ground_threshold
        # What makes a straight drive in each direction unsafe; the first hit names the reason.
        hits = ((front, REASON_FRONT), (force, REASON_FORCE), (ground, REASON_GROUND))
        ahead = next((why for hit, why in hits if hit), None)
        behind = REASON_REAR if rear else None

        if state.phase == "drive":
            blocked = ahead if state.direction > 0 else behind
            if blocked is not None:
                return self._begin_turn(state, blocked)
            return self._drive(state, REASON_ESCAPE)
        if state.phase == "turn":
            return self._turn(state, REASON_ESCAPE)

        if front:
            # Boxed in front and back: either straight move would hit something, so only turn.
            return self._begin_turn(state, REASON_FRONT) if rear else self._begin_drive(state, -1)
        if rear:
            # Escape forward unless the way ahead is unsafe too (front is already known clear).
            if ahead is not None:
                return self._begin_turn(state, REASON_REAR)
            return self._begin_drive(state, +1)
        if ahead is not None:  # force or ground
            return self._begin_turn(state, ahead)
        limit = c.backward_limit_steps
        # An intended stop is already what the limit wants: it passes and counts as no intervention.
        if limit is not None and backward > limit and (left, right) != STOP:
            return Decision(STOP, state, REASON_BACKWARD_LIMIT)
        return Decision((left, right), state, reason)

    def _begin_drive(self, state: SafetyState, direction: int) -> Decision:
        reason = REASON_FRONT if direction < 0 else REASON_REAR
        steps = self.config.escape_drive_steps
        if steps == 0:
            return self._begin_turn(state, reason)
        state = msgspec.structs.replace(state, phase="drive", steps_left=steps, direction=direction)
        return self._drive(state, reason)

    def _drive(self, state: SafetyState, reason: str) -> Decision:
        speed = state.direction * self.config.escape_speed
        remaining = state.steps_left - 1
        if remaining > 0:
            nxt = msgspec.structs.replace(state, steps_left=remaining)
        else:
            nxt = self._turn_state(state)
        return Decision((speed, speed), nxt, reason)

    def _turn_state(self, state: SafetyState) -> SafetyState:
        """Draw a turn: direction first, then its length (so one seed gives one sequence)."""
        c = self.config
        bits, rng = _splitmix64(state.rng)
        direction = 1 if bits >> 63 else -1
        bits, rng = _splitmix64(rng)
        steps = c.turn_steps_min + bits % (c.turn_steps_max - c.turn_steps_min + 1)
        return msgspec.structs.replace(
            state, phase="turn", steps_left=steps, direction=direction, rng=rng
        )

    def _begin_turn(self, state: SafetyState, reason: str) -> Decision:
        return self._turn(self._turn_state(state), reason)

    def _turn(self, state: SafetyState, reason: str) -> Decision:
        speed = state.direction * self.config.turn_speed
        remaining = state.steps_left - 1
        if remaining > 0:
            nxt = msgspec.structs.replace(state, steps_left=remaining)
        else:
            nxt = msgspec.structs.replace(state, phase="idle", steps_left=0, direction=0)
        return Decision((speed, -speed), nxt, reason)


def _peak(v: np.ndarray, idx: np.ndarray) -> float:
    # A rule whose sensors are absent never fires: -inf is below every threshold.
    return float(v[idx].max()) if idx.size else -math.inf


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
