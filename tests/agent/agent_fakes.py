"""Fakes for the agent tests: a scripted body, a clock that never sleeps, genomes with known output.

Kept in a module of its own (not conftest) so tests can import the classes directly.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable, Sequence
from ssl import SSLContext

import numpy as np

from drivers.body import Body, SensorFrame
from drivers.clock import Clock
from minimize_surprise.errors import ConnectionClosedError, HardwareError
from minimize_surprise.network import GenomeLayout, NetworkSpec
from minimize_surprise.sensors import GROUND_SENSORS, IR_SENSORS
from minimize_surprise.session import FrameAuth, master_proof, new_nonce, proof_matches, robot_proof
from minimize_surprise.wire import (
    REFUSED_BAD_SECRET,
    Authenticate,
    Challenge,
    Hello,
    Message,
    Refused,
    Welcome,
)
from robot_agent.config import AgentConfig, BackoffConfig, MasterConfig
from transport.stream import MessageStream

#: What the fake body carries by default: a plain Thymio.
THYMIO = IR_SENSORS + GROUND_SENSORS


class FakeClock(Clock):
    """Simulated time: ``sleep_until`` records the deadline, jumps there and yields once.

    ``advance(dt)`` models work that takes time (the fake body calls it from ``read``).
    """

    def __init__(self, start: float = 1000.0) -> None:
        self.t = start
        self.deadlines: list[float] = []

    def now(self) -> float:
        return self.t

    def advance(self, dt: float) -> None:
        self.t += dt

    async def sleep_until(self, deadline: float) -> None:
        self.deadlines.append(deadline)
        self.t = max(self.t, deadline)
        await asyncio.sleep(0)  # let other tasks (the link, a canceller) run, like a real sleep


class FakeBody(Body):
    """A body whose readings come from ``values(step)`` and which remembers every motor command.

    ``values`` is a constant (every sensor), a sequence (one frame) or a callable of the read
    index. ``work`` seconds are added to ``clock`` per read. ``hang(i)`` / ``fail(i)`` make read i
    never return / raise; ``drive_error(i)`` makes the i-th drive raise.
    """

    def __init__(
        self,
        values: float | Sequence[float] | Callable[[int], Sequence[float]] = 0.0,
        *,
        sensors: tuple[str, ...] = THYMIO,
        clock: FakeClock | None = None,
        work: float | Callable[[int], float] = 0.0,
        hang: Callable[[int], bool] = lambda i: False,
        fail: Callable[[int], bool] = lambda i: False,
        drive_error: Callable[[int], bool] = lambda i: False,
    ) -> None:
        self._sensors = sensors
        self._values = values
        self.clock = clock
        self._work = work
        self._hang = hang
        self._fail = fail
        self._drive_error = drive_error
        self.reads = 0
        self.drives: list[tuple[float, float]] = []
        self.stops = 0
        #: the wheel speeds the motors run at now
        self.motors: tuple[float, float] = (0.0, 0.0)
        self.opened = False
        self.closed = False
        self.moved = asyncio.Event()  # set at the first non-zero drive

    @property
    def sensors(self) -> tuple[str, ...]:
        return self._sensors

    def frame(self, i: int) -> np.ndarray:
        v = self._values
        if callable(v):
            v = v(i)
        if isinstance(v, int | float):
            return np.full(len(self._sensors), float(v))
        return np.array(v, dtype=np.float64)

    async def open(self) -> None:
        self.opened = True

    async def close(self) -> None:
        self.closed = True
        await self.stop()

    async def read(self) -> SensorFrame:
        i = self.reads
        self.reads += 1
        if self.clock is not None:
            work = self._work(i) if callable(self._work) else self._work
            self.clock.advance(work)
        if self._hang(i):
            await asyncio.get_running_loop().create_future()  # never completes
        if self._fail(i):
            raise HardwareError(f"read {i} failed")
        stamp = self.clock.now() if self.clock is not None else 0.0
        return SensorFrame(values=self.frame(i), timestamp=stamp)

    async def drive(self, left: float, right: float) -> None:
        if self._drive_error(len(self.drives)):
            self.drives.append((math.nan, math.nan))
            raise HardwareError("motor write failed")
        self.drives.append((float(left), float(right)))
        self.motors = (float(left), float(right))
        if self.motors != (0.0, 0.0):
            self.moved.set()

    async def stop(self) -> None:
        self.stops += 1
        self.motors = (0.0, 0.0)


class PosedBody(FakeBody):
    """A fake body with a ``pose`` attribute, like simulated bodies: x grows by 1 per drive."""

    def __init__(self, *args: object, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self.pose = (0.0, 0.0, 0.0)

    async def drive(self, left: float, right: float) -> None:
        await super().drive(left, right)
        x, y, theta = self.pose
        self.pose = (x + 1.0, y, theta)


def spec(
    sensors: Sequence[str] = THYMIO,
    predefined: dict[str, float] | None = None,
    *,
    actor_hidden: int = 2,
    predictor_hidden: int = 2,
) -> NetworkSpec:
    """A small network spec."""
    return NetworkSpec(
        sensors=tuple(sensors),
        actor_hidden=actor_hidden,
        predictor_hidden=predictor_hidden,
        predefined=dict(predefined or {}),
    )


def genome(
    network: NetworkSpec, *, speed_bias: float = 0.0, prediction_bias: float = 0.0
) -> np.ndarray:
    """A genome whose actor always outputs ``tanh(speed_bias)`` on both wheels and whose
    predictor always outputs ``sigmoid(prediction_bias)`` (every other weight is zero)."""
    layout = GenomeLayout(network)
    g = np.zeros(layout.size)
    blocks = layout.unpack(g)  # views into g
    blocks["actor.output"][:, -1] = speed_bias
    if layout.has_predictor:
        blocks["predictor.output"][:, -1] = prediction_bias
    return g


# --------------------------------------------------------------------------- a scripted master

SECRET = b"lab secret"


async def receive(stream: MessageStream, timeout: float = 5.0) -> Message:
    """The next message, or fail the test after ``timeout`` seconds."""
    async with asyncio.timeout(timeout):
        return await stream.receive()


class ScriptedMaster:
    """A few lines of master over loopback TCP: each connection is handed to the test, which
    plays the master's side of the conversation itself."""

    def __init__(self) -> None:
        self.connections: asyncio.Queue[MessageStream] = asyncio.Queue()
        self.streams: list[MessageStream] = []
        self.server: asyncio.Server | None = None
        self.port = 0

    async def start(self, port: int = 0, *, ssl: SSLContext | None = None) -> None:
        """Listen on 127.0.0.1 (``port`` 0: any free port), with TLS if ``ssl`` is given."""
        self.server = await asyncio.start_server(self._accept, "127.0.0.1", port, ssl=ssl)
        self.port = self.server.sockets[0].getsockname()[1]

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        stream = MessageStream(reader, writer)
        self.streams.append(stream)
        await self.connections.put(stream)

    async def next(self, timeout: float = 5.0) -> MessageStream:
        """The next connection from a robot."""
        async with asyncio.timeout(timeout):
            return await self.connections.get()

    async def welcome(
        self,
        stream: MessageStream,
        secret: bytes = SECRET,
        *,
        heartbeat: float = 30.0,
        run_id: str = "run-1",
    ) -> Hello:
        """Play the accepting side of the handshake with ``secret``; returns the robot's Hello.

        Raises ``AssertionError`` if the robot does not answer the challenge (it refused our
        proof) or its proof does not verify.
        """
        hello = await receive(stream)
        assert isinstance(hello, Hello) and hello.nonce is not None
        robot_id, robot_nonce, master_nonce = hello.robot_id, hello.nonce, new_nonce()
        proof = master_proof(secret, robot_nonce, master_nonce, robot_id)
        await stream.send(Challenge(nonce=master_nonce, proof=proof))
        try:
            auth = await receive(stream)
        except ConnectionClosedError:
            raise AssertionError("the robot did not accept the master's proof") from None
        assert isinstance(auth, Authenticate)
        if not proof_matches(robot_proof(secret, robot_nonce, master_nonce, robot_id), auth.proof):
            await stream.send(Refused(code=REFUSED_BAD_SECRET, reason="wrong proof"))
            await stream.close()
            raise AssertionError("the robot's proof did not verify")
        stream.authenticate(FrameAuth.for_master(secret, robot_nonce, master_nonce, robot_id))
        await stream.send(Welcome(run_id=run_id, heartbeat_interval=heartbeat))
        return hello

    async def close(self) -> None:
        """Stop listening and close every connection."""
        if self.server is not None:
            self.server.close()
            await self.server.wait_closed()
            self.server = None
        for stream in self.streams:
            await stream.close()
        self.streams.clear()


def agent_config(port: int, **overrides: object) -> AgentConfig:
    """An agent configuration for loopback tests, with tiny reconnection delays."""
    values: dict[str, object] = {
        "robot_id": "r1",
        "master": MasterConfig(host="127.0.0.1", port=port, secret_file="unused"),
        "reconnect": BackoffConfig(initial=0.01, max=0.04, jitter=0.5),
    }
    values.update(overrides)
    return AgentConfig(**values)  # type: ignore[arg-type]
