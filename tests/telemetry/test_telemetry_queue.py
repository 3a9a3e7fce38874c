"""Payloads, topics, the step sampler and the publisher's queue, without a broker.

The queue's promise is by construction: ``publish_nowait`` is a plain function (the caller never
awaits anything of telemetry) that appends to a bounded deque and returns; a full queue drops its
oldest entry and counts it.
"""

from __future__ import annotations

import inspect
import json

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from minimize_surprise.backoff import Backoff
from telemetry.config import TelemetryConfig
from telemetry.payloads import (
    ClientStatus,
    EvaluationSummary,
    RunStatus,
    StepSample,
    TopicInfo,
    decode_payload,
    encode_payload,
    parse_topic,
    robot_suffix,
)
from telemetry.publisher import TelemetryPublisher
from telemetry.robot import RobotTelemetry, StepSampler, steps_between_samples

BROKER = "mqtt://127.0.0.1:1"  # never contacted: these publishers are not started


def publisher(queue_size: int = 256, **config: object) -> TelemetryPublisher:
    return TelemetryPublisher(
        TelemetryConfig(broker=BROKER, queue_size=queue_size, **config),  # type: ignore[arg-type]
        status_suffix="robot/r1/status",
    )


def queued(pub: TelemetryPublisher) -> list:
    return [payload for _, payload, _ in pub._queue]


# --------------------------------------------------------------------------- payloads, topics


def test_payloads_are_compact_json_with_the_version_first():
    data = encode_payload(
        StepSample(
            t=1.5,
            evaluation=3,
            step=10,
            names=("ir.f0", "ground.0"),
            sensors=np.array([0.123456789, 1.0]),
            predictions=None,
            command=(0.5, -0.25),
        )
    )
    assert data.startswith(b'{"v":1,') and b" " not in data
    assert json.loads(data) == {
        "v": 1,
        "t": 1.5,
        "evaluation": 3,
        "step": 10,
        "names": ["ir.f0", "ground.0"],
        "sensors": [0.1235, 1.0],
        "predictions": None,
        "command": [0.5, -0.25],
        "reason": None,
    }


def test_a_payload_round_trips_and_unknown_fields_are_ignored():
    summary = EvaluationSummary(
        t=2.0, evaluation=4, requested=100, steps=100, fitness=0.75, interventions={"front": 2}
    )
    data = encode_payload(summary)
    assert decode_payload(data, EvaluationSummary) == summary
    extended = json.loads(data) | {"new_field": [1, 2]}
    assert decode_payload(json.dumps(extended), EvaluationSummary) == summary


@pytest.mark.parametrize(
    "data, match",
    [
        (b'{"v":2,"online":true}', "version 2"),
        (b'{"online":true}', "version None"),
        (b"[1,2]", "not a JSON object"),
        (b"not json", "not a JSON object"),
        (b'{"v":1,"online":"yes"}', "Expected `bool`"),
    ],
)
def test_unreadable_payloads_raise_value_error(data, match):
    with pytest.raises(ValueError, match=match):
        decode_payload(data, ClientStatus)


def test_the_last_will_is_a_plain_offline_status():
    will = decode_payload(encode_payload(ClientStatus(online=False)), ClientStatus)
    assert will.online is False and will.t is None


@pytest.mark.parametrize(
    "topic, info",
    [
        ("lab/run/status", TopicInfo("run", "status")),
        ("lab/master/status", TopicInfo("master", "status")),
        ("lab/robot/thymio-1/sample", TopicInfo("robot", "sample", "thymio-1")),
        ("lab/robot/r2/evaluation", TopicInfo("robot", "evaluation", "r2")),
        ("lab/robot/r2/status", TopicInfo("robot", "status", "r2")),
        ("lab/robot/r2/other", None),
        ("lab/robot//status", None),
        ("other/run/status", None),
        ("lab", None),
    ],
)
def test_topics_are_parsed_under_the_prefix(topic, info):
    assert parse_topic("lab", topic) == info


def test_robot_topics_are_limited_to_the_documented_kinds():
    assert robot_suffix("r1", "sample") == "robot/r1/sample"
    with pytest.raises(ValueError):
        robot_suffix("r1", "pose")


def test_run_status_defaults_keep_old_readers_working():
    status = RunStatus(
        t=0.0,
        online=True,
        run_id="x",
        phase="evolution",
        waiting=False,
        evaluations=0,
        total=10,
        best_fitness=None,
        last_fitness=None,
        robots_connected=0,
        robots_expected=2,
    )
    assert decode_payload(encode_payload(status), RunStatus) == status


# --------------------------------------------------------------------------- the queue


def test_publish_nowait_is_a_plain_function_that_never_waits():
    # Non-blocking by construction: nothing to await, and no event loop is even needed.
    assert not inspect.iscoroutinefunction(TelemetryPublisher.publish_nowait)
    pub = publisher(queue_size=2)
    assert pub.publish_nowait("x", ClientStatus(online=True)) is None
    assert pub.pending == 1


