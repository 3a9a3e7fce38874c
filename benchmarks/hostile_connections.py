"""Unauthenticated connections against the master: memory they hold, a flood during a run, and
robots rejoining during a flood of silent connections.

Three measurements, each with the master, the robots and the attacker in separate processes:

``held``: an attacker opens ``--held`` connections (default 1,000) and sends on each a Hello of
65,000 empty sensor names (the largest that fit a 64 KiB frame), then keeps them open for a few
seconds. Figures: the master's resident memory before, while the connections are held, and after
the attacker closed them; and how many connections the master closed before the attacker did.
Run with the master's default settings, and (when the master has ``max_pending_connections``)
again with the limit raised to the number of connections, so that the per-message bounds are
measured on their own, and with the largest Hello those bounds allow, which the master then
holds for the whole handshake.

``flood``: a run with 4 scripted robots (answering 10 ms after each Evaluate) goes on while an
attacker opens ``--flood`` connections (default 10,000) as fast as it can and holds them for a
few seconds. The master process runs with a soft limit of 1,024 file descriptors, a common
default. Figures: evaluations per second before, during and after the flood; the longest gap
between two checkpoints during the flood; whether the master's run ended with an error; how many
lines the master logged during the flood; how many of the attacker's connections the master
closed at once.

``rejoin``: ``--rejoin-clients`` clients (default 128, twice the master's default handshake
places) from 127.0.0.1 connect, say nothing, and connect again the moment the master closes them;
meanwhile a scripted robot joins (connect, Welcome, Bye) ``--rejoin`` times (default 200), with a
pause of 20 ms between two attempts, once from 127.0.0.2 (a robot of a lab, whose address is its
own) and once from 127.0.0.1 (the flood's address: robots behind one NAT, a simulated swarm).
Figures: the joins that succeeded, how long a successful join took (median), and how many
connections the flood opened meanwhile. The master runs with its default settings.

Works on any version of the master whose ``ScriptedRobot`` connects with ``connect()``, so the same
script measures before and after a change. Prints one figure a line as ``name: value unit``.
Run: ``python benchmarks/hostile_connections.py [--held N] [--flood N] [--rejoin N]
[--rejoin-clients N] [--only held,flood,rejoin]``
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import datetime
import functools
import inspect
import itertools
import multiprocessing
import os
import resource
import statistics
import struct
import tempfile
import time
from pathlib import Path
from typing import Any

import msgspec

SECRET = b"benchmark-secret"
#: Sensor names in the hostile Hello: its payload is just under 64 KiB.
HOSTILE_SENSORS = 65_000
#: Descriptor limit of the master in the flood: a common default soft limit.
MASTER_FD_LIMIT = 1024
#: Seconds of the run measured before the flood starts, the flood's hold time and the time after.
BEFORE_S, HOLD_S, AFTER_S = 4.0, 6.0, 4.0
#: Where the rejoin measurement's flood comes from, and the other address its robot may use.
FLOOD_ADDRESS, OTHER_ADDRESS = "127.0.0.1", "127.0.0.2"
#: A join slower than this counts as failed (a robot's own handshake deadline is 10 s).
JOIN_TIMEOUT_S = 10.0
#: Pause between two join attempts: a robot's backoff, shortened so the measurement is quick.
JOIN_PAUSE_S = 0.02


def hostile_hello() -> bytes:
    """A Hello frame whose sensors are 65,000 empty names (protocol version 1's layout)."""
    payload = msgspec.msgpack.encode(
        {
            "type": "hello",
            "robot_id": "r1",
            "software_version": "x",
            "protocol_version": 1,
            "sensors": [""] * HOSTILE_SENSORS,
        }
    )
    return struct.pack(">I", len(payload)) + payload


def largest_hello() -> bytes:
    """The largest Hello protocol version 2 accepts (every field at its bound): the most an
    unauthenticated peer can make the master hold for a whole handshake."""
    from minimize_surprise.wire import MAX_NAME_LENGTH, MAX_SENSORS, PROTOCOL_VERSION

    payload = msgspec.msgpack.encode(
        {
            "type": "hello",
            "robot_id": "r" * 64,
            "software_version": "v" * 64,
            "protocol_version": PROTOCOL_VERSION,
            "sensors": [f"{i:0{MAX_NAME_LENGTH}d}" for i in range(MAX_SENSORS)],
            "nonce": bytes(32),
        }
    )
    return struct.pack(">I", len(payload)) + payload


def _raise_fd_limit(soft: int | None = None) -> None:
    _, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    want = hard if soft is None else min(soft, hard)
    resource.setrlimit(resource.RLIMIT_NOFILE, (want, hard))


def _rss(pid: int) -> int:
    """Resident memory of process ``pid`` in bytes."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) * 1024
    raise RuntimeError("no VmRSS")


def _master_config(robots: int, evaluations: int, max_pending: int | None) -> Any:
    from master_service import MasterConfig
    from minimize_surprise.config import EvolutionConfig, ExperimentConfig

    experiment = ExperimentConfig(
        robots=robots,
        evaluation_steps=1,
        post_evaluation_steps=0,
        evolution=EvolutionConfig(evaluations=evaluations),
    )
    extra: dict[str, Any] = {}
    if max_pending is not None and "max_pending_connections" in MasterConfig.__struct_fields__:
        extra["max_pending_connections"] = max_pending
    return MasterConfig(
        experiment=experiment, port=0, round_margin=60.0, heartbeat_interval=2.0, **extra
    )


# ------------------------------------------------------------------------------- the master


def _master_process(queue: Any, stop: Any, kind: str, max_pending: int | None) -> None:
    _raise_fd_limit(MASTER_FD_LIMIT if kind == "flood" else 4 * 4096)
    asyncio.run(_master_main(queue, stop, kind, max_pending))


async def _master_main(queue: Any, stop: Any, kind: str, max_pending: int | None) -> None:
    from master_service import Master

    robots, evaluations = (4, 10**6) if kind == "flood" else (4, 10)
    config = _master_config(robots, evaluations, max_pending)
    progress: list[tuple[float, int]] = []
    with tempfile.TemporaryDirectory() as tmp:
        run_dir = Path(tmp) / "run"
        master = Master(config, run_dir, secret=SECRET)
        master.add_progress_listener(lambda p: progress.append((time.time(), p.evaluations)))
        error = None
        checkpoints: list[float] = []
        async with master:
            queue.put(("port", master.port, os.getpid()))
            run = asyncio.create_task(master.run()) if kind == "flood" else None
            checkpoint = run_dir / "checkpoint.json"
            last = 0.0
            while not stop.is_set():
                await asyncio.sleep(0.01)
                with contextlib.suppress(OSError):
                    mtime = checkpoint.stat().st_mtime
                    if mtime != last:
                        checkpoints.append(time.time())
                        last = mtime
                if run is not None and run.done():
                    break
            if run is not None:
                if run.done():
                    exc = run.exception()
                    error = None if exc is None else f"{type(exc).__name__}: {exc}"
                else:
                    run.cancel()
                    with contextlib.suppress(asyncio.CancelledError):
                        await run
        log = (run_dir / "master.log").read_text(errors="replace").splitlines()
    queue.put(("done", progress, checkpoints, error, log))


# ------------------------------------------------------------------------------- the robots


def _robots_process(port: int, count: int) -> None:
    async def main() -> None:
        from standins.scripted_robots import ScriptedRobot

        robots = [ScriptedRobot(f"r{i}", SECRET, port, index=i, delay=0.01) for i in range(count)]
        await asyncio.gather(*(r.connect() for r in robots))
        await asyncio.gather(*(r.closed.wait() for r in robots))

    asyncio.run(main())


# ------------------------------------------------------------------------------- the attacker


def _attacker_process(
    queue: Any, release: Any, port: int, count: int, payload: bytes, hold: float
) -> None:
    _raise_fd_limit()
    asyncio.run(_attack(queue, release, port, count, payload, hold))


async def _attack(
    queue: Any, release: Any, port: int, count: int, payload: bytes, hold: float
) -> None:
    writers: list[asyncio.StreamWriter] = []
    closed_by_master = 0
    failed = 0
    watchers: list[asyncio.Task[None]] = []

    async def watch(reader: asyncio.StreamReader) -> None:
        nonlocal closed_by_master
        with contextlib.suppress(OSError):
            while await reader.read(65536):
                pass
            closed_by_master += 1

    async def one() -> None:
        nonlocal failed
        try:
            reader, writer = await asyncio.open_connection("127.0.0.1", port)
        except OSError:
            failed += 1
            return
        if payload:
            writer.write(payload)
        writers.append(writer)
        watchers.append(asyncio.create_task(watch(reader)))

    started = time.time()
    for start in range(0, count, 500):
        await asyncio.gather(*(one() for _ in range(min(500, count - start))))
    opened = time.time()
    queue.put(("opened", started, opened))
    deadline = time.monotonic() + hold
    while time.monotonic() < deadline and not release.is_set():
        await asyncio.sleep(0.05)
    closed_before_release = closed_by_master
    for writer in writers:
        writer.transport.abort()
    for task in watchers:
        task.cancel()
    await asyncio.gather(*watchers, return_exceptions=True)
    queue.put(("closed", time.time(), closed_before_release, failed))


# ------------------------------------------------------------------------------- the rejoin


def _silent_flood_process(queue: Any, release: Any, port: int, clients: int) -> None:
    _raise_fd_limit()
    asyncio.run(_silent_flood(queue, release, port, clients))


async def _silent_flood(queue: Any, release: Any, port: int, clients: int) -> None:
    """``clients`` silent connections from FLOOD_ADDRESS, each reopened once the master closes
    it, until ``release``; reports how many connections were opened."""
    opened = 0
    stop = asyncio.Event()

    async def client() -> None:
        nonlocal opened
        while not stop.is_set():
            try:
                reader, writer = await asyncio.open_connection(
                    "127.0.0.1", port, local_addr=(FLOOD_ADDRESS, 0)
                )
            except OSError:
                await asyncio.sleep(0.01)
                continue
            opened += 1
            closed = asyncio.ensure_future(reader.read())
            stopped = asyncio.ensure_future(stop.wait())
            await asyncio.wait({closed, stopped}, return_when=asyncio.FIRST_COMPLETED)
            for task in (closed, stopped):
                task.cancel()
            await asyncio.gather(closed, stopped, return_exceptions=True)
            writer.transport.abort()

    tasks = [asyncio.create_task(client()) for _ in range(clients)]
    while opened < clients:
        await asyncio.sleep(0.01)
    queue.put(("flooding", opened))
    while not release.is_set():
        await asyncio.sleep(0.05)
    stop.set()
    await asyncio.gather(*tasks)
    queue.put(("stopped", opened))


def _rejoin_process(queue: Any, port: int, attempts: int, address: str) -> None:
    asyncio.run(_rejoin(queue, port, attempts, address))


async def _rejoin(queue: Any, port: int, attempts: int, address: str) -> None:
    from standins.scripted_robots import ScriptedRobot

    if "local_address" in inspect.signature(ScriptedRobot).parameters:
        robot = ScriptedRobot("r0", SECRET, port, local_address=address)
    else:  # an older ScriptedRobot: bind its connections in this process instead
        asyncio.open_connection = functools.partial(  # type: ignore[assignment]
            asyncio.open_connection, local_addr=(address, 0)
        )
        robot = ScriptedRobot("r0", SECRET, port)
    times = []
    for _ in range(attempts):
        started = time.monotonic()
        try:
            async with asyncio.timeout(JOIN_TIMEOUT_S):
                await robot.connect()
        except (OSError, EOFError, TimeoutError):
            pass
        else:
            times.append(time.monotonic() - started)
            await robot.close()
        await asyncio.sleep(JOIN_PAUSE_S)
    queue.put(("joined", times))


# ------------------------------------------------------------------------------- measurements


def _get(queue: Any, tag: str, timeout: float = 120.0) -> tuple[Any, ...]:
    item = queue.get(timeout=timeout)
    assert item[0] == tag, item
    return item[1:]


def measure_held(connections: int, max_pending: int | None, hello: bytes) -> dict[str, Any]:
    """Memory of the master while ``connections`` send ``hello`` and are held, and after."""
    context = multiprocessing.get_context("spawn")
    queue, stop, release = context.Queue(), context.Event(), context.Event()
    attacks = context.Queue()
    master = context.Process(target=_master_process, args=(queue, stop, "held", max_pending))
    master.start()
    port, pid = _get(queue, "port")
    time.sleep(0.5)
    before = _rss(pid)
    attacker = context.Process(
        target=_attacker_process,
        args=(attacks, release, port, connections, hello, 60.0),
    )
    attacker.start()
    _get(attacks, "opened")
    held = 0
    for _ in range(20):  # the master decodes what arrived; take the highest reading
        time.sleep(0.1)
        held = max(held, _rss(pid))
    release.set()
    _, closed_early, failed = _get(attacks, "closed")
    attacker.join()
    time.sleep(1.0)
    after = _rss(pid)
    stop.set()
    _get(queue, "done")
    master.join()
    return {
        "before": before,
        "held": held,
        "after": after,
        "closed_early": closed_early,
        "failed": failed,
    }


def _rate(progress: list[tuple[float, int]], start: float, end: float) -> float:
    inside = [n for t, n in progress if start <= t <= end]
    if len(inside) < 2:
        return 0.0
    return (inside[-1] - inside[0]) / (end - start)


def measure_flood(connections: int) -> dict[str, Any]:
    """A run under a flood of ``connections`` unauthenticated connections."""
    context = multiprocessing.get_context("spawn")
    queue, stop, release = context.Queue(), context.Event(), context.Event()
    attacks = context.Queue()
    master = context.Process(target=_master_process, args=(queue, stop, "flood", None))
    master.start()
    port, _ = _get(queue, "port")
    robots = context.Process(target=_robots_process, args=(port, 4))
    robots.start()
    time.sleep(1.0 + BEFORE_S)  # connecting, then the measured window before the flood
    attacker = context.Process(
        target=_attacker_process, args=(attacks, release, port, connections, b"", HOLD_S)
    )
    attacker.start()
    started, opened = _get(attacks, "opened")
    end, closed_early, failed = _get(attacks, "closed")
    attacker.join()
    time.sleep(AFTER_S)
    stop.set()
    progress, checkpoints, error, log = _get(queue, "done")
    master.join()
    robots.kill()
    robots.join()
    during = [t for t in checkpoints if started <= t <= end]
    # From the flood's start to its end: a master that stopped committing shows as one long gap.
    gaps = [b - a for a, b in itertools.pairwise([started, *during, end])]
    return {
        "before": _rate(progress, started - BEFORE_S, started),
        "during": _rate(progress, started, end),
        "after": _rate(progress, end, end + AFTER_S),
        "max_gap": max(gaps) if gaps else float("nan"),
        "checkpoints_during": len(during),
        "error": error,
        "log_lines_during": _log_lines_between(log, started, end + 1.0),
        "opened_s": opened - started,
        "closed_early": closed_early,
        "failed": failed,
    }


def measure_rejoin(attempts: int, clients: int, address: str) -> dict[str, Any]:
    """``attempts`` joins of a robot from ``address`` while ``clients`` silent connections from
    FLOOD_ADDRESS keep the master's handshake places taken."""
    context = multiprocessing.get_context("spawn")
    queue, stop, release = context.Queue(), context.Event(), context.Event()
    flood_queue, robot_queue = context.Queue(), context.Queue()
    master = context.Process(target=_master_process, args=(queue, stop, "held", None))
    master.start()
    port, _ = _get(queue, "port")
    flooder = context.Process(
        target=_silent_flood_process, args=(flood_queue, release, port, clients)
    )
    flooder.start()
    _get(flood_queue, "flooding")
    time.sleep(1.0)  # the flood settles: every place taken, closed ones coming back
    robot = context.Process(target=_rejoin_process, args=(robot_queue, port, attempts, address))
    robot.start()
    (times,) = _get(robot_queue, "joined", timeout=attempts * (JOIN_TIMEOUT_S + 1))
    robot.join()
    release.set()
    (opened,) = _get(flood_queue, "stopped")
    flooder.join()
    stop.set()
    _get(queue, "done")
    master.join()
    return {
        "joined": len(times),
        "median_s": statistics.median(times) if times else None,
        "opened": opened,
    }


def _log_lines_between(log: list[str], start: float, end: float) -> int:
    """Lines logged from ``start`` to ``end`` (epoch seconds), the run's progress lines aside.

    A line without a time stamp (a traceback's) belongs to the stamped line before it.
    """
    count = 0
    stamp = 0.0
    for line in log:
        with contextlib.suppress(ValueError):
            stamp = datetime.datetime.strptime(line[:23], "%Y-%m-%d %H:%M:%S,%f").timestamp()
        if start <= stamp <= end and " INFO evaluation " not in line:
            count += 1
    return count


def main() -> None:
    """Print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--held", type=int, default=1000)
    parser.add_argument("--flood", type=int, default=10_000)
    parser.add_argument("--rejoin", type=int, default=200)
    parser.add_argument("--rejoin-clients", type=int, default=128)
    parser.add_argument("--only", default="held,flood,rejoin", help="comma-separated")
    args = parser.parse_args()
    only = set(args.only.split(","))
    if "held" in only:
        _print_held(args.held)
    if "flood" in only:
        _print_flood(args.flood)
    if "rejoin" in only:
        _print_rejoin(args.rejoin, args.rejoin_clients)


def _print_held(connections: int) -> None:
    mib = 2**20
    from master_service import MasterConfig

    runs = [("default", None, hostile_hello())]
    if "max_pending_connections" in MasterConfig.__struct_fields__:
        runs += [
            ("uncapped", connections, hostile_hello()),
            ("largest_hello_uncapped", connections, largest_hello()),
        ]
    for label, cap, hello in runs:
        held = measure_held(connections, cap, hello)
        name = f"held_{connections}_{label}"
        print(f"{name}_master_rss_before: {held['before'] / mib:.1f} MiB")
        print(f"{name}_master_rss_held: {held['held'] / mib:.1f} MiB")
        print(f"{name}_master_rss_after_close: {held['after'] / mib:.1f} MiB")
        print(f"{name}_closed_by_master_while_held: {held['closed_early']} connections")
        print(f"{name}_connect_failures: {held['failed']} connections")


def _print_flood(connections: int) -> None:
    flood = measure_flood(connections)
    name = f"flood_{connections}"
    print(f"{name}_evaluations_before: {flood['before']:.1f} per s")
    print(f"{name}_evaluations_during: {flood['during']:.1f} per s")
    print(f"{name}_evaluations_after: {flood['after']:.1f} per s")
    print(f"{name}_checkpoints_during: {flood['checkpoints_during']} commits")
    print(f"{name}_longest_checkpoint_gap_during: {flood['max_gap'] * 1e3:.0f} ms")
    print(f"{name}_run_error: {flood['error'] or 'none'}")
    print(f"{name}_log_lines_during: {flood['log_lines_during']} lines")
    print(f"{name}_attacker_open_time: {flood['opened_s']:.2f} s")
    print(f"{name}_closed_by_master_while_held: {flood['closed_early']} connections")
    print(f"{name}_connect_failures: {flood['failed']} connections")


def _print_rejoin(attempts: int, clients: int) -> None:
    for label, address in (("other_address", OTHER_ADDRESS), ("flood_address", FLOOD_ADDRESS)):
        rejoin = measure_rejoin(attempts, clients, address)
        name = f"rejoin_{clients}_silent_robot_from_{label}"
        median = rejoin["median_s"]
        print(f"{name}_joined: {rejoin['joined']} of {attempts} attempts")
        print(f"{name}_median_join: {'-' if median is None else f'{median * 1e3:.1f}'} ms")
        print(f"{name}_flood_connections: {rejoin['opened']} connections")


if __name__ == "__main__":
    main()
