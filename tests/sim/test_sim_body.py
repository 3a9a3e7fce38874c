"""Simulated bodies over one shared world: lockstep and real time (simulator.body)."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from drivers.body import Body
from drivers.clock import Clock, MonotonicClock
from simulator.body import LockstepClock, SimBody, SimSwarm
from simulator.scenarios import scenario_config
from simulator.world import World

DT = 0.1


def swarm(robots: int = 3, **kwargs) -> SimSwarm:
    return SimSwarm(World(scenario_config("basic", {"robots": robots}), seed=1), **kwargs)


async def agent(body: SimBody, steps: int, command=(1.0, 1.0), frames=None, clock=None):
    """The robot agent's loop: read, drive, sleep to the next absolute deadline."""
    clock = clock or body.clock
    async with body:
        t0 = clock.now()
        for k in range(steps):
            frame = await body.read()
            if frames is not None:
                frames.append(frame)
            left, right = command(k) if callable(command) else command
            await body.drive(left, right)
            await clock.sleep_until(t0 + (k + 1) * DT)


async def bounded(*coros, timeout: float = 2.0):
    # A deadlock fails the test instead of hanging it.
    return await asyncio.wait_for(asyncio.gather(*coros), timeout)


def test_a_sim_body_is_a_body_and_its_clock_a_clock():
    s = swarm()
    body = s.body(0)
    assert isinstance(body, Body)
    assert isinstance(body.clock, LockstepClock) and isinstance(s.clock, Clock)
    assert body.sensors == s.world.sensors
    assert body.index == 0
    with pytest.raises(IndexError):
        s.body(3)


async def test_agents_run_in_lockstep():
    s = swarm(attach_all=True)
    assert s.participants == {0, 1, 2}
    frames = [[], [], []]
    await bounded(*(agent(b, 20, frames=f) for b, f in zip(s.bodies(), frames, strict=True)))
    assert s.world.steps == 20
    assert s.world.time == pytest.approx(2.0)
    for f in frames:
        assert [fr.timestamp for fr in f] == pytest.approx([k * DT for k in range(20)])
        assert all(fr.values.shape == (9,) for fr in f)
    # Leaving the context stopped the wheels and the lockstep.
    assert s.world.commands.tolist() == [[0.0, 0.0]] * 3
    assert s.participants == frozenset()


async def test_an_agent_alone_steps_the_world_alone():
    s = swarm()
    await bounded(agent(s.body(0), 5))
    assert s.world.steps == 5


async def test_the_world_steps_once_every_participant_has_driven():
    s = swarm()
    bodies = s.bodies()
    for b in bodies:
        await b.open()
    await bodies[0].drive(1.0, 1.0)
    await bodies[1].drive(1.0, 1.0)
    await bodies[0].drive(0.5, 0.5)  # a second command in the same step replaces the first
    assert s.world.steps == 0
    await bodies[2].stop()  # stop counts as this step's command
    assert s.world.steps == 1
    assert s.world.commands.tolist() == [[0.5, 0.5], [1.0, 1.0], [0.0, 0.0]]
    for b in bodies:
        await b.close()


async def test_drive_clamps_like_the_real_body():
    s = swarm(1)
    body = s.body(0)
    await body.drive(3.0, float("nan"))  # not participating: the command is only stored
    assert s.world.commands[0].tolist() == [1.0, 0.0]
    assert s.world.steps == 0


async def test_a_closed_body_does_not_hold_the_others_up():
    s = swarm()
    a, b, c = s.bodies()
    for body in (a, b, c):
        s.attach(body.index)
    await bounded(agent(a, 5), agent(b, 30), agent(c, 12))
    assert s.world.steps == 30


