"""Robots join a master that a flood of silent connections from one address keeps busy.

Issue 22 measured 128 clients from one address that connect and say nothing: they held every
handshake place of the master (``max_pending_connections``, 64) and a robot never got back in (0
of 251 attempts). Here the same flood runs against a real master over loopback TCP, each silent
connection reopened the moment the master closes it, while a scripted robot joins and leaves again
and again from another address, as every robot of a lab has its own.

A robot from the flood's own address gets in when its Hello is there by the time the master
accepts its connection (``test_master_server``); here it would share the master's event loop,
which accepts before the robot has written anything, so ``benchmarks/hostile_connections.py``
measures that case with separate processes.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator

from master_helpers import SECRET, master_config

from master_service import Master
from master_service.config import DEFAULT_HANDSHAKE_TIMEOUT, DEFAULT_MAX_PENDING_CONNECTIONS
from standins.scripted_robots import ScriptedRobot

#: Silent clients, as measured in issue 22: twice the master's handshake places.
FLOOD_CLIENTS = 128
#: Where the flood comes from; the robot of a lab comes from another address of loopback.
FLOOD_ADDRESS = "127.0.0.1"
LAB_ROBOT_ADDRESS = "127.0.0.2"
#: Joins the robot attempts; at least this share must succeed.
JOIN_ATTEMPTS = 40
REQUIRED_SHARE = 0.95
#: Far above a join's time on a loaded machine: a join slower than this counts as failed.
JOIN_TIMEOUT = 5.0


class Flood:
    """``clients`` silent connections from ``FLOOD_ADDRESS``, each reopened as soon as the master
    closes it, until :meth:`stop`."""

    def __init__(self, port: int, clients: int) -> None:
        self.port = port
        self.opened = 0
        self._stop = asyncio.Event()
        self._tasks = [asyncio.create_task(self._client()) for _ in range(clients)]

    async def _client(self) -> None:
        while not self._stop.is_set():
            try:
                reader, writer = await asyncio.open_connection(
                    "127.0.0.1", self.port, local_addr=(FLOOD_ADDRESS, 0)
                )
            except OSError:
                await asyncio.sleep(0.01)  # a full backlog: try again, as a script would
                continue
            self.opened += 1
            closed = asyncio.create_task(reader.read())
            stop = asyncio.create_task(self._stop.wait())
            await asyncio.wait({closed, stop}, return_when=asyncio.FIRST_COMPLETED)
            for task in (closed, stop):
                task.cancel()
            await asyncio.gather(closed, stop, return_exceptions=True)
            writer.transport.abort()

    async def stop(self) -> None:
        """End the flood and close its connections."""
        self._stop.set()
        await asyncio.gather(*self._tasks)


@contextlib.asynccontextmanager
async def flooded_master(tmp_path) -> AsyncIterator[Master]:
    """A master with the default handshake places and deadline, its places all taken by the
    flood before it is handed out."""
    config = master_config(
        max_pending_connections=DEFAULT_MAX_PENDING_CONNECTIONS,
        handshake_timeout=DEFAULT_HANDSHAKE_TIMEOUT,
    )
    async with Master(config, tmp_path / "run", secret=SECRET) as master:
        flood = Flood(master.port, FLOOD_CLIENTS)
        try:
            async with asyncio.timeout(10.0):
                while master.server.pending_connections < DEFAULT_MAX_PENDING_CONNECTIONS:
                    await asyncio.sleep(0.01)
            yield master
        finally:
            await flood.stop()
        assert flood.opened > FLOOD_CLIENTS  # the master closed some, and they came back


async def joins(robot: ScriptedRobot) -> int:
    """How many of ``JOIN_ATTEMPTS`` joins (connect, welcome, bye) succeed."""
    joined = 0
    for _ in range(JOIN_ATTEMPTS):
        try:
            async with asyncio.timeout(JOIN_TIMEOUT):
                await robot.connect()
        except (OSError, EOFError, TimeoutError):  # refused, reset, closed, too slow
            continue
        joined += 1
        await robot.close()
    return joined


async def test_a_robot_joins_during_a_flood_of_silent_connections_from_another_address(
    tmp_path,
):
    async with flooded_master(tmp_path) as master:
        robot = ScriptedRobot("r0", SECRET, master.port, local_address=LAB_ROBOT_ADDRESS)
        joined = await joins(robot)
        server = master.server
    assert joined >= REQUIRED_SHARE * JOIN_ATTEMPTS, f"{joined} of {JOIN_ATTEMPTS} joins"
    # Every place was taken: the flood's newcomers were refused, the robot took a flood
    # connection's place.
    assert server.refused_connections > 0 and server.evicted_connections > 0
