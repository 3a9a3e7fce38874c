"""``surprise-agent``: the composition root of the robot's daemon.

::

    surprise-agent --config /etc/surprise/agent.yaml [--log-level INFO]

Loads the configuration (a bad one exits with code 2 and one message on stderr; nothing starts),
builds the real body (``drivers.compose.build_body``, imported only here), opens it, and runs the
:class:`~robot_agent.agent.Agent` with a :class:`~drivers.clock.MonotonicClock` until SIGTERM,
SIGINT or SIGHUP (a closed SSH session), which stop the motors and exit with code 0. A robot that
cannot be reached at start (switched on later, medulla not up yet) does not end the agent: it
connects to the master, fails evaluations with the reason, and recovers the robot in the
background. Logs go to stdout, where systemd's journal collects them.

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

import surprise
from drivers.body import Body
from drivers.clock import Clock, MonotonicClock
from drivers.config import BodyConfig
from drivers.thymio import ThymioBase
from robot_agent.agent import Agent
from robot_agent.config import AgentConfig, load_agent_config, make_ssl_context, read_secret
from robot_agent.runner import finish, stop_motors
from surprise.errors import ConfigError, HardwareError
from telemetry.config import require_client_library

__all__ = ["EXIT_CONFIG", "EXIT_FAILURE", "EXIT_OK", "amain", "main", "run_agent"]

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
#: calls, each bounded by the driver's own timeout); systemd's stop timeout (5 s) bounds the whole.
STOP_ONCE_TIMEOUT = 3.0

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
    parser.add_argument("--version", action="version", version=surprise.__version__)
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
            print(f"surprise-agent: {exc}", file=sys.stderr)
            return EXIT_CONFIG
        except Exception as exc:  # e.g. the drivers' libraries are missing
            print(f"surprise-agent: cannot build the robot's body: {exc}", file=sys.stderr)
            return EXIT_FAILURE
        unreachable: str | None = None
        try:
            await body.open()
        except HardwareError as exc:  # e.g. asebamedulla not up yet, the robot switched off
            unreachable = str(exc)
        except Exception as exc:  # a bug, or a library the drivers need is broken
            print(f"surprise-agent: cannot open the robot's body: {exc!r}", file=sys.stderr)
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


async def stop_motors_once(config: AgentConfig) -> int:
    """Set the Thymio's motor targets to zero and confirm it; returns the exit code.

    This is the last line of defence after the agent ended, however it ended (even SIGKILL): it
    must not depend on the master, the secret or anything but the robot's own configuration. It
    only connects to D-Bus and stops the motors through whichever medulla runs now; it loads no
    program and opens no other part of the body.
    """
    thymio = ThymioBase(config.body.thymio)

    async def stop() -> None:
        await thymio.connect()
        await thymio.stop()

    error = await finish(stop(), STOP_ONCE_TIMEOUT)
    await finish(thymio.close(), 2 * config.loop.stop_timeout)
    if error is not None:
        print(f"surprise-agent: the motor stop was not confirmed: {error}", file=sys.stderr)
        return EXIT_FAILURE
    log.info("motors stopped")
    return EXIT_OK


async def _close(body: Body, config: AgentConfig) -> None:
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
    _setup_logging(args.log_level)
    try:
        config = load_agent_config(args.config)
        if args.stop_motors:
            return await stop_motors_once(config)
        secret = read_secret(config, config_file=args.config)
        make_ssl_context(config, config_file=args.config)  # fail now, not at the first connect
        require_client_library(config.telemetry, file=args.config)  # a broker needs aiomqtt
    except ConfigError as exc:
        print(f"surprise-agent: {exc}", file=sys.stderr)
        return EXIT_CONFIG
    try:
        return await run_agent(config, secret, body_factory=body_factory)
    except Exception:
        log.exception("the agent crashed")
        return EXIT_FAILURE


def _setup_logging(level: str) -> None:
    # basicConfig leaves an already configured root logger alone (an embedding process, pytest).
    # systemd's journal adds its own timestamps; keep ours for runs outside systemd.
    logging.basicConfig(
        stream=sys.stdout,
        level=level,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``surprise-agent``; returns the exit code."""
    return asyncio.run(amain(argv))


if __name__ == "__main__":
    sys.exit(main())
