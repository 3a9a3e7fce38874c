"""The control loop and the evaluation runner on a simulated clock: fitness, timing, trace,
safety counts, and motors at zero on every way an evaluation can end."""

from __future__ import annotations

import asyncio
import math

import numpy as np
import pytest
from agent_fakes import THYMIO, FakeBody, FakeClock, PosedBody, genome, spec

from minimize_surprise.network import NetworkPair
from minimize_surprise.wire import Evaluate, Failed, Result, genome_to_bytes
from robot_agent.bounded import finish
from robot_agent.config import LoopConfig
from robot_agent.loop import Deadlines, MissingSensorsError, sensor_index
from robot_agent.runner import EvaluationRunner, stop_motors
from robot_agent.watchdog import Watchdog

ALL_PREDEFINED = 0.25


def evaluate(network, g, steps, *, eid=1, record=False, period=0.1) -> Evaluate:
    return Evaluate(
        evaluation_id=eid,
        genome=genome_to_bytes(g),
        spec=network,
        steps=steps,
        step_period=period,
        record=record,
    )


def constant_prediction_spec(value: float = ALL_PREDEFINED):
    return spec(predefined=dict.fromkeys(THYMIO, value))


def moving(network):
    """A genome that drives straight ahead at tanh(2)."""
    return genome(network, speed_bias=2.0)


def make_runner(body, clock, **loop) -> EvaluationRunner:
    return EvaluationRunner(body, clock, loop=LoopConfig(**loop))


# --------------------------------------------------------------------------- fitness


@pytest.mark.parametrize("c, p", [(0.75, 0.25), (0.0, 1.0), (0.3, 0.3), (0.9, 0.1)])
async def test_constant_world_and_predefined_predictions_give_one_minus_the_gap(c, p):
    clock = FakeClock()
    body = FakeBody(c, clock=clock)
    network = constant_prediction_spec(p)
    outcome = await make_runner(body, clock).run(evaluate(network, genome(network), 20))
    assert isinstance(outcome, Result)
    assert outcome.fitness == pytest.approx(1 - abs(p - c), abs=1e-12)
    assert outcome.stats.steps_run == 20 and outcome.stats.overruns == 0
    assert outcome.stats.read_failures == 0 and outcome.trace is None


async def test_three_steps_by_hand_with_a_learned_and_a_predefined_prediction():
    # The experiment uses two of the body's sensors, in a different order than the body reports.
    readings = {0: (0.2, 0.1), 1: (0.4, 0.7), 2: (0.9, 0.75)}  # (ground.0, ir.f2) per step

    def values(i):
        frame = np.zeros(len(THYMIO))
        frame[THYMIO.index("ground.0")], frame[THYMIO.index("ir.f2")] = readings[i]
        return frame

    clock = FakeClock()
    body = FakeBody(values, clock=clock)
    network = spec(("ground.0", "ir.f2"), {"ground.0": 0.5})
    # Every weight zero except the predictor's output bias: p(ir.f2) = sigmoid(ln 3) = 0.75.
    g = genome(network, prediction_bias=math.log(3.0))
    outcome = await make_runner(body, clock).run(evaluate(network, g, 3, record=True))
    assert isinstance(outcome, Result)
    # Step 0 is not scored; step 1: 1 - (0.1 + 0.05) / 2 = 0.925; step 2: 1 - (0.4 + 0) / 2 = 0.8.
    assert outcome.fitness == pytest.approx((0.925 + 0.8) / 2, abs=1e-12)
    trace = outcome.trace
    assert trace is not None
    np.testing.assert_allclose(trace.array("sensors"), [readings[0], readings[1], readings[2]])
    np.testing.assert_allclose(trace.array("predictions"), [[0.5, 0.75]] * 3)


async def test_a_fresh_network_and_safety_state_for_every_evaluation():
    clock = FakeClock()
    body = FakeBody(0.5, clock=clock)
    network = spec()
    g = np.random.default_rng(3).uniform(-1, 1, NetworkPair(network, genome(network)).layout.size)
    runner = make_runner(body, clock)
    first = await runner.run(evaluate(network, g, 10, eid=1))
    second = await runner.run(evaluate(network, g, 10, eid=2))
    assert isinstance(first, Result) and isinstance(second, Result)
    # Same genome, same world, memory reset: the same fitness.
    assert first.fitness == second.fitness


# --------------------------------------------------------------------------- timing


async def test_deadlines_are_absolute_and_do_not_drift():
    clock = FakeClock(start=1000.0)
    body = FakeBody(0.5, clock=clock, work=0.037)
    network = constant_prediction_spec()
    outcome = await make_runner(body, clock).run(evaluate(network, genome(network), 1000))
    assert isinstance(outcome, Result) and outcome.stats.overruns == 0
    t0 = 1000.0
    assert clock.deadlines == [t0 + (k + 1) * 0.1 for k in range(1000)]
    # The last deadline is where 1000 periods end, not where 1000 added periods would.
    assert clock.deadlines[-1] == pytest.approx(t0 + 100.0, abs=1e-9)