async def test_a_robot_sleeping_on_its_own_clock_keeps_its_command():
    # Robot 0 drives once and then waits for 1 s without driving (as between evaluations);
    # robot 1 runs its loop meanwhile.
    s = swarm(2)
    a, b = s.bodies()
    s.attach(0)
    s.attach(1)

    async def idle():
        async with a:
            await a.drive(1.0, 1.0)
            await a.clock.sleep_until(1.0)
            assert s.world.time == pytest.approx(1.0)

    start = s.world.poses[0].copy()
    await bounded(idle(), agent(b, 10))
    assert s.world.steps == 10
    moved = np.hypot(*(s.world.poses[0, :2] - start[:2]))
    assert moved == pytest.approx(0.106, abs=1e-9)  # 1 s at full speed


async def test_on_the_shared_clock_the_world_waits_for_every_participant():
    s = swarm(2)
    a, b = s.bodies()
    await a.open()
    await b.open()
    await a.drive(1.0, 1.0)
    waiting = asyncio.create_task(s.clock.sleep_until(DT))
    await asyncio.sleep(0)
    assert not waiting.done() and s.world.steps == 0
    await b.drive(1.0, 1.0)
    await asyncio.wait_for(waiting, 1.0)
    assert s.world.steps == 1
    await a.close()
    await b.close()


async def test_with_nobody_participating_the_clock_advances_the_world():
    s = swarm(1)
    await asyncio.wait_for(s.clock.sleep_until(0.5), 1.0)
    assert s.world.steps == 5
    await s.clock.sleep_until(0.2)  # already past: returns at once
    assert s.world.steps == 5


async def test_a_waiter_left_alone_is_released_when_the_last_body_closes():
    s = swarm(1)
    body = s.body(0)
    await body.open()
    await body.drive(1.0, 1.0)  # steps at once: the only participant
    waiting = asyncio.create_task(s.clock.sleep_until(0.5))
    await asyncio.sleep(0)
    assert not waiting.done()
    await body.close()
    await asyncio.wait_for(waiting, 1.0)
    assert s.world.time == pytest.approx(0.5)


async def test_a_cancelled_sleeper_is_forgotten():
    s = swarm(2)
    a, b = s.bodies()
    s.attach(0)
    s.attach(1)
    sleeper = asyncio.create_task(a.clock.sleep_until(5.0))
    await asyncio.sleep(0)
    sleeper.cancel()
    with pytest.raises(asyncio.CancelledError):
        await sleeper
    # Robot 0 no longer counts as done: the world waits for it again.
    await b.drive(1.0, 1.0)
    assert s.world.steps == 0
    await a.drive(1.0, 1.0)
    assert s.world.steps == 1


