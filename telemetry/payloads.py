"""The topic tree and the payloads: compact JSON objects, each with the payload version ``v``.

Topics, under a configurable ``<prefix>`` (default ``minimize_surprise``)::

    <prefix>/run/status              retained  the master: where the run stands (RunStatus)
    <prefix>/master/status           retained  the master's telemetry client (ClientStatus)
    <prefix>/robot/<id>/status       retained  a robot's telemetry client (ClientStatus)
    <prefix>/robot/<id>/evaluation             one per evaluation a robot ran (EvaluationSummary)
    <prefix>/robot/<id>/sample                 rate-limited control steps (StepSample)

The ``status`` topics of the clients are retained and carry the MQTT last will
(``{"v":1,"online":false}``), so a watcher sees a robot go offline even when it vanished without
a word. Every payload is one JSON object; readers must ignore fields they do not know (new fields
may be added without changing ``v``) and skip payloads whose ``v`` they do not know (a change of
meaning or a removed field raises ``v``). Floats in arrays are rounded to :data:`DECIMALS`
decimals: sensor values are normalised to [0, 1], so 1e-4 is below any sensor's resolution.
"""

from __future__ import annotations

import time
from typing import Any, Final, TypeVar

import msgspec
import numpy as np

__all__ = [
    "DECIMALS",
    "KINDS",
    "VERSION",
    "ClientStatus",
    "EvaluationSummary",
    "Payload",
    "RunStatus",
    "StepSample",
    "TopicInfo",
    "decode_payload",
    "encode_payload",
    "master_status_suffix",
    "now",
    "parse_topic",
    "robot_suffix",
    "run_status_suffix",
]

#: The payload version this code writes and reads.
VERSION: Final = 1
#: Decimals kept of the floats in sensor, prediction and command arrays.
DECIMALS: Final = 4
#: The per-robot topics' last levels.
KINDS: Final = ("status", "evaluation", "sample")


class Payload(msgspec.Struct, kw_only=True):
    """Base of every payload: ``v`` first, so it leads every JSON object."""

    v: int = VERSION


class ClientStatus(Payload, kw_only=True):
    """``<prefix>/robot/<id>/status`` and ``<prefix>/master/status`` (retained).

    ``online`` false comes from a clean shutdown or from the broker as the last will (then
    without ``t`` and the counters). ``dropped`` counts messages dropped because the queue was
    full, ``sent`` messages handed to the broker, both since the client started. Republished
    every :data:`telemetry.publisher.STATUS_INTERVAL` seconds while connected.
    """

    online: bool
    t: float | None = None
    dropped: int | None = None
    sent: int | None = None


class EvaluationSummary(Payload, kw_only=True):
    """``<prefix>/robot/<id>/evaluation``: one evaluation as the robot saw it.

    ``fitness`` is None when the evaluation failed, and ``failure`` then says why (it starts with
    one of the agent's failure words: ``sensor-read``, ``watchdog``, ``hardware``, ``genome``,
    ``missing-sensors``, ``internal``). ``steps`` ran of ``requested``; ``interventions`` counts
    the safety layer's interventions by reason; ``duration_s`` is on the robot's clock (simulated
    time in simulation); ``battery_v`` the battery read after it (None: unknown).
    """

    t: float
    evaluation: int
    requested: int
    steps: int
    fitness: float | None
    failure: str | None = None
    interventions: dict[str, int] = msgspec.field(default_factory=dict)
    overruns: int = 0
    read_failures: int = 0
    duration_s: float | None = None
    battery_v: float | None = None


class StepSample(Payload, kw_only=True):
    """``<prefix>/robot/<id>/sample``: one control step, at most ``rate_hz`` times a second.

    ``names`` are the experiment's sensors; ``sensors`` the readings s(t) in that order;
    ``predictions`` what the predictor forecast for these readings one step earlier, p(t) (None
    at the first step and after a lost reading); ``command`` the wheel speeds applied after the
    safety layer; ``reason`` the safety layer's intervention at this step (None: none).
    """

    t: float
    evaluation: int
    step: int
    names: tuple[str, ...]
    # numpy arrays when built (copied from the loop's buffers), lists of floats when decoded
    sensors: Any
    predictions: Any
    command: tuple[float, float]
    reason: str | None = None


