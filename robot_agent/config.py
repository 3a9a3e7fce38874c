"""Configuration of one robot's agent (``surprise-agent --config FILE``).

One YAML file per robot::

    robot_id: thymio-01
    master:
      host: 192.168.1.10
      port: 7474                       # default
      secret_file: secret.key          # relative paths are relative to this file
      tls:                             # optional; plain TCP without it
        ca_file: ca.pem
        cert_file: robot.pem
        key_file: robot.key
        server_hostname: master.lab
    body: {thymio: {speed_scale: 265, failsafe: true}}   # drivers.config.BodyConfig
    safety: {profile: stop}                              # minimize_surprise.safety.SafetyConfig
    loop: {min_period: 0.1, max_steps: 36000, read_timeout: 0.15, max_read_failures: 3}
    reconnect: {initial: 0.5, max: 30, jitter: 0.25}
    telemetry: {broker: mqtt://192.168.1.10:1883}        # optional; see docs/telemetry.md

The optional Aseba failsafe (the Thymio stops itself when the Pi stops commanding it) is
``body.thymio.failsafe``; it lives with the other Thymio settings rather than twice.

Every failure is a :class:`~minimize_surprise.errors.ConfigError` naming the file, the dotted key
and what was expected. The shared secret is read from its own file (never from the YAML, which is
copied around for snapshots) by :func:`read_secret`.
"""

from __future__ import annotations

import ssl
from pathlib import Path
from typing import Annotated

import msgspec

from drivers.config import BodyConfig
from minimize_surprise.backoff import BackoffConfig
from minimize_surprise.config import Strict, load_yaml
from minimize_surprise.errors import ConfigError
from minimize_surprise.safety import SafetyConfig
from minimize_surprise.wire import DEFAULT_PORT, is_valid_robot_id
from robot_agent.watchdog import TIMEOUT as WATCHDOG_TIMEOUT
from telemetry.config import TelemetryConfig
from transport.tls import ClientTlsConfig, client_context

__all__ = [
    "MAX_PERIOD",
    "AgentConfig",
    "BackoffConfig",
    "LoopConfig",
    "MasterConfig",
    "load_agent_config",
    "make_ssl_context",
    "read_secret",
]

Port = Annotated[int, msgspec.Meta(ge=1, le=65535)]
Seconds = Annotated[float, msgspec.Meta(gt=0.0)]

#: Seconds of one control step besides the sensor read (network, safety, motor write): the margin
#: between a step's period or read and the watchdog's timeout.
STEP_MARGIN = 0.03
#: The longest control step the robot accepts: the loop feeds the watchdog once per step, so a
#: longer period would let the watchdog trip between two steps.
MAX_PERIOD = WATCHDOG_TIMEOUT - STEP_MARGIN


class MasterConfig(Strict, frozen=True):
    """Where the master listens and how the robot proves who it is."""

    #: the master's host name or address
    host: str
    #: file holding the shared secret (surrounding whitespace, e.g. a final newline, is ignored)
    secret_file: str
    #: the master's TCP port
    port: Port = DEFAULT_PORT
    #: TLS for the link (optional; plain TCP without it). Both sides prove the shared secret and
    #: authenticate every message either way (docs/protocol.md)
    tls: ClientTlsConfig | None = None

    def __post_init__(self) -> None:
        if not self.host:
            raise ValueError("`host`: must not be empty")
        if not self.secret_file:
            raise ValueError("`secret_file`: must not be empty")


class LoopConfig(Strict, frozen=True):
    """The control loop's limits; the period itself comes with each evaluation (the experiment's
    ``step_period``), and one outside [``min_period``, :data:`MAX_PERIOD`] is refused.

    The watchdog (``robot_agent.watchdog``) stops the motors after 0.25 s without a feed; the loop
    feeds it at the start and at the end of every step, so both the period and one sensor read must
    fit inside that time, with a margin for the rest of the step.
    """

    #: the shortest step the robot runs, in seconds. A real Thymio updates its sensors at 10 Hz: a
    #: shorter step would read the same values again and score predictions against stale
    #: readings. Simulated bodies have no such limit.
    min_period: Seconds = 0.1
    #: the longest evaluation the robot runs, in steps (an hour at 10 Hz; the paper's evaluations
    #: are 100 steps and its post-evaluation 1000): no master, however configured, keeps a robot
    #: driving for days.
    max_steps: Annotated[int, msgspec.Meta(ge=1)] = 36_000
    #: seconds one sensor read may take. The Thymio answers after its next 10 Hz sensor update
    #: (up to 100 ms) plus D-Bus latency; 150 ms allows that and still stops a hung read well
    #: before the watchdog would.
    read_timeout: Seconds = 0.15
    #: this many failed reads in a row stop the motors and fail the evaluation (one or two lost
    #: readings are tolerated: the motors stop for those steps and the loop carries on)
    max_read_failures: Annotated[int, msgspec.Meta(ge=1)] = 3
    #: seconds a motor stop may take before it is given up (and left to the watchdog to retry)
    stop_timeout: Seconds = 0.5

    def __post_init__(self) -> None:
        if self.min_period > MAX_PERIOD:
            raise ValueError(
                f"`min_period`: at most {MAX_PERIOD:.2f} s, so that the watchdog "
                f"({WATCHDOG_TIMEOUT} s without a feed) does not trip between steps"
            )
        if self.read_timeout > MAX_PERIOD:
            raise ValueError(
                f"`read_timeout`: at most {MAX_PERIOD:.2f} s, so that a hung read "
                f"is given up before the watchdog ({WATCHDOG_TIMEOUT} s) trips"
            )


