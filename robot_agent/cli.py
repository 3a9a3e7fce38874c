"""``surprise-agent``: the composition root of the robot's daemon.

::

    surprise-agent --config /etc/surprise/agent.yaml [--log-level INFO]

Loads the configuration (a bad one exits with code 2 and one message on stderr; nothing starts),
builds the real body (``drivers.compose.build_body``, imported only here), opens it, and runs the
:class:`~robot_agent.agent.Agent` with a :class:`~drivers.clock.MonotonicClock` until SIGTERM,
SIGINT or SIGHUP (a closed SSH session), which stop the motors and exit with code 0. A robot that
cannot be reached at start (switched on later, medulla not up yet) does not end the agent: it
connects to the master, fails evaluations with the reason, and recovers the robot in the
background. Logs go to stdout, where systemd's journal collects them, each line with its priority
(:mod:`robot_agent.journal`).

``--stop-motors`` (systemd's ``ExecStopPost``) reads only ``body.thymio`` of the file and stops the
motors. It runs in a fresh interpreter within the unit's stop timeout, on a slow Pi: this module
imports only what it needs at the top, and the agent's own modules (numpy, the networks, the
safety layer) where the agent starts.

Exit codes: 0 stopped by a signal, 1 could not start (the body cannot be built) or crashed, 2 bad
configuration.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import logging
import signal
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import msgspec

import minimize_surprise
from drivers.body import Body
from drivers.clock import Clock, MonotonicClock
from drivers.config import BodyConfig, ThymioConfig
from drivers.thymio import ThymioBase
from minimize_surprise.config import load_yaml
from minimize_surprise.errors import ConfigError, HardwareError
from robot_agent.bounded import finish
from robot_agent.journal import print_error, setup_logging

if TYPE_CHECKING:
    from robot_agent.config import AgentConfig

__all__ = [
    "EXIT_CONFIG",
    "EXIT_FAILURE",
    "EXIT_OK",
    "STOP_CLOSE_TIMEOUT",
    "STOP_ONCE_TIMEOUT",
    "amain",
    "load_thymio_config",
    "main",
    "run_agent",
    "stop_motors_once",
]

log = logging.getLogger("robot_agent")

#: Exit code after SIGTERM or SIGINT: stopping is the normal end of a daemon.
EXIT_OK = 0
#: Exit code when the agent cannot start (the body cannot be opened) or crashes.
EXIT_FAILURE = 1
#: Exit code for a bad configuration (the usual code for usage errors).
EXIT_CONFIG = 2

#: Each stops the agent and its motors. SIGHUP too: an agent started by hand over SSH gets it when
#: the session drops, and its default action would end the process with the motors running.
_SIGNALS = (signal.SIGTERM, signal.SIGINT, signal.SIGHUP)
#: Seconds ``--stop-motors`` may take to reach D-Bus and stop the Thymio (a connection and four
#: calls, each bounded by the driver's own timeout).
STOP_ONCE_TIMEOUT = 3.0
#: Seconds ``--stop-motors`` may then take to close the connection (which stops once more). With
#: the interpreter's start, both must fit the unit's ``TimeoutStopSec`` (tests/deploy checks).
STOP_CLOSE_TIMEOUT = 1.0

BodyFactory = Callable[[BodyConfig], Body]


def _build_real_body(config: BodyConfig) -> Body:
    # Imported here: the hardware drivers need dbus-fast and smbus2, which only the robot has.
    from drivers.compose import build_body

    return build_body(config)


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="surprise-agent",
        description="Run one robot's agent: connect to the master and evaluate genomes.",
    )
    parser.add_argument("--config", required=True, type=Path, help="the agent's YAML file")
    parser.add_argument(
        "--log-level",
        default="INFO",
        type=str.upper,
        choices=["DEBUG", "INFO", "WARNING", "ERROR"],
        help="log verbosity (default: INFO)",
    )
    parser.add_argument(
        "--stop-motors",
        action="store_true",
        help="only set the motors to zero and exit (systemd's ExecStopPost runs this, so the "
        "robot stands still however the agent ended)",
    )
    parser.add_argument("--version", action="version", version=minimize_surprise.__version__)
    return parser


async def run_agent(
    config: AgentConfig,
    secret: bytes,
    *,
    body_factory: BodyFactory = _build_real_body,
    clock: Clock | None = None,
) -> int:
    """Run the agent until SIGTERM, SIGINT or SIGHUP; returns the exit code.

    The signal handlers are installed on the running loop for the duration of the call and the
    previous handlers restored afterwards. ``body_factory`` builds the (unopened) body; tests pass
    a fake one. Must run in the main thread (signal handlers can only be set there).
    """
    from robot_agent.agent import Agent  # heavy: see the module docstring

    loop = asyncio.get_running_loop()
    task = asyncio.current_task()
    assert task is not None
    received: list[int] = []

    def on_signal(signum: int) -> None:
        if not received:
            log.info("received %s: stopping", signal.Signals(signum).name)
            task.cancel()
        received.append(signum)

    previous = {sig: signal.getsignal(sig) for sig in _SIGNALS}
    for sig in _SIGNALS:
        loop.add_signal_handler(sig, on_signal, sig)
    body: Body | None = None
    try:
        try:
            body = body_factory(config.body)
        except ConfigError as exc:
            print_error(f"surprise-agent: {exc}")
            return EXIT_CONFIG
        except Exception as exc:  # e.g. the drivers' libraries are missing
            print_error(f"surprise-agent: cannot build the robot's body: {exc}")
            return EXIT_FAILURE
        unreachable: str | None = None
        try:
            await body.open()
        except HardwareError as exc:  # e.g. asebamedulla not up yet, the robot switched off
            unreachable = str(exc)
        except Exception as exc:  # a bug, or a library the drivers need is broken
            print_error(f"surprise-agent: cannot open the robot's body: {exc!r}")
            # close() is idempotent and stops whatever part did open; a stop() on a body that
            # never opened would only add a misleading error to the log.
            await finish(body.close(), 2 * config.loop.stop_timeout)
            return EXIT_FAILURE
        try:
            log.info("robot %s: sensors %s", config.robot_id, ", ".join(body.sensors))
            async with Agent(config, body, clock or MonotonicClock(), secret) as agent:
                if unreachable is not None:
                    agent.health.lost(f"the body did not open: {unreachable}")
                await agent.run()
        finally:
            await _close(body, config)
        return EXIT_OK  # not reached: run() returns only by cancellation
    except asyncio.CancelledError:
        if not received:
            raise
        # Our own signal handler cancelled us: that is the normal way to stop.
        task.uncancel()
        log.info("stopped")
        return EXIT_OK
    finally:
        for sig in _SIGNALS:
            loop.remove_signal_handler(sig)
            signal.signal(sig, previous[sig])


class _ThymioOnly(msgspec.Struct):
    # Not Strict: the other keys of the body are the agent's business, not the stop's.
    thymio: ThymioConfig = msgspec.field(default_factory=ThymioConfig)


class _BodyOnly(msgspec.Struct):
    body: _ThymioOnly = msgspec.field(default_factory=_ThymioOnly)


def load_thymio_config(path: str | Path) -> ThymioConfig:
    """``body.thymio`` of an agent file, ignoring every other key.

    Raises :class:`ConfigError` for that section only: a mistake elsewhere in the file (made
    while the agent ran) must not keep ``--stop-motors`` from stopping the robot.
    """
    return load_yaml(path, _BodyOnly).body.thymio


async def stop_motors_once(config: ThymioConfig) -> int:
    """Set the Thymio's motor targets to zero and confirm it; returns the exit code.

    This is the last line of defence after the agent ended, however it ended (even SIGKILL): it
    must not depend on the master, the secret or anything but the robot's own configuration. It
    only connects to D-Bus and stops the motors through whichever medulla runs now; it loads no
    program and opens no other part of the body.
    """
    thymio = ThymioBase(config)

    async def stop() -> None:
        await thymio.connect()
        await thymio.stop()

    error = await finish(stop(), STOP_ONCE_TIMEOUT)
    await finish(thymio.close(), STOP_CLOSE_TIMEOUT)
    if error is not None:
        print_error(f"surprise-agent: the motor stop was not confirmed: {error}")
        return EXIT_FAILURE
    log.info("motors stopped")
    return EXIT_OK


async def _close(body: Body, config: AgentConfig) -> None:
    from robot_agent.runner import stop_motors  # heavy: see the module docstring

    # Motors first, bounded: close() of a vanished robot may hang, the stop must not wait for it.
    await stop_motors(body, config.loop.stop_timeout)
    with contextlib.suppress(Exception):
        async with asyncio.timeout(2 * config.loop.stop_timeout):
            await body.close()


async def amain(
    argv: Sequence[str] | None = None, *, body_factory: BodyFactory = _build_real_body
) -> int:
    """The whole command in a running loop: parse, load, run; returns the exit code."""
    args = _parser().parse_args(argv)
    setup_logging(args.log_level)
    if args.stop_motors:
        return await _stop_motors(args.config)
    return await _serve(args.config, body_factory)


async def _stop_motors(path: Path) -> int:
    try:
        config = load_thymio_config(path)
    except ConfigError as exc:
        print_error(f"surprise-agent: {exc}")
        return EXIT_CONFIG
    return await stop_motors_once(config)


async def _serve(path: Path, body_factory: BodyFactory) -> int:
    # Imported here, not at the top: they import numpy and the safety layer (see the docstring).
    from robot_agent.config import load_agent_config, make_ssl_context, read_secret
    from telemetry.config import require_client_library

    try:
        config = load_agent_config(path)
        secret = read_secret(config, config_file=path)
        make_ssl_context(config, config_file=path)  # fail now, not at the first connect
        require_client_library(config.telemetry, file=path)  # a broker needs aiomqtt
    except ConfigError as exc:
        print_error(f"surprise-agent: {exc}")
        return EXIT_CONFIG
    try:
        return await run_agent(config, secret, body_factory=body_factory)
    except Exception:
        log.exception("the agent crashed")
        return EXIT_FAILURE


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``surprise-agent``; returns the exit code."""
    return asyncio.run(amain(argv))


if __name__ == "__main__":
    sys.exit(main())