class RunStatus(Payload, kw_only=True):
    """``<prefix>/run/status`` (retained): the master's progress, republished on every change.

    The fields are those of ``master_service.master.Progress`` plus ``robots`` (the ids connected
    now) and ``online`` (false once the master has stopped).
    """

    t: float
    online: bool
    run_id: str
    phase: str
    waiting: bool
    evaluations: int
    total: int
    best_fitness: float | None
    last_fitness: float | None
    robots_connected: int
    robots_expected: int
    robots: list[str] = msgspec.field(default_factory=list)
    failed_attempts: int = 0
    elapsed_s: float = 0.0
    time_left_s: float | None = None
    #: why the run waits for a person (a battery swap, robots to place); None while it runs
    paused: str | None = None


def now() -> float:
    """Wall-clock time for the ``t`` fields: Unix seconds, to the millisecond."""
    return round(time.time(), 3)


def run_status_suffix() -> str:
    """The run status topic below the prefix."""
    return "run/status"


def master_status_suffix() -> str:
    """The master client's status topic below the prefix."""
    return "master/status"


def robot_suffix(robot_id: str, kind: str) -> str:
    """A robot's topic below the prefix; ``kind`` is one of :data:`KINDS`."""
    if kind not in KINDS:
        raise ValueError(f"unknown robot topic {kind!r}; expected one of {', '.join(KINDS)}")
    return f"robot/{robot_id}/{kind}"


class TopicInfo(msgspec.Struct, frozen=True):
    """A parsed topic: ``source`` is "run", "master" or "robot"; ``robot_id`` for robots."""

    source: str
    kind: str
    robot_id: str | None = None


def parse_topic(prefix: str, topic: str) -> TopicInfo | None:
    """What ``topic`` is in the tree under ``prefix``, or None if it is not one of ours."""
    if not topic.startswith(prefix + "/"):
        return None
    levels = topic[len(prefix) + 1 :].split("/")
    if levels == ["run", "status"]:
        return TopicInfo("run", "status")
    if levels == ["master", "status"]:
        return TopicInfo("master", "status")
    if len(levels) == 3 and levels[0] == "robot" and levels[1] and levels[2] in KINDS:
        return TopicInfo("robot", levels[2], levels[1])
    return None


def _enc_hook(obj: Any) -> Any:
    # numpy arrays (samples) become lists of rounded floats; numpy scalars plain numbers.
    if isinstance(obj, np.ndarray):
        return np.round(obj.astype(np.float64, copy=False), DECIMALS).tolist()
    if isinstance(obj, np.floating):
        return round(float(obj), DECIMALS)
    if isinstance(obj, np.integer):
        return int(obj)
    raise NotImplementedError(f"cannot encode {type(obj).__name__}")


_ENCODER = msgspec.json.Encoder(enc_hook=_enc_hook)


def encode_payload(payload: Payload) -> bytes:
    """Compact JSON for ``payload`` (``None`` fields are written as ``null``)."""
    return _ENCODER.encode(payload)


_P = TypeVar("_P", bound=Payload)
_VERSION_ONLY = msgspec.json.Decoder(dict[str, Any])
_DECODERS: dict[type[Any], msgspec.json.Decoder[Any]] = {}


def decode_payload(data: bytes | bytearray | str, type_: type[_P]) -> _P:
    """Decode a payload of ``type_``; unknown fields are ignored.

    Raises ValueError if it is not a JSON object, its ``v`` is not :data:`VERSION` (the message
    says which version it is), or a field has the wrong type.
    """
    if isinstance(data, str):
        data = data.encode("utf-8")
    try:
        head = _VERSION_ONLY.decode(data)
    except msgspec.DecodeError as exc:
        raise ValueError(f"not a JSON object: {exc}") from None
    version = head.get("v")
    if version != VERSION:
        raise ValueError(f"payload version {version!r} is not understood (this reads {VERSION})")
    decoder = _DECODERS.get(type_)
    if decoder is None:
        decoder = _DECODERS[type_] = msgspec.json.Decoder(type_)
    try:
        return decoder.decode(data)
    except msgspec.DecodeError as exc:
        raise ValueError(str(exc)) from None
