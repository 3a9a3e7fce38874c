"""A simulated Thymio behind the fake asebamedulla: one robot of a real-time world on D-Bus.

:class:`SimThymio` is the fake medulla's :class:`~standins.fake_medulla.ThymioModel` over robot
``index`` of a :class:`SignallingWorld`: the world's normalised sensor values become the raw
readings the real Thymio reports, and the motor targets written over D-Bus become the robot's
normalised wheel command (the exact inverse of :mod:`drivers.thymio`'s scaling):

- ``prox.horizontal``: ``round(ir * 4500)`` for ``ir.f0 .. ir.b1``, clipped to 0..4500;
- ``prox.ground.reflected`` and ``prox.ground.delta``: ``round(ground * 1023)`` (``ambiant`` 0);
- ``motor.left.target`` / ``motor.right.target``: ``target / speed_scale`` clamped to [-1, 1].

:class:`SimMedulla` adds what the real medulla does and the plain fake does not: a
``GetVariable`` of a sensor variable answers only after the robot's next sensor update, here the
world's next step (10 Hz), so an agent's control loop falls into step with the world as it does
with a real robot. The wait is bounded by :data:`STEP_WAIT_TIMEOUT`, so no call hangs forever
when the world stalls or stops.

:func:`serve_sim_thymio` serves one robot on one bus, like
:func:`~standins.fake_medulla.serve_fake_medulla` does for a plain fake. This module imports
``dbus_fast`` at the top, as :mod:`standins.fake_medulla` does.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
from collections.abc import Callable
from typing import Any

import numpy as np

from drivers.config import SPEED_SCALE
from drivers.thymio import (
    FWVERSION,
    GROUND_MAX,
    IR_MAX,
    LEDS_TOP,
    PROX_HORIZONTAL,
    VBAT,
    VBAT_SCALE,
)
from minimize_surprise.sensors import GROUND_SENSORS, IR_SENSORS
from simulator.battery import SimBattery
from simulator.scenarios import WorldConfig
from simulator.world import World
from standins.fake_medulla import GROUND_VARIABLES, FakeMedulla, serve_fake_medulla

__all__ = [
    "SENSOR_VARIABLES",
    "SIM_FWVERSION",
    "STEP_WAIT_TIMEOUT",
    "SignallingWorld",
    "SimMedulla",
    "SimThymio",
    "serve_sim_thymio",
]

#: What the simulated Thymio answers for ``_fwversion``: the version of a current Thymio II
#: firmware (14) in ``[0]``; its ``[1]`` is 0, as Playground's.
SIM_FWVERSION = (14, 0)
#: The variables whose ``GetVariable`` waits for the next sensor update, as on the robot.
SENSOR_VARIABLES = frozenset({PROX_HORIZONTAL, *GROUND_VARIABLES})
#: Seconds a sensor read waits for the world's next step at most (five 10 Hz steps). Longer than
#: the driver's own call timeout (0.25 s), so a client sees a stalled world as a stalled robot,
#: yet every call on the service side ends even when the world never steps again.
STEP_WAIT_TIMEOUT = 0.5
#: Calls kept in :attr:`SimMedulla.calls`: a served robot answers about 40 calls a second for
#: hours, so the record is a bounded window of the latest calls instead of a growing list.
CALL_LOG_SIZE = 1000


class SignallingWorld(World):
    """A :class:`World` that calls its step listeners after every step.

    The real-time :class:`~simulator.body.SimSwarm` steps it; the listeners (one per served robot)
    release the sensor reads waiting for that step.
    """

    def __init__(self, config: WorldConfig, seed: int = 0, *, record: bool = False) -> None:
        self._listeners: list[Callable[[], None]] = []
        super().__init__(config, seed, record=record)

    def add_step_listener(self, listener: Callable[[], None]) -> None:
        """Call ``listener()`` after every following step."""
        self._listeners.append(listener)

    def remove_step_listener(self, listener: Callable[[], None]) -> None:
        """Stop calling ``listener`` (idempotent)."""
        with contextlib.suppress(ValueError):
            self._listeners.remove(listener)

    def step(self) -> None:
        """Advance the world by one step, then call the step listeners."""
        super().step()
        for listener in tuple(self._listeners):
            listener()


class SimThymio:
    """Robot ``index`` of ``world`` as a :class:`~standins.fake_medulla.ThymioModel`.

    ``speed_scale`` is the motor target of a normalised speed of 1, as in the agent's
    :class:`~drivers.config.ThymioConfig` (the same default, ``drivers.config.SPEED_SCALE``).
    See the module docstring for the conversions. :meth:`next_update` waits for the world's
    next step; :meth:`release` ends every such wait for good (on shutdown).
    """

    def __init__(
        self,
        world: SignallingWorld,
        index: int,
        *,
        speed_scale: float = SPEED_SCALE,
        battery: SimBattery | None = None,
    ) -> None:
        if not 0 <= index < world.n_robots:
            raise IndexError(f"robot {index} is not in a world of {world.n_robots} robots")
        if not speed_scale > 0:
            raise ValueError("speed_scale must be positive")
        missing = [s for s in IR_SENSORS + GROUND_SENSORS if s not in world.sensors]
        if missing:
            raise ValueError(f"a simulated Thymio needs the sensors {', '.join(missing)}")
        self.world = world
        self.index = index
        self.speed_scale = float(speed_scale)
        #: A current Thymio II firmware's version (not measured on a lab robot here; docs/thymio.md)
        self.variables: dict[str, list[int]] = {FWVERSION: list(SIM_FWVERSION)}
        #: Its battery, read as a real Thymio's ``_vbat`` (two halves of volts x 397.8); it
        #: drains while the motors are commanded (by nothing, with SimBattery's default).
        self.battery = battery if battery is not None else SimBattery()
        self._show_battery()
        #: The latest motor targets received, in motor units.
        self.targets: dict[str, int] = {"left": 0, "right": 0}
        #: Every ``leds.top`` written, as ``(world step, [red, green, blue])`` (0..32): when a
        #: camera over the world would have seen it change.
        self.led_log: list[tuple[int, list[int]]] = []
        self._ir = np.array([world.sensors.index(s) for s in IR_SENSORS], dtype=np.intp)
        self._ground = np.array([world.sensors.index(s) for s in GROUND_SENSORS], dtype=np.intp)
        self._released = False
        self._update = asyncio.Event()
        world.add_step_listener(self._on_step)

    # -- ThymioModel ------------------------------------------------------------------------------

    def prox_horizontal(self) -> list[int]:
        """The 7 raw horizontal IR values of the current step: ``round(ir * 4500)``."""
        values = self.world.sensor_matrix()[self.index, self._ir]
        return [int(v) for v in np.clip(np.rint(values * IR_MAX), 0, IR_MAX)]

    def ground(self, variable: str) -> list[int]:
        """The 2 raw ground values: ``round(ground * 1023)``; ``prox.ground.ambiant`` is dark."""
        if variable == "prox.ground.ambiant":
            return [0, 0]  # no ambient light is simulated
        values = self.world.sensor_matrix()[self.index, self._ground]
        return [int(v) for v in np.clip(np.rint(values * GROUND_MAX), 0, GROUND_MAX)]

    def set_target(self, side: str, value: int) -> None:
        """A new target for one wheel; the robot's command is both targets / ``speed_scale``."""
        self.targets[side] = int(value)
        # World.set_command clamps to [-1, 1], as the Thymio clamps its targets.
        self.world.set_command(
            self.index,
            self.targets["left"] / self.speed_scale,
            self.targets["right"] / self.speed_scale,
        )

    def set_top_led(self, values: list[int]) -> None:
        """Record a ``leds.top`` write with the world's step in :attr:`led_log`."""
        self.led_log.append((self.world.steps, list(values)))

    # -- sensor updates ---------------------------------------------------------------------------

    async def next_update(self) -> None:
        """Return after the world's next step, or after :data:`STEP_WAIT_TIMEOUT` at most."""
        if self._released:
            return
        update = self._update
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(STEP_WAIT_TIMEOUT):
                await update.wait()

    def release(self) -> None:
        """End every wait of :meth:`next_update`, now and later, and stop listening to the world."""
        self._released = True
        self.world.remove_step_listener(self._on_step)
        self._on_step()

    def _show_battery(self) -> None:
        half = round(self.battery.volts * VBAT_SCALE / 2)
        self.variables[VBAT] = [half, half]

    def _on_step(self) -> None:
        if self.targets["left"] or self.targets["right"]:
            self.battery.step()
            self._show_battery()
        # A fresh event per step: the waiters of this step wake, later reads wait for the next.
        update, self._update = self._update, asyncio.Event()
        update.set()


