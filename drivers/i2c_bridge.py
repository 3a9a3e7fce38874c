"""An I2C bus reached over a Unix socket: a rehearsal's stand-in for ``/dev/i2c-N``.

On a robot the force and light drivers talk to ``/dev/i2c-N`` through ``smbus2``. A rehearsal
without robots (``surprise-sim-robots``, docs/separate-processes.md) serves emulated chips whose
readings come from a simulated world in another process; :class:`BridgeSMBus` is the
:class:`~drivers.i2c.SMBusLike` handle that forwards every SMBus call there, so that the very
same drivers run as on the robot. The agent uses it when its configuration names the socket
(``body.i2c_bridge``); the server is :mod:`standins.i2c_bridge`.

The protocol, shared by both sides and defined here because ``drivers`` is the lowest package
both may import: one request per SMBus call, answered by one reply, on one connection per opened
bus. Each message is a 4-byte big-endian length followed by that many bytes of msgpack:

- :class:`BridgeRequest` ``[op, bus, address, register, value]``: ``op`` is ``open`` (does bus
  ``bus`` exist?, as opening ``/dev/i2c-N`` asks) or the name of an :class:`~drivers.i2c.SMBusLike`
  method; ``register`` and ``value`` are 0 where the call has none.
- :class:`BridgeReply` ``[value, errno, message]``: ``errno`` 0 and the call's ``value`` (0 for a
  write), or the ``errno`` of the ``OSError`` the call raised (121, Remote I/O error, for a NACK)
  with its message.

Calls are synchronous: the drivers already run each transaction on the bus's worker thread
(:class:`~drivers.i2c.I2CBus`). Every call is bounded by a timeout, so a dead or stalled server is
a failed transfer (``OSError`` or :class:`~minimize_surprise.errors.HardwareError`, each naming
the socket), never a hang; after any failure the connection is dropped, so a late reply can never
answer a later request, and the next call connects again.
"""

from __future__ import annotations

import errno as errnos
import socket
import struct
import time
from typing import Annotated, Final, Literal, get_args

import msgspec

from minimize_surprise.errors import HardwareError

__all__ = [
    "BRIDGE_CALL_TIMEOUT",
    "HEADER_SIZE",
    "MAX_ERROR_MESSAGE",
    "MAX_MESSAGE_SIZE",
    "OPS",
    "BridgeReply",
    "BridgeRequest",
    "BridgeSMBus",
    "Op",
    "bridge_factory",
    "frame",
    "message_size",
]

#: Seconds one call may take from sending the request to the whole reply. The server answers from
#: an event loop that also steps the simulated world (a few milliseconds per step); 0.2 s, the
#: drivers' bound for a whole transaction (``drivers.i2c.TRANSACTION_TIMEOUT``), tolerates a
#: loaded machine and still frees the bus's worker thread within two 10 Hz steps when the server
#: is stalled.
BRIDGE_CALL_TIMEOUT: Final = 0.2
#: The longest message either side accepts, in bytes: a request is about 20, a reply about 20
#: plus an error's message; anything longer is a peer speaking another protocol.
MAX_MESSAGE_SIZE: Final = 1024
#: The longest error message a reply carries, in characters (an ``OSError``'s text and a path),
#: which keeps every reply far below :data:`MAX_MESSAGE_SIZE`.
MAX_ERROR_MESSAGE: Final = 400
#: The length prefix of every message.
_HEADER = struct.Struct(">I")
#: Bytes of the length prefix.
HEADER_SIZE: Final = _HEADER.size

#: What a request asks: ``open`` (does the bus exist?) or the name of an SMBus method.
Op = Literal[
    "open", "read_byte_data", "write_byte_data", "read_word_data", "write_word_data", "write_byte"
]  # fmt: skip
#: Every ``op`` a request may carry.
OPS: tuple[str, ...] = get_args(Op)

_Byte = Annotated[int, msgspec.Meta(ge=0, le=0xFF)]
_Word = Annotated[int, msgspec.Meta(ge=0, le=0xFFFF)]