@given(n=st.integers(0, 60), size=st.integers(1, 20))
def test_a_full_queue_drops_the_oldest_and_counts_it(n, size):
    pub = publisher(queue_size=size)
    for i in range(n):
        pub.publish_nowait("robot/r1/sample", ClientStatus(online=True, sent=i))
    assert [p.sent for p in queued(pub)] == list(range(max(0, n - size), n))
    assert pub.dropped == max(0, n - size)


def test_states_are_kept_latest_first_and_never_dropped():
    pub = publisher(queue_size=1)
    for i in range(5):
        pub.publish_nowait("run/status", ClientStatus(online=True, sent=i), retain=True)
        pub.publish_nowait("robot/r1/sample", ClientStatus(online=True, sent=i))
    assert pub._states["run/status"].sent == 4 and list(pub._dirty) == ["run/status"]
    assert pub.dropped == 4 and pub.pending == 2


def test_publish_nowait_swallows_its_own_failures(caplog):
    pub = publisher()
    pub._queue = None  # type: ignore[assignment]  # any internal fault
    pub.publish_nowait("x", ClientStatus(online=True))
    assert "could not queue" in caplog.text


async def test_closing_an_unstarted_publisher_is_a_no_op_and_later_messages_are_ignored():
    pub = publisher()
    await pub.aclose()
    await pub.aclose()
    pub.publish_nowait("x", ClientStatus(online=True))
    assert pub.pending == 0


def test_backoff_doubles_up_to_the_cap_with_jitter_below_it():
    from random import Random

    from minimize_surprise.backoff import BackoffConfig

    backoff = Backoff(BackoffConfig(initial=1.0, max=8.0, jitter=0.5), Random(1))
    delays = [backoff.next_delay() for _ in range(8)]
    caps = [1, 2, 4, 8, 8, 8, 8, 8]
    assert all(cap / 2 <= d <= cap for d, cap in zip(delays, caps, strict=True))
    backoff.reset()
    assert backoff.next_delay() <= 1.0
    for _ in range(5000):  # a very long outage must not overflow
        backoff.next_delay()


# --------------------------------------------------------------------------- the sampler


@pytest.mark.parametrize(
    "rate, period, every", [(2, 0.1, 5), (10, 0.1, 1), (50, 0.1, 1), (3, 0.1, 3), (0, 0.1, None)]
)
def test_the_rate_becomes_a_whole_number_of_steps(rate, period, every):
    assert steps_between_samples(rate, period) == every


def test_the_sampler_sends_every_nth_step_with_the_prediction_made_for_it():
    pub = publisher()
    sampler = StepSampler(pub, "robot/r1/sample", 7, ("a", "b"), every=3)
    buffer = np.zeros(2)  # the loop reuses its buffer: the sampler must copy
    for step in range(1, 10):
        buffer[:] = (step, step)
        prediction = np.array([step + 1.0, -1.0])  # p(t+1) = t + 1 for the first sensor
        sampler.sample(step, buffer, prediction, (0.1 * step, 0.0), "front" if step == 6 else None)
    samples = queued(pub)
    assert [s.step for s in samples] == [3, 6, 9]
    for s in samples:
        assert s.evaluation == 7 and s.names == ("a", "b")
        np.testing.assert_array_equal(s.sensors, [s.step, s.step])
        # The prediction made one step earlier, for this step's readings: p(t) = t.
        np.testing.assert_array_equal(s.predictions, [s.step, -1.0])
    assert [s.reason for s in samples] == [None, "front", None]
    assert samples[1].command == pytest.approx((0.6, 0.0))


def test_after_a_lost_reading_the_sample_has_no_prediction():
    pub = publisher()
    sampler = StepSampler(pub, "robot/r1/sample", 1, ("a",), every=2)
    sampler.sample(1, np.zeros(1), np.ones(1), (0.0, 0.0), None)
    # step 2 had no reading: the loop does not call the sink
    sampler.sample(3, np.zeros(1), np.ones(1), (0.0, 0.0), None)
    sampler.sample(4, np.zeros(1), np.ones(1), (0.0, 0.0), None)
    (sample,) = queued(pub)
    assert sample.step == 4 and sample.predictions is not None
    sampler2 = StepSampler(pub, "robot/r1/sample", 2, ("a",), every=2)
    sampler2.sample(2, np.zeros(1), np.ones(1), (0.0, 0.0), None)  # step 1 was lost
    assert queued(pub)[-1].predictions is None


def test_robot_telemetry_follows_the_rate_and_summarises_evaluations():
    pub = publisher(rate_hz=0)
    robot = RobotTelemetry(pub, "r1")
    assert robot.sampler(1, ("a",), 0.1) is None
    robot.evaluation(5, requested=10, steps=3, fitness=None, failure="sensor-read: x")
    ((suffix, summary, qos),) = list(pub._queue)
    assert suffix == "robot/r1/evaluation" and qos == 1
    assert summary.fitness is None and summary.failure == "sensor-read: x"