async def test_the_evaluation_runs_at_the_period_the_master_sends():
    clock = FakeClock(start=0.0)
    body = FakeBody(0.5, clock=clock)
    network = constant_prediction_spec()
    runner = make_runner(body, clock)
    outcome = await runner.run(evaluate(network, genome(network), 5, period=0.2))
    assert isinstance(outcome, Result) and outcome.stats.overruns == 0
    assert clock.deadlines == pytest.approx([0.2, 0.4, 0.6, 0.8, 1.0])
    # The next evaluation brings its own period: nothing of the last one is kept.
    await runner.run(evaluate(network, genome(network), 2, period=0.125))
    assert clock.deadlines[5:] == pytest.approx([1.125, 1.25])


@pytest.mark.parametrize(
    "loop, period, steps, words",
    [
        # A Thymio's sensors update at 10 Hz: a shorter step would read the same values again.
        ({}, 0.05, 10, "period: this robot runs steps of 0.1 s to 0.22 s"),
        # The watchdog (0.25 s without a feed) would trip between two steps.
        ({}, 0.3, 10, "not 0.3 s"),
        ({"min_period": 0.2}, 0.1, 10, "period: this robot runs steps of 0.2 s"),
        ({"max_steps": 50}, 0.1, 51, "steps: this robot runs at most 50 steps"),
    ],
)
async def test_an_evaluation_the_robot_cannot_keep_is_refused_with_a_reason(
    loop, period, steps, words
):
    clock = FakeClock()
    body = FakeBody(0.5, clock=clock)
    network = constant_prediction_spec()
    outcome = await make_runner(body, clock, **loop).run(
        evaluate(network, genome(network), steps, period=period)
    )
    assert isinstance(outcome, Failed) and words in outcome.reason
    assert body.drives == [] and body.reads == 0


async def test_an_overrun_is_counted_and_the_next_step_starts_at_once_on_the_grid():
    clock = FakeClock(start=0.0)
    # Step 2 (0.2 -> 0.35) ends past its deadline 0.3; step 5 (0.5 -> 0.85) past 0.6.
    body = FakeBody(0.5, clock=clock, work=lambda i: {2: 0.15, 5: 0.35}.get(i, 0.0))
    network = constant_prediction_spec()
    outcome = await make_runner(body, clock).run(evaluate(network, genome(network), 8))
    assert isinstance(outcome, Result)
    assert outcome.stats.overruns == 2 and outcome.stats.steps_run == 8
    # No sleep after a late step: the next starts at once, in the period it is in (3 and 8), and
    # later deadlines stay on the 0.1 s grid: no drift, no burst of catch-up steps.
    assert clock.deadlines == pytest.approx([0.1, 0.2, 0.4, 0.5, 0.9, 1.0])


async def test_deadlines_class_skips_to_the_current_period():
    clock = FakeClock(start=5.0)
    deadlines = Deadlines(clock, 0.1)
    deadlines.start()
    clock.advance(0.05)
    await deadlines.wait()
    assert clock.now() == pytest.approx(5.1) and deadlines.overruns == 0
    clock.advance(0.333)  # into the period [5.4, 5.5)
    await deadlines.wait()
    assert deadlines.overruns == 1 and deadlines.deadline == pytest.approx(5.5)
    await deadlines.wait()
    assert clock.now() == pytest.approx(5.5)


async def test_a_clock_that_adds_up_its_steps_reports_no_overrun():
    # A simulated clock reaches 0.31 + 3 * 0.01 as 0.34, the deadline computes 0.33999999999999997:
    # rounding, not a late step.
    clock = FakeClock(start=31 * 0.01)
    deadlines = Deadlines(clock, 0.01)
    deadlines.start()
    for k in range(1, 41):
        clock.t = (31 + k) * 0.01  # the world's time: its steps times its dt
        await deadlines.wait()
    assert deadlines.overruns == 0
    clock.advance(0.012)  # a step 2 ms past its deadline is late
    await deadlines.wait()
    assert deadlines.overruns == 1


# --------------------------------------------------------------------------- trace and safety


