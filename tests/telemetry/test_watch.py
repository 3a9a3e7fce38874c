"""``surprise-master watch``: the state fed by messages, its rendering without a terminal, and
the command against a real broker."""

from __future__ import annotations

import asyncio
import io
import json

import numpy as np
import pytest
from rich.console import Console
from telemetry_helpers import eventually

from minimize_surprise.backoff import BackoffConfig
from reporting.watch import SwarmState, collect, render, run_watch
from telemetry.config import TelemetryConfig, parse_broker_url
from telemetry.payloads import (
    ClientStatus,
    EvaluationSummary,
    RunStatus,
    StepSample,
    encode_payload,
)
from telemetry.publisher import TelemetryPublisher

NOW = 1_700_000_000.0
FAST = BackoffConfig(initial=0.02, max=0.1, jitter=0.5)


def run_status(**overrides: object) -> RunStatus:
    values: dict[str, object] = {
        "t": NOW,
        "online": True,
        "run_id": "20240501-basic",
        "phase": "evolution",
        "waiting": False,
        "evaluations": 5,
        "total": 10,
        "best_fitness": 0.9,
        "last_fitness": 0.85,
        "robots_connected": 2,
        "robots_expected": 2,
        "robots": ["r1", "r2"],
        "elapsed_s": 62.0,
        "time_left_s": 70.0,
    }
    values.update(overrides)
    return RunStatus(**values)  # type: ignore[arg-type]


def sample(**overrides: object) -> StepSample:
    values: dict[str, object] = {
        "t": NOW,
        "evaluation": 5,
        "step": 40,
        "names": ("ir.f0", "ground.0"),
        "sensors": np.array([0.1, 0.9]),
        "predictions": np.array([0.15, 0.2]),
        "command": (0.5, -0.25),
        "reason": "front",
    }
    values.update(overrides)
    return StepSample(**values)  # type: ignore[arg-type]


def text(state: SwarmState) -> str:
    console = Console(record=True, width=160, file=io.StringIO())
    console.print(render(state, now=NOW + 3))
    return console.export_text()


def feed(state: SwarmState, topic: str, payload: object) -> bool:
    data = payload if isinstance(payload, bytes) else encode_payload(payload)  # type: ignore[arg-type]
    return state.apply(f"surprise/{topic}", data, received=NOW)


def test_the_view_shows_a_pause_the_batteries_and_late_steps():
    state = SwarmState()
    reason = "battery below 3.60 V: swap the battery of r1 (3.52 V)"
    assert feed(state, "run/status", run_status(paused=reason))
    summary = EvaluationSummary(
        t=NOW, evaluation=5, requested=100, steps=100, fitness=0.8, overruns=2, battery_v=3.52
    )
    assert feed(state, "robot/r1/evaluation", summary)
    assert feed(state, "robot/r1/status", ClientStatus(online=True, t=NOW))
    out = text(state)
    assert f"paused       {reason}" in out
    assert "online 3.52 V" in out and "100/100, 2 late" in out


def test_an_empty_view_says_what_is_missing():
    out = text(SwarmState())
    assert "no run status yet" in out and "no robot seen yet" in out


def test_the_view_shows_the_run_the_robots_and_sensors_against_predictions():
    state = SwarmState()
    assert feed(state, "run/status", run_status())
    assert feed(state, "master/status", ClientStatus(online=True, t=NOW, dropped=0, sent=9))
    assert feed(state, "robot/r1/status", ClientStatus(online=True, t=NOW, dropped=3, sent=50))
    assert feed(state, "robot/r2/status", ClientStatus(online=False))
    summary = EvaluationSummary(
        t=NOW,
        evaluation=5,
        requested=100,
        steps=100,
        fitness=0.8123,
        interventions={"front": 2, "ground": 1},
    )
    assert feed(state, "robot/r1/evaluation", summary)
    failed = EvaluationSummary(
        t=NOW, evaluation=5, requested=100, steps=12, fitness=None, failure="sensor-read: 3 reads"
    )
    assert feed(state, "robot/r2/evaluation", failed)
    assert feed(state, "robot/r1/sample", sample())
    assert feed(state, "robot/r2/sample", sample(predictions=None, reason=None))
    out = text(state)
    for expected in (
        "run 20240501-basic",
        "evaluations  5/10",
        "best 0.9000, last 0.8500",
        "2/2 (r1, r2)",
        "elapsed 1m02s, left ~1m10s",
        "r1",
        "online",
        "offline",
        "3s ago",
        "0.8123",
        "100/100",
        "front 2, ground 1",
        "+0.50 -0.25",
        "failed: sensor-read: 3 reads",
        "12/100",
        "0.10/0.15",  # a good prediction
        "0.90/0.20",  # a surprise
        "0.10/-",  # no prediction for this reading
        "5:40",
        "master online",
    ):
        assert expected in out, f"{expected!r} not in\n{out}"
    r1 = next(line for line in out.splitlines() if "0.8123" in line)
    assert r1.rstrip("│ ").endswith(" 3")  # the dropped counter
    assert state.robots["r1"].evaluations_seen == 1


