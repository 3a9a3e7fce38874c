"""Messages over an asyncio stream pair: the transport of both the master and the agent.

The bytes on the wire are :mod:`transport.framing`'s frames of :mod:`minimize_surprise.wire`'s
messages. Once the handshake has established a session, :meth:`MessageStream.authenticate` turns on
its :class:`~minimize_surprise.session.FrameAuth`: from then on every frame sent carries a tag, and
every frame received must carry the right one before it is even decoded.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
from typing import Final

from minimize_surprise.errors import ConnectionClosedError, FrameTooLargeError, ProtocolError
from minimize_surprise.session import TAG_SIZE, FrameAuth
from minimize_surprise.wire import MAX_FRAME_SIZE, Message, decode_payload, encode_payload
from transport.framing import HEADER_SIZE, FrameDecoder
from transport.framing import frame as make_frame

__all__ = ["CHUNK_SIZE", "MessageStream"]

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
        # One read may complete several frames; their payloads wait here. They are checked and
        # decoded one by one as they are received, so a session turned on between two messages
        # applies to every later frame, even one that arrived in the same read.
        self._queue: collections.deque[bytes | bytearray] = collections.deque()
        #: the session's frame authentication, once :meth:`authenticate` turned it on
        self.auth: FrameAuth | None = None
        #: Bytes read so far: a message still arriving is a sign of life too.
        self.bytes_received = 0

    def set_max_frame_size(self, max_frame_size: int) -> None:
        """Change the frame size limit of both directions from the next frame on (both sides keep
        it small until the handshake is complete)."""
        self.max_frame_size = max_frame_size
        self._decoder.max_frame_size = max_frame_size

    def authenticate(self, auth: FrameAuth) -> None:
        """Tag every frame sent from now on and accept only correctly tagged frames."""
        self.auth = auth

    async def receive(self) -> Message:
        """Return the next message.

        Raises :class:`~minimize_surprise.errors.ConnectionClosedError` when the peer closes (or
        resets) the connection, :class:`~minimize_surprise.errors.AuthenticationError` for a frame
        whose tag does not verify, and :class:`~minimize_surprise.errors.ProtocolError` for
        malformed or oversized input. Any of these errors leaves the stream unusable.
        """
        while not self._queue:
            if self._decoder.poisoned:
                # Fail now rather than wait for bytes from a peer that may never send any.
                self._decoder.feed_payloads(b"")
            if self._decoder.pending:
                # A frame read with an earlier one may be complete already, judged by the limit
                # of now (the handshake's limit is raised between its last message and the next).
                self._queue.extend(self._decoder.feed_payloads(b""))
                if self._queue:
                    break
            try:
                # Never more than a frame's worth at a time: before the handshake is done, a peer
                # gets no more than its small frames buffered, whatever it sends.
                data = await self.reader.read(min(CHUNK_SIZE, self.max_frame_size + HEADER_SIZE))
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
            self._queue.extend(self._decoder.feed_payloads(data))
        payload = self._queue.popleft()
        try:
            body = payload if self.auth is None else self.auth.open(payload)
            return decode_payload(body)
        except ProtocolError as exc:
            self._queue.clear()
            self._decoder.poison(exc)
            raise

    def write(self, payload: bytes) -> None:
        """Write one encoded message (:func:`~minimize_surprise.wire.encode_payload`) now, tagged if
        the session is on, without waiting for the transport's buffer to drain.

        Raises :class:`~minimize_surprise.errors.FrameTooLargeError` before writing anything if the
        frame would exceed the limit.
        """
        if self.auth is not None:
            # Checked before sealing: a frame never sent must not use up a sequence number.
            size = len(payload) + TAG_SIZE
            if size > self.max_frame_size:
                raise FrameTooLargeError(size, self.max_frame_size)
            payload = self.auth.seal(payload)
        self.writer.write(make_frame(payload, max_frame_size=self.max_frame_size))

    async def send(self, msg: Message) -> None:
        """Send one message and wait until the transport's buffer has drained.

        Raises :class:`~minimize_surprise.errors.FrameTooLargeError` before sending anything if
        ``msg`` is too large and :class:`~minimize_surprise.errors.ConnectionClosedError` if the
        connection is gone.
        """
        payload = encode_payload(msg)
        try:
            self.write(payload)
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
