"""Configuration of the master: where it listens, who may join, how long a round may take.

A master configuration file names the experiment (inline under ``experiment`` or as a separate file
under ``experiment_file``), the shared secret's file and optionally TLS certificate files. Relative
paths are resolved against the configuration file's directory. :func:`load_master_config` returns a
*resolved* configuration: the experiment inline and every path absolute, which is what the run
directory's snapshot holds, so ``resume`` needs nothing but the run directory.

Example::

    experiment_file: experiment.yaml
    host: 0.0.0.0
    port: 7474
    secret_file: secret.txt
    inventory: fleet.yaml     # the fleet (docs/fleet.md); or allowed_robots: [thymio-1, ...]
    round_margin: 5.0
    heartbeat_interval: 2.0
    telemetry: {broker: mqtt://localhost:1883}   # optional; see docs/telemetry.md
"""

from __future__ import annotations

import ssl
from pathlib import Path
from typing import Annotated, Final

import msgspec

from master_service.inventory import Inventory, load_inventory
from minimize_surprise.config import (
    ExperimentConfig,
    Strict,
    decode,
    load_experiment,
    read_yaml,
    resolve_arena,
    with_setting,
)
from minimize_surprise.errors import ConfigError
from minimize_surprise.wire import (
    DEFAULT_PORT,
    MAX_BATTERY_V,
    MAX_FRAME_SIZE,
    MAX_HEARTBEAT_INTERVAL,
    MIN_HEARTBEAT_INTERVAL,
    ROBOT_ID_PATTERN,
)
from telemetry.config import TelemetryConfig
from transport.tls import ServerTlsConfig, server_context

__all__ = [
    "DEFAULT_BATTERY_MIN_V",
    "DEFAULT_HANDSHAKE_TIMEOUT",
    "DEFAULT_HEARTBEAT_INTERVAL",
    "DEFAULT_MAX_PENDING_CONNECTIONS",
    "DEFAULT_ROBOT_GONE_AFTER",
    "DEFAULT_ROUND_MARGIN",
    "MasterConfig",
    "build_ssl_context",
    "inventory_of",
    "load_master_config",
    "load_secret",
    "required_secret",
]

#: protocol.md: the whole handshake (TLS included) has a 10 s deadline; generous for a Pi on a busy
#: lab WLAN, short enough that a half-open or dribbling connection does not hold its slot long.
DEFAULT_HANDSHAKE_TIMEOUT: Final = 10.0
#: Handshakes that may run at once. A lab's swarm is a few dozen robots that reconnect with
#: backoff, so 64 lets all of them reconnect together; one more connection closes one at once,
#: always of the address holding the most (master_service.handshakes), so that peers without the
#: secret can never use up the master's file descriptors (the run's checkpoints need some) or its
#: memory, nor keep robots of other addresses out.
DEFAULT_MAX_PENDING_CONNECTIONS: Final = 64
#: The link is declared dead after 3 intervals without any message (protocol.md). 2 s notices a
#: dropped robot within 6-8 s, less than one 10 s evaluation, at a negligible ping traffic.
DEFAULT_HEARTBEAT_INTERVAL: Final = 2.0
#: Added to ``steps * step_period`` for a round's deadline: covers building the networks on the
#: Pi, the Result's transfer and a few late control steps, yet loses little time when a robot is
#: stuck.
DEFAULT_ROUND_MARGIN: Final = 5.0
#: Volts below which a robot's battery pauses the run for a swap: the Thymio's own second
#: low-battery step (its steps are 3.9, 3.6 and 3.4 V; at 3.4 V it soon switches itself off, and
#: a robot that dies mid-evaluation costs the round).
DEFAULT_BATTERY_MIN_V: Final = 3.6
#: Seconds a robot of the swarm may be away before the run stops waiting for it as for a
#: reconnect and pauses for a person (a spare, or going on without it). A Pi that reboots is
#: back in about a minute and an agent reconnects within its backoff's 30 s; three minutes tell
#: a robot that is gone for good (a dead battery, a crashed Pi) from one that is coming back.
DEFAULT_ROBOT_GONE_AFTER: Final = 180.0

