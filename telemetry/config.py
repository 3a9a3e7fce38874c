"""Configuration of telemetry: which MQTT broker, under which topic prefix, how much and how often.

The same section appears in the agent's and in the master's configuration file; absent (or without
``broker``) means telemetry is off and nothing MQTT-related is imported::

    telemetry:
      broker: mqtt://192.168.1.10:1883   # mqtt://host[:port], port 1883 by default
      prefix: surprise                   # topic prefix; separates labs or concurrent runs
      rate_hz: 2                         # step samples per second per robot (0: none)
      queue_size: 256                    # messages held while the broker is slow or away
      client_id: null                    # default: surprise-<robot_id>, random for the master
      keepalive: 10                      # seconds; a vanished client is declared offline
                                         # by the broker after 1.5 times this
      reconnect: {initial: 1.0, max: 30.0, jitter: 0.25}

See ``docs/telemetry.md`` for the topic tree and the payloads.
"""

from __future__ import annotations

import importlib.util
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Final
from urllib.parse import urlsplit

import msgspec

from minimize_surprise.backoff import BackoffConfig
from minimize_surprise.config import Strict
from minimize_surprise.errors import ConfigError

__all__ = [
    "DEFAULT_MQTT_PORT",
    "DEFAULT_PREFIX",
    "BrokerAddress",
    "TelemetryConfig",
    "check_prefix",
    "parse_broker_url",
    "require_client_library",
]

#: The IANA port of unencrypted MQTT.
DEFAULT_MQTT_PORT: Final = 1883
#: The default first level of every topic.
DEFAULT_PREFIX: Final = "surprise"

_Seconds = Annotated[float, msgspec.Meta(gt=0.0, le=3600.0)]
# A topic level may hold anything but the separator and the wildcards; keep prefixes plain.
_PREFIX_LEVEL = re.compile(r"[A-Za-z0-9._-]+")


@dataclass(frozen=True)
class BrokerAddress:
    """Where the broker listens, parsed from an ``mqtt://host[:port]`` URL."""

    host: str
    port: int = DEFAULT_MQTT_PORT

    @property
    def url(self) -> str:
        """The address as a URL again (IPv6 hosts in brackets)."""
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"mqtt://{host}:{self.port}"


def parse_broker_url(url: str) -> BrokerAddress:
    """Parse ``mqtt://host[:port]``; raises ValueError saying what is wrong.

    Only plain MQTT over TCP is supported: the broker is expected on the lab's own network, as is
    the master's TCP port.
    """
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as exc:  # a port that is not a number or out of range
        raise ValueError(f"not a broker URL ({exc}): expected mqtt://host[:port]") from None
    if parts.scheme != "mqtt":
        raise ValueError(f"expected a URL of the form mqtt://host[:port], got {url!r}")
    if not parts.hostname:
        raise ValueError(f"the URL names no host: {url!r}")
    if parts.username or parts.password or parts.path not in ("", "/") or parts.query:
        raise ValueError(f"expected only mqtt://host[:port], got {url!r}")
    if port == 0:
        raise ValueError(f"port 0 is not a broker's port: {url!r}")
    return BrokerAddress(parts.hostname, port if port is not None else DEFAULT_MQTT_PORT)


def check_prefix(prefix: str) -> str:
    """Return ``prefix`` if it is one or more plain topic levels (``lab/run-3``), else raise
    ValueError. Wildcards, empty levels and a leading ``$`` or ``/`` would make the documented
    subscriptions (``<prefix>/#``) match too much or nothing."""
    levels = prefix.split("/")
    if not prefix or not all(_PREFIX_LEVEL.fullmatch(level) for level in levels):
        raise ValueError(
            f"expected topic levels of letters, digits, '.', '_' or '-' separated by '/', "
            f"got {prefix!r}"
        )
    return prefix


class TelemetryConfig(Strict, frozen=True):
    """The ``telemetry`` section; see the module docstring for an example.

    ``broker`` None means off. ``rate_hz`` is the rate of a robot's step samples (0: none; it is
    rounded to a whole number of control steps). ``queue_size`` bounds the messages waiting for
    the broker; when it is full the oldest is dropped and counted. ``client_id`` must be unique on
    the broker (default: ``surprise-<robot_id>`` for a robot, a random one for the master).
    """

    #: the MQTT broker, ``mqtt://host[:port]`` (port 1883 by default); ``null``: telemetry off
    broker: str | None = None
    #: the first topic level(s), e.g. ``lab-a/run-3``; separates labs or concurrent runs
    prefix: str = DEFAULT_PREFIX
    #: a robot's step samples per second (0: none), rounded to a whole number of control steps
    rate_hz: Annotated[float, msgspec.Meta(ge=0.0, le=100.0)] = 2.0
    #: messages kept while the broker is slow or away; when full, the oldest is dropped and
    #: counted
    queue_size: Annotated[int, msgspec.Meta(ge=1, le=1_000_000)] = 256
    #: the client id, unique on the broker (``null``: ``surprise-<robot_id>`` on a robot, a
    #: random one on the master)
    client_id: Annotated[str, msgspec.Meta(min_length=1, max_length=128)] | None = None
    #: MQTT keep-alive in seconds; the broker declares a silent client gone (and publishes its
    #: last will) after 1.5 times this
    keepalive: Annotated[int, msgspec.Meta(ge=1, le=65535)] = 10
    #: delays between attempts to reach the broker
    reconnect: BackoffConfig = msgspec.field(default_factory=lambda: BackoffConfig(initial=1.0))

    def __post_init__(self) -> None:
        if self.broker is not None:
            try:
                parse_broker_url(self.broker)
            except ValueError as exc:
                raise ValueError(f"`broker`: {exc}") from None
        try:
            check_prefix(self.prefix)
        except ValueError as exc:
            raise ValueError(f"`prefix`: {exc}") from None

    @property
    def enabled(self) -> bool:
        """Whether a broker is configured."""
        return self.broker is not None

    @property
    def address(self) -> BrokerAddress:
        """The parsed broker address; only when :attr:`enabled`."""
        if self.broker is None:
            raise ValueError("telemetry is off: no broker configured")
        return parse_broker_url(self.broker)


def require_client_library(
    config: TelemetryConfig | None,
    *,
    file: str | Path | None = None,
    key: str = "telemetry.broker",
) -> None:
    """Raise :class:`ConfigError` if telemetry is on but the MQTT client (``aiomqtt``) is missing.

    Called by the composition roots so that a broker configured on a machine without the
    ``telemetry`` extra is one clear message at start, not a silent absence of telemetry.
    """
    if config is None or not config.enabled:
        return
    if importlib.util.find_spec("aiomqtt") is None:
        raise ConfigError(
            "a broker is configured but the MQTT client is not installed: "
            "pip install 'minimize-surprise[telemetry]'",
            file=str(file) if file is not None else None,
            key=key,
        )
