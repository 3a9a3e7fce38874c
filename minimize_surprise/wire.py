"""The wire protocol between the master and the robot agents.

One codec on both sides: every message is a msgspec Struct in one tagged union (the tag sits in the
field ``"type"``), encoded as msgpack into one frame's payload. After the handshake every payload
ends with a 16-byte tag (:mod:`minimize_surprise.session`) that the receiver checks before it
decodes anything. Encoding and decoding are pure; the frames that carry the payloads over a byte
stream (length header, incremental decoder) are :mod:`transport.framing`'s, and the asyncio
transport of both the master and the agent is :class:`transport.stream.MessageStream`. The
protocol's facts that both sides must agree on (default port, frame limits, keep-alive, robot ids)
are defined here too. Every message's bytes are pinned by golden files
(``tests/core/test_wire_golden.py``): a change to them is a change of the protocol.

A session (``docs/protocol.md``)::

    robot  -> Hello(robot_id, software_version, protocol_version, sensors, nonce)
    master -> Challenge(nonce, proof)             or Refused(code, reason), then close
    robot  -> Authenticate(proof)                 (only if the master's proof is right)
    master -> Welcome(run_id, heartbeat_interval) or Refused(code, reason), then close
              -- from Welcome on, every frame in both directions carries a tag --
    master -> Evaluate(...)  robot -> Result(...) | Failed(...);   master -> Abort(...) at any time
    master -> Check(seq)     robot -> CheckReport(seq, ...)        (between evaluations)
    master -> Escape(seq)    robot -> EscapeReply(seq, ...)        (only if its Hello offers it)
    master -> StopAll(seq)   robot -> Stopped(seq, ...)            (only if its Hello offers it)
    either -> Ping / Pong / Error / Bye

Everything that can arrive before authentication is bounded in its type, so decoding refuses it
(and a small frame limit, :data:`HANDSHAKE_MAX_FRAME_SIZE`, bounds it first). Decoding ignores
fields it does not know, so a newer peer may add optional fields without breaking an older one;
incompatible changes bump :data:`PROTOCOL_VERSION`, which the master checks in Hello. A message
an older peer of the same version would not decode goes only to a robot whose Hello lists its
feature (:data:`FEATURES`): such a peer would close the session on it.

Why one file of over 600 lines: the protocol is its one union of messages, their bounds and their
one codec, read together whenever it changes, and the golden bytes are enumerated from this union.
"""

from __future__ import annotations

import math
import re
from typing import Annotated, Final

import msgspec
import numpy as np

from minimize_surprise.config import MAX_RECORDED_STEPS, MAX_STEP_PERIOD
from minimize_surprise.errors import GenomeError, ProtocolError
from minimize_surprise.network import NetworkSpec
from minimize_surprise.session import NONCE_SIZE, PROOF_SIZE

__all__ = [
    "DEAD_AFTER_HEARTBEATS",
    "DEFAULT_PORT",
    "ESCAPE_REFUSED_IDLE",
    "ESCAPE_REFUSED_PROFILE",
    "FEATURES",
    "FEATURE_ESCAPE",
    "FEATURE_STOP",
    "HANDSHAKE_MAX_FRAME_SIZE",
    "LOGGED_TEXT_LIMIT",
    "MAX_BATTERY_V",
    "MAX_COMMIT_LENGTH",
    "MAX_FEATURES",
    "MAX_FIRMWARE",
    "MAX_FRAME_SIZE",
    "MAX_HEARTBEAT_INTERVAL",
    "MAX_NAME_LENGTH",
    "MAX_REASONS",
    "MAX_REASON_LENGTH",
    "MAX_SENSORS",
    "MAX_THROTTLED",
    "MIN_HEARTBEAT_INTERVAL",
    "PROTOCOL_VERSION",
    "REFUSED_BAD_SECRET",
    "REFUSED_CODES",
    "REFUSED_MISSING_SENSORS",
    "REFUSED_PROTOCOL",
    "REFUSED_UNKNOWN_ROBOT",
    "REFUSED_VERSION_MISMATCH",
    "ROBOT_ID_PATTERN",
    "TRACE_COLUMNS",
    "Abort",
    "Authenticate",
    "Bye",
    "Challenge",
    "Check",
    "CheckReport",
    "Error",
    "Escape",
    "EscapeReply",
    "Evaluate",
    "EvaluationStats",
    "Failed",
    "Hello",
    "Message",
    "PartCheck",
    "Ping",
    "Pong",
    "Refused",
    "Result",
    "StopAll",
    "Stopped",
    "Trace",
    "Welcome",
    "decode_payload",
    "encode_payload",
    "genome_from_bytes",
    "genome_to_bytes",
    "is_valid_robot_id",
    "printable",
]