async def test_record_mode_fills_the_trace_with_poses_when_the_body_has_them():
    clock = FakeClock()
    body = PosedBody(0.0, clock=clock)
    network = spec()
    g = genome(network, speed_bias=1.0, prediction_bias=0.0)
    outcome = await make_runner(body, clock).run(evaluate(network, g, 4, record=True))
    assert isinstance(outcome, Result) and outcome.trace is not None
    trace = outcome.trace
    assert trace.steps == 4 and trace.width == len(THYMIO)
    assert trace.array("sensors")[0].tolist() == [0.0] * len(THYMIO)
    np.testing.assert_allclose(trace.array("predictions"), 0.5)  # sigmoid(0)
    np.testing.assert_allclose(trace.array("actions"), math.tanh(1.0))
    # Nothing in the way: safety let it pass.
    assert np.array_equal(trace.array("commands"), trace.array("actions"))
    assert trace.safety == [""] * 4
    # The pose is taken right after each reading, before that step's drive.
    assert trace.array("poses").tolist() == [[float(k), 0.0, 0.0] for k in range(4)]


async def test_trace_without_pose_and_no_trace_without_record():
    clock = FakeClock()
    body = FakeBody(0.0, clock=clock)
    network = spec()
    runner = make_runner(body, clock)
    recorded = await runner.run(evaluate(network, genome(network), 3, record=True))
    plain = await runner.run(evaluate(network, genome(network), 3, eid=2))
    assert recorded.trace is not None and recorded.trace.poses is None
    assert plain.trace is None


async def test_safety_interventions_are_counted_by_reason_and_applied():
    clear = np.zeros(len(THYMIO))
    front = clear.copy()
    front[THYMIO.index("ir.f2")] = 0.9
    edge = clear.copy()
    edge[THYMIO.index("ground.1")] = 0.6
    frames = [clear, front, front, edge, clear]
    clock = FakeClock()
    body = FakeBody(lambda i: frames[i], clock=clock)
    network = spec()
    g = genome(network, speed_bias=3.0)  # straight ahead at tanh(3)
    outcome = await make_runner(body, clock).run(evaluate(network, g, 5, record=True))
    assert isinstance(outcome, Result)
    assert outcome.stats.interventions == {"front": 2, "ground": 1}
    ahead = math.tanh(3.0)
    assert body.drives == [(ahead, ahead), (0, 0), (0, 0), (0, 0), (ahead, ahead)]
    assert outcome.trace is not None
    assert outcome.trace.safety == ["", "front", "front", "ground", ""]
    np.testing.assert_allclose(outcome.trace.array("actions"), ahead)  # intended, not applied


async def test_a_stale_frame_is_stopped_by_safety():
    clock = FakeClock()
    body = FakeBody(0.0, clock=clock)
    original = body.read

    async def old_read():
        frame = await original()
        return type(frame)(values=frame.values, timestamp=frame.timestamp - 1.0)

    body.read = old_read  # type: ignore[method-assign]
    network = spec()
    outcome = await make_runner(body, clock).run(evaluate(network, moving(network), 3))
    assert outcome.stats.interventions == {"stale": 3}
    assert set(body.drives) == {(0.0, 0.0)}


# --------------------------------------------------------------------------- refusals


def test_sensor_index_maps_and_names_the_missing():
    assert sensor_index(THYMIO, THYMIO) is None
    assert list(sensor_index(("ground.0", "ir.f0"), THYMIO)) == [7, 0]
    with pytest.raises(MissingSensorsError) as info:
        sensor_index(("ir.f0", "force", "light.0"), THYMIO)
    assert info.value.missing == ["force", "light.0"]


async def test_an_experiment_needing_a_missing_sensor_fails_without_moving():
    clock = FakeClock()
    body = FakeBody(0.0, clock=clock)
    network = spec((*THYMIO, "force"))
    outcome = await make_runner(body, clock).run(evaluate(network, genome(network), 5))
    assert isinstance(outcome, Failed)
    assert outcome.reason.startswith("missing-sensors:") and "force" in outcome.reason
    assert body.reads == 0 and body.drives == []


async def test_a_genome_of_the_wrong_length_fails():
    clock = FakeClock()
    body = FakeBody(0.0, clock=clock)
    network = spec()
    outcome = await make_runner(body, clock).run(evaluate(network, np.zeros(3), 5))
    assert isinstance(outcome, Failed) and outcome.reason.startswith("genome:")


# --------------------------------------------------------------------------- stop paths


async def test_normal_end_leaves_the_motors_stopped():
    clock = FakeClock()
    body = FakeBody(0.0, clock=clock)
    network = spec()
    outcome = await make_runner(body, clock).run(evaluate(network, moving(network), 5))
    assert isinstance(outcome, Result)
    assert body.moved.is_set() and body.motors == (0.0, 0.0) and body.stops == 1


async def test_cancelling_an_evaluation_stops_the_motors():
    clock = FakeClock()
    body = FakeBody(0.0, clock=clock)
    network = spec()
    runner = make_runner(body, clock)
    task = asyncio.create_task(runner.run(evaluate(network, genome(network, speed_bias=2), 30_000)))
    await body.moved.wait()
    assert body.motors != (0.0, 0.0)
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    assert body.motors == (0.0, 0.0) and runner.running is None


