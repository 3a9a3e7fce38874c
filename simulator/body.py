"""Simulated robots: the drivers' :class:`~drivers.body.Body` over one shared :class:`World`.

A :class:`SimSwarm` owns the world and hands out one :class:`SimBody` per robot. It runs in one of
two modes:

* **Lockstep** (the default): time is the world's time. ``drive`` and ``stop`` record the robot's
  command for the current step without blocking; the world takes its step as soon as every
  *participating* body has submitted a command since the last step; ``clock.sleep_until(t)``
  waits (on futures, never polling) until the world's time reaches ``t``. A body participates
  while it is open (``async with body`` or :meth:`SimBody.open`) or explicitly attached with
  :meth:`SimSwarm.attach` (or ``SimSwarm(..., attach_all=True)``); closing or detaching it lets
  the others go on without it. Attach every robot before the agents start: an agent whose body
  is the only one open so far steps the world alone. With nobody participating,
  ``sleep_until`` advances the world by itself, so a lone waiter never deadlocks. Runs repeat
  exactly for a seed, whatever the order the agents' tasks run in.
* **Real time** (``realtime=True``): a background task started by :meth:`SimSwarm.start` (or
  ``async with swarm``) steps the world every ``dt`` seconds of wall-clock time with the latest
  commands; the clock is a :class:`~drivers.clock.MonotonicClock`.

The control loop of an agent is expected to look like::

    t0 = clock.now()
    for k in range(steps):
        frame = await body.read()
        await body.drive(left, right)
        await clock.sleep_until(t0 + (k + 1) * dt)

Give each agent its body's own clock (:attr:`SimBody.clock`): waiting on it also counts as
"done with this step, keep my last command", so an agent that sleeps without driving (for
example while waiting for its next evaluation) does not hold the others up. The shared
:attr:`SimSwarm.clock` has no such meaning.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Sequence
from types import TracebackType
from typing import NamedTuple, Self

import numpy as np

from drivers.body import Body, SensorFrame, clamp_unit, led_level
from drivers.clock import Clock, MonotonicClock
from simulator.battery import SimBattery
from simulator.world import World

# Deadlines computed as t0 + k * dt may land a rounding error above the world time steps * dt.
_TIME_SLACK = 1e-9
# Steps taken in one go at most before yielding to the event loop (when every robot sleeps).
_BURST = 1000


class LockstepClock(Clock):
    """The world's time; ``sleep_until`` waits for the swarm to step the world that far.

    A clock bound to a robot (``index`` given, see :attr:`SimBody.clock`) also marks that robot
    as done with the current step while it waits.
    """

    def __init__(self, swarm: SimSwarm, index: int | None = None) -> None:
        self._swarm = swarm
        self._index = index

    def now(self) -> float:
        """World time in seconds."""
        return self._swarm.world.time

    async def sleep_until(self, deadline: float) -> None:
        """Return once the world's time has reached ``deadline``."""
        await self._swarm._wait_until(deadline, self._index)


class _Waiter:
    # One task in ``sleep_until``; ``index`` is the robot it stands for while it sleeps on its
    # robot's clock (None on the shared clock, and once woken).
    __slots__ = ("deadline", "future", "index")

    def __init__(self, deadline: float, future: asyncio.Future[None], index: int | None) -> None:
        self.deadline = deadline
        self.future = future
        self.index = index


class LedChange(NamedTuple):
    """A robot's top LED set to ``colour`` (red, green, blue in [0, 1]; all 0 is off), showing
    from world step ``step`` on (steps since the world's last reset, as its recording counts)."""

    step: int
    robot: int
    colour: tuple[float, float, float]