class BridgeRequest(msgspec.Struct, frozen=True, array_like=True, forbid_unknown_fields=True):
    """One SMBus call: ``op`` on ``bus`` to the device at ``address`` (see the module docstring)."""

    #: ``open`` or the SMBus method
    op: Op
    #: the bus number, as in ``/dev/i2c-N``
    bus: _Byte
    #: the device's 7-bit address
    address: Annotated[int, msgspec.Meta(ge=0, le=0x7F)] = 0
    #: the register (command byte); 0 where the call has none
    register: _Byte = 0
    #: the byte or word written; 0 for a read
    value: _Word = 0


class BridgeReply(msgspec.Struct, frozen=True, array_like=True, forbid_unknown_fields=True):
    """The answer to one :class:`BridgeRequest`: ``value``, or the call's ``errno`` and message."""

    #: what a read returned (0 for a write or after an error)
    value: _Word = 0
    # Linux's error numbers are below 4096 (MAX_ERRNO).
    #: 0 on success, else the errno of the call's ``OSError``
    errno: Annotated[int, msgspec.Meta(ge=0, le=4095)] = 0
    #: the error's message ('' on success)
    message: Annotated[str, msgspec.Meta(max_length=MAX_ERROR_MESSAGE)] = ""


_encoder = msgspec.msgpack.Encoder()
_reply_decoder = msgspec.msgpack.Decoder(BridgeReply)


def frame(message: BridgeRequest | BridgeReply) -> bytes:
    """``message`` with its length prefix, ready to send."""
    payload = _encoder.encode(message)
    return _HEADER.pack(len(payload)) + payload


def message_size(header: bytes) -> int:
    """The payload's length announced by a 4-byte ``header``; ``ValueError`` if it is too long."""
    (size,) = _HEADER.unpack(header)
    if size > MAX_MESSAGE_SIZE:
        raise ValueError(f"a message of {size} bytes (at most {MAX_MESSAGE_SIZE})")
    return int(size)