class SimMedulla(FakeMedulla):
    """The fake medulla for a :class:`SimThymio`: sensor reads answer after the next step.

    Everything else is :class:`~standins.fake_medulla.FakeMedulla`'s; :attr:`calls` keeps only
    the latest :data:`CALL_LOG_SIZE` calls.
    """

    model: SimThymio

    def __init__(self, model: SimThymio, node: str = "thymio-II") -> None:
        super().__init__(model, node)
        # A real Thymio's firmware declares them (Playground's does not).
        self.native.update((VBAT, LEDS_TOP))
        self.calls: Any = collections.deque(maxlen=CALL_LOG_SIZE)
        self._pending = 0
        self._no_pending = asyncio.Event()
        self._no_pending.set()

    @property
    def pending(self) -> int:
        """How many ``GetVariable`` calls are not answered yet (waiting for a step or the robot)."""
        return self._pending

    async def get_variable(self, node: str, variable: str) -> list[int]:
        """``GetVariable``: a sensor variable of this node waits for the world's next step."""
        self._pending += 1
        self._no_pending.clear()
        try:
            # Unknown nodes and variables are left to the base class, which fails them at once.
            if variable in SENSOR_VARIABLES and node == self.node:
                await self.model.next_update()
            return await super().get_variable(node, variable)
        finally:
            self._pending -= 1
            if not self._pending:
                self._no_pending.set()

    def close(self) -> None:
        """Release every waiting ``GetVariable`` (the sensor reads with an error, as the base)."""
        self.model.release()
        super().close()

    async def wait_idle(self) -> None:
        """Return once no ``GetVariable`` is pending, including those waiting for a step."""
        await self._no_pending.wait()
        await super().wait_idle()


def serve_sim_thymio(
    address: str, model: SimThymio, *, node: str = "thymio-II"
) -> contextlib.AbstractAsyncContextManager[FakeMedulla]:
    """Serve a :class:`SimMedulla` for ``model`` on the bus at ``address`` during the context."""
    return serve_fake_medulla(address, model, node=node, medulla=SimMedulla)
