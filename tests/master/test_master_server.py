"""The robots' server: handshake, refusals, malformed input, replacement, keep-alive, TLS.

After every refusal or broken connection a good robot must still be welcomed.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import ssl
import struct
import subprocess

import msgspec
import pytest
from master_helpers import SECRET, master_config

from master_service import Master
from minimize_surprise.sensors import ALL_SENSORS, IR_SENSORS
from minimize_surprise.session import FrameAuth, master_proof, new_nonce, proof_matches, robot_proof
from minimize_surprise.wire import (
    MAX_FRAME_SIZE,
    PROTOCOL_VERSION,
    REFUSED_BAD_SECRET,
    REFUSED_MISSING_SENSORS,
    REFUSED_PROTOCOL,
    REFUSED_UNKNOWN_ROBOT,
    REFUSED_VERSION_MISMATCH,
    Authenticate,
    Bye,
    Hello,
    Ping,
    Pong,
    Refused,
    Welcome,
)
from needs import require_binary
from standins.scripted_robots import RobotRefusedError, ScriptedRobot
from transport.framing import FrameDecoder, encode, frame
from transport.stream import MessageStream
from transport.tls import ServerTlsConfig


async def still_serving(master: Master, robot_id: str = "good") -> None:
    """A well-behaved robot is welcomed, then leaves."""
    robot = ScriptedRobot(robot_id, SECRET, master.port)
    welcome = await robot.connect()
    assert welcome.run_id == master.run_id
    await robot.close()


async def read_all(reader: asyncio.StreamReader, timeout: float = 3.0) -> list:
    """Every message the master sends until it closes the connection."""
    decoder = FrameDecoder()
    messages = []
    async with asyncio.timeout(timeout):
        while data := await reader.read(65536):
            messages += decoder.feed(data)
    return messages


def hello_payload(**changes: object) -> bytes:
    fields = {
        "type": "hello",
        "robot_id": "r0",
        "software_version": "x",
        "protocol_version": PROTOCOL_VERSION,
        "sensors": list(ALL_SENSORS),
        "nonce": new_nonce(),
    }
    fields.update(changes)
    return msgspec.msgpack.encode(fields)


async def test_a_robot_is_welcomed(tmp_path):
    async with Master(master_config(), tmp_path / "run", secret=SECRET) as master:
        robot = ScriptedRobot("r0", SECRET, master.port)
        welcome = await robot.connect()
        assert welcome.run_id == "run" and welcome.heartbeat_interval == 0.25
        assert master.connected_robots == ["r0"]
        await robot.close()
    log = (tmp_path / "run" / "master.log").read_text()
    assert "robot r0 joined" in log and "the robot said bye" in log


@pytest.mark.parametrize(
    "kwargs, config, code, words",
    [
        # A robot that answers although the master's proof did not verify on it (a real one
        # would not): the master's own check refuses it.
        ({"secret": b"wrong", "verify_master": False}, {}, REFUSED_BAD_SECRET, "does not match"),
        ({"protocol_version": PROTOCOL_VERSION + 1}, {}, REFUSED_VERSION_MISMATCH, "version"),
        ({}, {"allowed_robots": ["a", "b", "c"]}, REFUSED_UNKNOWN_ROBOT, "not among the allowed"),
        ({"sensors": IR_SENSORS}, {}, REFUSED_MISSING_SENSORS, "ground.0, ground.1"),
        ({"robot_id": "no spaces"}, {}, REFUSED_PROTOCOL, "robot_id"),
    ],
)
async def test_refusals_carry_a_code_and_reason(tmp_path, kwargs, config, code, words):
    async with Master(master_config(**config), tmp_path / "run", secret=SECRET) as master:
        args = {"robot_id": "r0", "secret": SECRET, **kwargs}
        robot = ScriptedRobot(args.pop("robot_id"), args.pop("secret"), master.port, **args)
        with pytest.raises(RobotRefusedError) as info:
            await robot.connect()
        assert info.value.code == code and words in info.value.reason
        assert master.connected_robots == []
        await still_serving(master, "a" if config else "good")
    assert "refused robot" in (tmp_path / "run" / "master.log").read_text()


async def test_version_mismatch_is_refused_before_the_challenge(tmp_path):
    async with Master(master_config(), tmp_path / "run", secret=SECRET) as master:
        reader, writer = await asyncio.open_connection("127.0.0.1", master.port)
        hello = Hello(robot_id="r0", software_version="x", protocol_version=99, sensors=())
        writer.write(encode(hello))
        messages = await read_all(reader)
        writer.close()
        assert len(messages) == 1 and isinstance(messages[0], Refused)
        assert messages[0].code == REFUSED_VERSION_MISMATCH


async def test_a_complete_swarm_refuses_a_further_robot(tmp_path):
    async with Master(master_config(), tmp_path / "run", secret=SECRET) as master:
        robots = [ScriptedRobot(f"r{i}", SECRET, master.port) for i in range(3)]
        for robot in robots:
            await robot.connect()
        with pytest.raises(RobotRefusedError, match="complete") as info:
            await ScriptedRobot("r9", SECRET, master.port).connect()
        assert info.value.code == REFUSED_UNKNOWN_ROBOT
        # A robot of the swarm may always come back (it replaces its stale session).
        await ScriptedRobot("r1", SECRET, master.port).connect()
        await robots[1].closed.wait()
        assert master.connected_robots == ["r0", "r1", "r2"]


@pytest.mark.parametrize(
    "data, words",
    [
        pytest.param(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n", "exceeds the limit", id="http"),
        pytest.param(b"\x00\x00\x00\x05\xc1\xc1\xc1\xc1\xc1", "malformed", id="garbage"),
        pytest.param(struct.pack(">I", MAX_FRAME_SIZE + 1), "exceeds the limit", id="oversized"),
        # Before authentication a frame cannot be large: an unauthenticated peer must not make
        # the master buffer anything sizeable per connection until the handshake times out.
        pytest.param(struct.pack(">I", 1024 * 1024), "exceeds the limit", id="large-before-auth"),
        pytest.param(struct.pack(">I", 8 * 1024), "exceeds the limit", id="8k-before-auth"),
        # Within the small frame, every field is bounded too.
        pytest.param(
            frame(hello_payload(sensors=[""] * 17)), "length <= 16", id="too-many-sensors"
        ),
        pytest.param(
            frame(hello_payload(software_version="v" * 65)), "software_version", id="long-version"
        ),
        pytest.param(b"\x00\x00\x00\x00", "empty frame", id="empty"),
        pytest.param(encode(Ping(seq=1)), "expected hello", id="ping-first"),
    ],
)
async def test_malformed_handshakes_are_refused_and_closed(tmp_path, data, words):
    async with Master(master_config(), tmp_path / "run", secret=SECRET) as master:
        reader, writer = await asyncio.open_connection("127.0.0.1", master.port)
        writer.write(data)
        messages = await read_all(reader)
        writer.close()
        assert len(messages) == 1 and messages[0].code == REFUSED_PROTOCOL
        assert words in messages[0].reason
        await still_serving(master)


async def test_a_silent_peer_is_closed_after_the_handshake_timeout(tmp_path):
    config = master_config(handshake_timeout=0.2)
    async with Master(config, tmp_path / "run", secret=SECRET) as master:
        reader, writer = await asyncio.open_connection("127.0.0.1", master.port)
        messages = await read_all(reader, timeout=2.0)
        writer.close()
        assert messages[0].code == REFUSED_PROTOCOL and "handshake" in messages[0].reason
        await still_serving(master)


async def test_a_peer_that_vanishes_mid_frame_leaves_the_master_serving(tmp_path):
    async with Master(master_config(), tmp_path / "run", secret=SECRET) as master:
        _, writer = await asyncio.open_connection("127.0.0.1", master.port)
        hello = Hello(robot_id="r0", software_version="x", protocol_version=1, sensors=())
        writer.write(encode(hello)[:7])
        await writer.drain()
        writer.transport.abort()
        await still_serving(master)


async def test_a_second_connection_replaces_the_stale_one(tmp_path):
    async with Master(master_config(), tmp_path / "run", secret=SECRET) as master:
        stale = ScriptedRobot("r0", SECRET, master.port)
        await stale.connect()
        fresh = ScriptedRobot("r0", SECRET, master.port)
        await fresh.connect()
        await asyncio.wait_for(stale.closed.wait(), 2)
        assert master.connected_robots == ["r0"]
        assert master.server.sessions["r0"].robot_id == "r0"
        assert not fresh.closed.is_set()
        await fresh.close()
    assert "replaced by a new connection" in (tmp_path / "run" / "master.log").read_text()


async def test_keep_alive_drops_a_dead_link_and_keeps_a_live_one(tmp_path):
    # heartbeat 0.1 s: a silent robot is dead after 0.3 s, noticed within 0.4 s.
    async with Master(master_config(heartbeat_interval=0.1), tmp_path / "run", secret=SECRET) as m:
        live = ScriptedRobot("r0", SECRET, m.port)
        dead = ScriptedRobot("r1", SECRET, m.port, answer_pings=False)
        await live.connect()
        await dead.connect()
        await asyncio.wait_for(dead.closed.wait(), 3)
        assert m.connected_robots == ["r0"]
        await live.close()
    assert "link dead: no message for" in (tmp_path / "run" / "master.log").read_text()


async def test_a_long_message_still_arriving_keeps_the_link_alive(tmp_path):
    # A post-evaluation trace over a slow, shared Wi-Fi can take longer than three heartbeats to
    # arrive; its bytes are signs of life, and the robot must not be dropped in the middle of it.
    async with Master(master_config(heartbeat_interval=0.1), tmp_path / "run", secret=SECRET) as m:
        robot = ScriptedRobot("r0", SECRET, m.port, answer_pings=False)
        await robot.connect()
        frame = robot.sealed_frame(Bye(reason="x" * 4000))
        for i in range(0, len(frame) - 50, 50):  # 80 pieces over 1.6 s; dead after 0.3 s
            robot.send_raw(frame[i : i + 50])
            await asyncio.sleep(0.02)
            assert not robot.closed.is_set(), f"dropped after {i + 50} bytes"
        robot.send_raw(frame[i + 50 :])
        await asyncio.wait_for(robot.closed.wait(), 3)
    assert "the robot said bye: xxx" in (tmp_path / "run" / "master.log").read_text()


async def test_the_master_answers_a_robots_ping(tmp_path):
    async with Master(master_config(), tmp_path / "run", secret=SECRET) as master:
        reader, writer = await asyncio.open_connection("127.0.0.1", master.port)
        stream = MessageStream(reader, writer)
        robot_nonce = new_nonce()
        hello = Hello(
            robot_id="r0",
            software_version="x",
            protocol_version=PROTOCOL_VERSION,
            sensors=ALL_SENSORS,
            nonce=robot_nonce,
        )
        await stream.send(hello)
        challenge = await stream.receive()
        nonces = (robot_nonce, challenge.nonce, "r0")
        assert proof_matches(master_proof(SECRET, *nonces), challenge.proof)
        await stream.send(Authenticate(proof=robot_proof(SECRET, *nonces)))
        stream.authenticate(FrameAuth.for_robot(SECRET, *nonces))
        assert isinstance(await stream.receive(), Welcome)
        await stream.send(Ping(seq=41))
        async with asyncio.timeout(2):
            # The master's own pings may come first.
            while not isinstance(msg := await stream.receive(), Pong):
                assert isinstance(msg, Ping)
        assert msg.seq == 41
        await stream.close()


def _make_certificate(directory) -> tuple[str, str]:
    require_binary("openssl")
    cert, key = directory / "cert.pem", directory / "key.pem"
    subprocess.run(
        [
            "openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "1",
            "-subj", "/CN=localhost", "-addext", "subjectAltName=IP:127.0.0.1",
            "-keyout", str(key), "-out", str(cert),
        ],
        check=True,
        capture_output=True,
    )  # fmt: skip
    return str(cert), str(key)


async def test_tls(tmp_path):
    cert, key = _make_certificate(tmp_path)
    config = master_config(tls=ServerTlsConfig(cert_file=cert, key_file=key))
    async with Master(config, tmp_path / "run", secret=SECRET) as master:
        client = ssl.create_default_context(cafile=cert)
        robot = ScriptedRobot("r0", SECRET, master.port, ssl_context=client)
        assert (await robot.connect()).run_id == "run"
        # A plain-TCP robot gets nowhere, and the master carries on.
        plain = ScriptedRobot("r1", SECRET, master.port)
        with pytest.raises((ConnectionError, OSError, asyncio.IncompleteReadError)):
            await asyncio.wait_for(plain.connect(), 3)
        await robot.close()
        again = ScriptedRobot("r2", SECRET, master.port, ssl_context=client)
        await again.connect()
        await again.close()


async def test_sessions_of_a_closing_master_get_a_bye(tmp_path):
    master = Master(master_config(), tmp_path / "run", secret=SECRET)
    await master.start()
    robot = ScriptedRobot("r0", SECRET, master.port)
    await robot.connect()
    await master.close()
    await asyncio.wait_for(robot.closed.wait(), 2)


# ---------------------------------------------------------------------------------------------
# Peers without the secret cannot starve the master


async def idle_connections(port: int, count: int) -> list[asyncio.StreamWriter]:
    writers = []
    for _ in range(count):
        _, writer = await asyncio.open_connection("127.0.0.1", port)
        writers.append(writer)
    return writers


async def test_connections_beyond_the_pending_limit_are_closed_at_once(tmp_path):
    config = master_config(max_pending_connections=3, handshake_timeout=5.0)
    async with Master(config, tmp_path / "run", secret=SECRET) as master:
        idle = await idle_connections(master.port, 3)
        reader, writer = await asyncio.open_connection("127.0.0.1", master.port)
        # Closed without a word and long before the handshake timeout: no handshake work at all.
        async with asyncio.timeout(1.0):
            assert await reader.read() == b""
        writer.close()
        assert master.server.refused_connections == 1
        assert master.server.pending_connections == 3
        for w in idle:
            w.close()
        # Their slots come back as they close; then robots are served again.
        async with asyncio.timeout(2.0):
            while master.server.pending_connections:
                await asyncio.sleep(0.01)
        await still_serving(master)
        assert master.server.pending_connections == 0
    log = (tmp_path / "run" / "master.log").read_text()
    assert "refused a connection from 127.0.0.1" in log and "3 handshakes are running" in log


async def test_a_flood_of_refused_connections_logs_a_bounded_number_of_lines(tmp_path):
    config = master_config(max_pending_connections=1, handshake_timeout=5.0)
    async with Master(config, tmp_path / "run", secret=SECRET) as master:
        (holder,) = await idle_connections(master.port, 1)
        for _ in range(40):
            reader, writer = await asyncio.open_connection("127.0.0.1", master.port)
            assert await reader.read() == b""
            writer.close()
        holder.close()
        assert master.server.refused_connections == 40
    lines = (tmp_path / "run" / "master.log").read_text().splitlines()
    refused = [line for line in lines if "refused a connection" in line]
    assert len(refused) == 10  # ThrottledLog's lines per minute
    # The other 30 (and the holder's end) are counted, in one line.
    (count,) = [line for line in lines if "more refused or failed connections" in line]
    assert int(count.split(" more ")[0].rsplit(" ", 1)[-1]) >= 30


Connection = tuple[asyncio.StreamReader, asyncio.StreamWriter]


async def silent_connections(port: int, count: int, source: str = "127.0.0.1") -> list[Connection]:
    """Connections from ``source`` that say nothing."""
    return [
        await asyncio.open_connection("127.0.0.1", port, local_addr=(source, 0))
        for _ in range(count)
    ]


async def hello_connections(port: int, count: int) -> list[Connection]:
    """Connections that said Hello and wait in the handshake (they have their Challenge)."""
    connections = []
    for _ in range(count):
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        writer.write(frame(hello_payload()))
        decoder = FrameDecoder()
        while not decoder.feed(await reader.read(65536)):
            pass
        connections.append((reader, writer))
    return connections


async def speaking_at_once(port: int) -> Connection:
    """A connection whose Hello is there before the master accepts it, as a robot's is under
    load: it is connected and written without giving the event loop (the master's) a turn."""
    sock = socket.create_connection(("127.0.0.1", port))
    sock.sendall(frame(hello_payload()))
    sock.setblocking(False)
    return await asyncio.open_connection(sock=sock)


async def closed_at_once(connection: Connection) -> bool:
    """Whether the master closes the connection without a word, long before the handshake
    timeout (5 s in these tests)."""
    reader, _ = connection
    try:
        async with asyncio.timeout(1.0):
            return await reader.read() == b""
    except ConnectionResetError:
        return True  # an abort, which is how the master closes it


async def wait_for_pending(master: Master, count: int) -> None:
    async with asyncio.timeout(2.0):
        while master.server.pending_connections != count:
            await asyncio.sleep(0.01)


def close_all(connections: list[Connection]) -> None:
    for _, writer in connections:
        writer.close()


async def test_a_connection_from_another_address_takes_the_place_of_a_silent_one(tmp_path):
    config = master_config(max_pending_connections=3, handshake_timeout=5.0)
    async with Master(config, tmp_path / "run", secret=SECRET) as master:
        flood = await silent_connections(master.port, 3)
        await wait_for_pending(master, 3)
        # Silent itself, but its address holds nothing: the flooding address gives one up.
        other = await silent_connections(master.port, 1, source="127.0.0.2")
        assert await closed_at_once(flood[0])  # the oldest
        await wait_for_pending(master, 3)
        assert master.server.handshakes.count("127.0.0.2") == 1
        assert master.server.evicted_connections == 1
        assert master.server.refused_connections == 0
        close_all(flood + other)
        await wait_for_pending(master, 0)
        await still_serving(master)
    log = (tmp_path / "run" / "master.log").read_text()
    assert "closed the handshake of 127.0.0.1:" in log and "to make room for 127.0.0.2:" in log


async def test_a_connection_that_speaks_at_once_takes_the_place_of_a_silent_one(tmp_path):
    # A robot behind the flooding address: its Hello is there when the master accepts it.
    config = master_config(max_pending_connections=3, handshake_timeout=5.0)
    async with Master(config, tmp_path / "run", secret=SECRET) as master:
        speaking = await hello_connections(master.port, 2)
        silent = await silent_connections(master.port, 1)
        await wait_for_pending(master, 3)
        robot = await speaking_at_once(master.port)
        assert await closed_at_once(silent[0])
        await wait_for_pending(master, 3)
        assert not any(writer.transport.is_closing() for _, writer in [*speaking, robot])
        assert master.server.evicted_connections == 1
        # With no silent one left, the next one that speaks at once is refused: robots halfway
        # through their handshakes stay.
        late = await speaking_at_once(master.port)
        assert await closed_at_once(late)
        assert master.server.refused_connections == 1
        close_all([*speaking, robot, late])
        await wait_for_pending(master, 0)


async def test_the_whole_handshake_has_one_deadline(tmp_path):
    # A peer dribbling its bytes keeps each step under the timeout (0.7 s each, 1 s allowed),
    # but not the whole handshake: it is refused at 1 s, never welcomed, however it goes on.
    config = master_config(handshake_timeout=1.0)
    async with Master(config, tmp_path / "run", secret=SECRET) as master:
        reader, writer = await asyncio.open_connection("127.0.0.1", master.port)

        async def dribble(data: bytes) -> None:
            pieces = [
                data[i : i + len(data) // 7 + 1] for i in range(0, len(data), len(data) // 7 + 1)
            ]
            for piece in pieces:
                writer.write(piece)
                await asyncio.sleep(0.1)

        robot_nonce = new_nonce()
        await dribble(frame(hello_payload(nonce=robot_nonce)))
        decoder = FrameDecoder()
        challenge = None
        while challenge is None:
            messages = decoder.feed(await reader.read(65536))
            challenge = messages[0] if messages else None
        assert proof_matches(
            master_proof(SECRET, robot_nonce, challenge.nonce, "r0"), challenge.proof
        )
        proof = robot_proof(SECRET, robot_nonce, challenge.nonce, "r0")

        async def collect() -> list:
            # Until the master closes; what it sent arrives before our writes start to fail.
            received = []
            with contextlib.suppress(ConnectionError):
                while data := await reader.read(65536):
                    received += decoder.feed(data)
            return received

        answers = asyncio.create_task(collect())
        with contextlib.suppress(ConnectionError):
            await dribble(encode(Authenticate(proof=proof)))
        messages = await asyncio.wait_for(answers, 3)
        writer.close()
        assert master.server.pending_connections == 0  # its slot is free again
    assert len(messages) == 1 and isinstance(messages[0], Refused)
    assert messages[0].code == REFUSED_PROTOCOL
    assert "the handshake took longer than 1 s" in messages[0].reason


async def test_stopping_the_master_with_handshakes_pending_prints_no_tracebacks(tmp_path, caplog):
    caplog.set_level(logging.DEBUG)
    # Handshakes that would still be waiting long after the master stopped.
    master = Master(master_config(handshake_timeout=30.0), tmp_path / "run", secret=SECRET)
    await master.start()
    idle = await idle_connections(master.port, 20)
    robot = ScriptedRobot("r0", SECRET, master.port)
    await robot.connect()
    async with asyncio.timeout(2.0):
        while master.server.pending_connections < 20:
            await asyncio.sleep(0.01)
    await master.close()
    for _ in range(5):  # let asyncio run whatever callbacks the closed connections left
        await asyncio.sleep(0)
    for w in idle:
        w.close()
    assert robot.closed.is_set()  # the robot's session had its Bye
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR or r.exc_info]
    assert errors == []
    assert "Traceback" not in (tmp_path / "run" / "master.log").read_text()
