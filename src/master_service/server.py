"""The robots' TCP server: handshake, authenticated sessions, replacement and keep-alive.

The conversation follows ``docs/protocol.md``. A connection becomes a :class:`Session` once the
robot has said Hello with our protocol version and its nonce, checked our proof of the shared
secret, proved the secret itself, and been admitted (allow-list, swarm membership, sensors).
Anything else gets a ``Refused`` with a code and a reason the robot logs, and the connection is
closed. From the Welcome on, every frame in both directions is tagged with the session's keys; a
frame whose tag does not verify (forged, replayed, reflected) closes the session.

The server knows nothing about evolution: it reports joins, departures and the robots' Result and
Failed messages to callbacks, and offers :meth:`RobotServer.send` for already encoded messages, so
a genome sent to a hundred robots is encoded once and only tagged per session.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import ssl
from collections.abc import Callable, Iterable, Sequence
from typing import Final

from surprise.errors import AuthenticationError, ConnectionClosedError, ProtocolError
from surprise.session import FrameAuth, master_proof, new_nonce, proof_matches, robot_proof
from surprise.wire import (
    DEAD_AFTER_HEARTBEATS,
    HANDSHAKE_MAX_FRAME_SIZE,
    MAX_REASON_LENGTH,
    PROTOCOL_VERSION,
    REFUSED_BAD_SECRET,
    REFUSED_MISSING_SENSORS,
    REFUSED_PROTOCOL,
    REFUSED_VERSION_MISMATCH,
    Authenticate,
    Bye,
    Challenge,
    Error,
    Failed,
    Hello,
    Message,
    Ping,
    Pong,
    Refused,
    Result,
    Welcome,
    encode_payload,
    printable,
)
from transport.stream import MessageStream

__all__ = ["RobotServer", "Session"]

#: Bytes a session may have queued unsent before we call the peer stuck and drop it. Far above
#: anything the master sends in one go (an Evaluate is a few kB), far below hurting memory.
MAX_PENDING_OUTPUT: Final = 4 * 1024 * 1024
#: How long a closing connection may take to flush its last message (a Refused, a Bye) before
#: it is aborted; the peer is not worth more of our time.
CLOSE_TIMEOUT: Final = 2.0
#: The listen backlog: a thousand robots (the benchmark) may connect at the same instant; the
#: default of 100 would make some retry their SYN a second later.
LISTEN_BACKLOG: Final = 1024

Admit = Callable[[str], tuple[str, str] | None]


class Session:
    """One authenticated robot connection; ``hello`` is what the robot announced."""

    def __init__(self, hello: Hello, stream: MessageStream, peer: str, now: float) -> None:
        self.hello = hello
        self.robot_id = hello.robot_id
        self.stream = stream
        self.peer = peer
        #: Event-loop time of the last message received (any message counts as a sign of life).
        self.last_received = now
        #: ``stream.bytes_received`` when the keep-alive last looked.
        self.bytes_seen = stream.bytes_received
        self.closed = False
        self.close_reason: str | None = None

    def __repr__(self) -> str:
        return f"<Session {self.robot_id} {self.peer}{' closed' if self.closed else ''}>"


class RobotServer:
    """Accepts robots and keeps their sessions; callbacks tell the owner what happens.

    ``admit(robot_id)`` returns None or a ``(code, reason)`` refusal; it is asked after the
    secret was verified. ``on_join(session)`` and ``on_leave(session, reason)`` are called once
    per session; ``on_message(session, msg)`` gets every Result and Failed. Callbacks run in the
    event loop and must not block.
    """

    def __init__(
        self,
        *,
        host: str,
        port: int,
        secret: bytes,
        sensors: Sequence[str],
        run_id: str,
        heartbeat_interval: float,
        handshake_timeout: float,
        max_frame_size: int,
        ssl_context: ssl.SSLContext | None,
        admit: Admit,
        on_join: Callable[[Session], None],
        on_leave: Callable[[Session, str], None],
        on_message: Callable[[Session, Result | Failed], None],
        logger: logging.Logger,
    ) -> None:
        self.host = host
        self.requested_port = port
        self._secret = secret
        self._sensors = tuple(sensors)
        self.run_id = run_id
        self.heartbeat_interval = heartbeat_interval
        self.handshake_timeout = handshake_timeout
        self.max_frame_size = max_frame_size
        self._ssl = ssl_context
        self._admit = admit
        self._on_join = on_join
        self._on_leave = on_leave
        self._on_message = on_message
        self.log = logger
        #: The live session of each robot id.
        self.sessions: dict[str, Session] = {}
        self._server: asyncio.Server | None = None
        self._port: int | None = None
        self._handlers: set[asyncio.Task[None]] = set()
        self._keepalive: asyncio.Task[None] | None = None

    # -- lifecycle ---------------------------------------------------------------------------

    async def bind(self) -> None:
        """Bind the listening socket without accepting yet (errors such as a busy port surface
        here, before the run directory is touched)."""
        self._server = await asyncio.start_server(
            self._handle,
            self.host,
            self.requested_port,
            ssl=self._ssl,
            ssl_handshake_timeout=self.handshake_timeout if self._ssl else None,
            backlog=LISTEN_BACKLOG,
            start_serving=False,
        )
        self._port = self._server.sockets[0].getsockname()[1]

    async def start_serving(self) -> None:
        """Start accepting robots and the keep-alive."""
        assert self._server is not None, "bind() first"
        await self._server.start_serving()
        self._keepalive = asyncio.create_task(self._keep_alive(), name="keep-alive")

    @property
    def port(self) -> int:
        """The bound port (useful when the configured port is 0); kept after :meth:`close`."""
        assert self._port is not None, "bind() first"
        return self._port

    async def close(self, reason: str = "master shutting down") -> None:
        """Stop accepting, say Bye to every robot and close every connection."""
        if self._keepalive is not None:
            self._keepalive.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._keepalive
        if self._server is not None:
            self._server.close()
        bye = encode_payload(Bye(reason=reason))
        for session in list(self.sessions.values()):
            self._write(session, bye)
            self.drop(session, reason, graceful=True)
        # Let handlers flush their Bye and finish; cancel the ones that do not (handshakes).
        if self._handlers:
            _, pending = await asyncio.wait(set(self._handlers), timeout=CLOSE_TIMEOUT)
            for task in pending:
                task.cancel()
            if pending:
                await asyncio.wait(pending)
        if self._server is not None:
            await self._server.wait_closed()

    # -- sending -----------------------------------------------------------------------------

    def send(self, robot_ids: Iterable[str], payload: bytes) -> list[str]:
        """Write one encoded message (:func:`~surprise.wire.encode_payload`) to each robot's live
        session, tagged for that session; return the ids it did not reach.

        Never waits: a peer that lets output pile up past :data:`MAX_PENDING_OUTPUT` is dropped.
        """
        missed = []
        for robot_id in robot_ids:
            session = self.sessions.get(robot_id)
            if session is None or not self._write(session, payload):
                missed.append(robot_id)
        return missed

    def _write(self, session: Session, payload: bytes) -> bool:
        if session.closed:
            return False
        transport = session.stream.writer.transport
        if transport.is_closing():
            return False
        session.stream.write(payload)
        if transport.get_write_buffer_size() > MAX_PENDING_OUTPUT:
            self.drop(session, "the robot does not read what the master sends")
            return False
        return True

    def drop(self, session: Session, reason: str, *, graceful: bool = False) -> None:
        """Close a session now and report its departure (once). ``graceful`` flushes output."""
        if session.closed:
            return
        session.closed = True
        session.close_reason = reason
        current = self.sessions.get(session.robot_id) is session
        if current:
            del self.sessions[session.robot_id]
        writer = session.stream.writer
        if graceful:
            writer.close()
        else:
            # A dead or replaced link has nothing worth flushing; do not wait for it.
            writer.transport.abort()
        self.log.info("robot %s (%s) left: %s", session.robot_id, session.peer, reason)
        if current:
            self._on_leave(session, reason)

    # -- one connection ----------------------------------------------------------------------

    async def _handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._handlers.add(task)
        peer = _peer_name(writer)
        limit = min(HANDSHAKE_MAX_FRAME_SIZE, self.max_frame_size)
        stream = MessageStream(reader, writer, max_frame_size=limit)
        session: Session | None = None
        reason = "connection closed"
        try:
            session = await self._handshake(stream, peer)
            if session is not None:
                reason = await self._serve(session)
        except asyncio.CancelledError:
            reason = "master shutting down"
            raise
        except Exception:
            # A bug must cost one connection, never the master.
            self.log.exception("unexpected error on the connection from %s", peer)
            reason = "internal error"
        finally:
            if session is not None:
                self.drop(session, reason)
            await _close(writer)
            self._handlers.discard(task)

    async def _receive(self, stream: MessageStream) -> Message:
        # asyncio.timeout rather than wait_for, which in Python 3.11 may swallow a cancellation.
        async with asyncio.timeout(self.handshake_timeout):
            return await stream.receive()

    async def _handshake(self, stream: MessageStream, peer: str) -> Session | None:
        robot_id = "?"

        async def refuse(code: str, reason: str) -> None:
            reason = reason[:MAX_REASON_LENGTH]
            self.log.warning("refused robot %s (%s): %s: %s", robot_id, peer, code, reason)
            # Tagged once the robot has proved the secret (stream.auth is on), plain before.
            refused = Refused(code=code, reason=reason)
            with contextlib.suppress(Exception):
                async with asyncio.timeout(CLOSE_TIMEOUT):
                    await stream.send(refused)

        try:
            hello = await self._receive(stream)
            if not isinstance(hello, Hello):
                await refuse(REFUSED_PROTOCOL, f"expected hello, got {type(hello).__name__}")
                return None
            # Decoding checked it against ROBOT_ID_PATTERN: plain and short.
            robot_id = hello.robot_id
            if hello.protocol_version != PROTOCOL_VERSION:
                await refuse(
                    REFUSED_VERSION_MISMATCH,
                    f"the master speaks protocol version {PROTOCOL_VERSION}, "
                    f"the robot {hello.protocol_version}",
                )
                return None
            if hello.nonce is None:
                await refuse(REFUSED_PROTOCOL, "the hello carries no nonce")
                return None
            robot_nonce, master_nonce = hello.nonce, new_nonce()
            proof = master_proof(self._secret, robot_nonce, master_nonce, robot_id)
            await stream.send(Challenge(nonce=master_nonce, proof=proof))
            auth = await self._receive(stream)
            if not isinstance(auth, Authenticate):
                await refuse(REFUSED_PROTOCOL, f"expected auth, got {type(auth).__name__}")
                return None
            expected = robot_proof(self._secret, robot_nonce, master_nonce, robot_id)
            if not proof_matches(expected, auth.proof):
                await refuse(REFUSED_BAD_SECRET, "the robot's proof of the secret does not match")
                return None
            stream.authenticate(
                FrameAuth.for_master(self._secret, robot_nonce, master_nonce, robot_id)
            )
            refusal = self._admit(hello.robot_id)
            if refusal is not None:
                await refuse(*refusal)
                return None
            missing = [name for name in self._sensors if name not in hello.sensors]
            if missing:
                await refuse(
                    REFUSED_MISSING_SENSORS,
                    f"the experiment needs the sensors {', '.join(missing)}, which the robot lacks",
                )
                return None
        except TimeoutError:
            await refuse(
                REFUSED_PROTOCOL, f"a handshake step took longer than {self.handshake_timeout} s"
            )
            return None
        except ProtocolError as exc:
            # Garbage or an oversized frame: the stream is out of sync; say why and close.
            await refuse(REFUSED_PROTOCOL, str(exc))
            return None
        except (ConnectionClosedError, OSError) as exc:
            self.log.info("connection from %s closed during the handshake: %s", peer, exc)
            return None

        stream.set_max_frame_size(self.max_frame_size)
        loop = asyncio.get_running_loop()
        session = Session(hello, stream, peer, loop.time())
        # Register and welcome without awaiting in between: the admission check above stays
        # true, and the Welcome is queued before any Evaluate the owner may send on_join.
        stale = self.sessions.get(hello.robot_id)
        if stale is not None:
            self.drop(stale, f"replaced by a new connection from {peer}")
        self.sessions[hello.robot_id] = session
        welcome = Welcome(run_id=self.run_id, heartbeat_interval=self.heartbeat_interval)
        self._write(session, encode_payload(welcome))
        self.log.info(
            "robot %s joined from %s (software %s)",
            hello.robot_id,
            peer,
            printable(hello.software_version),
        )
        self._on_join(session)
        return session

    async def _serve(self, session: Session) -> str:
        """Read the session's messages until it ends; return why it ended."""
        stream = session.stream
        loop = asyncio.get_running_loop()
        while True:
            try:
                msg = await stream.receive()
            except ConnectionClosedError as exc:
                return f"connection closed by the robot ({exc})"
            except AuthenticationError as exc:
                # Not the robot's own doing, unless it is broken: someone on the path forged,
                # replayed or reflected a frame. Whatever else that connection carries is suspect.
                self.log.error("robot %s: %s; the session is closed", session.robot_id, exc)
                return self._close_with_error(session, "authentication", str(exc))
            except ProtocolError as exc:
                self.log.error("malformed input from robot %s: %s", session.robot_id, exc)
                return self._close_with_error(session, "malformed", f"malformed input: {exc}")
            except OSError as exc:
                return f"connection error: {exc}"
            if session.closed:
                return session.close_reason or "closed"
            session.last_received = loop.time()
            if isinstance(msg, Result | Failed):
                self._on_message(session, msg)
            elif isinstance(msg, Ping):
                self._write(session, encode_payload(Pong(seq=msg.seq)))
            elif isinstance(msg, Pong):
                pass
            elif isinstance(msg, Bye):
                return f"the robot said bye: {printable(msg.reason)}"
            elif isinstance(msg, Error):
                code, text = printable(msg.code), printable(msg.message)
                self.log.error("robot %s reported an error: %s: %s", session.robot_id, code, text)
                return f"the robot reported an error: {code}"
            else:
                text = f"unexpected {type(msg).__name__} after the handshake"
                return self._close_with_error(session, "protocol", text)

    def _close_with_error(self, session: Session, code: str, text: str) -> str:
        # Graceful: an abort (RST) could destroy the Error before the robot has read it.
        self._write(session, encode_payload(Error(code=code, message=text)))
        self.drop(session, text, graceful=True)
        return text

    async def _keep_alive(self) -> None:
        """Ping every session each interval; drop those silent for too long."""
        loop = asyncio.get_running_loop()
        limit = DEAD_AFTER_HEARTBEATS * self.heartbeat_interval
        seq = 0
        while True:
            await asyncio.sleep(self.heartbeat_interval)
            seq += 1
            ping = encode_payload(Ping(seq=seq))
            now = loop.time()
            for session in list(self.sessions.values()):
                received = session.stream.bytes_received
                if received != session.bytes_seen:
                    # Part of a long message (a trace on a slow link) arrived: the link lives.
                    session.bytes_seen = received
                    session.last_received = max(session.last_received, now)
                silent = now - session.last_received
                if silent > limit:
                    self.drop(session, f"link dead: no message for {silent:.1f} s")
                else:
                    self._write(session, ping)


def _peer_name(writer: asyncio.StreamWriter) -> str:
    peer = writer.get_extra_info("peername")
    if isinstance(peer, tuple) and len(peer) >= 2:
        return f"{peer[0]}:{peer[1]}"
    return str(peer)


async def _close(writer: asyncio.StreamWriter) -> None:
    writer.close()
    try:
        async with asyncio.timeout(CLOSE_TIMEOUT):
            await writer.wait_closed()
    except (TimeoutError, OSError, ssl.SSLError):
        writer.transport.abort()