_PositiveSeconds = Annotated[float, msgspec.Meta(gt=0.0, le=86400.0)]
_HeartbeatInterval = Annotated[
    float, msgspec.Meta(ge=MIN_HEARTBEAT_INTERVAL, le=MAX_HEARTBEAT_INTERVAL)
]
_RobotId = Annotated[str, msgspec.Meta(pattern=ROBOT_ID_PATTERN)]


class MasterConfig(Strict, frozen=True):
    """Everything the master needs besides the run directory.

    ``experiment`` or ``experiment_file`` (exactly one) defines the experiment. ``port`` 0 picks
    any free port (tests). ``allowed_robots`` empty admits any authenticated robot; with an
    ``inventory`` (docs/fleet.md) it is the inventory's swarm (its enabled robots that are not
    spares) unless given, and given it must be that swarm.
    ``expected_robots`` (default: the experiment's ``robots``) is how many robots form the swarm:
    a round starts only when that many are connected. The swarm is fixed when it first completes
    (those robots' ids are the CSV's columns); from then on only its members are admitted, so
    with spares in ``allowed_robots`` the first robots to connect take part, and the others can
    replace a robot gone for longer than ``robot_gone_after`` (``surprise-master swap``,
    docs/runs.md). ``round_margin`` is
    added to ``steps * step_period`` (the experiment's) for a round's deadline;
    ``heartbeat_interval`` is how often the master pings (a link is dead after three silent
    intervals; robots accept 0.05 s to 60 s); ``handshake_timeout`` bounds a whole handshake;
    ``max_pending_connections`` bounds how many handshakes run at once (one more connection
    closes one at once, of the address holding the most); ``max_frame_size`` bounds one
    incoming message (bytes). ``telemetry`` (optional) publishes the run's status
    over MQTT (``docs/telemetry.md``).
    """

    #: the experiment, inline (give exactly one of ``experiment`` and ``experiment_file``)
    experiment: ExperimentConfig | None = None
    #: the experiment's file (give exactly one of ``experiment`` and ``experiment_file``)
    experiment_file: str | None = None
    #: the address the master listens on (``0.0.0.0``: every interface, e.g. the lab network)
    host: str = "127.0.0.1"
    #: the TCP port the master listens on (0: any free port)
    port: Annotated[int, msgspec.Meta(ge=0, le=65535)] = DEFAULT_PORT
    #: the file holding the shared secret (surrounding whitespace is ignored); every robot has
    #: a copy
    secret_file: str | None = None
    #: the fleet's inventory file (docs/fleet.md), relative to this file; its enabled robots that
    #: are not spares are the ``allowed_robots``, the preflight checks them and its spares
    inventory: str | None = None
    #: the robot ids that may join; empty: any robot that proves the secret (with an
    #: ``inventory``: its swarm, unless given)
    allowed_robots: list[_RobotId] = msgspec.field(default_factory=list)
    #: how many robots form the swarm; a round starts only when that many are connected
    #: (``null``: the experiment's ``robots``)
    expected_robots: Annotated[int, msgspec.Meta(ge=1)] | None = None
    #: TLS for the robots' connections (optional; the secret's proofs and the message tags work
    #: with or without it)
    tls: ServerTlsConfig | None = None
    #: seconds added to ``steps * step_period`` for a round's deadline
    round_margin: _PositiveSeconds = DEFAULT_ROUND_MARGIN
    #: seconds between the master's pings; a link is dead after three silent intervals
    heartbeat_interval: _HeartbeatInterval = DEFAULT_HEARTBEAT_INTERVAL
    #: seconds a whole handshake (TLS included) may take
    handshake_timeout: _PositiveSeconds = DEFAULT_HANDSHAKE_TIMEOUT
    #: handshakes that may run at once; one more connection closes one at once, of the address
    #: holding the most (docs/protocol.md)
    max_pending_connections: Annotated[int, msgspec.Meta(ge=1)] = DEFAULT_MAX_PENDING_CONNECTIONS
    #: the largest incoming message, in bytes
    max_frame_size: Annotated[int, msgspec.Meta(ge=1024)] = MAX_FRAME_SIZE
    #: live telemetry of the run's status over MQTT (docs/telemetry.md)
    telemetry: TelemetryConfig | None = None
    #: volts: a robot whose battery reads below this after an evaluation pauses the run for a
    #: swap (docs/runs.md); ``null``: never pause. Robots that report no battery never pause it.
    battery_min_v: Annotated[float, msgspec.Meta(ge=0.0, le=MAX_BATTERY_V)] | None = (
        DEFAULT_BATTERY_MIN_V
    )
    #: seconds a robot of the swarm may be away before the run pauses naming it, for
    #: ``surprise-master swap`` to bring in a spare, or goes on without it where the
    #: experiment's ``min_robots`` allows (docs/runs.md); ``null``: wait for it forever
    robot_gone_after: _PositiveSeconds | None = DEFAULT_ROBOT_GONE_AFTER

    def __post_init__(self) -> None:
        if (self.experiment is None) == (self.experiment_file is None):
            raise ValueError("`experiment`: give exactly one of `experiment` and `experiment_file`")
        if len(set(self.allowed_robots)) != len(self.allowed_robots):
            raise ValueError("`allowed_robots`: a robot id is listed twice")
        # Unresolved (experiment_file) configurations are checked once the experiment is loaded.
        allowed = self.allowed_robots
        if self.experiment is not None and allowed and self.robot_count > len(allowed):
            raise ValueError(
                f"`expected_robots`: the swarm needs {self.robot_count} robots but "
                f"`allowed_robots` lists only {len(allowed)}"
            )
        minimum = None if self.experiment is None else self.experiment.min_robots
        if minimum is not None and minimum > self.robot_count:
            raise ValueError(
                f"`experiment.min_robots`: {minimum} is more than the swarm's "
                f"{self.robot_count} robots"
            )

    @property
    def robot_count(self) -> int:
        """How many robots form the swarm (``expected_robots`` or the experiment's ``robots``)."""
        if self.expected_robots is not None:
            return self.expected_robots
        if self.experiment is None:
            raise ConfigError("the experiment is not loaded yet", key="experiment_file")
        return self.experiment.robots


