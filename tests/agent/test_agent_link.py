"""The agent against a scripted master over real loopback TCP: handshake, refusal and backoff,
evaluations, abort, replacement, keep-alive, losing the master and finding it again."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import random
import struct
from collections.abc import AsyncIterator

import pytest
from agent_fakes import (
    SECRET,
    THYMIO,
    FakeBody,
    FakeClock,
    ScriptedMaster,
    agent_config,
    genome,
    receive,
    spec,
)

import minimize_surprise
from minimize_surprise.backoff import Backoff
from minimize_surprise.errors import ConnectionClosedError
from minimize_surprise.provenance import software_commit
from minimize_surprise.session import NONCE_SIZE, master_proof, new_nonce
from minimize_surprise.wire import (
    FEATURE_ESCAPE,
    FEATURE_STOP,
    LOGGED_TEXT_LIMIT,
    MAX_REASON_LENGTH,
    PROTOCOL_VERSION,
    REFUSED_BAD_SECRET,
    REFUSED_VERSION_MISMATCH,
    Abort,
    Bye,
    Challenge,
    Evaluate,
    Failed,
    Hello,
    Ping,
    Pong,
    Refused,
    Result,
    Welcome,
    genome_to_bytes,
)
from relay import Relay, tagged_message
from robot_agent.agent import Agent
from robot_agent.config import BackoffConfig
from transport.framing import encode
from transport.stream import MessageStream

LONG = 30_000  # steps of an evaluation that only ends when stopped


@pytest.fixture
async def master() -> AsyncIterator[ScriptedMaster]:
    m = ScriptedMaster()
    await m.start()
    yield m
    await m.close()


@contextlib.asynccontextmanager
async def running(agent: Agent) -> AsyncIterator[asyncio.Task[None]]:
    task = asyncio.create_task(agent.run())
    try:
        yield task
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


def make_agent(port: int, *, body: FakeBody | None = None, secret: bytes = SECRET, **config):
    clock = FakeClock()
    body = body if body is not None else FakeBody(0.0, clock=clock)
    body.clock = clock
    agent = Agent(agent_config(port, **config), body, clock, secret, rng=random.Random(1))
    return agent, body


def evaluate(
    eid: int, steps: int, *, speed: float = 2.0, network=None, record=False, period=0.1
) -> Evaluate:
    network = network if network is not None else spec()
    g = genome(network, speed_bias=speed)
    return Evaluate(
        evaluation_id=eid,
        genome=genome_to_bytes(g),
        spec=network,
        steps=steps,
        step_period=period,
        record=record,
    )


async def connect(master: ScriptedMaster, **kwargs) -> tuple[MessageStream, Hello]:
    stream = await master.next()
    hello = await master.welcome(stream, **kwargs)
    return stream, hello


async def wait_for(predicate, timeout: float = 5.0) -> None:
    async with asyncio.timeout(timeout):
        while not predicate():
            await asyncio.sleep(0.001)


# --------------------------------------------------------------------------- connecting


async def test_handshake_introduces_the_robot_and_answers_the_challenge(master):
    agent, _ = make_agent(master.port)
    async with running(agent):
        _, hello = await connect(master, run_id="run-7", heartbeat=2.0)
        assert hello == Hello(
            robot_id="r1",
            software_version=minimize_surprise.__version__,
            protocol_version=PROTOCOL_VERSION,
            sensors=THYMIO,
            nonce=hello.nonce,
            features=(FEATURE_ESCAPE, FEATURE_STOP),
            software_commit=software_commit(),
            thymio_firmware=None,  # a body without firmware
        )
        assert hello.nonce is not None and len(hello.nonce) == NONCE_SIZE
        await asyncio.wait_for(agent.connected.wait(), 5)
        assert agent.link.run_id == "run-7" and agent.link.heartbeat_interval == 2.0


async def test_the_hello_names_the_firmware_once_the_robot_answers(master):
    """Read before a connection until known: a robot away at the start is named later."""
    answers = iter([RuntimeError("robot away"), 14])

    class FirmwareBody(FakeBody):
        async def read_firmware(self) -> int | None:
            answer = next(answers, 99)  # read once known: never 99
            if isinstance(answer, Exception):
                raise answer
            return answer

    agent, _ = make_agent(master.port, body=FirmwareBody(0.0))
    async with running(agent):
        stream, hello = await connect(master)
        assert hello.thymio_firmware is None
        await stream.close()
        for _ in range(2):
            stream, hello = await connect(master)
            assert hello.thymio_firmware == 14
            await stream.close()


async def test_a_wrong_secret_is_found_out_and_the_robot_backs_off_and_retries(master, caplog):
    # The secrets differ: the master's proof does not verify on the robot, which says so loudly,
    # sends nothing more and tries again later (the lab may fix the secret file).
    agent, _ = make_agent(master.port, secret=b"not the lab secret")
    caplog.set_level(logging.INFO, logger="robot_agent")
    async with running(agent):
        for attempt in (1, 2, 3):
            stream = await master.next()
            with pytest.raises(AssertionError, match="did not accept the master's proof"):
                await master.welcome(stream)
            await wait_for(lambda a=attempt: agent.link.backoff.attempts == a)
        assert not agent.connected.is_set()
    failures = [r for r in caplog.records if "did not prove" in r.getMessage()]
    assert len(failures) >= 3 and all(r.levelno == logging.ERROR for r in failures)
    assert "secret file differs" in failures[0].getMessage()
    assert any("reconnecting in" in r.getMessage() for r in caplog.records)


async def test_a_version_mismatch_is_logged_as_an_error_on_every_try(master, caplog):
    agent, _ = make_agent(master.port)
    async with running(agent):
        for _ in range(2):
            stream = await master.next()
            assert isinstance(await receive(stream), Hello)
            await stream.send(Refused(code=REFUSED_VERSION_MISMATCH, reason="master speaks 2"))
            await stream.close()
        await master.next()  # and it still tries again
    errors = [r for r in caplog.records if REFUSED_VERSION_MISMATCH in r.getMessage()]
    assert len(errors) == 2 and all(r.levelno == logging.ERROR for r in errors)


async def test_welcome_resets_the_backoff(master):
    agent, _ = make_agent(master.port)
    async with running(agent):
        stream = await master.next()
        assert isinstance(await receive(stream), Hello)
        await stream.send(Refused(code=REFUSED_BAD_SECRET, reason="try again"))
        await stream.close()
        await connect(master)
        await asyncio.wait_for(agent.connected.wait(), 5)
        assert agent.link.backoff.attempts == 0


def test_backoff_doubles_up_to_the_cap_with_bounded_jitter():
    config = BackoffConfig(initial=0.5, max=30.0, jitter=0.25)
    backoff = Backoff(config, random.Random(0))
    delays = [backoff.next_delay() for _ in range(12)]
    bases = [min(30.0, 0.5 * 2**n) for n in range(12)]
    for delay, base in zip(delays, bases, strict=True):
        assert 0.75 * base <= delay <= base
    assert max(delays) <= 30.0 and delays[-1] >= 22.5
    # Seeded: the same sequence again; another seed: another sequence.
    again = Backoff(config, random.Random(0))
    assert [again.next_delay() for _ in range(12)] == delays
    other = Backoff(config, random.Random(1))
    assert [other.next_delay() for _ in range(12)] != delays
    backoff.reset()
    assert backoff.next_delay() <= 0.5


# --------------------------------------------------------------------------- evaluating


async def test_evaluate_runs_and_returns_the_result(master):
    network = spec(predefined=dict.fromkeys(THYMIO, 0.25))
    agent, body = make_agent(master.port, body=FakeBody(0.75))
    async with running(agent):
        stream, _ = await connect(master)
        await stream.send(evaluate(7, 12, network=network, record=True))
        result = await receive(stream)
        assert isinstance(result, Result) and result.evaluation_id == 7
        assert result.fitness == pytest.approx(0.5) and result.stats.steps_run == 12
        assert result.trace is not None and result.trace.steps == 12
        assert body.motors == (0.0, 0.0)


async def test_an_evaluation_the_body_cannot_run_is_answered_with_failed(master):
    agent, body = make_agent(master.port)
    async with running(agent):
        stream, _ = await connect(master)
        await stream.send(evaluate(3, 10, network=spec((*THYMIO, "light.0"))))
        failed = await receive(stream)
        assert isinstance(failed, Failed) and failed.evaluation_id == 3
        assert "light.0" in failed.reason and body.drives == []


async def test_abort_stops_the_motors_and_nothing_is_sent_for_it(master):
    agent, body = make_agent(master.port)
    async with running(agent):
        stream, _ = await connect(master)
        await stream.send(evaluate(1, LONG))
        await asyncio.wait_for(body.moved.wait(), 5)
        await stream.send(Abort(evaluation_id=99, reason="not that one"))  # ignored
        await stream.send(Abort(evaluation_id=1, reason="round timed out"))
        await stream.send(Ping(seq=1))
        # The Abort was handled (and the evaluation stopped) before the Ping: no Result in between.
        assert await receive(stream) == Pong(seq=1)
        assert body.motors == (0.0, 0.0)
        drives = len(body.drives)
        await stream.send(Ping(seq=2))
        assert await receive(stream) == Pong(seq=2)
        assert len(body.drives) == drives  # it stays stopped


async def test_a_new_evaluate_replaces_the_running_one(master):
    agent, body = make_agent(master.port)
    async with running(agent):
        stream, _ = await connect(master)
        await stream.send(evaluate(1, LONG))
        await asyncio.wait_for(body.moved.wait(), 5)
        stops = body.stops
        await stream.send(evaluate(2, 5))
        result = await receive(stream)
        assert isinstance(result, Result) and result.evaluation_id == 2
        assert result.stats.steps_run == 5
        assert body.stops >= stops + 2  # the replaced one stopped, and the new one at its end
        await stream.send(Ping(seq=3))
        assert await receive(stream) == Pong(seq=3)  # nothing was ever sent for evaluation 1


# --------------------------------------------------------------------------- keep-alive, loss


async def test_ping_is_answered_with_pong(master):
    agent, _ = make_agent(master.port)
    async with running(agent):
        stream, _ = await connect(master)
        for seq in (0, 1, 42):
            await stream.send(Ping(seq=seq))
            assert await receive(stream) == Pong(seq=seq)


async def test_a_silent_master_is_probed_then_dropped_and_the_robot_reconnects(master):
    agent, _ = make_agent(master.port)
    async with running(agent):
        stream, _ = await connect(master, heartbeat=0.05)
        loop = asyncio.get_running_loop()
        start = loop.time()
        probe = await receive(stream)
        assert isinstance(probe, Ping)
        assert loop.time() - start >= 0.07  # 1.5 heartbeats of silence before probing
        await stream.send(Pong(seq=probe.seq))  # an answer keeps it alive...
        probe = await receive(stream)
        assert isinstance(probe, Ping)
        # ...silence after the probe ends the session at 3 heartbeats.
        with pytest.raises(ConnectionClosedError):
            await receive(stream)
        assert loop.time() - start >= 0.15
        await connect(master)  # and it comes back


async def test_losing_the_master_during_an_evaluation_stops_the_motors_and_reconnects(master):
    agent, body = make_agent(master.port)
    async with running(agent):
        stream, _ = await connect(master)
        await stream.send(evaluate(1, LONG))
        await asyncio.wait_for(body.moved.wait(), 5)
        await stream.close()
        next_stream = await master.next()
        assert body.motors == (0.0, 0.0)
        assert agent.watchdog.tripped_reason is not None
        assert agent.watchdog.tripped_reason.startswith("link lost")
        await master.welcome(next_stream)
        # The next evaluation re-arms the watchdog and runs normally.
        await next_stream.send(evaluate(2, 3))
        result = await receive(next_stream)
        assert isinstance(result, Result) and not agent.watchdog.tripped


async def test_a_vanished_master_is_retried_with_backoff_until_it_returns(master):
    agent, _ = make_agent(master.port)
    async with running(agent):
        await connect(master)
        await asyncio.wait_for(agent.connected.wait(), 5)
        port = master.port
        await master.close()  # the master process is gone: connections are refused
        await wait_for(lambda: agent.link.backoff.attempts >= 3)
        assert not agent.connected.is_set()
        await master.start(port)
        await connect(master)
        await asyncio.wait_for(agent.connected.wait(), 5)
        assert agent.link.sessions == 2


async def test_an_unexpected_message_is_reported_and_the_session_closed(master):
    agent, _ = make_agent(master.port)
    async with running(agent):
        stream, _ = await connect(master)
        await stream.send(Hello(robot_id="x", software_version="0", protocol_version=1, sensors=()))
        error = await receive(stream)
        assert error.code == "protocol" and "Hello" in error.message
        with pytest.raises(ConnectionClosedError):
            await receive(stream)
        await connect(master)


async def test_bye_from_the_master_ends_the_session_and_the_robot_comes_back(master):
    agent, _ = make_agent(master.port)
    async with running(agent):
        stream, _ = await connect(master)
        await stream.send(Bye(reason="run finished"))
        with pytest.raises(ConnectionClosedError):
            await receive(stream)
        await connect(master)


async def test_stopping_the_agent_stops_the_motors_and_says_bye(master, caplog):
    agent, body = make_agent(master.port)
    async with running(agent) as task:
        stream, _ = await connect(master)
        await stream.send(evaluate(1, LONG))
        await asyncio.wait_for(body.moved.wait(), 5)
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
        assert body.motors == (0.0, 0.0)
        # An orderly stop is not a lost link: the watchdog stays quiet.
        assert agent.watchdog.tripped_reason is None
        assert "link lost" not in caplog.text
        assert await receive(stream) == Bye(reason="agent stopping")
        with pytest.raises(ConnectionClosedError):
            await receive(stream)


async def test_several_agents_share_one_event_loop(master):
    agents = []
    for i in range(3):
        agent, _ = make_agent(master.port, robot_id=f"r{i}")
        agents.append(agent)
    async with contextlib.AsyncExitStack() as stack:
        for agent in agents:
            await stack.enter_async_context(running(agent))
        streams = {}
        for _ in agents:
            stream, hello = await connect(master)
            streams[hello.robot_id] = stream
        assert sorted(streams) == ["r0", "r1", "r2"]
        for eid, stream in enumerate(streams.values()):
            await stream.send(evaluate(eid, 4))
        for eid, stream in enumerate(streams.values()):
            result = await receive(stream)
            assert isinstance(result, Result) and result.evaluation_id == eid


# --------------------------------------------------------------------------- TLS


async def test_the_link_can_run_over_tls(tmp_path):
    import ssl
    import subprocess

    from needs import require_binary
    from robot_agent.config import MasterConfig
    from transport.tls import ClientTlsConfig

    require_binary("openssl")
    cert, key = tmp_path / "master.pem", tmp_path / "master.key"
    subprocess.run(
        ["openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1",
         "-nodes", "-keyout", str(key), "-out", str(cert), "-days", "1",
         "-subj", "/CN=master.test", "-addext", "subjectAltName=DNS:master.test"],
        check=True,
        capture_output=True,
    )  # fmt: skip
    server_context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    server_context.load_cert_chain(cert, key)
    master = ScriptedMaster()
    await master.start(ssl=server_context)
    try:
        tls = ClientTlsConfig(ca_file=str(cert), server_hostname="master.test")
        agent, _ = make_agent(
            master.port,
            master=MasterConfig(host="127.0.0.1", port=master.port, secret_file="x", tls=tls),
        )
        async with running(agent):
            stream, hello = await connect(master)
            assert hello.robot_id == "r1"
            await stream.send(Ping(seq=9))
            assert await receive(stream) == Pong(seq=9)
    finally:
        await master.close()


# --------------------------------------------------------------------------- who may drive


async def test_an_impostor_master_cannot_make_the_robot_drive(master):
    # A server without the secret: its proof cannot be right, so the robot sends it nothing more
    # and runs nothing, however eagerly the impostor sends its Welcome and Evaluate.
    agent, body = make_agent(master.port)
    async with running(agent):
        stream = await master.next()
        hello = await receive(stream)
        nonce = new_nonce()
        guess = master_proof(b"a guessed secret", hello.nonce, nonce, hello.robot_id)
        stream.writer.write(
            encode(Challenge(nonce=nonce, proof=guess))
            + encode(Welcome(run_id="impostor", heartbeat_interval=30.0))
            + encode(evaluate(1, LONG))
        )
        with pytest.raises(ConnectionClosedError):
            await receive(stream)  # no Authenticate, no Result: the robot just leaves
        await master.next()  # and tries again later
        assert body.drives == [] and not body.moved.is_set()
        assert not agent.connected.is_set() and agent.link.sessions == 0


@pytest.fixture
async def relay(master):
    r = Relay(master.port)
    await r.start()
    yield r
    await r.close()


async def test_an_evaluate_injected_by_a_relay_is_detected_and_never_run(master, relay):
    agent, body = make_agent(relay.port)
    async with running(agent):
        stream, _ = await connect(master)  # the handshake passes the relay untouched
        await asyncio.wait_for(agent.connected.wait(), 5)
        relay.connections[0].inject_to_client(encode(evaluate(1, LONG)))
        with pytest.raises(ConnectionClosedError):
            await receive(stream)
        await master.next()  # the robot reconnects
        assert body.drives == [] and not body.moved.is_set()


async def test_an_evaluate_replayed_by_a_relay_is_detected_and_not_run_again(master, relay):
    agent, body = make_agent(relay.port)
    async with running(agent):
        stream, _ = await connect(master)
        await stream.send(evaluate(1, 3))
        assert isinstance(await receive(stream), Result)
        drives = len(body.drives)
        link = relay.connections[0]
        genuine = [f for f in link.to_client if isinstance(tagged_message(f), Evaluate)]
        link.inject_to_client(genuine[0])
        with pytest.raises(ConnectionClosedError):
            await receive(stream)
        await master.next()
        assert len(body.drives) == drives  # the replay never ran


async def test_a_frame_sent_back_to_the_robot_is_detected(master, relay):
    agent, _ = make_agent(relay.port)
    async with running(agent):
        stream, _ = await connect(master)
        await stream.send(Ping(seq=5))
        assert await receive(stream) == Pong(seq=5)
        link = relay.connections[0]
        pongs = lambda: [f for f in link.to_server if isinstance(tagged_message(f), Pong)]  # noqa: E731
        await relay.wait_for(lambda: bool(pongs()))
        pong = pongs()[0]
        link.inject_to_client(pong)  # the robot's own answer, returned to it
        with pytest.raises(ConnectionClosedError):
            await receive(stream)
        await master.next()


# --------------------------------------------------------------------------- what a master may ask


@pytest.mark.parametrize("heartbeat", [1e-4, 1e6])
async def test_a_heartbeat_interval_out_of_bounds_ends_the_session(master, heartbeat, caplog):
    # A tiny interval would make the robot ping in a busy loop and drop the link at once; a huge
    # one would let it miss a dead master for days.
    agent, _ = make_agent(master.port)
    async with running(agent):
        stream = await master.next()
        with pytest.raises(ConnectionClosedError):
            await master.welcome(stream, heartbeat=heartbeat)
            await receive(stream)
        assert not agent.connected.is_set() and agent.link.sessions == 0
        await master.next()
    assert any("heartbeat_interval" in r.getMessage() for r in caplog.records)


async def test_a_large_frame_before_the_welcome_is_refused_at_once(master):
    # Before the master has proved the secret, nobody makes the robot wait for or buffer a big
    # frame: a header announcing 1 MiB ends the connection right away.
    agent, _ = make_agent(master.port)
    async with running(agent):
        stream = await master.next()
        assert isinstance(await receive(stream), Hello)
        stream.writer.write(struct.pack(">I", 1024 * 1024))
        with pytest.raises(ConnectionClosedError):
            # Far below the 10 s handshake timeout: the robot did not wait for the body.
            await receive(stream, timeout=2.0)
        await master.next()


async def test_a_refusal_reason_is_cut_and_cleaned_before_it_is_logged(master, caplog):
    agent, _ = make_agent(master.port)
    caplog.set_level(logging.INFO, logger="robot_agent")
    async with running(agent):
        stream = await master.next()
        assert isinstance(await receive(stream), Hello)
        reason = "\x1b[2J\x1b[31mwipe the screen\n" + "x" * (MAX_REASON_LENGTH - 40)
        await stream.send(Refused(code=REFUSED_BAD_SECRET, reason=reason))
        await stream.close()
        await master.next()
    (record,) = [r for r in caplog.records if "refused by the master" in r.getMessage()]
    text = record.getMessage()
    assert "\x1b" not in text and "\n" not in text and "?[2J?[31mwipe the screen?" in text
    assert len(text) < LOGGED_TEXT_LIMIT + 100 and text.endswith("...")
