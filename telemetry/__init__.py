"""Telemetry over MQTT, shared by the robots' agent and the master; off unless a broker is set.

* :mod:`telemetry.config` — the ``telemetry`` configuration section (:class:`TelemetryConfig`).
* :mod:`telemetry.payloads` — the topic tree and the versioned JSON payloads.
* :mod:`telemetry.publisher` — :class:`TelemetryPublisher`: a bounded, never-blocking queue in
  front of one MQTT connection with reconnection.
* :mod:`telemetry.robot` — a robot's evaluation summaries and rate-limited step samples.

The MQTT client (``aiomqtt``, the ``telemetry`` extra) is imported only by the publisher's
background task, so neither side needs it unless a broker is configured. See
``docs/telemetry.md``.
"""

from telemetry.config import TelemetryConfig, parse_broker_url, require_client_library
from telemetry.payloads import (
    VERSION,
    ClientStatus,
    EvaluationSummary,
    RunStatus,
    StepSample,
    decode_payload,
    encode_payload,
    parse_topic,
)
from telemetry.publisher import TelemetryPublisher
from telemetry.robot import RobotTelemetry, StepSampler

__all__ = [
    "VERSION",
    "ClientStatus",
    "EvaluationSummary",
    "RobotTelemetry",
    "RunStatus",
    "StepSample",
    "StepSampler",
    "TelemetryConfig",
    "TelemetryPublisher",
    "decode_payload",
    "encode_payload",
    "parse_broker_url",
    "parse_topic",
    "require_client_library",
]