#: The master's TCP port unless configured otherwise (the default of both sides' configuration).
DEFAULT_PORT: Final = 7474
#: A link is dead when nothing at all arrived for this many heartbeat intervals (either side): one
#: lost ping is no reason to drop a robot, three in a row on a lab network are.
DEAD_AFTER_HEARTBEATS: Final = 3
#: The heartbeat intervals a master may configure and a robot accepts, in seconds. Below 50 ms
#: the pings alone would keep a Pi busy and one late packet would count as a dead link; above a
#: minute a dead link would go unnoticed for minutes while the robot waits.
MIN_HEARTBEAT_INTERVAL: Final = 0.05
MAX_HEARTBEAT_INTERVAL: Final = 60.0
#: What a robot id may look like: it names a CSV column and a trace file on the master and goes
#: into the authentication, so no separators or spaces, and a bounded length.
ROBOT_ID_PATTERN: Final = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$"
_ROBOT_ID_RE: Final = re.compile(ROBOT_ID_PATTERN)

#: The most sensors a robot may announce or a trace row may hold: the project knows 12
#: (``minimize_surprise.sensors.ALL_SENSORS``); 16 leaves room for a few more while a trace of
#: ``MAX_RECORDED_STEPS`` steps still fits one frame.
MAX_SENSORS: Final = 16
#: The longest sensor name, safety reason or Refused code, in characters (the project's longest
#: has 14).
MAX_NAME_LENGTH: Final = 32
#: The most distinct safety reasons an evaluation's statistics may count.
MAX_REASONS: Final = 32
#: The longest software version a robot may announce, in characters.
MAX_VERSION_LENGTH: Final = 64
#: The longest source commit a robot may announce, in characters: a SHA-256 name (64) and a
#: ``-dirty`` mark (:mod:`minimize_surprise.provenance`), with room to spare.
MAX_COMMIT_LENGTH: Final = 80
#: The highest Thymio firmware version a robot may announce: one Aseba word.
MAX_FIRMWARE: Final = 0xFFFF
#: The longest run id, in characters: a run directory's name (file systems allow 255 bytes).
MAX_RUN_ID_LENGTH: Final = 255
#: The longest reason a Refused may give, in characters; the master cuts its reasons to it.
MAX_REASON_LENGTH: Final = 512
#: Highest battery voltage a robot may report: a Thymio's Li-ion cell is 4.2 V full; anything
#: far above is a broken reading, not a battery.
MAX_BATTERY_V: Final = 10.0
#: The highest value of a Raspberry Pi's ``vcgencmd get_throttled`` flags: bits up to 0x80000
#: are defined (under-voltage, capped, throttled, soft limit: now and since boot).
MAX_THROTTLED: Final = 0xFFFFF
#: How many characters of a text a peer sent (a reason, a message) go into a log line.
LOGGED_TEXT_LIMIT: Final = 200

