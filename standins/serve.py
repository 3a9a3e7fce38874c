"""``surprise-sim-robots``: simulated Thymios served over D-Bus, as in a lab, for separate agents.

::

    surprise-sim-robots --scenario basic --robots 4 --seed 1 --dir robots \\
        [--ids thymio-1,thymio-2,...] [--backend sim|playground] [--arena 1.0] \\
        [--master-host 127.0.0.1] [--master-port 7474] [--secret-file secret.key] \\
        [--reconnect-initial 0.5] [--reconnect-max 30] [--speed-scale 265] [--poses]

Each robot is served on a private ``dbus-daemon`` of its own, by one of two backends:

- ``sim`` (the default): one process holds a real-time world (:class:`~simulator.body.SimSwarm`,
  one step every 0.1 s of wall-clock time) and serves each of its robots as an
  asebamedulla-like service (:mod:`standins.medulla_model`).
- ``playground``: Aseba Playground's simulated Thymios, each behind Debian's real
  ``asebamedulla``, restarted like systemd's ``Restart=always`` (:mod:`standins.playground`), in
  the scenario's arena with walls: a lab day rehearsed without robots (docs/rehearsal.md). Its
  files (world, ground texture, every process's log) are in ``DIR/playground``.

In ``--dir`` it writes one ready-to-use agent configuration per robot, ``agent-<id>.yaml``
(the robot's id, ``sim-<i>`` unless ``--ids`` names them as a lab's master file does, the
master's address and secret, ``body.thymio.bus`` set to that robot's bus, and the Thymio
settings the backend needs), so that ``surprise-agent --config DIR/agent-<id>.yaml`` drives the
simulated robot with the real Thymio driver, in its own process, exactly as on a robot's Pi.
``DIR/robots.json`` announces the running service (process id, each robot's bus and
configuration); it is written once every robot is served and removed on exit. The command lines
to start the agents are printed.

It runs until SIGTERM or SIGINT, then stops every process it started (the world, Playground,
the medullas, every dbus-daemon; exit code 0). With ``--poses`` (``sim`` only) the poses of every
step are written to ``DIR/poses.npy`` (shape: steps + 1, robots, 3 for x, y, theta) on exit.

Exit codes: 0 stopped by a signal; 1 could not start (no dbus-daemon, no Aseba, DIR not writable,
another server on DIR) or Playground ended by itself; 2 bad arguments (argparse's usage error),
or the ``robot`` extra (``dbus-fast``) is not installed: the D-Bus modules are imported only once
the arguments are parsed, so ``--help`` works without it.

Without ``--secret-file``, ``DIR/secret.key`` is used and created with a random secret if
absent; the master's ``secret_file`` must name the same file. A robot's force and light sensors
(``boxes``, ``gradient``) are emulated I2C chips on a Unix socket of its own
(:class:`~standins.i2c_bridge.RobotBridges`), which its agent configuration and robots.json name.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import os
import re
import shutil
import signal
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from drivers.config import SPEED_SCALE
from minimize_surprise.errors import ConfigError
from minimize_surprise.files import write_atomic, write_new_secret
from minimize_surprise.sensors import FORCE_SENSORS, GROUND_SENSORS, IR_SENSORS, LIGHT_SENSORS
from minimize_surprise.wire import DEFAULT_PORT
from simulator.arenas import load_arena
from simulator.scenarios import SCENARIOS, WorldConfig, scenario_config
from standins.agent_files import (
    HEADER,
    PLAYGROUND_THYMIO,
    SIM_THYMIO,
    robot_id,
    write_agent_config,
)
from standins.i2c_bridge import RobotBridges
from standins.playground import PLAYGROUND_SPEED_SCALE, speed_scale_for

if TYPE_CHECKING:
    from standins.medulla_model import SignallingWorld
    from standins.playground import PlaygroundLab

__all__ = ["EXIT_FAILURE", "EXIT_OK", "EXIT_USAGE", "main", "serve"]

log = logging.getLogger("standins.serve")

#: Exit code after SIGTERM or SIGINT: stopping is the normal end of a server.
EXIT_OK = 0
#: Exit code when the robots cannot be served (no dbus-daemon, DIR unusable).
EXIT_FAILURE = 1
#: Exit code for bad arguments (argparse's own code for usage errors).
EXIT_USAGE = 2

#: The master's default TCP port.
DEFAULT_MASTER_PORT = DEFAULT_PORT
ROBOTS_FILE = "robots.json"
POSES_FILE = "poses.npy"
SECRET_FILE = "secret.key"
#: The subdirectory of DIR with the playground backend's files.
PLAYGROUND_DIR = "playground"
BACKENDS = ("sim", "playground")
#: The agents' reconnection backoff, as ``robot_agent.config.BackoffConfig`` defaults it.
RECONNECT_INITIAL = 0.5
RECONNECT_MAX = 30.0

_SIGNALS = (signal.SIGTERM, signal.SIGINT)
#: What to install when the D-Bus modules are missing.
ROBOT_EXTRA = "pip install -e '.[robot]'"
_SERVED_SENSORS = frozenset(IR_SENSORS + GROUND_SENSORS + FORCE_SENSORS + LIGHT_SENSORS)


def _ids(text: str) -> list[str]:
    ids = [part.strip() for part in text.split(",")]
    for robot in ids:
        if not re.fullmatch(r"[A-Za-z0-9_.-]{1,64}", robot):
            raise argparse.ArgumentTypeError(
                f"{robot!r} is no robot id (letters, digits, '_', '.', '-'; at most 64)"
            )
    if len(set(ids)) != len(ids):
        raise argparse.ArgumentTypeError(f"the ids repeat: {text}")
    return ids


def _positive(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text}")
    return value


def _arena(text: str) -> float | str:
    # A number is the square carpet's side (as before arenas were files); else a name or a path.
    try:
        return _positive(text)
    except ValueError:
        return text


def _count(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected at least 1, got {text}")
    return value


def _port(text: str) -> int:
    value = int(text)
    if not 1 <= value <= 65535:
        raise argparse.ArgumentTypeError(f"expected a TCP port 1..65535, got {text}")
    return value


def servable_scenarios() -> tuple[str, ...]:
    """The scenarios whose robots carry only sensors this command serves: the Thymio's own (IR
    and ground) over D-Bus, the force and light sensors as emulated I2C chips over a bridge."""
    return tuple(
        name for name in SCENARIOS if set(scenario_config(name).sensors) <= _SERVED_SENSORS
    )


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="surprise-sim-robots",
        description="Serve simulated Thymios over D-Bus (one private bus each, real time) for "
        "separate surprise-agent processes, and write their configurations.",
    )
    parser.add_argument(
        "--scenario",
        default="basic",
        choices=servable_scenarios(),
        help="the world (default: basic; force and light sensors as emulated I2C chips)",
    )
    parser.add_argument(
        "--backend",
        default="sim",
        choices=BACKENDS,
        help="sim: this process simulates the world; playground: Aseba Playground's Thymios "
        "behind real asebamedulla processes (default: sim)",
    )
    parser.add_argument("--robots", type=_count, help="number of robots (default: the scenario's)")
    parser.add_argument(
        "--ids",
        type=_ids,
        metavar="ID,ID,...",
        help="the robots' ids, e.g. the lab's thymio-1,thymio-2,thymio-3,thymio-4, so that the "
        "lab's master.yaml is rehearsed as it is (default: sim-0, sim-1, ...; sets --robots)",
    )
    parser.add_argument(
        "--arena",
        type=_arena,
        metavar="ARENA",
        help="the arena: a shipped one's name (e.g. real-objects), an arena file, or the side "
        "of the scenario's square carpet in metres (default: the scenario's own)",
    )
    parser.add_argument("--seed", type=int, default=0, help="the world's seed (default: 0)")
    parser.add_argument(
        "--dir", required=True, type=Path, help="where the agent configurations are written"
    )
    parser.add_argument("--master-host", default="127.0.0.1", help="default: 127.0.0.1")
    parser.add_argument(
        "--master-port", type=_port, default=DEFAULT_MASTER_PORT, help="default: 7474"
    )
    parser.add_argument(
        "--secret-file",
        type=Path,
        help=f"the shared secret's file (default: DIR/{SECRET_FILE}, created if absent)",
    )
    parser.add_argument(
        "--reconnect-initial",
        type=_positive,
        default=RECONNECT_INITIAL,
        help=f"the agents' first reconnection delay in seconds (default: {RECONNECT_INITIAL})",
    )
    parser.add_argument(
        "--reconnect-max",
        type=_positive,
        default=RECONNECT_MAX,
        help=f"the agents' longest reconnection delay in seconds (default: {RECONNECT_MAX:g})",
    )
    parser.add_argument(
        "--speed-scale",
        type=_positive,
        help=f"motor units for full speed, in the robots and their configs (default: "
        f"{SPEED_SCALE:g} with sim, {PLAYGROUND_SPEED_SCALE:g} with playground: its Thymios "
        "drive the lab's 10.6 cm/s at full speed)",
    )
    parser.add_argument(
        "--poses",
        action="store_true",
        help=f"write every step's poses to DIR/{POSES_FILE} (sim only)",
    )
    parser.add_argument(
        "--log-level",
        default="INFO",
        type=str.upper,
        choices=["DEBUG", "INFO", "WARNING", "ERROR"],
        help="log verbosity (default: INFO)",
    )
    return parser


def _secret_file(given: Path | None, directory: Path) -> Path:
    if given is not None:
        path = given.expanduser().resolve()
        if not path.is_file():
            log.warning("the secret file %s does not exist (yet); the agents need it", path)
        return path
    path = directory / SECRET_FILE
    if not path.exists():
        # As `surprise-master secret` writes one: only the owner may read it.
        write_new_secret(path)
        log.info("wrote a new shared secret to %s", path)
    return path


def _running_server(directory: Path) -> int | None:
    """The process id of a live server that announced itself in ``directory``, if any."""
    try:
        pid = int(json.loads((directory / ROBOTS_FILE).read_text(encoding="utf-8"))["pid"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if pid == os.getpid():
        return None
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return None
    except PermissionError:
        return pid  # alive, someone else's
    return pid


def _prepare_dir(directory: Path) -> None:
    directory.mkdir(parents=True, exist_ok=True)
    other = _running_server(directory)
    if other is not None:
        raise RuntimeError(f"{directory} is served by another surprise-sim-robots (pid {other})")
    # Configurations of an earlier server name dead buses: an agent started on one would only
    # fail to connect, so they go.
    for stale in directory.glob("agent-*.yaml"):
        with contextlib.suppress(OSError):
            if stale.read_text(encoding="utf-8").startswith(HEADER):
                stale.unlink()
    with contextlib.suppress(FileNotFoundError):
        (directory / ROBOTS_FILE).unlink()


def _announce(args: argparse.Namespace, info: dict[str, Any], scenario: str) -> None:
    robots = info["robots"]
    kind = "Aseba Playground Thymios" if args.backend == "playground" else "simulated Thymios"
    print(
        f"surprise-sim-robots: {len(robots)} {kind} of scenario {scenario} "
        f"(seed {args.seed}) in real time, master {args.master_host}:{args.master_port}",
        flush=True,
    )
    for robot in robots:
        port = robot.get("medulla_port")
        medulla = f", asebamedulla on TCP {port}" if port else ""
        bridge = robot.get("i2c_bridge")
        i2c = f", I2C bridge {bridge}" if bridge else ""
        print(f"  {robot['robot_id']}: D-Bus {robot['bus']}{medulla}{i2c}", flush=True)
    if "i2c" in info:
        print(f"  {info['i2c']}", flush=True)
    print("start one agent per robot (each in its own terminal, or with &):", flush=True)
    for robot in robots:
        print(f"  surprise-agent --config {robot['config']}", flush=True)
    print(f"stop with Ctrl-C or: kill {os.getpid()}", flush=True)


async def serve(args: argparse.Namespace) -> int:
    """Serve the robots until SIGTERM or SIGINT; returns the exit code.

    Must run in the main thread (signal handlers can only be set there). Needs ``dbus-fast``
    (the ``robot`` extra).
    """
    overrides: dict[str, Any] = {}
    if args.ids and args.robots is not None and args.robots != len(args.ids):
        print(
            f"surprise-sim-robots: --robots {args.robots} but --ids names {len(args.ids)}",
            file=sys.stderr,
        )
        return 2
    if args.ids:
        args.robots = len(args.ids)
    if args.robots is not None:
        overrides["robots"] = args.robots
    arena = None
    if isinstance(args.arena, float):
        overrides["arena_side"] = args.arena
    try:
        if isinstance(args.arena, str):
            arena = load_arena(args.arena)
        config = scenario_config(args.scenario, overrides, arena=arena)
    except ConfigError as exc:
        print(f"surprise-sim-robots: {exc}", file=sys.stderr)
        return EXIT_USAGE
    playground = args.backend == "playground"
    if args.speed_scale is None:
        args.speed_scale = speed_scale_for(config.max_speed) if playground else SPEED_SCALE
    directory: Path = args.dir.expanduser().resolve()
    try:
        _prepare_dir(directory)
        secret_file = _secret_file(args.secret_file, directory)
    except (OSError, RuntimeError) as exc:
        print(f"surprise-sim-robots: {exc}", file=sys.stderr)
        return EXIT_FAILURE

    loop = asyncio.get_running_loop()
    task = asyncio.current_task()
    assert task is not None
    received: list[int] = []

    def on_signal(signum: int) -> None:
        if not received:
            log.info("received %s: stopping", signal.Signals(signum).name)
            task.cancel()
        received.append(signum)

    for sig in _SIGNALS:
        loop.add_signal_handler(sig, on_signal, sig)
    world: SignallingWorld | None = None
    announced = False
    try:
        async with contextlib.AsyncExitStack() as stack:
            info: dict[str, Any] = {
                "pid": os.getpid(),
                "backend": args.backend,
                "scenario": args.scenario,
                "seed": args.seed,
                "dt": config.dt,
                "arena": None if arena is None else arena.name,
                "arena_side": config.arena_side,
                "speed_scale": args.speed_scale,
                "master": {"host": args.master_host, "port": args.master_port},
                "secret_file": str(secret_file),
            }
            lab: PlaygroundLab | None = None
            if playground:
                lab = await _serve_playground(stack, args, config, directory, secret_file, info)
            else:
                world = await _serve_sim(stack, args, config, directory, secret_file, info)
            text = json.dumps(info, indent=2) + "\n"
            write_atomic(directory / ROBOTS_FILE, text.encode("utf-8"), durable=False)
            announced = True
            place = args.scenario + (f" in {arena.name}" if arena is not None else "")
            _announce(args, info, place)
            if lab is None:
                await asyncio.Event().wait()  # until a signal cancels this task
                return EXIT_OK  # not reached: the wait ends only by cancellation
            code = await lab.watch()  # until a signal cancels this task, or Playground ends
            print(
                f"surprise-sim-robots: asebaplayground ended by itself (exit code {code}): every "
                f"robot is gone; see its log in {lab.directory}",
                file=sys.stderr,
            )
            return EXIT_FAILURE
    except asyncio.CancelledError:
        if not received:
            raise
        # Our own signal handler cancelled us: that is the normal way to stop.
        task.uncancel()
        if world is not None:
            log.info("stopped after %d steps (%.1f s of world time)", world.steps, world.time)
        return EXIT_OK
    except (OSError, RuntimeError, TimeoutError) as exc:
        # e.g. dbus-daemon or Aseba missing, or a robot that never came up
        print(f"surprise-sim-robots: cannot serve the robots: {exc}", file=sys.stderr)
        return EXIT_FAILURE
    finally:
        for sig in _SIGNALS:
            loop.remove_signal_handler(sig)
        if announced:
            with contextlib.suppress(OSError):
                (directory / ROBOTS_FILE).unlink()
        if args.poses and world is not None:
            _save_poses(directory / POSES_FILE, world)


async def _serve_sim(
    stack: contextlib.AsyncExitStack,
    args: argparse.Namespace,
    config: WorldConfig,
    directory: Path,
    secret_file: Path,
    info: dict[str, Any],
) -> SignallingWorld:
    """Serve a real-time world's robots (entered on ``stack``), their entries in ``info``."""
    # Imported here, not at the top: they need dbus-fast, which --help must do without.
    from simulator.body import SimSwarm
    from simulator.warmup import warm_up
    from standins.fake_medulla import private_bus
    from standins.medulla_model import SignallingWorld, SimThymio, serve_sim_thymio

    # Compile (or load) the world's kernels before any robot is served: a first step that
    # compiles would stall the real-time world for seconds, and the agents' reads time out.
    await asyncio.to_thread(warm_up)
    world = SignallingWorld(config, args.seed, record=args.poses)
    bridges = await stack.enter_async_context(RobotBridges(config.sensors))
    if bridges.needed:
        info["i2c"] = bridges.readings("sim")
    robots = []
    for index in range(world.n_robots):
        bus = await stack.enter_async_context(private_bus())
        model = SimThymio(world, index, speed_scale=args.speed_scale)
        await stack.enter_async_context(serve_sim_thymio(bus, model))
        parts = await bridges.serve_world(robot_id(index, args.ids), world, index)
        what = f"simulated Thymio {index} of scenario {args.scenario}, seed {args.seed}"
        robots.append(
            write_agent_config(args, directory, index, bus, secret_file, what, SIM_THYMIO, parts)
        )
    # The exit stack stops the world before the services hang up and the buses go.
    await stack.enter_async_context(SimSwarm(world, realtime=True))
    info["robots"] = robots
    return world


