"""The experimenter's hand and the post-evaluation's start flash on the robot, on a simulated
clock: an escape asked for mid-evaluation starts at the next step and shows in the step
statistics and the trace; refused in the stop profile and while idle; the flash lights the top LED
at the first step and puts it out after half a second, and an LED that fails or hangs never
stops or slows the control loop."""

from __future__ import annotations

import asyncio
import logging

import pytest
from agent_fakes import FakeBody, FakeClock, genome, spec

from minimize_surprise.errors import HardwareError
from minimize_surprise.safety import REASON_ESCAPE, REASON_EXPERIMENTER, SafetyConfig
from minimize_surprise.wire import (
    ESCAPE_REFUSED_IDLE,
    ESCAPE_REFUSED_PROFILE,
    Evaluate,
    Result,
    genome_to_bytes,
)
from robot_agent.config import LoopConfig
from robot_agent.led import FLASH_COLOUR, LED_TIMEOUT, OFF
from robot_agent.runner import EvaluationRunner


def evaluate(steps: int, *, record: bool = False, post: bool = False) -> Evaluate:
    network = spec()
    return Evaluate(
        evaluation_id=9,
        genome=genome_to_bytes(genome(network, speed_bias=2.0)),  # straight ahead
        spec=network,
        steps=steps,
        step_period=0.1,
        record=record,
        post_evaluation=post,
    )


def runner_for(body: FakeBody, clock: FakeClock, profile: str = "escape") -> EvaluationRunner:
    return EvaluationRunner(
        body, clock, loop=LoopConfig(), safety=SafetyConfig(profile=profile), safety_seed=4
    )


# --------------------------------------------------------------------------- the escape


async def test_an_escape_asked_for_mid_evaluation_starts_at_the_next_step():
    clock = FakeClock()
    replies = []

    def frame(i: int) -> float:
        if i == 10:  # while step 11 reads: the request arrives between two steps
            replies.append(runner.request_escape(3))
        return 0.0  # nothing in sight, a dark floor: no rule of the layer's own fires

    body = FakeBody(frame, clock=clock)
    runner = runner_for(body, clock)
    outcome = await runner.run(evaluate(120, record=True))
    assert isinstance(outcome, Result)
    (reply,) = replies
    assert reply.accepted and reply.seq == 3 and reply.evaluation_id == 9
    # Counted once like any rule, its manoeuvre's further steps as escape.
    counts = outcome.stats.interventions
    assert counts[REASON_EXPERIMENTER] == 1 and counts[REASON_ESCAPE] >= 29 + 24
    assert outcome.trace is not None
    safety = outcome.trace.safety
    assert safety[:10] == [""] * 10 and safety[10] == REASON_EXPERIMENTER
    assert safety[11:40] == [REASON_ESCAPE] * 29
    commands = outcome.trace.array("commands")
    assert commands[10:40].tolist() == [[-1.0, -1.0]] * 30  # the reverse, whatever the network
    assert runner.loop.escapes_started == [11] and not runner.loop.escape_requested
    assert body.motors == (0.0, 0.0)


async def test_an_escape_is_refused_in_the_stop_profile_and_while_idle():
    clock = FakeClock()
    replies = []

    def frame(i: int) -> float:
        if i == 3:
            replies.append(runner.request_escape(1))
        return 0.0

    body = FakeBody(frame, clock=clock)
    runner = runner_for(body, clock, profile="stop")
    outcome = await runner.run(evaluate(10))
    assert isinstance(outcome, Result) and REASON_EXPERIMENTER not in outcome.stats.interventions
    (refused,) = replies
    assert not refused.accepted and refused.reason.startswith(f"{ESCAPE_REFUSED_PROFILE}: ")
    assert "'stop' profile" in refused.reason

    idle = runner_for(FakeBody(0.0, clock=clock), clock).request_escape(2)
    assert not idle.accepted and idle.reason.startswith(f"{ESCAPE_REFUSED_IDLE}: ")