#: The features a robot may offer in its Hello (:attr:`Hello.features`): messages added to
#: version 2 after robots of that version were deployed, which such a robot would not decode.
#: ``escape``: it handles :class:`Escape` (``surprise-master escape``).
FEATURE_ESCAPE: Final = "escape"
#: ``stop``: it handles :class:`StopAll` (``surprise-master fleet stop``).
FEATURE_STOP: Final = "stop"
#: Every feature this code offers, as its agent announces them.
FEATURES: Final = (FEATURE_ESCAPE, FEATURE_STOP)
#: An :class:`EscapeReply`'s refusal starts with one of these words (then ": " and the details):
#: the robot's safety profile has no escape behaviour (``stop``) ...
ESCAPE_REFUSED_PROFILE: Final = "profile"
#: ... or no evaluation runs, the motors are stopped (the master may ask again in a moment).
ESCAPE_REFUSED_IDLE: Final = "idle"
#: The most features a Hello may list (it arrives before authentication: bounded).
MAX_FEATURES: Final = 16

#: Version of this protocol; sent in Hello. Bump it for any change an older peer cannot decode.
#: 2: mutual authentication and tagged frames; the step period in Evaluate; packed traces.
PROTOCOL_VERSION: Final = 2

#: Default upper bound of one frame's payload, in bytes. A post-evaluation trace of 1000 steps x 12
#: sensors is about 0.25 MB; 8 MiB leaves ample room for longer traces while bounding the memory a
#: single (possibly hostile) connection can make us buffer.
MAX_FRAME_SIZE: Final = 8 * 1024 * 1024
#: Upper bound of one frame until the handshake is complete, on both sides. The largest handshake
#: message (a Hello of 16 sensor names and 16 features of 32 characters, a 64-character version,
#: an 80-character commit; a refusal of 512 characters) takes well under 3 KiB; a peer that has
#: not authenticated can make us buffer no more than this per connection.
HANDSHAKE_MAX_FRAME_SIZE: Final = 4 * 1024

#: Refused codes: the shared secret did not match.
REFUSED_BAD_SECRET: Final = "bad-secret"
#: Refused codes: the robot speaks another :data:`PROTOCOL_VERSION`.
REFUSED_VERSION_MISMATCH: Final = "version-mismatch"
#: Refused codes: the robot id is not part of this run.
REFUSED_UNKNOWN_ROBOT: Final = "unknown-robot"
#: Refused codes: the robot lacks a sensor the experiment needs.
REFUSED_MISSING_SENSORS: Final = "missing-sensors"
#: Refused codes: the robot broke the handshake (wrong message, wrong order, too slow).
REFUSED_PROTOCOL: Final = "protocol"
#: Every Refused code.
REFUSED_CODES: Final = frozenset(
    {
        REFUSED_BAD_SECRET,
        REFUSED_VERSION_MISMATCH,
        REFUSED_UNKNOWN_ROBOT,
        REFUSED_MISSING_SENSORS,
        REFUSED_PROTOCOL,
    }
)

# Bounds checked while decoding (msgspec does not check them when a Struct is built in code).
_NonNegative = Annotated[int, msgspec.Meta(ge=0)]
_Positive = Annotated[int, msgspec.Meta(ge=1)]
_Name = Annotated[str, msgspec.Meta(max_length=MAX_NAME_LENGTH)]
_StepPeriod = Annotated[float, msgspec.Meta(gt=0.0, le=MAX_STEP_PERIOD)]
_Nonce = Annotated[bytes, msgspec.Meta(min_length=NONCE_SIZE, max_length=NONCE_SIZE)]
_Proof = Annotated[bytes, msgspec.Meta(min_length=PROOF_SIZE, max_length=PROOF_SIZE)]
_RobotId = Annotated[str, msgspec.Meta(pattern=ROBOT_ID_PATTERN)]
_HeartbeatInterval = Annotated[
    float, msgspec.Meta(ge=MIN_HEARTBEAT_INTERVAL, le=MAX_HEARTBEAT_INTERVAL)
]


