"""The robot's link to the master: connect, authenticate, serve evaluations, reconnect.

The conversation is fixed by ``docs/protocol.md``::

    Hello(nonce) -> (Challenge(nonce, proof) | Refused) -> Authenticate(proof)
    -> (Welcome | Refused); then, every frame tagged:
    Evaluate -> Result | Failed;  Abort;  Check -> CheckReport;  Escape -> EscapeReply;
    StopAll -> Stopped;  Ping -> Pong;  Bye / Error close the session

The robot trusts nothing from a master that has not proved the shared secret: it checks the
Challenge's proof before it sends anything else, and from then on accepts only frames tagged with
the session's key, so neither an impostor nor a relay can make it drive. It also bounds what even
a genuine master may ask: frames before the Welcome are small (``HANDSHAKE_MAX_FRAME_SIZE``), the
heartbeat interval lies within the protocol's bounds (checked as the Welcome is decoded), an
evaluation is at most ``loop.max_steps`` long (the runner refuses longer ones) and a master's text
is cut and cleaned before it is logged. An Escape only asks the safety layer to start its own
bounded escape manoeuvre (:meth:`EvaluationRunner.request_escape`); no message drives a motor.
A StopAll (``surprise-master fleet stop``) is never refused: the watchdog stops the motors at
once, the running evaluation is cancelled, and the robot's own stop is confirmed in Stopped.

:class:`Link.run` loops forever: one session per connection, and after any end of a session
(refused, closed, silent for too long, broken input) a delay from :class:`Backoff` before the next
attempt. An evaluation runs in its own task; a new Evaluate replaces (aborts) a running one, an
Abort with its id cancels it, and a session that ends while it runs trips the watchdog (the motors
stop at once) and cancels it. A cancelled evaluation sends nothing.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
import ssl
from collections.abc import Awaitable, Callable
from typing import Any, Final, TypeVar

import minimize_surprise
from minimize_surprise.backoff import Backoff
from minimize_surprise.errors import (
    AuthenticationError,
    FrameTooLargeError,
    ProtocolError,
    SurpriseError,
)
from minimize_surprise.provenance import software_commit
from minimize_surprise.session import FrameAuth, master_proof, new_nonce, proof_matches, robot_proof
from minimize_surprise.wire import (
    DEAD_AFTER_HEARTBEATS,
    FEATURES,
    HANDSHAKE_MAX_FRAME_SIZE,
    MAX_FRAME_SIZE,
    PROTOCOL_VERSION,
    REFUSED_VERSION_MISMATCH,
    Abort,
    Authenticate,
    Bye,
    Challenge,
    Check,
    Error,
    Escape,
    Evaluate,
    Failed,
    Hello,
    Message,
    Ping,
    Pong,
    Refused,
    Result,
    StopAll,
    Welcome,
    encode_payload,
    printable,
)
from robot_agent.bounded import finish
from robot_agent.config import AgentConfig
from robot_agent.runner import EvaluationRunner
from robot_agent.watchdog import Watchdog
from transport.stream import MessageStream

__all__ = [
    "CLOSE_TIMEOUT",
    "CONNECT_TIMEOUT",
    "FIRMWARE_TIMEOUT",
    "HANDSHAKE_TIMEOUT",
    "PROBE_AFTER_HEARTBEATS",
    "Backoff",
    "Link",
    "LinkDeadError",
    "RefusedError",
]

log = logging.getLogger(__name__)

#: Seconds to open the TCP (and TLS) connection. A master on the lab network answers within
#: milliseconds; a host that silently drops packets would otherwise hold us for minutes of SYN
#: retries instead of backing off.
CONNECT_TIMEOUT: Final = 10.0
#: Seconds for the whole handshake, from Hello to Welcome (``HANDSHAKE_TIMEOUT`` of
#: docs/protocol.md): generous for a busy lab WLAN, short enough that a master that stalls is
#: left for another attempt.
HANDSHAKE_TIMEOUT: Final = 10.0
#: After this many heartbeat intervals without a message the robot sends a Ping itself: a live
#: master answers with a Pong, so a master that is late with its own pings (busy writing a
#: checkpoint) is not dropped, while a dead one still is at DEAD_AFTER_HEARTBEATS. Above 1 so that
#: a master pinging on time never causes an extra ping.
PROBE_AFTER_HEARTBEATS: Final = 1.5
#: Seconds to close a connection (TLS shutdown included) before it is abandoned.
CLOSE_TIMEOUT: Final = 1.0
#: Seconds the robot's firmware version may take to read before a Hello: one medulla round trip;
#: a robot that is away costs each connection attempt no more than this.
FIRMWARE_TIMEOUT: Final = 1.0

_CODE_PROTOCOL: Final = "protocol"

_M = TypeVar("_M", Challenge, Welcome)


class RefusedError(SurpriseError, ConnectionError):
    """The master refused the robot; ``code`` is one of ``minimize_surprise.wire.REFUSED_CODES``
    (both ``code`` and ``reason`` come cut and cleaned for the log)."""

    def __init__(self, code: str, reason: str) -> None:
        self.code = code
        self.reason = reason
        super().__init__(f"refused by the master ({code}): {reason}")


class LinkDeadError(SurpriseError, ConnectionError):
    """Nothing arrived from the master for ``DEAD_AFTER_HEARTBEATS`` heartbeat intervals."""


Spawn = Callable[..., asyncio.Task[Any]]


class _Prefixed(logging.LoggerAdapter):
    # Several agents may share one process (the master's ``sim`` command): say which robot speaks.
    def process(self, msg: Any, kwargs: Any) -> tuple[Any, Any]:
        assert self.extra is not None  # robot_logger always passes it
        return f"[{self.extra['robot']}] {msg}", kwargs


def robot_logger(logger: logging.Logger, robot_id: str) -> logging.LoggerAdapter:
    """``logger`` with every message prefixed by ``[robot_id]``."""
    return _Prefixed(logger, {"robot": robot_id})


class Link:
    """The link of one robot to the master.

    ``runner`` runs the evaluations; ``sensors`` are the body's (sent in Hello); ``watchdog`` is
    tripped when the link is lost during an evaluation; ``ssl_context`` enables TLS; ``spawn``
    creates the evaluation tasks (the agent passes its TaskGroup's ``create_task``);
    ``read_firmware`` reads the robot's firmware version for the Hello (the body's
    ``read_firmware``; read until it is known, before each connection, within
    :data:`FIRMWARE_TIMEOUT`). :attr:`connected` is set while a session is welcomed.
    """

    def __init__(
        self,
        config: AgentConfig,
        secret: bytes,
        runner: EvaluationRunner,
        sensors: tuple[str, ...],
        *,
        watchdog: Watchdog | None = None,
        rng: random.Random | None = None,
        ssl_context: ssl.SSLContext | None = None,
        spawn: Spawn | None = None,
        read_firmware: Callable[[], Awaitable[int | None]] | None = None,
    ) -> None:
        if not secret:
            raise ValueError("the shared secret must not be empty")
        self.config = config
        self.secret = secret
        self.runner = runner
        self.sensors = tuple(sensors)
        self.watchdog = watchdog
        self.ssl_context = ssl_context
        self.spawn: Spawn = spawn if spawn is not None else asyncio.create_task
        #: what the Hello announces of this installation (docs/fleet.md); tests change them
        self.software_version: str = minimize_surprise.__version__
        self.software_commit: str | None = software_commit()
        #: the Thymio's firmware version, once read (None: not known yet, or the robot has none)
        self.thymio_firmware: int | None = None
        self._read_firmware = read_firmware
        self.backoff = Backoff(config.reconnect, rng)
        self.log = robot_logger(log, config.robot_id)
        #: set while the master has welcomed us
        self.connected = asyncio.Event()
        #: the current session's run id and heartbeat interval (after Welcome)
        self.run_id: str | None = None
        self.heartbeat_interval: float | None = None
        #: sessions welcomed so far (for tests and status)
        self.sessions = 0
        self._evaluation: tuple[int, asyncio.Task[None]] | None = None
        self._ping_seq = 0
        self._send_lock = asyncio.Lock()

    # ------------------------------------------------------------------ the reconnect loop

    async def run(self) -> None:
        """Connect and serve forever, reconnecting with backoff; returns only when cancelled."""
        master = self.config.master
        while True:
            try:
                await self._session()
            except RefusedError as exc:
                # A version mismatch never fixes itself; keep it loud on every try.
                level = logging.ERROR if exc.code == REFUSED_VERSION_MISMATCH else logging.WARNING
                self.log.log(level, "%s", exc)
            except AuthenticationError as exc:
                # An impostor, a relay tampering with frames, or a secret that differs: loud.
                self.log.error("link to %s:%d: %s", master.host, master.port, exc)
            except (OSError, ProtocolError) as exc:  # includes timeouts and lost connections
                self.log.warning("link to %s:%d: %s", master.host, master.port, _describe(exc))
            except Exception:  # a bug in a session must not end the agent: log it and retry
                self.log.exception("link to %s:%d failed unexpectedly", master.host, master.port)
            delay = self.backoff.next_delay()
            self.log.info("reconnecting in %.2f s", delay)
            await asyncio.sleep(delay)

    async def _firmware(self) -> None:
        """Read the firmware's version once it can be: the robot may be away at the start."""
        if self.thymio_firmware is not None or self._read_firmware is None:
            return
        try:
            async with asyncio.timeout(FIRMWARE_TIMEOUT):
                self.thymio_firmware = await self._read_firmware()
        except Exception as exc:  # unknown for this Hello, never a reason not to connect
            self.log.debug("firmware version not read: %s", _describe(exc))

    async def _session(self) -> None:
        master = self.config.master
        await self._firmware()
        self.log.info("connecting to %s:%d", master.host, master.port)
        extra: dict[str, Any] = {}
        if self.ssl_context is not None:
            extra["ssl"] = self.ssl_context
            if master.tls is not None and master.tls.server_hostname:
                extra["server_hostname"] = master.tls.server_hostname
        try:
            async with asyncio.timeout(CONNECT_TIMEOUT):
                reader, writer = await asyncio.open_connection(master.host, master.port, **extra)
        except TimeoutError:
            raise TimeoutError(f"no connection within {CONNECT_TIMEOUT} s") from None
        # Small frames until the master has proved the secret and welcomed us.
        stream = MessageStream(reader, writer, max_frame_size=HANDSHAKE_MAX_FRAME_SIZE)
        bye: str | None = None
        try:
            welcome = await self._handshake(stream)
            self.backoff.reset()
            self.sessions += 1
            self.run_id, self.heartbeat_interval = welcome.run_id, welcome.heartbeat_interval
            self.log.info(
                "welcomed into run %s (heartbeat %.2f s)",
                welcome.run_id,
                welcome.heartbeat_interval,
            )
            self.connected.set()
            await self._serve(stream, welcome.heartbeat_interval)
        except asyncio.CancelledError:
            bye = "agent stopping"
            raise
        finally:
            self.connected.clear()
            # An orderly stop (we are cancelled) stops the motors through the evaluation's own
            # clean-up; only a session that ended under us is a lost link for the watchdog.
            await self._cancel_evaluation(
                "agent stopping" if bye is not None else "session ended", link_lost=bye is None
            )
            if bye is not None:
                # Best effort and without waiting: we are being cancelled.
                with contextlib.suppress(OSError, RuntimeError, ProtocolError):
                    stream.write(encode_payload(Bye(reason=bye)))
            await finish(stream.close(), CLOSE_TIMEOUT)

    async def _handshake(self, stream: MessageStream) -> Welcome:
        robot_id, secret = self.config.robot_id, self.secret
        robot_nonce = new_nonce()
        step: type[Challenge] | type[Welcome] = Challenge
        try:
            # One deadline for the whole handshake: a master dribbling bytes gains nothing.
            async with asyncio.timeout(HANDSHAKE_TIMEOUT):
                await stream.send(
                    Hello(
                        robot_id=robot_id,
                        software_version=self.software_version,
                        protocol_version=PROTOCOL_VERSION,
                        sensors=self.sensors,
                        nonce=robot_nonce,
                        features=FEATURES,
                        software_commit=self.software_commit,
                        thymio_firmware=self.thymio_firmware,
                    )
                )
                challenge = _expect(await stream.receive(), Challenge)
                master_nonce = challenge.nonce
                expected = master_proof(secret, robot_nonce, master_nonce, robot_id)
                if not proof_matches(expected, challenge.proof):
                    # Nothing more goes to this peer: not even our own proof.
                    raise AuthenticationError(
                        "the master did not prove that it knows the shared secret: an impostor, "
                        "or this robot's secret file differs from the master's"
                    )
                proof = robot_proof(secret, robot_nonce, master_nonce, robot_id)
                await stream.send(Authenticate(proof=proof))
                stream.authenticate(
                    FrameAuth.for_robot(secret, robot_nonce, master_nonce, robot_id)
                )
                step = Welcome
                welcome = _expect(await stream.receive(), Welcome)
        except TimeoutError:
            raise TimeoutError(
                f"no {step.__name__} from the master within {HANDSHAKE_TIMEOUT} s"
            ) from None
        stream.set_max_frame_size(MAX_FRAME_SIZE)
        return welcome

    # ------------------------------------------------------------------ a welcomed session

    async def _serve(self, stream: MessageStream, heartbeat: float) -> None:
        loop = asyncio.get_running_loop()
        last = loop.time()
        probed = False
        dead_after = DEAD_AFTER_HEARTBEATS * heartbeat
        while True:
            limit = last + (DEAD_AFTER_HEARTBEATS if probed else PROBE_AFTER_HEARTBEATS) * heartbeat
            try:
                # Cancelling a receive is safe: MessageStream keeps any partial frame.
                async with asyncio.timeout_at(limit):
                    msg = await stream.receive()
            except TimeoutError:
                if probed:
                    raise LinkDeadError(
                        f"no message from the master for {dead_after:.2f} s"
                    ) from None
                probed = True
                self._ping_seq += 1
                await self._send(stream, Ping(seq=self._ping_seq), dead_after)
                continue
            last = loop.time()
            probed = False
            match msg:
                case Evaluate():
                    await self._start_evaluation(stream, msg, dead_after)
                case Abort(evaluation_id=eid, reason=reason):
                    running = self._evaluation[0] if self._evaluation is not None else None
                    if running == eid:
                        reason = printable(reason)
                        self.log.info("evaluation %d aborted by the master: %s", eid, reason)
                        await self._cancel_evaluation("aborted")
                    else:
                        # Late or duplicate: that attempt already ended (its result may be in
                        # flight; the master ignores it by id).
                        self.log.debug("abort of evaluation %d ignored: not running", eid)
                case Check():
                    # In its own task: the reads take up to a few seconds, the link's
                    # heartbeat must not wait for them.
                    self.spawn(self._answer_check(stream, msg, dead_after), name="check")
                case Escape(seq=seq):
                    reply = self.runner.request_escape(seq)
                    if reply.accepted:
                        self.log.info(
                            "the experimenter asked for an escape: it starts at the next step "
                            "of evaluation %s",
                            reply.evaluation_id,
                        )
                    else:
                        self.log.info("the experimenter's escape refused: %s", reply.reason)
                    await self._send(stream, reply, dead_after)
                case StopAll():
                    await self._stop_all(stream, msg, dead_after)
                case Ping(seq=seq):
                    await self._send(stream, Pong(seq=seq), dead_after)
                case Pong():
                    pass  # any message proves the link alive; nothing else to do
                case Bye(reason=reason):
                    self.log.info("the master closed the session: %s", printable(reason))
                    return
                case Error(code=code, message=text):
                    code, text = printable(code), printable(text)
                    self.log.error("the master reported an error (%s): %s", code, text)
                    return
                case _:
                    text = f"unexpected {_kind(msg)} in a welcomed session"
                    await self._send_quietly(stream, Error(code=_CODE_PROTOCOL, message=text))
                    raise ProtocolError(text)

    async def _stop_all(self, stream: MessageStream, msg: StopAll, timeout: float) -> None:
        running = self._evaluation[0] if self._evaluation is not None else None
        self.log.warning(
            "fleet stop (%s): the motors stop%s",
            printable(msg.reason) or "no reason given",
            "" if running is None else f", evaluation {running} is cancelled",
        )
        if running is not None and self.watchdog is not None:
            # At once, before the evaluation's task unwinds: a tripped watchdog keeps the loop
            # from driving again.
            await finish(self.watchdog.trip("fleet stop"), self.runner.config.stop_timeout)
        await self._cancel_evaluation("fleet stop")
        reply = await self.runner.stop_all(msg.seq, running)
        if reply.confirmed:
            self.log.warning("fleet stop: the motors are stopped until the next evaluation")
        else:
            self.log.error("fleet stop: the robot did not confirm the stop: %s", reply.detail)
        await self._send(stream, reply, timeout)

    async def _answer_check(self, stream: MessageStream, msg: Check, timeout: float) -> None:
        try:
            report = await self.runner.check(msg.seq)
            self.log.info("check %d answered%s", msg.seq, " (busy)" * report.busy)
            await self._send(stream, report, timeout)
        except (OSError, ProtocolError) as exc:
            self.log.warning("could not send the answer to check %d: %s", msg.seq, exc)
        except Exception:  # never let a bug escape into the agent's task group
            self.log.exception("check %d: unexpected error", msg.seq)

    async def _send(self, stream: MessageStream, msg: Message, timeout: float) -> None:
        # One sender at a time: the evaluation task and the receive loop both send.
        async with self._send_lock, asyncio.timeout(timeout):
            await stream.send(msg)

    async def _send_quietly(self, stream: MessageStream, msg: Message) -> None:
        with contextlib.suppress(OSError, ProtocolError):
            await self._send(stream, msg, CLOSE_TIMEOUT)

    # ------------------------------------------------------------------ evaluations

    async def _start_evaluation(self, stream: MessageStream, msg: Evaluate, timeout: float) -> None:
        if self._evaluation is not None:
            old = self._evaluation[0]
            self.log.info("evaluation %d replaces the running %d", msg.evaluation_id, old)
            await self._cancel_evaluation("replaced")
        task = self.spawn(
            self._evaluate(stream, msg, timeout), name=f"evaluation-{msg.evaluation_id}"
        )
        self._evaluation = (msg.evaluation_id, task)

    async def _evaluate(self, stream: MessageStream, msg: Evaluate, timeout: float) -> None:
        try:
            outcome: Result | Failed = await self.runner.run(msg)
            try:
                await self._send(stream, outcome, timeout)
            except FrameTooLargeError as exc:
                await self._send(
                    stream,
                    Failed(evaluation_id=msg.evaluation_id, reason=f"result too large: {exc}"),
                    timeout,
                )
        except (OSError, ProtocolError) as exc:
            # The session ends on its own when the connection is gone; the result is lost and
            # the master repeats the round.
            self.log.warning(
                "could not send the outcome of evaluation %d: %s", msg.evaluation_id, exc
            )
        except Exception:  # never let a bug escape into the agent's task group
            self.log.exception("evaluation %d: unexpected error", msg.evaluation_id)
        finally:
            current = self._evaluation
            if current is not None and current[1] is asyncio.current_task():
                self._evaluation = None

    async def _cancel_evaluation(self, why: str, *, link_lost: bool = False) -> None:
        """Cancel the running evaluation (if any) and wait until its motors are stopped."""
        current, self._evaluation = self._evaluation, None
        if current is None:
            return
        eid, task = current
        if task.done():
            return
        if link_lost and self.watchdog is not None:
            # Stop the motors now rather than after the task unwinds; the loop checks the
            # watchdog before it drives, so nothing restarts them.
            await finish(self.watchdog.trip(f"link lost ({why})"), self.runner.config.stop_timeout)
        self.log.info("cancelling evaluation %d: %s", eid, why)
        task.cancel()
        # The runner's clean-up is bounded (a motor stop, perhaps a watchdog trip); wait for it.
        await finish(asyncio.wait((task,)), 4 * self.runner.config.stop_timeout)


def _kind(msg: object) -> str:
    return type(msg).__name__


def _expect(msg: Message, expected: type[_M]) -> _M:
    """``msg`` if it is the handshake's ``expected`` message; else the error it amounts to."""
    if isinstance(msg, expected):
        return msg
    if isinstance(msg, Refused):
        raise RefusedError(printable(msg.code), printable(msg.reason))
    if isinstance(msg, Error):
        code, text = printable(msg.code), printable(msg.message)
        raise ProtocolError(f"the master reported an error ({code}): {text}")
    raise ProtocolError(f"expected {expected.__name__} during the handshake, got {_kind(msg)}")


def _describe(exc: BaseException) -> str:
    text = str(exc)
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__