async def _serve_playground(
    stack: contextlib.AsyncExitStack,
    args: argparse.Namespace,
    config: WorldConfig,
    directory: Path,
    secret_file: Path,
    info: dict[str, Any],
) -> PlaygroundLab:
    """Start Playground and a medulla per robot (entered on ``stack``), their entries in
    ``info``."""
    from standins.playground import PROGRAMS, Arena, PlaygroundLab

    for program in PROGRAMS:
        if shutil.which(program) is None:
            package = "dbus-daemon" if program == "dbus-daemon" else "aseba"
            raise RuntimeError(f"{program} is not installed (apt-get install {package})")
    arena = Arena.of(config, args.seed)
    lab = await stack.enter_async_context(PlaygroundLab(directory / PLAYGROUND_DIR, arena))
    assert lab.playground is not None and lab.world_bus is not None
    bridges = await stack.enter_async_context(RobotBridges(config.sensors))
    if bridges.needed:
        info["i2c"] = bridges.readings("playground")
    robots = []
    for robot in lab.robots:
        # Enki has no blade and no lamp: an unloaded blade, the scenario's uniform light.
        parts = await bridges.serve_constant(robot_id(robot.index, args.ids), config.light_uniform)
        what = (
            f"Aseba Playground Thymio {robot.index} of scenario {args.scenario}, seed "
            f"{args.seed}, behind asebamedulla"
        )
        bus = robot.bus.address
        entry = write_agent_config(
            args, directory, robot.index, bus, secret_file, what, PLAYGROUND_THYMIO, parts
        )
        entry.update(robot_port=robot.robot_port, medulla_port=robot.medulla.port)
        robots.append(entry)
    info["robots"] = robots
    info["playground"] = {
        "pid": lab.playground.pid,
        "world": str(lab.playground.world),
        "bus": lab.world_bus.address,
        "directory": str(lab.directory),
    }
    return lab


def _save_poses(path: Path, world: SignallingWorld) -> None:
    try:
        np.save(path, world.recorded_poses())
    except OSError as exc:
        log.error("cannot write %s: %s", path, exc)
    else:
        log.info("wrote the poses of %d steps to %s", world.steps, path)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``surprise-sim-robots``; returns the exit code."""
    parser = _parser()
    args = parser.parse_args(argv)
    if args.poses and args.backend != "sim":
        parser.error("--poses needs --backend sim (Playground's poses are on its D-Bus)")
    try:
        import dbus_fast  # noqa: F401  # the D-Bus services need it; --help does not
    except ImportError:
        print(
            "surprise-sim-robots: serving robots over D-Bus needs dbus-fast, the robot extra: "
            f"{ROBOT_EXTRA}",
            file=sys.stderr,
        )
        return EXIT_USAGE
    # Logs go to stderr: stdout carries the announcement, which scripts may read.
    logging.basicConfig(
        stream=sys.stderr,
        level=args.log_level,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
    )
    return asyncio.run(serve(args))


if __name__ == "__main__":
    sys.exit(main())