def is_valid_robot_id(robot_id: str) -> bool:
    """Whether ``robot_id`` matches :data:`ROBOT_ID_PATTERN`."""
    return _ROBOT_ID_RE.match(robot_id) is not None


def printable(text: str, limit: int = LOGGED_TEXT_LIMIT) -> str:
    """``text`` from a peer, fit for one log line: control characters (line breaks, terminal
    escapes) shown as ``?`` and at most ``limit`` characters, a cut marked with ``...``."""
    head = "".join(c if c.isprintable() else "?" for c in text[:limit])
    return head + "..." if len(text) > limit else head


# ---------------------------------------------------------------------------------------------
# Genomes


def genome_to_bytes(genome: np.ndarray) -> bytes:
    """Return a flat genome as float64 little-endian bytes (bit-exact on every platform).

    Raises :class:`GenomeError` if the genome is not one-dimensional or holds a non-finite value:
    such a genome is a bug on the sending side and must not reach a robot.
    """
    array = np.asarray(genome)
    if array.ndim != 1:
        raise GenomeError(f"a genome must be one-dimensional, got shape {array.shape}")
    array = array.astype("<f8", copy=False)
    if not np.isfinite(array).all():
        raise GenomeError("a genome must hold finite values only")
    return array.tobytes()


def genome_from_bytes(data: bytes) -> np.ndarray:
    """Return the float64 genome encoded by :func:`genome_to_bytes` as a new writable array.

    Raises :class:`ProtocolError` if the length is not a multiple of 8 or a value is not finite.
    """
    if len(data) % 8:
        raise ProtocolError(f"genome of {len(data)} bytes is not a whole number of float64 values")
    # Copy to native byte order: the caller owns the result and may compute with it directly.
    array = np.frombuffer(data, dtype="<f8").astype(np.float64)
    if not np.isfinite(array).all():
        raise ProtocolError("genome holds a non-finite value")
    return array


# ---------------------------------------------------------------------------------------------
# Messages


class _Message(msgspec.Struct, frozen=True, kw_only=True, tag_field="type"):
    """Base of every message; the subclass's tag goes in the field ``type``."""


class Hello(_Message, tag="hello", frozen=True):
    """Robot -> master, the first message: who the robot is, what it can sense, and a fresh
    ``nonce`` (:func:`minimize_surprise.session.new_nonce`) the master's proof must cover.

    ``nonce`` may only be missing in a Hello of another protocol version (so that such a robot is
    told about the version, not about a missing field). ``features`` lists the later additions to
    this version the robot handles (:data:`FEATURES`); a robot older than them sends none, and
    the master sends it none of their messages.

    ``software_commit`` is the source's commit the agent was built from
    (:func:`minimize_surprise.provenance.software_commit`) and ``thymio_firmware`` its Thymio's
    firmware version (``_fwversion[0]``): None when unknown, and from a robot older than these
    fields, which the master still accepts. The preflight compares the commit with the
    master's; the run directory records both (docs/fleet.md).
    """

    robot_id: _RobotId
    software_version: Annotated[str, msgspec.Meta(max_length=MAX_VERSION_LENGTH)]
    protocol_version: int
    sensors: Annotated[tuple[_Name, ...], msgspec.Meta(max_length=MAX_SENSORS)]
    nonce: _Nonce | None = None
    features: Annotated[tuple[_Name, ...], msgspec.Meta(max_length=MAX_FEATURES)] = ()
    software_commit: Annotated[str, msgspec.Meta(max_length=MAX_COMMIT_LENGTH)] | None = None
    thymio_firmware: Annotated[int, msgspec.Meta(ge=0, le=MAX_FIRMWARE)] | None = None


class Challenge(_Message, tag="challenge", frozen=True):
    """Master -> robot: the master's fresh ``nonce`` and its ``proof`` of the shared secret
    (:func:`minimize_surprise.session.master_proof`), which the robot checks before it answers."""

    nonce: _Nonce
    proof: _Proof


