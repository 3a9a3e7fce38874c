"""A test double: a scripted robot that speaks the protocol, for the master's tests and benchmarks.

It lives with the simulator's other doubles (the fake asebamedulla, the emulated I2C chips) and
is never part of a lab run: no network, no body, no safety layer, just the conversation.

It answers every Evaluate with a fitness computed from the genome alone
(:func:`deterministic_fitness`), so two runs with the same seed give the same ``evaluations.csv``
whatever faults happened in between. A ``behaviour(count, evaluate)`` callable can make it
misbehave for the ``count``-th Evaluate it receives: return one of the ``REPLY``... constants.

It speaks the whole handshake (``docs/protocol.md``), checking the master's proof; with
``verify_master=False`` it answers even a master whose proof is wrong (a robot with a wrong
secret then reaches the master's own check, which refuses it).
"""

from __future__ import annotations

import asyncio
import contextlib
import ssl
from collections.abc import Callable, Sequence
from typing import Final, TypeVar

import numpy as np

from minimize_surprise.errors import AuthenticationError, ConnectionClosedError, ProtocolError
from minimize_surprise.sensors import ALL_SENSORS
from minimize_surprise.session import FrameAuth, master_proof, new_nonce, proof_matches, robot_proof
from minimize_surprise.wire import (
    PROTOCOL_VERSION,
    Abort,
    Authenticate,
    Bye,
    Challenge,
    Evaluate,
    EvaluationStats,
    Failed,
    Hello,
    Message,
    Ping,
    Pong,
    Refused,
    Result,
    Trace,
    Welcome,
    encode_payload,
    genome_from_bytes,
)
from transport.framing import frame
from transport.stream import MessageStream

__all__ = [
    "DISCONNECT",
    "DUPLICATE",
    "FAIL",
    "IGNORE",
    "LATE",
    "REPLY",
    "RobotRefusedError",
    "ScriptedRobot",
    "deterministic_fitness",
]

#: Answer with the deterministic fitness (after ``delay`` seconds).
REPLY: Final = "reply"
#: Never answer (the master's deadline passes).
IGNORE: Final = "ignore"
#: Answer Failed.
FAIL: Final = "fail"
#: Drop the connection at once.
DISCONNECT: Final = "disconnect"
#: Answer twice.
DUPLICATE: Final = "duplicate"
#: Hold the answer back and send it only after the master aborted the evaluation.
LATE: Final = "late"

Behaviour = Callable[[int, Evaluate], str]
M = TypeVar("M")


def deterministic_fitness(genome: np.ndarray, index: int) -> float:
    """A fitness that depends on the genome and the robot's index only: ``0.5 + 0.4 *
    mean(tanh(genome)) - 0.01 * (index mod 10)`` (no hashing, so equal genomes give equal
    values), in [0.01, 0.9] however large the swarm, as a surprise fitness must be."""
    return float(0.5 + 0.4 * np.tanh(genome).mean() - 0.01 * (index % 10))


class RobotRefusedError(ConnectionError):
    """The master refused the robot; ``code`` and ``reason`` are the master's."""

    def __init__(self, code: str, reason: str) -> None:
        self.code = code
        self.reason = reason
        super().__init__(f"refused: {code}: {reason}")


