"""MessageStream over loopback TCP: round trips, bursts, peers closing mid-frame, limits."""

from __future__ import annotations

import asyncio
import contextlib
import struct
from collections.abc import Awaitable, Callable

import numpy as np
import pytest

from minimize_surprise.errors import (
    AuthenticationError,
    ConnectionClosedError,
    FrameTooLargeError,
    ProtocolError,
    SurpriseError,
)
from minimize_surprise.session import TAG_SIZE, FrameAuth
from minimize_surprise.wire import (
    MAX_FRAME_SIZE,
    Bye,
    EvaluationStats,
    Hello,
    Message,
    Ping,
    Pong,
    Result,
    Trace,
    decode_payload,
    encode_payload,
)
from transport.framing import encode, frame
from transport.stream import MessageStream

Handler = Callable[[asyncio.StreamReader, asyncio.StreamWriter], Awaitable[None]]


class Loopback:
    """A server on 127.0.0.1 running ``handler`` for one client, and that client's stream."""

    def __init__(self, handler: Handler, *, max_frame_size: int = MAX_FRAME_SIZE) -> None:
        self.handler = handler
        self.max_frame_size = max_frame_size
        self.handled = asyncio.Event()

    async def __aenter__(self) -> MessageStream:
        async def run(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            try:
                await self.handler(reader, writer)
            finally:
                self.handled.set()

        self.server = await asyncio.start_server(run, "127.0.0.1", 0)
        port = self.server.sockets[0].getsockname()[1]
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        self.client = MessageStream(reader, writer, max_frame_size=self.max_frame_size)
        return self.client

    async def __aexit__(self, *exc_info: object) -> None:
        await self.client.close()
        # Wait for the handler so no task outlives the test's event loop.
        await asyncio.wait_for(self.handled.wait(), timeout=5)
        self.server.close()
        await self.server.wait_closed()


def sample_trace(steps: int, width: int) -> Trace:
    row = np.arange(width) * 0.123456789
    return Trace.from_arrays(
        sensors=np.tile(row, (steps, 1)),
        predictions=np.tile(row, (steps, 1)),
        actions=np.tile([0.5, -0.5], (steps, 1)),
        commands=np.tile([0.5, -0.5], (steps, 1)),
        safety=[""] * steps,
        poses=np.tile([1.0, 2.0, 3.0], (steps, 1)),
    )


async def test_stream_round_trips_messages_over_tcp() -> None:
    async def echo(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        async with MessageStream(reader, writer) as stream:
            while True:
                try:
                    msg = await stream.receive()
                except ConnectionClosedError:
                    return
                await stream.send(msg)

    big = Result(
        evaluation_id=9,
        fitness=0.25,
        stats=EvaluationStats(steps_run=2000, overruns=2, interventions={"cliff": 3}),
        trace=sample_trace(2000, 12),
    )
    assert len(encode(big)) > 4 * 64 * 1024  # spans many reads
    sent: list[Message] = [
        Hello(robot_id="t1", software_version="0.1", protocol_version=1, sensors=("ir.f0",)),
        Ping(seq=1),
        big,
        Bye(reason="done"),
    ]
    async with asyncio.timeout(5), Loopback(echo) as client:
        for msg in sent:
            await client.send(msg)
        received = [await client.receive() for _ in sent]
    assert received == sent


async def test_stream_queues_several_messages_from_one_read() -> None:
    async def burst(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writer.write(b"".join(encode(Ping(seq=i)) for i in range(50)))
        await writer.drain()
        writer.close()
        await writer.wait_closed()

    async with asyncio.timeout(5), Loopback(burst) as client:
        assert [await client.receive() for _ in range(50)] == [Ping(seq=i) for i in range(50)]
        with pytest.raises(ConnectionClosedError) as info:
            await client.receive()
    assert not info.value.mid_frame


async def test_peer_closing_mid_frame_raises_connection_closed() -> None:
    async def half(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        data = encode(Pong(seq=1)) + encode(Bye(reason="cut"))
        writer.write(data[:-3])
        await writer.drain()
        writer.close()
        await writer.wait_closed()

    async with asyncio.timeout(5), Loopback(half) as client:
        assert await client.receive() == Pong(seq=1)
        with pytest.raises(ConnectionClosedError, match="inside a frame") as info:
            await client.receive()
    assert info.value.mid_frame
    assert isinstance(info.value, ConnectionError)
    assert isinstance(info.value, SurpriseError)


async def test_peer_closing_right_after_a_header_is_mid_frame() -> None:
    async def header_only(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writer.write(struct.pack(">I", 10))
        await writer.drain()
        writer.close()
        await writer.wait_closed()

    async with asyncio.timeout(5), Loopback(header_only) as client:
        with pytest.raises(ConnectionClosedError) as info:
            await client.receive()
    assert info.value.mid_frame


async def test_stream_rejects_oversized_frame_from_peer() -> None:
    async def hostile(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        # Announce 1 GiB but send only the header: the receiver must not wait for the body.
        writer.write(struct.pack(">I", 1 << 30))
        await writer.drain()
        await reader.read()  # hold the connection open until the client closes it
        writer.close()
        await writer.wait_closed()

    async with asyncio.timeout(5), Loopback(hostile) as client:
        with pytest.raises(FrameTooLargeError):
            await client.receive()
        # The stream stays poisoned: the caller must close it.
        with pytest.raises(ProtocolError):
            await client.receive()


async def test_stream_send_refuses_oversized_message_before_writing() -> None:
    received: list[bytes] = []

    async def sink(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        received.append(await reader.read())
        writer.close()
        await writer.wait_closed()

    async with asyncio.timeout(5), Loopback(sink, max_frame_size=100) as client:
        with pytest.raises(FrameTooLargeError):
            await client.send(Bye(reason="x" * 200))
        await client.send(Ping(seq=1))
    assert received == [encode(Ping(seq=1))]


# ---------------------------------------------------------------------------------------------
# Authenticated sessions

NR, NM = bytes(32), bytes(range(32))


def session_pair() -> tuple[FrameAuth, FrameAuth]:
    """The master's and the robot's side of one session."""
    return (
        FrameAuth.for_master(b"secret", NR, NM, "r1"),
        FrameAuth.for_robot(b"secret", NR, NM, "r1"),
    )


async def test_an_authenticated_stream_tags_what_it_sends_and_checks_what_it_receives() -> None:
    master_auth, robot_auth = session_pair()
    on_the_wire: list[bytes] = []

    async def master(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        for seq in range(3):
            writer.write(frame(master_auth.seal(encode_payload(Ping(seq=seq)))))
            (length,) = struct.unpack(">I", await reader.readexactly(4))
            sealed = await reader.readexactly(length)
            on_the_wire.append(sealed)
            assert decode_payload(master_auth.open(sealed)) == Pong(seq=seq)
        await reader.read()
        writer.close()

    async with asyncio.timeout(5), Loopback(master) as client:
        client.authenticate(robot_auth)
        for _ in range(3):
            ping = await client.receive()
            await client.send(Pong(seq=ping.seq))
    # Each frame is the plain payload followed by its 16-byte tag.
    for seq, sealed in enumerate(on_the_wire):
        assert sealed[:-TAG_SIZE] == encode_payload(Pong(seq=seq)) and TAG_SIZE == 16
    assert (robot_auth.sent, robot_auth.received) == (3, 3)


async def test_a_plain_frame_in_an_authenticated_session_ends_it() -> None:
    _, robot_auth = session_pair()

    async def impostor(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writer.write(encode(Ping(seq=1)) + encode(Ping(seq=2)))
        await writer.drain()
        await reader.read()
        writer.close()

    async with asyncio.timeout(5), Loopback(impostor) as client:
        client.authenticate(robot_auth)
        with pytest.raises(AuthenticationError):
            await client.receive()
        # Unusable from then on, even though a second frame had arrived with the first.
        with pytest.raises(ProtocolError):
            await client.receive()


async def test_an_oversized_message_uses_up_no_sequence_number() -> None:
    master_auth, robot_auth = session_pair()
    received: list[Message] = []

    async def master(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        async with MessageStream(reader, writer) as stream:
            stream.authenticate(master_auth)
            received.append(await stream.receive())

    async with asyncio.timeout(5), Loopback(master, max_frame_size=200) as client:
        client.authenticate(robot_auth)
        with pytest.raises(FrameTooLargeError) as info:
            await client.send(Bye(reason="x" * 190))  # fits untagged, not with its tag
        assert info.value.size == len(encode(Bye(reason="x" * 190))) - 4 + TAG_SIZE
        await client.send(Bye(reason="done"))
    assert received == [Bye(reason="done")]  # the next frame still carries sequence number 0


async def test_before_the_handshake_a_stream_reads_no_more_than_a_small_frame() -> None:
    async def flood(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writer.write(struct.pack(">I", 3000) + bytes(1024 * 1024))
        with contextlib.suppress(ConnectionError):
            await writer.drain()
            await reader.read()
        writer.close()

    async with asyncio.timeout(5), Loopback(flood, max_frame_size=4096) as client:
        with pytest.raises(ProtocolError):
            await client.receive()
        assert client.bytes_received <= 4096 + 4


async def test_a_large_message_right_behind_the_handshake_s_last_is_received_after_it() -> None:
    # The master welcomes a robot and sends its first (large) evaluation at once: both may come
    # in one read, while the robot's limit is still the handshake's. The first is received, the
    # limit raised, then the second, with no more bytes from the peer; not raised, it is refused.
    large = Hello(
        robot_id="r1", software_version="x" * 60, protocol_version=1, sensors=("ir.f0",) * 16
    )
    assert len(encode(large)) > 200

    async def both(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writer.write(encode(Ping(seq=1)) + encode(large) + encode(Ping(seq=2)))
        await writer.drain()
        await reader.read()  # keep the connection open: no bytes follow
        writer.close()

    async with asyncio.timeout(5), Loopback(both, max_frame_size=100) as client:
        assert await client.receive() == Ping(seq=1)
        client.set_max_frame_size(MAX_FRAME_SIZE)
        assert await client.receive() == large
        assert await client.receive() == Ping(seq=2)
    async with asyncio.timeout(5), Loopback(both, max_frame_size=100) as client:
        assert await client.receive() == Ping(seq=1)
        with pytest.raises(FrameTooLargeError):
            await client.receive()