class Authenticate(_Message, tag="auth", frozen=True):
    """Robot -> master: the robot's ``proof`` (:func:`minimize_surprise.session.robot_proof`)."""

    proof: _Proof


class Welcome(_Message, tag="welcome", frozen=True):
    """Master -> robot, the first tagged frame: accepted into run ``run_id``; send or expect a
    Ping every ``heartbeat_interval`` seconds (within the protocol's bounds)."""

    run_id: Annotated[str, msgspec.Meta(max_length=MAX_RUN_ID_LENGTH)]
    heartbeat_interval: _HeartbeatInterval


class Refused(_Message, tag="refused", frozen=True):
    """Master -> robot before closing: why the robot was not accepted (one of REFUSED_CODES)."""

    code: _Name
    reason: Annotated[str, msgspec.Meta(max_length=MAX_REASON_LENGTH)]


class Evaluate(_Message, tag="eval", frozen=True):
    """Master -> robot: run ``genome`` (see :func:`genome_to_bytes`) for ``steps`` control steps
    of ``step_period`` seconds each (the experiment's period; a robot that cannot keep it answers
    Failed).

    With ``record`` (post-evaluation) the robot returns the full :class:`Trace` in its Result.
    ``post_evaluation``: this is the run's post-evaluation (or a replay's); the robot flashes its
    top LED at its start, for an overhead camera to find (docs/robot-agent.md). A robot older
    than the field ignores it and does not flash.
    """

    evaluation_id: _NonNegative
    genome: bytes
    spec: NetworkSpec
    steps: _Positive
    step_period: _StepPeriod
    record: bool = False
    post_evaluation: bool = False

    def __post_init__(self) -> None:
        # Reject a malformed genome where it enters, not deep inside the robot's control loop.
        genome_from_bytes(self.genome)
        if self.record and self.steps > MAX_RECORDED_STEPS:
            # The trace would not fit one frame: the robot could never send its Result.
            raise ProtocolError(
                f"a recorded evaluation has at most {MAX_RECORDED_STEPS} steps, not {self.steps}"
            )


class EvaluationStats(msgspec.Struct, frozen=True, kw_only=True):
    """What happened during an evaluation besides the fitness.

    ``overruns`` counts steps that missed their deadline, ``interventions`` counts safety
    interventions by reason and ``read_failures`` sensor reads that failed or timed out.
    ``battery_v`` is the robot's battery voltage read after the evaluation, None where the robot
    does not report one (Aseba Playground, a simulated robot): unknown, never a guess.
    """

    steps_run: _NonNegative
    overruns: _NonNegative
    interventions: Annotated[dict[_Name, _NonNegative], msgspec.Meta(max_length=MAX_REASONS)]
    read_failures: _NonNegative = 0
    battery_v: Annotated[float, msgspec.Meta(ge=0.0, le=MAX_BATTERY_V)] | None = None


#: Columns of each of a :class:`Trace`'s arrays; None: the trace's ``width`` (its sensors).
TRACE_COLUMNS: Final[dict[str, int | None]] = {
    "sensors": None,
    "predictions": None,
    "actions": 2,
    "commands": 2,
    "poses": 3,
}
_TRACE_DTYPE: Final = np.dtype("<f8")
# The most bytes one array of a trace can need; the decoder refuses a longer one before copying.
_MAX_TRACE_ARRAY: Final = MAX_RECORDED_STEPS * MAX_SENSORS * _TRACE_DTYPE.itemsize
_TraceArray = Annotated[bytes, msgspec.Meta(max_length=_MAX_TRACE_ARRAY)]


