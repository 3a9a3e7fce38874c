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

Connections that have not authenticated cost the master as little as possible and can never
starve it: at most ``max_pending_connections`` handshakes run at once, and when one more arrives
one connection is closed at once, from the source address that holds the most
(:mod:`master_service.handshakes`): a flood from one address keeps no robot of another address
out, and a silent connection beyond the limit is closed before any handshake work, so its file
descriptor is free again; the whole handshake, TLS included, has one deadline; its frames are small
and every field in them is bounded; and what goes wrong with such connections is logged through a
:class:`ThrottledLog`.

Why one file of over 600 lines: a connection's life, from the socket's arrival through the
handshake to the session's close, is one state machine whose limits must be read together; the
policy of whom to evict is apart, in :mod:`master_service.handshakes`.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import socket
import ssl
from collections.abc import Callable, Iterable, Sequence
from typing import Any, Final

from master_service.handshakes import HandshakeTable, source_of
from master_service.throttled_log import ThrottledLog
from minimize_surprise.errors import AuthenticationError, ConnectionClosedError, ProtocolError
from minimize_surprise.session import FrameAuth, master_proof, new_nonce, proof_matches, robot_proof
from minimize_surprise.wire import (
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
    CheckReport,
    Error,
    EscapeReply,
    Failed,
    Hello,
    Message,
    Ping,
    Pong,
    Refused,
    Result,
    Stopped,
    Welcome,
    encode_payload,
    printable,
)
from transport.stream import MessageStream

__all__ = ["Answer", "RobotServer", "Session"]

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
#: What a robot sends the owner of a session: an evaluation's outcome, or an answer it asked for.
Answer = Result | Failed | CheckReport | EscapeReply | Stopped


class _Refusal(Exception):
    """A handshake ends with a Refused(code, reason); internal to the server."""

    def __init__(self, code: str, reason: str) -> None:
        self.code = code
        self.reason = reason[:MAX_REASON_LENGTH]
        super().__init__(f"{code}: {reason}")


class _Slot:
    """One unauthenticated connection in the server's table of handshakes, from the moment it is
    accepted until its handshake ends or its connection is lost, whichever comes first."""

    __slots__ = ("evicted", "server", "source", "spoke", "transport")

    def __init__(self, server: RobotServer, transport: asyncio.BaseTransport) -> None:
        self.server = server
        self.transport = transport
        self.source = source_of(transport.get_extra_info("peername"))
        #: something was received from the peer
        self.spoke = False
        #: closed by the server to make room for a newer connection
        self.evicted = False

    @property
    def peer(self) -> str:
        return _peer_name(self.transport)

    def received(self) -> None:
        if not self.spoke:
            self.spoke = True
            self.server.handshakes.spoke(self)

    def release(self) -> None:
        self.server.handshakes.remove(self)

    def evict(self) -> None:
        self.evicted = True
        self.transport.abort()  # type: ignore[attr-defined]


class _Arrival(asyncio.Protocol):
    """A connection just accepted. Only once its address is known can the server tell whether it
    gets a place among the handshakes; only then is it given a stream (:class:`_PendingProtocol`),
    so that a connection closed at once costs next to nothing."""

    def __init__(self, server: RobotServer) -> None:
        self._server = server

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self._server.arrived(transport)


class _PendingProtocol(asyncio.StreamReaderProtocol):
    """A stream protocol whose connection holds a place among the handshakes until it ends."""

    def __init__(self, reader: asyncio.StreamReader, handler: Any, slot: _Slot) -> None:
        super().__init__(reader, handler)
        self._slot = slot

    def data_received(self, data: bytes) -> None:
        self._slot.received()
        super().data_received(data)

    def connection_lost(self, exc: Exception | None) -> None:
        self._slot.release()
        super().connection_lost(exc)