def run_swarm(order: list[int]) -> np.ndarray:
    s = SimSwarm(World(scenario_config("basic"), seed=7, record=True), attach_all=True)
    bodies = s.bodies()

    def command(i):
        rng = np.random.default_rng(i)
        table = rng.uniform(-1, 1, size=(40, 2))
        return lambda k: table[k // 5]

    async def main():
        await bounded(*(agent(bodies[i], 40, command(i)) for i in order))

    asyncio.run(main())
    return s.world.recorded_poses()


def test_lockstep_runs_repeat_exactly_whatever_the_task_order():
    forward = run_swarm(list(range(10)))
    backward = run_swarm(list(reversed(range(10))))
    assert forward.shape == (41, 10, 3)
    assert np.array_equal(forward, backward)


async def test_a_body_reads_its_sensors_in_the_order_asked():
    s = SimSwarm(World(scenario_config("gradient", {"robots": 1}), seed=0))
    body = s.body(0, ["light.1", "ground.0", "ir.f2"])
    assert body.sensors == ("light.1", "ground.0", "ir.f2")
    frame = await body.read()
    full = s.world.sensor_values(0)
    names = s.world.sensors
    assert frame.values.tolist() == [full[names.index(n)] for n in body.sensors]
    with pytest.raises(ValueError, match="sonar"):
        s.body(0, ["ir.f2", "sonar"])
    with pytest.raises(ValueError, match="twice"):
        s.body(0, ["ir.f2", "ir.f2"])


async def test_the_pose_is_the_world_pose():
    s = swarm(2)
    x, y, theta = s.body(1).pose
    assert (x, y, theta) == tuple(s.world.poses[1])
    assert all(isinstance(v, float) for v in (x, y, theta))


async def test_real_time_mode_steps_at_ten_hertz():
    s = swarm(1, realtime=True)
    body = s.body(0)
    assert isinstance(s.clock, MonotonicClock) and body.clock is s.clock
    async with s, body:
        await body.drive(1.0, 1.0)
        assert s.world.steps == 0  # driving never steps the world in real time
        t0 = s.clock.now()
        await s.clock.sleep_until(t0 + 0.35)
        steps = s.world.steps
        frame = await body.read()
    assert 2 <= steps <= 4
    assert frame.timestamp == pytest.approx(t0 + 0.35, abs=0.05)
    assert s.world.commands[0].tolist() == [0.0, 0.0]  # the body stopped on leaving
    # The stepping stopped on leaving too.
    after = s.world.steps
    await asyncio.sleep(0.15)
    assert s.world.steps == after


async def test_robots_sleeping_on_their_own_clocks_wake_in_turn():
    # A sleeps to 0.5 s; B sleeps to 0.3 s, then drives and sleeps to 1.0 s. The world runs on
    # by itself while both sleep, and lets B drive before it steps past 0.3 s.
    s = swarm(2, attach_all=True)
    a, b = s.bodies()
    woke = {}

    async def robot_a():
        async with a:
            await a.clock.sleep_until(0.5)
            woke["a"] = s.world.time

    async def robot_b():
        async with b:
            await b.clock.sleep_until(0.3)
            woke["b"] = s.world.time
            await b.drive(1.0, 1.0)
            await b.clock.sleep_until(1.0)

    start = s.world.poses[1].copy()
    await bounded(robot_a(), robot_b())
    assert woke == pytest.approx({"a": 0.5, "b": 0.3})
    assert s.world.time == pytest.approx(1.0)
    travelled = np.hypot(*(s.world.poses[1, :2] - start[:2]))
    assert travelled == pytest.approx(0.7 * 0.106, abs=1e-9)


async def test_a_long_sleep_alone_leaves_the_event_loop_responsive():
    s = swarm(1)
    ticks = 0

    async def ticker():
        nonlocal ticks
        while not sleeper.done():
            ticks += 1
            await asyncio.sleep(0)

    sleeper = asyncio.create_task(s.clock.sleep_until(300.0))
    await bounded(sleeper, ticker(), timeout=10.0)
    assert s.world.steps == 3_000
    assert ticks >= 2  # the world stepped in bursts, the loop ran in between


async def test_top_leds_are_recorded_by_world_step_for_a_synthetic_camera():
    s = swarm(2, attach_all=True)  # in lockstep from the start: neither runs ahead
    lit = []

    async def flashing(body: SimBody, on: int, off: int) -> None:
        # An agent's loop that lights its LED at step ``on`` and puts it out at step ``off``.
        async with body:
            t0 = body.clock.now()
            for k in range(8):
                if k == on:
                    await body.set_top_led(0.0, 1.0, 0.0)
                if k == off:
                    await body.set_top_led(0.0, 0.0, 0.0)
                await body.read()
                await body.drive(0.0, 0.0)
                await body.clock.sleep_until(t0 + (k + 1) * DT)
        lit.append(body.index)

    await bounded(flashing(s.body(0), 0, 5), flashing(s.body(1), 2, 9))
    assert sorted(lit) == [0, 1]
    assert s.lit_steps(0) == [(0, 5)]
    assert s.lit_steps(1) == [(2, None)]  # still lit
    assert s.top_leds[0].colour == (0.0, 1.0, 0.0)
    await s.body(1).set_top_led(2.0, float("nan"), -1.0)  # clamped, NaN off: never an error
    assert s.top_leds[-1].colour == (1.0, 0.0, 0.0)
    s.clear_top_leds()  # with a reset of the world, whose steps count anew
    assert s.lit_steps(0) == [] and s.top_leds == []