async def test_an_escape_never_carries_over_into_the_next_evaluation():
    clock = FakeClock()
    body = FakeBody(0.0, clock=clock)
    runner = runner_for(body, clock)
    runner.loop.escape_requested = True  # left over, as if asked as the last step ended
    outcome = await runner.run(evaluate(5))
    assert isinstance(outcome, Result) and REASON_EXPERIMENTER not in outcome.stats.interventions


# --------------------------------------------------------------------------- the flash


class LitBody(FakeBody):
    """A fake body with a top LED: every colour it is set to, with the clock's time."""

    def __init__(self, *args: object, blocking: bool = True, led=None, **kwargs: object) -> None:
        super().__init__(*args, **kwargs)  # type: ignore[arg-type]
        self.blocking = blocking  # type: ignore[misc]
        self.leds: list[tuple[tuple[float, float, float], float]] = []
        self._led = led

    async def set_top_led(self, red: float, green: float, blue: float) -> None:
        if self._led is not None:
            await self._led(len(self.leds))
        assert self.clock is not None
        self.leds.append(((red, green, blue), self.clock.now()))


@pytest.mark.parametrize("blocking", [False, True], ids=["simulated", "waits-for-io"])
async def test_a_post_evaluation_flashes_the_top_led_for_half_a_second(blocking):
    clock = FakeClock(start=100.0)
    body = LitBody(0.0, clock=clock, blocking=blocking)
    outcome = await runner_for(body, clock).run(evaluate(20, post=True))
    assert isinstance(outcome, Result) and outcome.stats.steps_run == 20
    assert [colour for colour, _ in body.leds] == [FLASH_COLOUR, OFF]
    # On at the first step, off at the step that starts 0.5 s later (step 6 of 0.1 s). A body
    # that waits for I/O is written to in a task of its own, which runs when the step first
    # waits: here only at its sleep (this clock jumps), on a robot at the step's first read.
    late = 0.1 if blocking else 0.0
    assert [at for _, at in body.leds] == pytest.approx([100.0 + late, 100.5 + late])


async def test_an_ordinary_evaluation_does_not_flash_and_a_short_one_ends_dark():
    clock = FakeClock()
    body = LitBody(0.0, clock=clock, blocking=False)
    await runner_for(body, clock).run(evaluate(10))
    assert body.leds == []
    await runner_for(body, clock).run(evaluate(2, post=True))  # over before the time is up
    assert [colour for colour, _ in body.leds] == [FLASH_COLOUR, OFF]


async def test_a_failing_led_is_logged_once_and_the_evaluation_runs_on(caplog):
    clock = FakeClock()

    async def broken(_: int) -> None:
        raise HardwareError("leds.top: no such variable")

    body = LitBody(0.0, clock=clock, led=broken)
    with caplog.at_level(logging.WARNING, logger="robot_agent.led"):
        outcome = await runner_for(body, clock).run(evaluate(20, post=True))
    assert isinstance(outcome, Result) and outcome.stats.steps_run == 20
    assert outcome.stats.overruns == 0 and body.motors == (0.0, 0.0)
    lines = [r.getMessage() for r in caplog.records if "start flash" in r.getMessage()]
    assert len(lines) == 1 and "no such variable" in lines[0]


async def test_a_hanging_led_holds_up_neither_a_step_nor_the_end():
    clock = FakeClock()

    async def hang(_: int) -> None:
        await asyncio.get_running_loop().create_future()  # never answers

    body = LitBody(0.0, clock=clock, led=hang)
    started = asyncio.get_running_loop().time()
    outcome = await runner_for(body, clock).run(evaluate(20, post=True))
    assert isinstance(outcome, Result) and outcome.stats.steps_run == 20
    assert outcome.stats.overruns == 0 and body.motors == (0.0, 0.0)
    # The on and off writes time out one after the other; the end waits for them, bounded.
    assert asyncio.get_running_loop().time() - started < 4 * LED_TIMEOUT + 1.0