class _Refuse(asyncio.Protocol):
    """A connection accepted while the server is closing: closed the moment it is accepted."""

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        transport.abort()  # type: ignore[attr-defined]


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

    ``handshake_timeout`` bounds a whole handshake (TLS included); ``max_pending_connections``
    bounds how many run at once (:mod:`master_service.handshakes` says which one is closed when
    one more arrives). ``admit(robot_id)`` returns None or a ``(code, reason)``
    refusal; it is asked after the secret was verified. ``on_join(session)`` and
    ``on_leave(session, reason)`` are called once per session; ``on_message(session, msg)`` gets
    every Result, Failed, CheckReport, EscapeReply and Stopped (:data:`Answer`),
    ``on_pong(session, pong)`` (optional) every Pong.
    Callbacks run in the event loop and must not block.
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
        max_pending_connections: int,
        max_frame_size: int,
        ssl_context: ssl.SSLContext | None,
        admit: Admit,
        on_join: Callable[[Session], None],
        on_leave: Callable[[Session, str], None],
        on_message: Callable[[Session, Answer], None],
        logger: logging.Logger,
        on_pong: Callable[[Session, Pong], None] | None = None,
    ) -> None:
        self.host = host
        self.requested_port = port
        self._secret = secret
        self._sensors = tuple(sensors)
        self.run_id = run_id
        self.heartbeat_interval = heartbeat_interval
        self.handshake_timeout = handshake_timeout
        self.max_pending_connections = max_pending_connections
        self.max_frame_size = max_frame_size
        self._ssl = ssl_context
        self._admit = admit
        self._on_join = on_join
        self._on_leave = on_leave
        self._on_message = on_message
        self._on_pong = on_pong
        self.log = logger
        #: What happens to connections that have not authenticated: anyone can cause it.
        self.unauthenticated_log = ThrottledLog(
            logger, "refused or failed connections of unauthenticated peers"
        )
        #: The connections whose handshake is running now, by source address.
        self.handshakes: HandshakeTable[_Slot] = HandshakeTable(max_pending_connections)
        #: New connections closed at once: max_pending_connections handshakes were running, most
        #: of them from the new connection's address.
        self.refused_connections = 0
        #: Connections closed in their handshake to make room for a newer one.
        self.evicted_connections = 0
        #: The live session of each robot id.
        self.sessions: dict[str, Session] = {}
        self._server: asyncio.Server | None = None
        self._port: int | None = None
        self._handlers: set[asyncio.Task[None]] = set()
        # The handlers still in their handshake: nothing of theirs is worth waiting for.
        self._handshaking: set[asyncio.Task[None]] = set()
        self._closing = False
        self._keepalive: asyncio.Task[None] | None = None

    # -- lifecycle ---------------------------------------------------------------------------

    async def bind(self) -> None:
        """Bind the listening socket without accepting yet (errors such as a busy port surface
        here, before the run directory is touched)."""
        # Plain TCP: TLS starts inside the handshake, under its deadline and its slot, so that
        # connections beyond the limit are refused before any TLS work too.
        loop = asyncio.get_running_loop()
        self._server = await loop.create_server(
            self._make_protocol,
            self.host,
            self.requested_port,
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
    def pending_connections(self) -> int:
        """Connections whose handshake is running now."""
        return len(self.handshakes)

    @property
    def port(self) -> int:
        """The bound port (useful when the configured port is 0); kept after :meth:`close`."""
        assert self._port is not None, "bind() first"
        return self._port

    async def close(self, reason: str = "master shutting down") -> None:
        """Stop accepting, say Bye to every robot and close every connection."""
        self._closing = True
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
        for task in self._handshaking:
            task.cancel()
        # Let the sessions' handlers flush their Bye and finish; cancel the ones that do not.
        if self._handlers:
            _, pending = await asyncio.wait(set(self._handlers), timeout=CLOSE_TIMEOUT)
            for task in pending:
                task.cancel()
            if pending:
                await asyncio.wait(pending)
        if self._server is not None:
            await self._server.wait_closed()
        self.unauthenticated_log.flush()

    # -- sending -----------------------------------------------------------------------------

    def send(self, robot_ids: Iterable[str], payload: bytes) -> list[str]:
        """Write one encoded message (:func:`~minimize_surprise.wire.encode_payload`) to each
        robot's live session, tagged for that session; return the ids it did not reach.

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

    def _make_protocol(self) -> asyncio.BaseProtocol:
        """A protocol for a connection just accepted: the place among the handshakes is decided
        when its address is known (:meth:`arrived`); an immediate close if the server is
        closing."""
        return _Refuse() if self._closing else _Arrival(self)

    def arrived(self, transport: asyncio.BaseTransport) -> None:
        """A connection was accepted: give it a place among the handshakes and a handshake, or
        close it at once (see :mod:`master_service.handshakes`)."""
        slot = _Slot(self, transport)
        if len(self.handshakes) >= self.max_pending_connections:
            # Only a full table asks whether the newcomer has spoken: one syscall less otherwise.
            slot.spoke = _input_waiting(transport)
        victim = self.handshakes.add(slot, slot.source, spoke=slot.spoke)
        if victim is slot:
            transport.abort()  # type: ignore[attr-defined]
            self._refused(slot)
            return
        if victim is not None:
            self._evict(victim, slot)
        protocol = _PendingProtocol(
            asyncio.StreamReader(), functools.partial(self._handle, slot), slot
        )
        transport.set_protocol(protocol)
        protocol.connection_made(transport)

    def _refused(self, slot: _Slot) -> None:
        self.refused_connections += 1
        self.unauthenticated_log.log(
            logging.WARNING,
            "refused a connection from %s at once: %d handshakes are running "
            "(max_pending_connections), %d of them from its address",
            slot.peer,
            self.pending_connections,
            self.handshakes.count(slot.source),
        )

    def _evict(self, victim: _Slot, newcomer: _Slot) -> None:
        self.evicted_connections += 1
        self.unauthenticated_log.log(
            logging.WARNING,
            "closed the handshake of %s, one of %d from its address, to make room for %s: "
            "%d handshakes are running (max_pending_connections)",
            victim.peer,
            self.handshakes.count(victim.source) + 1,
            newcomer.peer,
            self.pending_connections,
        )
        victim.evict()

    async def _handle(
        self, slot: _Slot, reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._handlers.add(task)
        self._handshaking.add(task)
        peer = slot.peer
        session: Session | None = None
        reason = "connection closed"
        cancelled = False
        try:
            session = await self._handshake(reader, writer, slot)
            self._handshaking.discard(task)
            slot.release()
            if session is not None:
                reason = await self._serve(session)
        except asyncio.CancelledError:
            # Only close() cancels a connection's task. It ends here, quietly: a connection task
            # ending cancelled would make asyncio print a traceback for every one of them.
            cancelled = True
            reason = "master shutting down"
        except Exception:
            # A bug must cost one connection, never the master.
            self.log.exception("unexpected error on the connection from %s", peer)
            reason = "internal error"
        finally:
            slot.release()
            if session is not None:
                self.drop(session, reason)
            if cancelled:
                writer.transport.abort()
            else:
                await _close(writer)
            self._handlers.discard(task)
            self._handshaking.discard(task)

    async def _handshake(
        self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter, slot: _Slot
    ) -> Session | None:
        """Run the handshake under one deadline; returns the new session, or None when the
        connection was refused or lost (and logged)."""
        peer = slot.peer
        stream: MessageStream | None = None
        robot_id = "?"
        try:
            # One deadline for everything, TLS included: a peer dribbling a byte now and then
            # holds its slot no longer than that.
            async with asyncio.timeout(self.handshake_timeout):
                if self._ssl is not None:
                    await writer.start_tls(self._ssl)
                limit = min(HANDSHAKE_MAX_FRAME_SIZE, self.max_frame_size)
                stream = MessageStream(reader, writer, max_frame_size=limit)
                hello = await stream.receive()
                if isinstance(hello, Hello):
                    # Decoding checked it against ROBOT_ID_PATTERN: plain and short.
                    robot_id = hello.robot_id
                hello = await self._negotiate(stream, hello)
        except _Refusal as refusal:
            await self._refuse(stream, robot_id, peer, refusal)
            return None
        except TimeoutError:
            late = _Refusal(
                REFUSED_PROTOCOL, f"the handshake took longer than {self.handshake_timeout:g} s"
            )
            await self._refuse(stream, robot_id, peer, late)
            return None
        except ProtocolError as exc:
            # Garbage or an oversized frame: the stream is out of sync; say why and close.
            await self._refuse(stream, robot_id, peer, _Refusal(REFUSED_PROTOCOL, str(exc)))
            return None
        except (ConnectionClosedError, OSError) as exc:  # ssl.SSLError is an OSError
            if not slot.evicted:  # an eviction was logged as such
                self.unauthenticated_log.log(
                    logging.INFO, "connection from %s closed during the handshake: %s", peer, exc
                )
            return None
        return self._admit_session(stream, hello, peer)

    async def _negotiate(self, stream: MessageStream, hello: Message) -> Hello:
        """The handshake after the first message: both proofs, then admission. Returns the
        robot's Hello with the session's tagging turned on, or raises :class:`_Refusal`."""
        if not isinstance(hello, Hello):
            raise _Refusal(REFUSED_PROTOCOL, f"expected hello, got {type(hello).__name__}")
        robot_id = hello.robot_id
        if hello.protocol_version != PROTOCOL_VERSION:
            raise _Refusal(
                REFUSED_VERSION_MISMATCH,
                f"the master speaks protocol version {PROTOCOL_VERSION}, "
                f"the robot {hello.protocol_version}",
            )
        if hello.nonce is None:
            raise _Refusal(REFUSED_PROTOCOL, "the hello carries no nonce")
        robot_nonce, master_nonce = hello.nonce, new_nonce()
        proof = master_proof(self._secret, robot_nonce, master_nonce, robot_id)
        await stream.send(Challenge(nonce=master_nonce, proof=proof))
        auth = await stream.receive()
        if not isinstance(auth, Authenticate):
            raise _Refusal(REFUSED_PROTOCOL, f"expected auth, got {type(auth).__name__}")
        expected = robot_proof(self._secret, robot_nonce, master_nonce, robot_id)
        if not proof_matches(expected, auth.proof):
            raise _Refusal(REFUSED_BAD_SECRET, "the robot's proof of the secret does not match")
        # From here on the robot is authenticated: every frame is tagged, a refusal too.
        stream.authenticate(FrameAuth.for_master(self._secret, robot_nonce, master_nonce, robot_id))
        refusal = self._admit(robot_id)
        if refusal is not None:
            raise _Refusal(*refusal)
        missing = [name for name in self._sensors if name not in hello.sensors]
        if missing:
            raise _Refusal(
                REFUSED_MISSING_SENSORS,
                f"the experiment needs the sensors {', '.join(missing)}, which the robot lacks",
            )
        return hello

    async def _refuse(
        self, stream: MessageStream | None, robot_id: str, peer: str, refusal: _Refusal
    ) -> None:
        """Log a refusal and send it (best effort, bounded); an authenticated robot's refusal is
        logged as such, anyone else's through the throttled log."""
        line = ("refused robot %s (%s): %s: %s", robot_id, peer, refusal.code, refusal.reason)
        if stream is not None and stream.auth is not None:
            self.log.warning(*line)
        else:
            self.unauthenticated_log.log(logging.WARNING, *line)
        if stream is None:
            return  # TLS never completed: there is nobody to tell
        with contextlib.suppress(Exception):
            async with asyncio.timeout(CLOSE_TIMEOUT):
                await stream.send(Refused(code=refusal.code, reason=refusal.reason))

    def _admit_session(self, stream: MessageStream, hello: Hello, peer: str) -> Session:
        stream.set_max_frame_size(self.max_frame_size)
        loop = asyncio.get_running_loop()
        session = Session(hello, stream, peer, loop.time())
        # Nothing was awaited since the admission check in _negotiate, and nothing is here: it
        # still holds, and the Welcome is queued before any Evaluate the owner may send on_join.
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
            if isinstance(msg, Result | Failed | CheckReport | EscapeReply | Stopped):
                self._on_message(session, msg)
            elif isinstance(msg, Ping):
                self._write(session, encode_payload(Pong(seq=msg.seq)))
            elif isinstance(msg, Pong):
                if self._on_pong is not None:
                    self._on_pong(session, msg)
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


def _input_waiting(transport: asyncio.BaseTransport) -> bool:
    """Whether bytes from the peer wait on a connection just accepted. A robot sends its Hello
    (or its TLS ClientHello) as soon as it is connected: under load, before the master accepted
    the connection, and that is when the master must tell it from a silent one."""
    trsock = transport.get_extra_info("socket")
    if trsock is None:
        return False
    # A view of the same descriptor (detached again, never closed): asyncio's socket wrapper
    # offers no recv, and the descriptor is non-blocking, so a peek never waits.
    sock = socket.socket(fileno=trsock.fileno())
    try:
        return bool(sock.recv(1, socket.MSG_PEEK))
    except OSError:  # nothing yet (BlockingIOError), or already reset
        return False
    finally:
        sock.detach()


def _peer_name(transport: asyncio.BaseTransport) -> str:
    peer = transport.get_extra_info("peername")
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