async def test_an_exception_in_the_network_fails_the_evaluation_and_stops(monkeypatch):
    clock = FakeClock()
    body = FakeBody(0.0, clock=clock)
    network = spec()
    real_step = NetworkPair.step
    calls = []

    def broken_step(self, sensors):
        calls.append(1)
        if len(calls) == 3:
            raise FloatingPointError("boom")
        return real_step(self, sensors)

    monkeypatch.setattr(NetworkPair, "step", broken_step)
    outcome = await make_runner(body, clock).run(evaluate(network, moving(network), 9))
    assert isinstance(outcome, Failed)
    assert outcome.reason.startswith("internal:") and "boom" in outcome.reason
    assert body.moved.is_set() and body.motors == (0.0, 0.0)


async def test_a_failing_motor_write_fails_the_evaluation_and_stops():
    clock = FakeClock()
    body = FakeBody(0.0, clock=clock, drive_error=lambda i: i == 2)
    network = spec()
    outcome = await make_runner(body, clock).run(evaluate(network, moving(network), 9))
    assert isinstance(outcome, Failed) and outcome.reason.startswith("hardware:")
    assert body.motors == (0.0, 0.0) and body.stops == 1


async def test_a_hanging_read_is_bounded_and_repeated_failures_fail_with_motors_zero():
    clock = FakeClock()
    body = FakeBody(0.0, clock=clock, hang=lambda i: i >= 2)
    network = spec()
    runner = make_runner(body, clock, read_timeout=0.01, max_read_failures=3)
    outcome = await runner.run(evaluate(network, genome(network, speed_bias=2), 50))
    assert isinstance(outcome, Failed)
    assert outcome.reason.startswith("sensor-read: 3 reads in a row failed")
    assert "no reading within 0.01 s" in outcome.reason
    assert body.reads == 5 and body.motors == (0.0, 0.0)
    # The two lost steps before the last one stopped the robot while waiting.
    assert body.drives[2:] == [(0.0, 0.0), (0.0, 0.0)]


async def test_a_single_lost_reading_stops_one_step_and_drops_its_prediction():
    readings = [0.2, 0.9, 0.0, 0.4, 0.4]  # read 1 fails; each frame is constant
    clock = FakeClock()
    body = FakeBody(lambda i: [readings[i]] * len(THYMIO), clock=clock, fail=lambda i: i == 1)
    network = constant_prediction_spec(0.5)
    outcome = await make_runner(body, clock).run(evaluate(network, genome(network), 5, record=True))
    assert isinstance(outcome, Result)
    assert outcome.stats.read_failures == 1 and outcome.stats.steps_run == 5
    assert outcome.stats.interventions == {"stale": 1}
    # Scored: steps 3 and 4 against 0.4 -> 0.9. Step 2 has no prediction left to score (scoring
    # the one made for step 1 against 0.0 would give 0.5 and a mean of 0.77).
    assert outcome.fitness == pytest.approx(0.9)
    assert outcome.trace.steps == 4  # the lost step is not in the trace
    assert outcome.trace.array("sensors").shape == (4, len(THYMIO))


async def test_a_tripped_watchdog_ends_the_evaluation_and_the_next_one_rearms_it():
    clock = FakeClock()
    body = FakeBody(0.0, clock=clock)
    watchdog = Watchdog(body.stop)
    network = spec()
    runner = EvaluationRunner(body, clock, watchdog=watchdog)
    original = body.read

    async def read_then_trip():
        if body.reads == 3:
            await watchdog.trip("test")
        return await original()

    body.read = read_then_trip  # type: ignore[method-assign]
    async with watchdog:
        outcome = await runner.run(evaluate(network, genome(network, speed_bias=2), 9))
        assert isinstance(outcome, Failed) and outcome.reason == "watchdog: test"
        assert body.motors == (0.0, 0.0) and not watchdog.armed
        again = await runner.run(evaluate(network, genome(network, speed_bias=2), 2, eid=2))
        assert isinstance(again, Result) and not watchdog.tripped and not watchdog.armed


async def test_stop_motors_is_bounded_and_survives_cancellation():
    class StuckBody(FakeBody):
        async def stop(self):
            await asyncio.sleep(10)

    assert await stop_motors(StuckBody(), 0.01) is not None  # the failure is reported

    body = FakeBody()
    body.motors = (1.0, 1.0)

    async def stop_then_get_cancelled():
        await stop_motors(body, 1.0)

    task = asyncio.create_task(stop_then_get_cancelled())
    await asyncio.sleep(0)
    task.cancel()  # while the stop is in flight: it still completes, then the task is cancelled
    with pytest.raises(asyncio.CancelledError):
        await task
    assert body.motors == (0.0, 0.0)
    assert isinstance(await finish(asyncio.sleep(1), 0.001), TimeoutError)