class Trace(msgspec.Struct, frozen=True, kw_only=True):
    """A post-evaluation record of ``steps`` control steps as packed arrays, one row per step.

    Each array is float64 little-endian bytes, row after row: ``sensors`` the ``width`` sensor
    values, ``predictions`` the ``width`` values predicted at that step for the next, ``actions``
    the 2 intended wheel speeds, ``commands`` the 2 applied after safety and, in simulation,
    ``poses`` (x, y, theta). ``safety`` holds each step's intervention reason ("" when none).
    Build one with :meth:`from_arrays`; read one with :meth:`array`.

    Packed arrays are checked for shape and size as they are decoded: ``steps`` and ``width``
    are bounded, an array longer than any trace can need is refused before it is copied, and
    every array must hold exactly ``steps`` rows. (Rows as lists of floats would let a peer make
    the receiver build millions of objects before the shape could be checked.)
    """

    steps: Annotated[int, msgspec.Meta(ge=0, le=MAX_RECORDED_STEPS)]
    width: Annotated[int, msgspec.Meta(ge=1, le=MAX_SENSORS)]
    sensors: _TraceArray
    predictions: _TraceArray
    actions: _TraceArray
    commands: _TraceArray
    safety: Annotated[list[_Name], msgspec.Meta(max_length=MAX_RECORDED_STEPS)]
    poses: _TraceArray | None = None

    def __post_init__(self) -> None:
        size = _TRACE_DTYPE.itemsize
        for name, columns in TRACE_COLUMNS.items():
            data = getattr(self, name)
            if data is None:
                continue
            columns = self.width if columns is None else columns
            expected = self.steps * columns * size
            if len(data) != expected:
                raise ValueError(
                    f"a trace's {name} must hold {self.steps} x {columns} float64 values "
                    f"({expected} bytes), not {len(data)} bytes"
                )
        if len(self.safety) != self.steps:
            raise ValueError(
                f"a trace's safety must hold one entry per step ({self.steps}), "
                f"not {len(self.safety)}"
            )

    @classmethod
    def from_arrays(
        cls,
        *,
        sensors: np.ndarray,
        predictions: np.ndarray,
        actions: np.ndarray,
        commands: np.ndarray,
        safety: list[str],
        poses: np.ndarray | None = None,
    ) -> Trace:
        """Pack arrays shaped (steps, columns); raises ``ValueError`` if their shapes disagree."""
        arrays = {
            "sensors": sensors,
            "predictions": predictions,
            "actions": actions,
            "commands": commands,
            "poses": poses,
        }
        first = np.asarray(sensors)
        if first.ndim != 2:
            raise ValueError(
                f"a trace's sensors must be shaped (steps, sensors), not {first.shape}"
            )
        steps, width = first.shape
        packed: dict[str, bytes | None] = {}
        for name, array in arrays.items():
            if array is None:
                packed[name] = None
                continue
            columns = TRACE_COLUMNS[name]
            shape = (steps, width if columns is None else columns)
            values = np.ascontiguousarray(array, dtype=_TRACE_DTYPE)
            if values.shape != shape:
                raise ValueError(f"a trace's {name} must be shaped {shape}, not {values.shape}")
            packed[name] = values.tobytes()
        return cls(steps=steps, width=width, safety=list(safety), **packed)  # type: ignore[arg-type]

    def array(self, name: str) -> np.ndarray:
        """The array ``name`` (one of :data:`TRACE_COLUMNS`) shaped (steps, columns), as a
        read-only float64 view of the bytes; raises ``KeyError`` for an unknown name and
        ``ValueError`` for ``poses`` when the trace has none."""
        columns = TRACE_COLUMNS[name]
        data = getattr(self, name)
        if data is None:
            raise ValueError(f"this trace has no {name}")
        columns = self.width if columns is None else columns
        return np.frombuffer(data, dtype=_TRACE_DTYPE).reshape(self.steps, columns)


class Result(_Message, tag="result", frozen=True):
    """Robot -> master: the fitness of evaluation ``evaluation_id``, with its trace if recorded.

    A surprise fitness lies in [0, 1] (paper Eq. 1); decoding refuses anything else, NaN
    included: one robot's garbage must not steer (or freeze) the evolution.
    """

    evaluation_id: _NonNegative
    fitness: Annotated[float, msgspec.Meta(ge=0.0, le=1.0)]
    stats: EvaluationStats
    trace: Trace | None = None