def _resolve(base: Path, value: str | None) -> str | None:
    if value is None:
        return None
    return str((base / Path(value).expanduser()).resolve())


def load_master_config(path: str | Path) -> MasterConfig:
    """Load a master configuration file and resolve it (experiment inline, paths absolute).

    Every failure is one :class:`~minimize_surprise.errors.ConfigError` naming the file and the key:
    this file's, or the experiment file's when that one is wrong. The files it names must exist.
    """
    path = Path(path)
    raw = read_yaml(path)
    if isinstance(raw.get("experiment"), dict):
        # An inline experiment takes what it leaves out from its setting, as a file does, and
        # names an arena file relative to this one.
        raw["experiment"] = with_setting(resolve_arena(raw["experiment"], path.resolve().parent))
    config = decode(raw, MasterConfig, file=path)
    base = path.resolve().parent
    experiment = config.experiment
    if config.experiment_file is not None:
        experiment_path = Path(_resolve(base, config.experiment_file) or "")
        if not experiment_path.is_file():
            raise ConfigError(
                f"the experiment file {experiment_path} does not exist",
                file=str(path),
                key="experiment_file",
            )
        experiment = load_experiment(experiment_path)
    inventory_path = _resolve(base, config.inventory)
    allowed = _allowed_robots(path, config, inventory_path)
    tls = config.tls
    if tls is not None:
        tls = ServerTlsConfig(
            cert_file=_resolve(base, tls.cert_file) or "",
            key_file=_resolve(base, tls.key_file) or "",
            ca_file=_resolve(base, tls.ca_file),
        )
    data = msgspec.to_builtins(config)
    data.update(
        experiment=msgspec.to_builtins(experiment),
        experiment_file=None,
        secret_file=_resolve(base, config.secret_file),
        inventory=inventory_path,
        allowed_robots=allowed,
        tls=None if tls is None else msgspec.to_builtins(tls),
    )
    # Decode again so the checks that need the experiment (robots vs allow-list) run now.
    resolved = decode(data, MasterConfig, file=path)
    for key, file in _named_files(resolved):
        if not Path(file).is_file():
            raise ConfigError(f"the file {file} does not exist", file=str(path), key=key)
    return resolved


