"""The publisher against a real broker: topics and retained states arrive, the broker's loss and
return are survived, and a broker that never answers costs one log line."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import sys

from telemetry_helpers import WAIT, eventually

from minimize_surprise.backoff import BackoffConfig
from telemetry.config import TelemetryConfig
from telemetry.payloads import ClientStatus, RunStatus
from telemetry.publisher import TelemetryPublisher

#: Fast retries, so that a test does not wait for the production delays.
FAST = BackoffConfig(initial=0.02, max=0.1, jitter=0.5)


def make(url: str, **config: object) -> TelemetryPublisher:
    return TelemetryPublisher(
        TelemetryConfig(broker=url, reconnect=FAST, **config),  # type: ignore[arg-type]
        status_suffix="robot/r1/status",
        client_id="test-r1",
    )


def status(n: int) -> RunStatus:
    return RunStatus(
        t=1.0,
        online=True,
        run_id="run",
        phase="evolution",
        waiting=False,
        evaluations=n,
        total=10,
        best_fitness=0.5,
        last_fitness=0.5,
        robots_connected=1,
        robots_expected=1,
    )


async def test_events_and_retained_states_arrive_on_their_topics(mosquitto, subscriber):
    async with subscriber(mosquitto.port) as live, make(mosquitto.url) as pub:
        assert (await live.wait_for("robot/r1/status"))["online"] is True
        pub.publish_nowait("robot/r1/sample", ClientStatus(online=True, sent=1))
        pub.publish_nowait("run/status", status(3), retain=True)
        assert (await live.wait_for("robot/r1/sample"))["sent"] == 1
        assert (await live.wait_for("run/status"))["evaluations"] == 3
        # A subscriber arriving later still gets the states, as retained messages.
        async with subscriber(mosquitto.port) as late:
            await late.wait_for("run/status")
            await late.wait_for("robot/r1/status")
            assert all(retain for _, _, retain in late.messages)
            assert late.payloads("robot/r1/sample") == []
    # A clean close says offline itself (the broker then has no will to publish).
    async with subscriber(mosquitto.port) as after:
        gone = await after.wait_for("robot/r1/status")
        assert gone["online"] is False and gone["sent"] >= 3 and gone["dropped"] == 0


#: A robot's agent in another process, for the test of the last will: it connects, says so on
#: stdout and waits to be killed.
_VANISHING = """
import asyncio, sys
from telemetry.config import TelemetryConfig
from telemetry.publisher import TelemetryPublisher

async def main():
    pub = TelemetryPublisher(TelemetryConfig(broker=sys.argv[1]), status_suffix="robot/r9/status")
    pub.start()
    while not (pub.connected and pub.pending == 0):
        await asyncio.sleep(0.01)
    print("connected", flush=True)
    await asyncio.sleep(3600)

asyncio.run(main())
"""


async def test_the_last_will_marks_a_vanished_client_offline(mosquitto, subscriber):
    async with subscriber(mosquitto.port) as live:
        process = await asyncio.create_subprocess_exec(
            sys.executable, "-c", _VANISHING, mosquitto.url, stdout=asyncio.subprocess.PIPE
        )
        try:
            assert process.stdout is not None
            async with asyncio.timeout(WAIT):
                assert await process.stdout.readline() == b"connected\n"
            await live.wait_for("robot/r9/status", lambda p: p["online"])
        finally:
            process.kill()  # as a robot whose Pi loses power: no DISCONNECT, no goodbye
            await process.wait()
        offline = await live.wait_for("robot/r9/status", lambda p: not p["online"])
    assert offline == {"v": 1, "online": False, "t": None, "dropped": None, "sent": None}


async def test_an_unreachable_broker_costs_one_log_line_and_blocks_nothing(closed_port, caplog):
    caplog.set_level(logging.DEBUG)
    pub = make(f"mqtt://127.0.0.1:{closed_port}", queue_size=4)
    async with pub:
        await eventually(lambda: pub._backoff.attempts >= 5)
        for i in range(10):
            pub.publish_nowait("robot/r1/sample", ClientStatus(online=True, sent=i))
        assert pub.dropped == 6 and not pub.connected and pub.sent == 0
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1, [r.getMessage() for r in warnings]
    assert "cannot reach the broker" in warnings[0].getMessage()
    assert str(closed_port) in warnings[0].getMessage()


async def test_the_broker_stopped_and_restarted_is_survived(mosquitto, subscriber, caplog):
    caplog.set_level(logging.INFO, logger="telemetry")
    async with make(mosquitto.url) as pub:
        pub.publish_nowait("run/status", status(1), retain=True)
        await eventually(lambda: pub.connected and pub.pending == 0)
        sent = pub.sent

        mosquitto.stop()
        await eventually(lambda: not pub.connected)
        # Meanwhile the caller goes on publishing; nothing waits, the events are kept.
        pub.publish_nowait("robot/r1/evaluation", ClientStatus(online=True, sent=99))
        pub.publish_nowait("run/status", status(2), retain=True)
        assert pub.pending == 2

        mosquitto.start()  # without persistence: it has forgotten every retained message
        await eventually(lambda: pub.connections == 2 and pub.pending == 0)
        assert pub.sent >= sent + 3  # own status, the run status, the evaluation
        async with subscriber(mosquitto.port) as late:
            # The states were published again after reconnecting.
            assert (await late.wait_for("run/status"))["evaluations"] == 2
            assert (await late.wait_for("robot/r1/status"))["online"] is True
            pub.publish_nowait("robot/r1/sample", ClientStatus(online=True, sent=100))
            assert (await late.wait_for("robot/r1/sample"))["sent"] == 100
    messages = [r.getMessage() for r in caplog.records if r.name.startswith("telemetry")]
    assert any("lost the broker" in m for m in messages)
    assert any("connected" in m and "again" in m for m in messages)


async def test_closing_waits_briefly_for_the_queue_to_drain(mosquitto, subscriber):
    async with subscriber(mosquitto.port) as live:
        pub = make(mosquitto.url)
        async with pub:
            await eventually(lambda: pub.connected)
            for i in range(50):
                pub.publish_nowait("robot/r1/sample", ClientStatus(online=True, sent=i))
        assert pub.pending == 0 and pub.dropped == 0
        await eventually(lambda: len(live.payloads("robot/r1/sample")) == 50, WAIT)
        assert [p["sent"] for p in live.payloads("robot/r1/sample")] == list(range(50))


async def test_a_broker_that_accepts_but_never_answers_leaks_nothing(monkeypatch, caplog):
    # A wrong service on the broker's port: TCP connects, MQTT's CONNACK never comes.
    monkeypatch.setattr("telemetry.publisher.BROKER_TIMEOUT", 0.1)
    open_connections: set[asyncio.StreamWriter] = set()

    async def silent(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        open_connections.add(writer)
        with contextlib.suppress(ConnectionError):
            await reader.read()  # returns at EOF: the client closed its socket
        open_connections.discard(writer)
        writer.close()

    server = await asyncio.start_server(silent, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    try:
        async with make(f"mqtt://127.0.0.1:{port}") as pub:
            await eventually(lambda: pub._backoff.attempts >= 4)
            # Every abandoned attempt closed its socket; at most the current one is open.
            await eventually(lambda: len(open_connections) <= 1)
            assert not pub.connected
        await eventually(lambda: not open_connections)
    finally:
        server.close()
        await server.wait_closed()
    warnings = [r for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and "cannot reach the broker" in warnings[0].getMessage()