def test_unreadable_and_foreign_messages_are_counted_not_fatal():
    state = SwarmState()
    assert not feed(state, "robot/r1/status", b'{"v":2,"online":true}')
    assert not feed(state, "robot/r1/sample", b"garbage")
    assert not state.apply("elsewhere/run/status", encode_payload(run_status()))
    assert not feed(state, "robot/r1/pose", b"{}")
    assert (state.messages, state.ignored) == (0, 4)
    out = text(state)
    assert "unreadable message: sample: not a JSON object" in out
    assert feed(state, "robot/r1/status", ClientStatus(online=True))
    assert state.robots["r1"].problem is None


def test_a_finished_or_waiting_run_says_so():
    state = SwarmState()
    feed(state, "run/status", run_status(phase="done", online=False, time_left_s=0.0))
    assert "done (master stopped)" in text(state)
    feed(state, "run/status", run_status(waiting=True, robots_connected=1, robots=["r1"]))
    out = text(state)
    assert "waiting for robots" in out and "1/2 (r1)" in out


async def test_collect_feeds_the_state_from_the_broker(mosquitto):
    config = TelemetryConfig(broker=mosquitto.url, reconnect=FAST)
    state = SwarmState()
    watcher = asyncio.create_task(collect(parse_broker_url(mosquitto.url), state, duration=30))
    try:
        await eventually(lambda: state.broker.startswith("connected"))
        async with TelemetryPublisher(config, status_suffix="robot/r7/status") as pub:
            pub.publish_nowait("robot/r7/sample", sample(step=5))
            pub.publish_nowait("run/status", run_status(), retain=True)
            await eventually(lambda: state.run is not None and "r7" in state.robots)
            await eventually(lambda: state.robots["r7"].sample is not None)
        await eventually(lambda: state.robots["r7"].online is False)
    finally:
        watcher.cancel()
        with pytest.raises(asyncio.CancelledError):
            await watcher
    sampled = state.robots["r7"].sample
    assert sampled is not None and sampled.step == 5 and sampled.sensors == [0.1, 0.9]


def _publish_retained(url: str) -> None:
    async def publish() -> None:
        config = TelemetryConfig(broker=url, reconnect=FAST)
        async with TelemetryPublisher(config, status_suffix="master/status") as master:
            master.publish_nowait("run/status", run_status(), retain=True)
            async with TelemetryPublisher(config, status_suffix="robot/r3/status") as robot:
                await eventually(lambda: master.sent >= 2 and robot.sent >= 1)

    asyncio.run(publish())


def test_once_prints_a_snapshot_of_the_retained_state(mosquitto):
    _publish_retained(mosquitto.url)
    out = io.StringIO()
    assert run_watch(mosquitto.url, once=True, collect_s=0.3, stream=out) == 0
    snapshot = out.getvalue()
    assert "run 20240501-basic" in snapshot and "5/10" in snapshot
    assert "r3" in snapshot and "offline" in snapshot and "master offline" in snapshot


def test_once_with_an_unreachable_broker_says_so(closed_port, capsys):
    assert run_watch(f"mqtt://127.0.0.1:{closed_port}", once=True, collect_s=0.1) == 1
    assert "cannot reach the broker" in capsys.readouterr().err


@pytest.mark.parametrize("broker, prefix", [("localhost:1883", "surprise"), ("mqtt://h", "a/#")])
def test_bad_arguments_are_usage_errors(broker, prefix, capsys):
    assert run_watch(broker, prefix=prefix, once=True) == 2
    assert "surprise-master watch:" in capsys.readouterr().err


def test_the_payload_examples_of_the_docs_are_readable():
    # docs/telemetry.md shows one payload per topic; they must stay valid for this code.
    from pathlib import Path

    docs = Path(__file__).resolve().parents[2] / "docs" / "telemetry.md"
    examples = [
        line for line in docs.read_text(encoding="utf-8").splitlines() if line.startswith('{"v":')
    ]
    assert len(examples) >= 5
    state = SwarmState()
    topics = {
        "run_id": "run/status",
        "names": "robot/r1/sample",
        "requested": "robot/r1/evaluation",
    }
    for line in examples:
        data = json.loads(line)
        topic = next((t for key, t in topics.items() if key in data), "robot/r1/status")
        assert feed(state, topic, line.encode()), line


def test_the_watch_command_of_surprise_master(mosquitto, closed_port, capsys):
    from master_service.cli import main

    _publish_retained(mosquitto.url)
    assert main(["watch", "--broker", mosquitto.url, "--once"]) == 0
    assert "run 20240501-basic" in capsys.readouterr().out
    assert main(["watch", "--broker", mosquitto.url, "--prefix", "other", "--once"]) == 0
    assert "no run status yet" in capsys.readouterr().out
    assert main(["watch", "--broker", f"mqtt://127.0.0.1:{closed_port}", "--once"]) == 1
    assert "cannot reach the broker" in capsys.readouterr().err