def _allowed_robots(path: Path, config: MasterConfig, inventory: str | None) -> list[str]:
    """The robots the master admits: ``allowed_robots``, or the inventory's swarm; both given,
    they must agree (a ConfigError naming this file and the key)."""
    if inventory is None:
        return list(config.allowed_robots)
    if not Path(inventory).is_file():
        raise ConfigError(
            f"the inventory file {inventory} does not exist", file=str(path), key="inventory"
        )
    swarm = load_inventory(inventory).swarm
    if not swarm:
        raise ConfigError(
            f"the inventory {inventory} has no enabled robot that is not a spare",
            file=str(path),
            key="inventory",
        )
    given = config.allowed_robots
    if given and set(given) != set(swarm):
        extra = sorted(set(given) - set(swarm))
        lacking = sorted(set(swarm) - set(given))
        parts = [f"{', '.join(extra)} not in its swarm"] if extra else []
        parts += [f"{', '.join(lacking)} of its swarm not listed"] if lacking else []
        raise ConfigError(
            f"disagrees with the inventory {inventory} ({'; '.join(parts)}): leave "
            "`allowed_robots` out to take the inventory's enabled robots that are not spares",
            file=str(path),
            key="allowed_robots",
        )
    return list(given) if given else swarm


def inventory_of(config: MasterConfig) -> Inventory | None:
    """The inventory a resolved configuration names (read again: a ConfigError names it when
    it changed for the worse since), None when it names none."""
    return None if config.inventory is None else load_inventory(config.inventory)


def _named_files(config: MasterConfig) -> list[tuple[str, str]]:
    files = []
    if config.inventory is not None:
        files.append(("inventory", config.inventory))
    if config.secret_file is not None:
        files.append(("secret_file", config.secret_file))
    if config.tls is not None:
        files += [("tls.cert_file", config.tls.cert_file), ("tls.key_file", config.tls.key_file)]
        if config.tls.ca_file is not None:
            files.append(("tls.ca_file", config.tls.ca_file))
    return files


def required_secret(config: MasterConfig, source: str | Path) -> bytes:
    """The shared secret ``config`` names; a :class:`ConfigError` naming ``source`` (the file the
    configuration came from) and the key when it names none."""
    if config.secret_file is None:
        raise ConfigError(
            "the robots' shared secret is needed: name its file",
            file=str(source),
            key="secret_file",
        )
    return load_secret(config.secret_file)


def load_secret(path: str | Path) -> bytes:
    """The shared secret: the file's bytes without leading and trailing whitespace.

    Whitespace is stripped because editors add a final newline; the robots' agent must read its
    copy the same way. Raises :class:`~minimize_surprise.errors.ConfigError` naming the file if it
    cannot be read or is empty.
    """
    path = Path(path)
    try:
        secret = path.read_bytes().strip()
    except OSError as exc:
        raise ConfigError(
            f"cannot read the secret file: {exc.strerror or exc}", file=str(path)
        ) from None
    if not secret:
        raise ConfigError("the secret file is empty", file=str(path))
    return secret


def build_ssl_context(tls: ServerTlsConfig) -> ssl.SSLContext:
    """A server-side TLS context from ``tls``; a bad certificate or key is a ConfigError."""
    return server_context(tls, key="tls")
