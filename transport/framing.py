"""Frames: how the protocol's messages travel over a byte stream, on both sides.

A frame is a 4-byte big-endian unsigned length followed by that many payload bytes; the payload is
one message as encoded by :mod:`minimize_surprise.wire` (msgpack), and after the handshake it ends
with a 16-byte tag (:mod:`minimize_surprise.session`). The frame size limits are protocol facts and
stay in :mod:`minimize_surprise.wire` (:data:`~minimize_surprise.wire.MAX_FRAME_SIZE`,
:data:`~minimize_surprise.wire.HANDSHAKE_MAX_FRAME_SIZE`), next to the codec this module frames.
Everything here is pure: :class:`FrameDecoder` is incremental, so any transport can feed it
whatever bytes arrive (the asyncio one of both the master and the agent is
:class:`transport.stream.MessageStream`).
"""

from __future__ import annotations

import struct
from typing import Final

from minimize_surprise.errors import FrameTooLargeError, ProtocolError
from minimize_surprise.wire import MAX_FRAME_SIZE, Message, decode_payload, encode_payload

__all__ = ["HEADER_SIZE", "FrameDecoder", "encode", "frame"]

_HEADER = struct.Struct(">I")
#: Bytes of a frame's length header.
HEADER_SIZE: Final = _HEADER.size


def frame(payload: bytes, *, max_frame_size: int = MAX_FRAME_SIZE) -> bytes:
    """Return ``payload`` (a tagged one after the handshake) with its length header.

    Raises :class:`FrameTooLargeError` if the payload exceeds ``max_frame_size`` (the peer would
    refuse it anyway).
    """
    if len(payload) > max_frame_size:
        raise FrameTooLargeError(len(payload), max_frame_size)
    return _HEADER.pack(len(payload)) + payload


def encode(msg: Message, *, max_frame_size: int = MAX_FRAME_SIZE) -> bytes:
    """Return ``msg`` as one complete untagged frame (length header and payload), as sent
    during the handshake.

    Raises :class:`FrameTooLargeError` if the payload exceeds ``max_frame_size`` and
    ``TypeError`` if ``msg`` is not a protocol message.
    """
    return frame(encode_payload(msg), max_frame_size=max_frame_size)


class FrameDecoder:
    """Incremental splitter and decoder of a byte stream of frames.

    :meth:`feed_payloads` returns the payloads of the frames completed so far, however the stream
    is split (a transport that checks tags decodes them itself); :meth:`feed` decodes them too.
    Any error poisons the decoder: the stream is out of sync and the connection must be closed.
    """

    def __init__(self, max_frame_size: int = MAX_FRAME_SIZE) -> None:
        self.max_frame_size = max_frame_size
        self._buffer = bytearray()
        # Start of unconsumed data in _buffer; consumed bytes are dropped once per feed(), so a
        # frame fed a byte at a time costs amortised O(1) per byte, not a copy of the buffer.
        self._start = 0
        # Payload length of the frame being received, once its header is complete.
        self._length: int | None = None
        self._poisoned: ProtocolError | None = None

    @property
    def poisoned(self) -> bool:
        """Whether an earlier error made the decoder unusable (every feed raises)."""
        return self._poisoned is not None

    @property
    def pending(self) -> int:
        """Number of bytes received but not yet decoded (a partial frame, header included)."""
        # Count a header already parsed too, so that a peer closing right after a header is seen
        # as closing mid-frame.
        header = 0 if self._length is None else _HEADER.size
        return header + len(self._buffer) - self._start

    def poison(self, error: ProtocolError) -> None:
        """Make the decoder unusable after ``error`` (found by the caller in a payload)."""
        self._poisoned = error
        self._buffer = bytearray()
        self._start = 0
        self._length = None

    def feed(self, data: bytes | bytearray | memoryview) -> list[Message]:
        """Add received bytes; return every message they complete, in order.

        Raises :class:`FrameTooLargeError` as soon as a header announces an oversized frame,
        :class:`ProtocolError` for an empty frame or an undecodable payload, and
        :class:`ProtocolError` on every call after an error.
        """
        payloads = self.feed_payloads(data)
        try:
            return [decode_payload(payload) for payload in payloads]
        except ProtocolError as exc:
            self.poison(exc)
            raise

    def feed_payloads(self, data: bytes | bytearray | memoryview) -> list[bytes | bytearray]:
        """Add received bytes; return the payloads of every frame they complete, in order.

        Raises :class:`FrameTooLargeError` as soon as a header announces an oversized frame
        (one behind frames completed in the same call waits, unparsed, for the next call, so
        that a limit raised between two messages applies to it; feeding ``b""`` judges it
        again), :class:`ProtocolError` for an empty frame, and on every call after an error.
        """
        if self._poisoned is not None:
            raise ProtocolError(f"decoder unusable after an earlier error: {self._poisoned}")
        try:
            return self._feed(data)
        except ProtocolError as exc:
            self.poison(exc)
            raise

    def _feed(self, data: bytes | bytearray | memoryview) -> list[bytes | bytearray]:
        buffer = self._buffer
        if not buffer and self._length is None and len(data) >= _HEADER.size:
            # Refuse an oversized frame before its first bytes are copied anywhere.
            (length,) = _HEADER.unpack_from(data)
            if length > self.max_frame_size:
                raise FrameTooLargeError(length, self.max_frame_size)
        buffer += data
        payloads: list[bytes | bytearray] = []
        while True:
            available = len(buffer) - self._start
            if self._length is None:
                if available < _HEADER.size:
                    break
                (length,) = _HEADER.unpack_from(buffer, self._start)
                if length > self.max_frame_size:
                    if payloads:
                        # Frames completed before it go out first: one of them may be what
                        # raises the limit (the handshake's last message, with the first large
                        # one right behind it in the same read). The next feed judges it again.
                        break
                    raise FrameTooLargeError(length, self.max_frame_size)
                if length == 0:
                    raise ProtocolError("empty frame")
                self._start += _HEADER.size
                self._length = length
                available -= _HEADER.size
            if available < self._length:
                break
            end = self._start + self._length
            if end == len(buffer):
                # The buffer ends with this frame (always so for a large one): hand the buffer
                # over rather than copy megabytes (dropping its head is cheap for a bytearray).
                del buffer[: self._start]
                payloads.append(buffer)
                buffer = self._buffer = bytearray()
                self._start = 0
            else:
                with memoryview(buffer) as view:
                    payloads.append(bytes(view[self._start : end]))
                self._start = end
            self._length = None
        if self._start:
            del buffer[: self._start]
            self._start = 0
        return payloads