class Failed(_Message, tag="failed", frozen=True):
    """Robot -> master: evaluation ``evaluation_id`` could not be completed, and why."""

    evaluation_id: _NonNegative
    reason: str


class Abort(_Message, tag="abort", frozen=True):
    """Master -> robot: stop evaluation ``evaluation_id`` now (motors stop; no Result follows)."""

    evaluation_id: _NonNegative
    reason: str


class Check(_Message, tag="check", frozen=True):
    """Master -> robot, between evaluations (``surprise-master check``): read every part of the
    body once and answer a :class:`CheckReport` with the same ``seq``. Never drives."""

    seq: _NonNegative


class PartCheck(msgspec.Struct, frozen=True, kw_only=True):
    """One part of a robot's body as read for a check: its ``sensors`` and their normalised
    ``values``, or the ``error`` that kept it from answering (``values`` then empty)."""

    part: _Name
    sensors: Annotated[tuple[_Name, ...], msgspec.Meta(max_length=MAX_SENSORS)]
    values: Annotated[tuple[float, ...], msgspec.Meta(max_length=MAX_SENSORS)] = ()
    error: Annotated[str, msgspec.Meta(max_length=MAX_REASON_LENGTH)] | None = None


class CheckReport(_Message, tag="check-report", frozen=True):
    """Robot -> master: the answer to :class:`Check` ``seq``.

    ``time`` is the robot's wall clock (Unix seconds) when it answered, for the clock offset;
    ``battery_v`` None where the robot reports no battery; ``parts`` each part's reading;
    ``forward_safety`` the reason the robot's safety layer would stop a forward drive on this
    reading (None: it would let it pass), with ``ground_rule`` saying what its ground rule takes
    for the arena's boundary. ``busy``: an evaluation runs, nothing was read.
    """

    seq: _NonNegative
    time: float
    battery_v: Annotated[float, msgspec.Meta(ge=0.0, le=MAX_BATTERY_V)] | None = None
    parts: Annotated[tuple[PartCheck, ...], msgspec.Meta(max_length=MAX_SENSORS)] = ()
    forward_safety: _Name | None = None
    ground_rule: Annotated[str, msgspec.Meta(max_length=MAX_NAME_LENGTH)] = ""
    busy: bool = False
    throttled: Annotated[int, msgspec.Meta(ge=0, le=MAX_THROTTLED)] | None = None

    def __post_init__(self) -> None:
        # A clock or a reading that is not a number is a broken robot's message: refused where
        # it enters, as any malformed one (a part out of [0, 1] is a finding, not an error).
        if not math.isfinite(self.time):
            raise ProtocolError(f"a check report's time must be finite, not {self.time}")
        for part in self.parts:
            if not all(math.isfinite(v) for v in part.values):
                raise ProtocolError(f"check report: {part.part} holds a value that is not finite")

    def readings(self) -> dict[str, float]:
        """Every value the report holds, by sensor name (a part that failed holds none)."""
        return {
            name: value
            for part in self.parts
            for name, value in zip(part.sensors, part.values, strict=False)
        }


class Escape(_Message, tag="escape", frozen=True):
    """Master -> robot (``surprise-master escape``): the experimenter asks for the safety layer's
    escape manoeuvre now (paper Sec. V-C: forcing a robot back into the arena). The robot's layer
    starts it at the next control step of the running evaluation, bounded as its own escapes; the
    message carries no command. Sent only to a robot offering :data:`FEATURE_ESCAPE`; it answers
    an :class:`EscapeReply` with the same ``seq``."""

    seq: _NonNegative