class SimSwarm:
    """One shared :class:`World` and the bodies of its robots (see the module docstring).

    ``attach_all=True`` makes every robot a participant from the start (see :meth:`attach`).
    """

    def __init__(self, world: World, *, realtime: bool = False, attach_all: bool = False) -> None:
        self.world = world
        self.realtime = realtime
        # ``attach_all``: every robot participates from the start, so that no agent runs ahead
        # while the others are still starting; each leaves when its body closes.
        self._participants: set[int] = set(range(world.n_robots)) if attach_all else set()
        self._submitted: set[int] = set()
        self._sleeping: dict[int, int] = {}
        self._waiters: list[_Waiter] = []
        self._advance_pending = False
        self._task: asyncio.Task[None] | None = None
        self._clock: Clock = MonotonicClock() if realtime else LockstepClock(self)
        #: every change of a robot's top LED, in order, since :meth:`clear_top_leds` (a synthetic
        #: camera draws them; :meth:`lit_steps` reads them per robot)
        self.top_leds: list[LedChange] = []

    # --- bodies and participation --------------------------------------------------------------

    @property
    def clock(self) -> Clock:
        """The swarm's clock: world time in lockstep, wall-clock time in real time."""
        return self._clock

    def body(self, index: int, sensors: Sequence[str] | None = None) -> SimBody:
        """The body of robot ``index`` (0 <= index < robots), reading ``sensors`` (a subset of
        the world's, in any order; default: all the world's, in its order)."""
        if not 0 <= index < self.world.n_robots:
            raise IndexError(f"robot {index} is not in a world of {self.world.n_robots} robots")
        return SimBody(self, index, sensors)

    def bodies(self, sensors: Sequence[str] | None = None) -> list[SimBody]:
        """One body per robot, in robot order."""
        return [self.body(i, sensors) for i in range(self.world.n_robots)]

    @property
    def participants(self) -> frozenset[int]:
        """Robots whose commands the world waits for in lockstep."""
        return frozenset(self._participants)

    def attach(self, index: int) -> None:
        """Make the world wait for robot ``index``'s command at every step (idempotent).

        Attach every robot before starting the agents so that none runs ahead while the others
        are still starting.
        """
        self._participants.add(index)

    def detach(self, index: int) -> None:
        """Stop waiting for robot ``index`` (idempotent); its last command stays in force."""
        self._participants.discard(index)
        self._submitted.discard(index)
        self._advance()

    def submit(self, index: int, left: float, right: float) -> None:
        """Set robot ``index``'s command for the current step (clamped); in lockstep, the world
        steps once every participant has submitted."""
        self.world.set_command(index, left, right)
        if self.realtime:
            return
        if index in self._participants:
            self._submitted.add(index)
            self._advance()

    # --- top LEDs ------------------------------------------------------------------------------

    def set_top_led(self, index: int, colour: tuple[float, float, float]) -> None:
        """Robot ``index``'s top LED shows ``colour`` from the world's current step on."""
        self.top_leds.append(LedChange(self.world.steps, index, colour))

    def clear_top_leds(self) -> None:
        """Forget the LED changes so far: call it with a world reset, whose steps count anew."""
        self.top_leds.clear()

    def lit_steps(self, index: int) -> list[tuple[int, int | None]]:
        """The world steps in which robot ``index``'s top LED was lit, as ``(first, end)`` spans
        (``end`` excluded; None: still lit)."""
        spans: list[tuple[int, int | None]] = []
        lit_from: int | None = None
        for change in self.top_leds:
            if change.robot != index:
                continue
            on = any(change.colour)
            if on and lit_from is None:
                lit_from = change.step
            elif not on and lit_from is not None:
                if change.step > lit_from:  # lit and off within one step: never seen
                    spans.append((lit_from, change.step))
                lit_from = None
        if lit_from is not None:
            spans.append((lit_from, None))
        return spans

    # --- lockstep ------------------------------------------------------------------------------

    def _advance(self) -> None:
        # Step while nobody is waited for: every participant has submitted or sleeps on its own
        # clock (with no participants: while anyone sleeps). Once a sleeper wakes, stepping on
        # is left to a callback, so that the woken tasks run first (they may drive, attach or
        # leave); long runs of steps (everyone asleep) also yield to the event loop now and then.
        self._advance_pending = False
        if self.realtime:
            return
        for _ in range(_BURST):
            if not self._may_step():
                return
            self._submitted.clear()
            self.world.step()
            if self._wake():
                break
        if self._may_step():
            self._advance_soon()

    def _may_step(self) -> bool:
        if not self._participants:
            return bool(self._waiters)
        done = self._submitted | {i for i, n in self._sleeping.items() if n}
        return self._participants <= done

    def _advance_soon(self) -> None:
        if self._advance_pending:
            return
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:  # no event loop, so nobody can be waiting
            return
        self._advance_pending = True
        loop.call_soon(self._advance)

    def _wake(self) -> bool:
        # Release the sleepers whose deadline the world has reached; whether there were any.
        now = self.world.time + _TIME_SLACK
        if not any(w.deadline <= now for w in self._waiters):
            return False
        due = [w for w in self._waiters if w.deadline <= now]
        self._waiters = [w for w in self._waiters if w.deadline > now]
        for w in due:
            self._unsleep(w)
            if not w.future.done():
                w.future.set_result(None)
        return True

    def _unsleep(self, waiter: _Waiter) -> None:
        if waiter.index is not None:
            self._sleeping[waiter.index] -= 1
            waiter.index = None

    async def _wait_until(self, deadline: float, index: int | None) -> None:
        if self.world.time + _TIME_SLACK >= deadline:
            return
        fut: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        if index is not None and index in self._participants:
            # Sleeping on its own clock, a robot is done with every step until it wakes.
            self._sleeping[index] = self._sleeping.get(index, 0) + 1
        else:
            index = None
        waiter = _Waiter(deadline, fut, index)
        self._waiters.append(waiter)
        try:
            self._advance()
            await fut
        finally:
            # Cancelled while waiting: forget the waiter (both are no-ops once it was woken).
            self._unsleep(waiter)
            if waiter in self._waiters:
                self._waiters.remove(waiter)

    # --- real time -----------------------------------------------------------------------------

    async def start(self) -> None:
        """Real time only: start stepping the world every ``dt`` seconds of wall-clock time."""
        if not self.realtime or self._task is not None:
            return
        self._task = asyncio.create_task(self._run_realtime(), name="sim-world")

    async def stop(self) -> None:
        """Stop the real-time stepping (idempotent)."""
        task, self._task = self._task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    async def _run_realtime(self) -> None:
        clock = self._clock
        dt = self.world.config.dt
        deadline = clock.now()
        while True:
            deadline += dt
            await clock.sleep_until(deadline)
            self.world.step()
            # After a stall (a busy event loop) resume the 10 Hz pace from now instead of
            # catching up with a burst of steps.
            if clock.now() - deadline > dt:
                deadline = clock.now()

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.stop()