class BridgeSMBus:
    """Bus ``bus`` of the I2C bridge at ``path``, as an :class:`~drivers.i2c.SMBusLike`.

    Connects and asks whether the bus exists at construction, as ``smbus2.SMBus(bus)`` opens
    ``/dev/i2c-<bus>``: a missing socket or bus raises ``OSError`` there. Each call waits at most
    ``timeout`` seconds. Not thread-safe, as an ``smbus2`` handle is not: one bus worker owns it.
    """

    def __init__(self, path: str, bus: int, *, timeout: float = BRIDGE_CALL_TIMEOUT) -> None:
        self.path = path
        self.bus = bus
        self.timeout = timeout
        self._socket: socket.socket | None = None
        self._closed = False
        self._call("open", 0)

    def __repr__(self) -> str:
        return f"BridgeSMBus({self.path!r}, bus={self.bus})"

    # -- SMBusLike ----------------------------------------------------------------------------

    def read_byte_data(self, i2c_addr: int, register: int) -> int:
        """Read the byte at ``register``."""
        return self._call("read_byte_data", i2c_addr, register)

    def write_byte_data(self, i2c_addr: int, register: int, value: int) -> None:
        """Write ``value`` to ``register``."""
        self._call("write_byte_data", i2c_addr, register, value)

    def read_word_data(self, i2c_addr: int, register: int) -> int:
        """Read the word at ``register`` (low byte first, as SMBus words are)."""
        return self._call("read_word_data", i2c_addr, register)

    def write_word_data(self, i2c_addr: int, register: int, value: int) -> None:
        """Write the word ``value`` to ``register`` (low byte first)."""
        self._call("write_word_data", i2c_addr, register, value)

    def write_byte(self, i2c_addr: int, value: int) -> None:
        """Write one byte without a register (a multiplexer's channel mask)."""
        self._call("write_byte", i2c_addr, 0, value)

    def close(self) -> None:
        """Close the connection (idempotent); later calls fail as on a closed ``smbus2`` handle."""
        self._closed = True
        self._disconnect()

    # -- the wire -----------------------------------------------------------------------------

    def _call(self, op: Op, address: int, register: int = 0, value: int = 0) -> int:
        if self._closed:
            raise OSError(errnos.EBADF, f"I2C bridge {self.path}: the bus handle is closed")
        # Constructing a struct checks no bounds (decoding does): a driver's bad argument is
        # refused here, as smbus2 refuses it, instead of costing the connection at the server.
        top = 0xFFFF if op == "write_word_data" else 0xFF
        if not (0 <= address <= 0x7F and 0 <= register <= 0xFF and 0 <= value <= top):
            raise ValueError(
                f"I2C bridge {self.path}: {op}: address 0x{address:X}, register {register} or "
                f"value {value} out of range"
            )
        request = BridgeRequest(op, self.bus, address, register, value)
        reply = self._exchange(request)
        if reply.errno:
            raise OSError(reply.errno, f"{reply.message} (I2C bridge {self.path})")
        return reply.value

    def _exchange(self, request: BridgeRequest) -> BridgeReply:
        what = (
            f"open bus {request.bus}"
            if request.op == "open"
            else f"{request.op} 0x{request.address:02X} on bus {request.bus}"
        )
        # One deadline for the whole call: the socket's own timeout bounds each operation only.
        deadline = time.monotonic() + self.timeout
        try:
            sock = self._connected(deadline)
            sock.settimeout(_remaining(deadline))
            sock.sendall(frame(request))
            size = message_size(self._receive(sock, HEADER_SIZE, deadline))
            return _reply_decoder.decode(self._receive(sock, size, deadline))
        except TimeoutError:
            self._disconnect()
            # Not a plain TimeoutError: the bus would report it with its own transaction's
            # timeout, and this one is the bridge's.
            raise HardwareError(
                f"I2C bridge {self.path}: {what}: no answer within {self.timeout} s"
            ) from None
        except OSError as exc:
            self._disconnect()
            code = exc.errno if exc.errno is not None else errnos.EIO
            reason = exc.strerror or str(exc)
            raise OSError(code, f"I2C bridge {self.path}: {what}: {reason}") from exc
        except (ValueError, msgspec.DecodeError) as exc:
            self._disconnect()
            raise OSError(
                errnos.EPROTO, f"I2C bridge {self.path}: {what}: not a bridge's reply: {exc}"
            ) from exc

    def _connected(self, deadline: float) -> socket.socket:
        if self._socket is None:
            sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            try:
                sock.settimeout(_remaining(deadline))
                sock.connect(self.path)
            except BaseException:
                sock.close()
                raise
            self._socket = sock
        return self._socket

    @staticmethod
    def _receive(sock: socket.socket, size: int, deadline: float) -> bytes:
        data = bytearray()
        while len(data) < size:
            sock.settimeout(_remaining(deadline))
            chunk = sock.recv(size - len(data))
            if not chunk:
                raise ConnectionResetError(errnos.ECONNRESET, "the bridge closed the connection")
            data += chunk
        return bytes(data)

    def _disconnect(self) -> None:
        if self._socket is not None:
            self._socket.close()
            self._socket = None


def _remaining(deadline: float) -> float:
    """Seconds left until ``deadline``; ``TimeoutError`` once it has passed."""
    left = deadline - time.monotonic()
    if left <= 0:
        raise TimeoutError
    return left


def bridge_factory(path: str, *, timeout: float = BRIDGE_CALL_TIMEOUT) -> _Factory:
    """An ``smbus_factory`` (see :func:`drivers.compose.build_body`) opening buses of the bridge
    at ``path`` instead of ``/dev/i2c-N``."""
    return _Factory(path, timeout)


class _Factory:
    # A class rather than a closure: its repr names the socket in a log line.
    def __init__(self, path: str, timeout: float) -> None:
        self.path = path
        self.timeout = timeout

    def __call__(self, bus: int) -> BridgeSMBus:
        return BridgeSMBus(self.path, bus, timeout=self.timeout)

    def __repr__(self) -> str:
        return f"bridge_factory({self.path!r})"
