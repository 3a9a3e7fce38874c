"""A man-in-the-middle for the tests: a TCP proxy on loopback between robots and a master.

It forwards whole frames (split at their length headers) in both directions, keeps a copy of each,
and lets a test write frames of its own into either direction: forged ones, replays of frames it
saw, or frames sent back to where they came from. It knows no secret.
"""

from __future__ import annotations

import asyncio
import contextlib
import struct
from collections.abc import Callable

from minimize_surprise.errors import ProtocolError
from minimize_surprise.session import TAG_SIZE
from minimize_surprise.wire import Message, decode_payload

_HEADER = struct.Struct(">I")


class Relayed:
    """One relayed connection: the frames seen each way, and the means to add some."""

    def __init__(self, client: asyncio.StreamWriter, server: asyncio.StreamWriter) -> None:
        self._client = client
        self._server = server
        #: frames (header included) from the client (robot) to the server (master), in order
        self.to_server: list[bytes] = []
        #: frames from the server to the client
        self.to_client: list[bytes] = []
        self.closed = asyncio.Event()

    def inject_to_server(self, data: bytes) -> None:
        """Write ``data`` to the server as if the client had sent it."""
        self._server.write(data)

    def inject_to_client(self, data: bytes) -> None:
        """Write ``data`` to the client as if the server had sent it."""
        self._client.write(data)


def tagged_message(frame: bytes) -> Message | None:
    """The message in a tagged frame seen on the wire (tags sign, they do not hide), or None."""
    with contextlib.suppress(ProtocolError):
        return decode_payload(frame[_HEADER.size : -TAG_SIZE])
    return None


class Relay:
    """Listens on 127.0.0.1 (``port`` after :meth:`start`) and relays each connection to the
    target port; ``connections`` lists them in order."""

    def __init__(self, target_port: int) -> None:
        self.target_port = target_port
        self.port = 0
        self.connections: list[Relayed] = []
        self._server: asyncio.Server | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        self._changed = asyncio.Event()

    async def start(self) -> int:
        """Start listening; returns the port robots should connect to."""
        self._server = await asyncio.start_server(self._accept, "127.0.0.1", 0)
        self.port = self._server.sockets[0].getsockname()[1]
        return self.port

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self.target_port)
        relayed = Relayed(writer, up_writer)
        self.connections.append(relayed)
        self._changed.set()
        pumps = [
            asyncio.create_task(self._pump(reader, up_writer, relayed.to_server)),
            asyncio.create_task(self._pump(up_reader, writer, relayed.to_client)),
        ]
        self._tasks.update(pumps)
        # Either side closing ends the relayed connection.
        await asyncio.wait(pumps, return_when=asyncio.FIRST_COMPLETED)
        for task in pumps:
            task.cancel()
        await asyncio.gather(*pumps, return_exceptions=True)
        self._tasks.difference_update(pumps)
        for w in (writer, up_writer):
            w.transport.abort()
        relayed.closed.set()
        self._changed.set()

    async def _pump(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, seen: list[bytes]
    ) -> None:
        buffer = bytearray()
        with contextlib.suppress(OSError):
            while data := await reader.read(65536):
                buffer += data
                while len(buffer) >= _HEADER.size:
                    (length,) = _HEADER.unpack_from(buffer)
                    end = _HEADER.size + length
                    if len(buffer) < end:
                        break
                    frame = bytes(buffer[:end])
                    del buffer[:end]
                    seen.append(frame)
                    writer.write(frame)
                    self._changed.set()

    async def wait_for(self, predicate: Callable[[], bool], timeout: float = 5.0) -> None:
        """Wait until ``predicate()`` holds; checked whenever a frame passes or a connection
        opens or closes."""
        async with asyncio.timeout(timeout):
            while not predicate():
                self._changed.clear()
                await self._changed.wait()

    async def close(self) -> None:
        """Stop listening and cut every relayed connection."""
        if self._server is not None:
            self._server.close()
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        if self._server is not None:
            await self._server.wait_closed()