class SimBody(Body):
    """Robot ``index`` of a :class:`SimSwarm`, behind the drivers' ``Body`` interface."""

    #: read, drive and stop compute their answer at once (no I/O): no timeouts needed.
    blocking = False

    def __init__(self, swarm: SimSwarm, index: int, sensors: Sequence[str] | None = None) -> None:
        self._swarm = swarm
        self._index = index
        world_sensors = swarm.world.sensors
        if sensors is None:
            sensors = world_sensors
        missing = [s for s in sensors if s not in world_sensors]
        if missing:
            raise ValueError(
                f"the simulated robots do not carry {', '.join(missing)}; "
                f"they carry {', '.join(world_sensors)}"
            )
        if len(set(sensors)) != len(sensors):
            raise ValueError("a sensor is listed twice")
        self._sensors = tuple(sensors)
        self._columns = np.array([world_sensors.index(s) for s in self._sensors], dtype=np.intp)
        self._clock: Clock = swarm.clock if swarm.realtime else LockstepClock(swarm, index)
        #: the robot's battery; None: it reports none, as Aseba Playground's Thymio
        self.battery: SimBattery | None = None
        #: each wheel's real speed per commanded speed (left, right): a real robot's motors differ
        #: by a few per cent (``surprise-master calibrate`` measures it; docs/fleet.md)
        self.wheel_scale: tuple[float, float] = (1.0, 1.0)

    @property
    def sensors(self) -> tuple[str, ...]:
        """Names of the values :meth:`read` returns, in that order."""
        return self._sensors

    @property
    def index(self) -> int:
        """This robot's index in the world."""
        return self._index

    @property
    def clock(self) -> Clock:
        """The clock this robot's control loop should use (see the module docstring)."""
        return self._clock

    @property
    def pose(self) -> tuple[float, float, float]:
        """``(x, y, theta)`` of this robot now, in metres and radians (for traces)."""
        x, y, theta = self._swarm.world.poses[self._index]
        return float(x), float(y), float(theta)

    async def open(self) -> None:
        """Join the lockstep: the world waits for this robot's command at every step."""
        self._swarm.attach(self._index)

    async def close(self) -> None:
        """Stop the wheels and leave the lockstep; idempotent."""
        self._swarm.world.set_command(self._index, 0.0, 0.0)
        self._swarm.detach(self._index)

    async def read(self) -> SensorFrame:
        """The sensor values of the current step (never blocks)."""
        values = self._swarm.world.sensor_matrix()[self._index, self._columns]
        return SensorFrame(values=values, timestamp=self._clock.now())

    async def read_battery(self) -> float | None:
        """The simulated battery's voltage, None without one."""
        return None if self.battery is None else round(self.battery.volts, 3)

    async def drive(self, left: float, right: float) -> None:
        """Set the wheel speeds for this step, normalised to [-1, 1] (clamped; NaN is 0)."""
        if self.battery is not None:
            self.battery.step()
        scale_left, scale_right = self.wheel_scale
        self._swarm.submit(
            self._index, clamp_unit(left) * scale_left, clamp_unit(right) * scale_right
        )

    async def stop(self) -> None:
        """Set both wheel speeds to zero; counts as this step's command."""
        self._swarm.submit(self._index, 0.0, 0.0)

    async def set_top_led(self, red: float, green: float, blue: float) -> None:
        """Light the top LED (recorded in :attr:`SimSwarm.top_leds` at the current step)."""
        self._swarm.set_top_led(self._index, (led_level(red), led_level(green), led_level(blue)))