class AgentConfig(Strict, frozen=True):
    """Everything one robot's agent needs; see the module docstring for an example file."""

    #: this robot's id: 1 to 64 letters, digits, ``.``, ``_`` or ``-``, starting with a letter or
    #: digit; it names the robot's column and trace on the master
    robot_id: str
    #: where the master listens and how the robot proves who it is
    master: MasterConfig
    #: the robot's parts: the Thymio base and the extra sensors on its Raspberry Pi
    body: BodyConfig = msgspec.field(default_factory=BodyConfig)
    #: the safety layer between the networks and the motors (docs/safety.md)
    safety: SafetyConfig = msgspec.field(default_factory=SafetyConfig)
    #: the control loop's limits
    loop: LoopConfig = msgspec.field(default_factory=LoopConfig)
    #: delays between attempts to reach the master
    reconnect: BackoffConfig = msgspec.field(default_factory=BackoffConfig)
    #: MQTT telemetry (telemetry.config.TelemetryConfig); absent or without a broker: off
    telemetry: TelemetryConfig | None = None

    def __post_init__(self) -> None:
        if not is_valid_robot_id(self.robot_id):
            raise ValueError(
                "`robot_id`: expected 1 to 64 letters, digits, '.', '_' or '-' (not starting "
                f"with a symbol), got {self.robot_id!r}"
            )


def _resolve(base: Path, value: str | None) -> str | None:
    if value is None:
        return None
    path = Path(value).expanduser()
    return str(path if path.is_absolute() else base / path)


def load_agent_config(path: str | Path) -> AgentConfig:
    """Load an agent configuration file; relative file names in it become relative to its folder.

    Raises :class:`ConfigError` naming the file and key. Files it names (secret, certificates) are
    not opened here: see :func:`read_secret` and :func:`make_ssl_context`.
    """
    path = Path(path)
    config = load_yaml(path, AgentConfig)
    base = path.parent
    master = config.master
    tls = master.tls
    if tls is not None:
        tls = msgspec.structs.replace(
            tls,
            ca_file=_resolve(base, tls.ca_file),
            cert_file=_resolve(base, tls.cert_file),
            key_file=_resolve(base, tls.key_file),
        )
    master = msgspec.structs.replace(
        master, secret_file=_resolve(base, master.secret_file), tls=tls
    )
    return msgspec.structs.replace(config, master=master)


def read_secret(config: AgentConfig, *, config_file: str | Path | None = None) -> bytes:
    """The shared secret from ``master.secret_file``, without surrounding whitespace.

    Raises :class:`ConfigError` (naming ``config_file`` and the key ``master.secret_file``) if the
    file cannot be read or holds nothing.
    """
    secret_path = config.master.secret_file
    where = {"file": str(config_file) if config_file else None, "key": "master.secret_file"}
    try:
        secret = Path(secret_path).read_bytes().strip()
    except OSError as exc:
        raise ConfigError(
            f"cannot read the secret file {secret_path}: {exc.strerror or exc}", **where
        ) from None
    if not secret:
        raise ConfigError(f"the secret file {secret_path} is empty", **where)
    return secret


def make_ssl_context(
    config: AgentConfig, *, config_file: str | Path | None = None
) -> ssl.SSLContext | None:
    """The TLS context for the link to the master, or None for plain TCP.

    Raises :class:`ConfigError` naming the ``master.tls`` key whose file cannot be loaded.
    """
    tls = config.master.tls
    if tls is None:
        return None
    return client_context(tls, file=str(config_file) if config_file else None, key="master.tls")