class EscapeReply(_Message, tag="escape-reply", frozen=True):
    """Robot -> master: the answer to :class:`Escape` ``seq``. ``accepted``: the escape starts at
    the next control step of evaluation ``evaluation_id``; otherwise ``reason`` says why not,
    starting with a word (:data:`ESCAPE_REFUSED_PROFILE`: its safety layer has no escape
    behaviour; :data:`ESCAPE_REFUSED_IDLE`: no evaluation runs, so the motors are stopped)."""

    seq: _NonNegative
    accepted: bool
    evaluation_id: _NonNegative | None = None
    reason: Annotated[str, msgspec.Meta(max_length=MAX_REASON_LENGTH)] = ""


class StopAll(_Message, tag="stop-all", frozen=True):
    """Master -> robot (``surprise-master fleet stop``): stop the motors now, whatever runs; the
    running evaluation, if any, is cancelled (no Result follows) and the motors stay stopped
    until the next :class:`Evaluate`. Sent only to a robot offering :data:`FEATURE_STOP`; it
    answers a :class:`Stopped` with the same ``seq`` and never refuses. ``reason`` is for the
    robot's log."""

    seq: _NonNegative
    reason: Annotated[str, msgspec.Meta(max_length=MAX_REASON_LENGTH)] = ""


class Stopped(_Message, tag="stopped", frozen=True):
    """Robot -> master: the answer to :class:`StopAll` ``seq``. ``confirmed``: the robot itself
    confirmed the motors' stop (false: the stop's write failed or hung, ``detail`` says how;
    the agent's watchdog then took over). ``evaluation_id``: the evaluation it cancelled, None
    when none ran (the motors were stopped already)."""

    seq: _NonNegative
    confirmed: bool
    evaluation_id: _NonNegative | None = None
    detail: Annotated[str, msgspec.Meta(max_length=MAX_REASON_LENGTH)] = ""


class Ping(_Message, tag="ping", frozen=True):
    """Either way: liveness probe; the peer answers with a Pong of the same ``seq``."""

    seq: _NonNegative


class Pong(_Message, tag="pong", frozen=True):
    """Either way: the answer to the Ping with the same ``seq``."""

    seq: _NonNegative


class Error(_Message, tag="error", frozen=True):
    """Either way, before closing: the peer broke the protocol or something failed."""

    code: str
    message: str


class Bye(_Message, tag="bye", frozen=True):
    """Either way: orderly close; the sender closes the connection after it."""

    reason: str


#: Any message of the protocol.
Message = (
    Hello
    | Challenge
    | Authenticate
    | Welcome
    | Refused
    | Evaluate
    | Result
    | Failed
    | Abort
    | Check
    | CheckReport
    | Escape
    | EscapeReply
    | StopAll
    | Stopped
    | Ping
    | Pong
    | Error
    | Bye
)

_MESSAGE_TYPES: Final = Message.__args__
_encoder = msgspec.msgpack.Encoder()
_decoder = msgspec.msgpack.Decoder(Message)


# ---------------------------------------------------------------------------------------------
# The codec


def encode_payload(msg: Message) -> bytes:
    """Return ``msg`` as a frame's payload (msgpack, without the length header).

    Raises ``TypeError`` if ``msg`` is not a protocol message.
    """
    if not isinstance(msg, _MESSAGE_TYPES):
        raise TypeError(f"not a protocol message: {type(msg).__name__}")
    return _encoder.encode(msg)


def decode_payload(payload: bytes | bytearray | memoryview) -> Message:
    """Return the message in one frame's payload (without the length header or tag).

    This is the one place where decoding failures become :class:`ProtocolError` with the reason.
    """
    try:
        return _decoder.decode(payload)
    except RecursionError as exc:  # deeply nested data in an ignored field
        raise ProtocolError("malformed message: nested too deeply") from exc
    except ValueError as exc:
        # msgspec.DecodeError (and its ValidationError, which wraps __post_init__ failures), and
        # UnicodeDecodeError, which msgspec raises as is for a string that is not UTF-8.
        raise ProtocolError(f"malformed message: {exc}") from exc
