"""Messages over an asyncio stream pair: the transport of both the master and the agent.

The bytes on the wire are :mod:`surprise.wire`'s frames; this module only moves them.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
from typing import Final

from surprise.errors import ConnectionClosedError
from surprise.wire import MAX_FRAME_SIZE, FrameDecoder, Message, encode

__all__ = ["MessageStream"]

#: Bytes asked of the socket per read: large enough that a 0.5 MB trace takes a handful of reads,
#: small enough not to matter for memory.
CHUNK_SIZE: Final = 64 * 1024


class MessageStream:
    """Messages over an asyncio stream pair; the same class on the master and on the agent.

    One task may :meth:`receive` while others :meth:`send`; concurrent receives are not supported.
    Usable as an async context manager that closes the stream.
    """

    def __init__(
        self,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        *,
        max_frame_size: int = MAX_FRAME_SIZE,
    ) -> None:
        self.reader = reader
        self.writer = writer
        self.max_frame_size = max_frame_size
        self._decoder = FrameDecoder(max_frame_size)
        # One read may complete several frames; the extra messages wait here.
        self._queue: collections.deque[Message] = collections.deque()
        #: Bytes read so far: a message still arriving is a sign of life too.
        self.bytes_received = 0

    def set_max_frame_size(self, max_frame_size: int) -> None:
        """Change the frame size limit of both directions from the next frame on (a server keeps
        it small until its peer has authenticated)."""
        self.max_frame_size = max_frame_size
        self._decoder.max_frame_size = max_frame_size

    async def receive(self) -> Message:
        """Return the next message.

        Raises :class:`~surprise.errors.ConnectionClosedError` when the peer closes (or resets)
        the connection and :class:`~surprise.errors.ProtocolError` for malformed or oversized
        input.
        """
        while not self._queue:
            if self._decoder.poisoned:
                # Fail now rather than wait for bytes from a peer that may never send any.
                self._decoder.feed(b"")
            try:
                data = await self.reader.read(CHUNK_SIZE)
            except ConnectionError as exc:
                raise ConnectionClosedError(f"connection lost: {exc}") from exc
            if not data:
                pending = self._decoder.pending
                if pending:
                    raise ConnectionClosedError(
                        f"peer closed the connection inside a frame ({pending} bytes pending)",
                        mid_frame=True,
                    )
                raise ConnectionClosedError()
            self.bytes_received += len(data)
            self._queue.extend(self._decoder.feed(data))
        return self._queue.popleft()

    async def send(self, msg: Message) -> None:
        """Send one message and wait until the transport's buffer has drained.

        Raises :class:`~surprise.errors.FrameTooLargeError` before sending anything if ``msg`` is
        too large and :class:`~surprise.errors.ConnectionClosedError` if the connection is gone.
        """
        frame = encode(msg, max_frame_size=self.max_frame_size)
        try:
            self.writer.write(frame)
            await self.writer.drain()
        except ConnectionError as exc:
            raise ConnectionClosedError(f"connection lost: {exc}") from exc

    async def close(self) -> None:
        """Close the connection; errors of an already broken connection are ignored."""
        self.writer.close()
        # The peer may already have reset the connection; closed is closed.
        with contextlib.suppress(OSError):
            await self.writer.wait_closed()

    async def __aenter__(self) -> MessageStream:
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        await self.close()