class ScriptedRobot:
    """A robot stand-in: connects, authenticates, answers pings and evaluations.

    ``evaluations`` and ``aborts`` record what the master sent; ``closed`` is set when the
    connection ends. After it ended, :meth:`connect` may be called again (a robot coming back).
    ``local_address`` binds its connections to that source address (``127.0.0.2``: a robot on
    another machine, seen from a master on loopback). ``software`` is the version, commit and
    firmware its Hello announces (a version of its own, neither commit nor firmware: an agent
    that names none).
    """

    def __init__(
        self,
        robot_id: str,
        secret: bytes,
        port: int,
        *,
        host: str = "127.0.0.1",
        index: int = 0,
        sensors: Sequence[str] = ALL_SENSORS,
        protocol_version: int = PROTOCOL_VERSION,
        fitness: Callable[[np.ndarray, int], float] = deterministic_fitness,
        behaviour: Behaviour | None = None,
        delay: float = 0.0,
        answer_pings: bool = True,
        poses: bool = False,
        ssl_context: ssl.SSLContext | None = None,
        verify_master: bool = True,
        local_address: str | None = None,
        software: tuple[str, str | None, int | None] = ("scripted", None, None),
    ) -> None:
        self.robot_id = robot_id
        self.secret = secret
        self.host = host
        self.port = port
        self.index = index
        self.sensors = tuple(sensors)
        self.protocol_version = protocol_version
        self.fitness = fitness
        self.behaviour = behaviour
        self.delay = delay
        self.answer_pings = answer_pings
        self.poses = poses
        self.ssl_context = ssl_context
        self.verify_master = verify_master
        self.local_address = local_address
        self.software = software
        self.welcome: Welcome | None = None
        self.evaluations: list[Evaluate] = []
        self.aborts: list[Abort] = []
        self.closed = asyncio.Event()
        self._changed = asyncio.Event()
        self._stream: MessageStream | None = None
        self._serving: asyncio.Task[None] | None = None
        self._running: dict[int, asyncio.Task[None]] = {}
        self._held: dict[int, Result] = {}

    # -- connection --------------------------------------------------------------------------

    async def connect(self) -> Welcome:
        """Connect and complete the handshake; raises :class:`RobotRefusedError` if refused and
        :class:`~minimize_surprise.errors.AuthenticationError` if the master's proof is wrong
        (unless ``verify_master`` is off)."""
        reader, writer = await asyncio.open_connection(
            self.host,
            self.port,
            ssl=self.ssl_context,
            server_hostname=self.host if self.ssl_context else None,
            local_addr=None if self.local_address is None else (self.local_address, 0),
        )
        stream = MessageStream(reader, writer)
        secret, robot_id, robot_nonce = self.secret, self.robot_id, new_nonce()
        try:
            await stream.send(
                Hello(
                    robot_id=robot_id,
                    software_version=self.software[0],
                    protocol_version=self.protocol_version,
                    sensors=self.sensors,
                    nonce=robot_nonce,
                    software_commit=self.software[1],
                    thymio_firmware=self.software[2],
                )
            )
            challenge = _expect(await stream.receive(), Challenge)
            master_nonce = challenge.nonce
            expected = master_proof(secret, robot_nonce, master_nonce, robot_id)
            same_secret = proof_matches(expected, challenge.proof)
            if not same_secret and self.verify_master:
                raise AuthenticationError("the master did not prove the shared secret")
            proof = robot_proof(secret, robot_nonce, master_nonce, robot_id)
            await stream.send(Authenticate(proof=proof))
            if same_secret:
                # With different secrets no tag could verify; the master's refusal comes plain.
                auth = FrameAuth.for_robot(secret, robot_nonce, master_nonce, robot_id)
                stream.authenticate(auth)
            welcome = _expect(await stream.receive(), Welcome)
        except BaseException:
            await stream.close()
            raise
        self.welcome = welcome
        self._stream = stream
        self.closed.clear()
        self._serving = asyncio.create_task(self._serve(stream), name=f"robot {self.robot_id}")
        return welcome

    async def close(self, bye: bool = True) -> None:
        """End the connection (with a Bye if ``bye``) and wait until it is closed."""
        stream = self._stream
        if stream is not None and bye:
            with contextlib.suppress(Exception):
                await stream.send(Bye(reason="scripted robot stops"))
        if stream is not None:
            await stream.close()
        if self._serving is not None:
            await self._serving

    def send_raw(self, data: bytes) -> None:
        """Write raw bytes on the connection (garbage, a forged header...), untagged."""
        if self._stream is not None:
            self._stream.writer.write(data)

    def sealed_frame(self, msg: Message) -> bytes:
        """``msg`` as the session's next frame, tagged, for a test to write in pieces with
        :meth:`send_raw` (it uses up the frame's sequence number: send nothing in between)."""
        assert self._stream is not None and self._stream.auth is not None, "connect() first"
        sealed = self._stream.auth.seal(encode_payload(msg))
        return frame(sealed, max_frame_size=self._stream.max_frame_size)

    def send_payload(self, payload: bytes) -> None:
        """Write one message's payload, tagged like any other: a message this robot's software
        would never send (say, a fitness outside [0, 1]), from an authenticated robot."""
        if self._stream is not None:
            self._stream.write(payload)

    def drop(self) -> None:
        """Cut the connection abruptly (like a robot whose Wi-Fi went away)."""
        if self._stream is not None:
            self._stream.writer.transport.abort()

    async def wait_until(self, predicate: Callable[[], bool], timeout: float = 5.0) -> None:
        """Wait until ``predicate()`` is true; it is checked whenever a message arrives."""
        async with asyncio.timeout(timeout):
            while not predicate():
                self._changed.clear()
                await self._changed.wait()

    # -- serving -----------------------------------------------------------------------------

    async def _serve(self, stream: MessageStream) -> None:
        try:
            while True:
                try:
                    msg = await stream.receive()
                except (ConnectionClosedError, ProtocolError, OSError):
                    break
                if isinstance(msg, Ping):
                    if self.answer_pings:
                        await self._send(stream, Pong(seq=msg.seq))
                elif isinstance(msg, Evaluate):
                    self.evaluations.append(msg)
                    await self._evaluate(stream, msg)
                elif isinstance(msg, Abort):
                    self.aborts.append(msg)
                    task = self._running.pop(msg.evaluation_id, None)
                    if task is not None:
                        task.cancel()
                    held = self._held.pop(msg.evaluation_id, None)
                    if held is not None:
                        await self._send(stream, held)
                elif isinstance(msg, Bye):
                    break
                self._changed.set()
        finally:
            for task in self._running.values():
                task.cancel()
            self._running.clear()
            await stream.close()
            self._stream = None
            self.closed.set()
            self._changed.set()

    async def _evaluate(self, stream: MessageStream, msg: Evaluate) -> None:
        # An Evaluate replaces the one running (protocol.md).
        for task in self._running.values():
            task.cancel()
        self._running.clear()
        action = self.behaviour(len(self.evaluations), msg) if self.behaviour else REPLY
        if action == IGNORE:
            return
        if action == DISCONNECT:
            stream.writer.transport.abort()
            return
        if action == FAIL:
            await self._send(stream, Failed(evaluation_id=msg.evaluation_id, reason="scripted"))
            return
        result = self.result(msg)
        if action == LATE:
            self._held[msg.evaluation_id] = result
        elif action == DUPLICATE:
            await self._send(stream, result)
            await self._send(stream, result)
        elif self.delay > 0:
            self._running[msg.evaluation_id] = asyncio.create_task(
                self._reply_later(stream, msg.evaluation_id, result)
            )
        else:
            await self._send(stream, result)

    async def _reply_later(self, stream: MessageStream, evaluation_id: int, result: Result) -> None:
        await asyncio.sleep(self.delay)
        self._running.pop(evaluation_id, None)
        await self._send(stream, result)

    async def _send(self, stream: MessageStream, msg: Message) -> None:
        # A robot whose link just went away has nobody to tell; the serve loop notices the end.
        with contextlib.suppress(ConnectionError, OSError):
            await stream.send(msg)

    def result(self, msg: Evaluate) -> Result:
        """The Result this robot answers ``msg`` with (a synthetic trace when recording)."""
        genome = genome_from_bytes(msg.genome)
        trace = None
        if msg.record:
            trace = self._trace(msg.steps, len(msg.spec.sensors))
        return Result(
            evaluation_id=msg.evaluation_id,
            fitness=self.fitness(genome, self.index),
            # Every fifth step a safety stop, as in the trace.
            stats=EvaluationStats(
                steps_run=msg.steps, overruns=0, interventions={"front": (msg.steps + 4) // 5}
            ),
            trace=trace,
        )

    def _trace(self, steps: int, sensors: int) -> Trace:
        base = 0.1 * (self.index + 1)
        i = np.arange(steps)
        readings = base + 0.01 * (i[:, None] % 10) + 0.001 * np.arange(sensors)
        poses = None
        if self.poses:
            # Robots staggered 10 cm apart in x and 5 cm in y, each driving 1 cm and turning
            # 0.1 rad per step.
            x, y = 0.1 * self.index, 0.05 * self.index
            poses = np.column_stack([x + 0.01 * i, np.full(steps, y), 0.1 * i])
        return Trace.from_arrays(
            sensors=readings,
            predictions=np.full((steps, sensors), base),
            actions=np.full((steps, 2), 0.5),
            commands=np.full((steps, 2), 0.5),
            safety=["" if k % 5 else "front" for k in range(steps)],
            poses=poses,
        )


def _expect(msg: Message, kind: type[M]) -> M:
    if isinstance(msg, Refused):
        raise RobotRefusedError(msg.code, msg.reason)
    if not isinstance(msg, kind):
        raise ConnectionError(f"expected {kind.__name__}, got {type(msg).__name__}")
    return msg
