"""``surprise-master fleet status | stop | logs | inventory`` and ``surprise-master calibrate``
(docs/fleet.md): the parsers and the handlers (``inventory``'s in
:mod:`master_service.fleet_hosts`, calibrate's measuring in :mod:`master_service.calibrate`).

``status`` and ``stop`` reach the agents over their own protocol (:mod:`master_service.fleet`),
listening where the master file says; ``stop --run DIR`` goes through the master running that
run. ``logs`` is the one that needs ssh: each robot's journal (its agent's and asebamedulla's
units) is read with ``journalctl`` on the robot, over ``ssh`` to the inventory's address, and
written into the run directory's ``journals/`` (or ``--out``).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import shlex
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Final

from master_service.agent_server import CONNECT_TIMEOUT
from master_service.cli_args import add_timeout
from master_service.config import MasterConfig, load_master_config, required_secret
from master_service.fleet import fleet_status, fleet_stop, format_status
from master_service.fleet_hosts import fleet_inventory_command
from master_service.inventory import Inventory, load_inventory
from master_service.rundir import RunDir, RunDirError
from master_service.stopall import STOP_ANSWER_TIMEOUT, format_stop, request_stop

__all__ = [
    "JOURNALS",
    "JOURNAL_UNITS",
    "SSH_TIMEOUT",
    "add_fleet_parser",
    "calibrate_command",
    "fleet_logs",
    "journal_command",
]

#: Seconds one robot's ``ssh ... journalctl`` may take: the connection (ssh's own
#: ``ConnectTimeout`` below) and a day's journal of two units over Wi-Fi.
SSH_TIMEOUT: Final = 120.0
#: Seconds ssh may take to connect before it gives up on a robot that is off.
SSH_CONNECT_TIMEOUT: Final = 10
#: The units whose journal ``fleet logs`` gathers: the agent and the Thymio's D-Bus bridge.
JOURNAL_UNITS: Final = ("surprise-agent", "asebamedulla")
#: Where in the run directory (or ``--out``) the journals go, one ``ROBOT.log`` each.
JOURNALS: Final = "journals"


def add_fleet_parser(sub: argparse._SubParsersAction) -> None:
    """Add ``fleet`` and its commands ``status``, ``stop``, ``logs`` and ``inventory``."""
    fleet = sub.add_parser("fleet", help="the whole fleet at once: status, stop, logs, inventory")
    commands = fleet.add_subparsers(dest="fleet_command", required=True, metavar="COMMAND")

    def where(parser: argparse.ArgumentParser) -> None:
        parser.add_argument(
            "--config",
            type=Path,
            metavar="FILE",
            help="the master file: where the agents connect, the secret, and its inventory",
        )
        parser.add_argument(
            "--inventory",
            type=Path,
            metavar="FILE",
            help="the fleet's inventory (default: the one the master file names)",
        )

    status = commands.add_parser("status", help="each robot: reachable, software, battery, ...")
    where(status)
    add_timeout(status, CONNECT_TIMEOUT, "the agents to connect")
    status.add_argument("--json", action="store_true", help="print the rows as JSON")
    status.set_defaults(handler=status_command)

    stop = commands.add_parser("stop", help="stop every robot's motors now")
    where(stop)
    stop.add_argument(
        "--run",
        type=Path,
        metavar="DIR",
        help="a run is going: stop through its master, which pauses the run",
    )
    stop.add_argument(
        "--timeout",
        type=float,
        default=None,
        metavar="S",
        help=f"seconds to wait for the agents (default: {CONNECT_TIMEOUT:g}; with --run, for "
        f"the master's answer: {STOP_ANSWER_TIMEOUT:g})",
    )
    stop.set_defaults(handler=stop_command)

    logs = commands.add_parser("logs", help="gather each robot's journal over ssh")
    where(logs)
    logs.add_argument(
        "--since",
        required=True,
        metavar="T",
        help='journalctl\'s --since ("2025-03-01 14:00", "1 hour ago", "today")',
    )
    target = logs.add_mutually_exclusive_group(required=True)
    target.add_argument("--run", type=Path, metavar="DIR", help="into DIR/journals/")
    target.add_argument("--out", type=Path, metavar="DIR", help="into DIR/journals/")
    logs.set_defaults(handler=logs_command)

    inventory = commands.add_parser(
        "inventory", help="print the fleet file as an Ansible inventory (deploy/ansible)"
    )
    inventory.add_argument("file", type=Path, metavar="FLEET", help="the fleet file")
    inventory.set_defaults(handler=fleet_inventory_command)

    calibrate = sub.add_parser(
        "calibrate",
        help="measure one robot's floor, rim and wheels into the inventory",
        description="Measure ROBOT's ground readings on the arena's floor and rim (the safety "
        "layer's threshold between them) and, with --video, its wheels' real speeds from an "
        "overhead camera's film of a straight drive; write them into its inventory entry. "
        "The command says each step and waits for Enter (docs/fleet.md).",
    )
    calibrate.add_argument("robot", metavar="ROBOT", help="the robot's name in the inventory")
    where(calibrate)
    calibrate.add_argument(
        "--skip-ground", action="store_true", help="do not measure the floor and the rim"
    )
    calibrate.add_argument(
        "--video",
        type=Path,
        metavar="FILE",
        help="measure the wheels: the video the camera saves of the drive (the command asks "
        "you to start and stop filming)",
    )
    calibrate.add_argument(
        "--tracking",
        type=Path,
        metavar="FILE",
        help="the tracker's configuration (floor, corner markers, camera; docs/tracking.md)",
    )
    add_timeout(calibrate, CONNECT_TIMEOUT, "the robot's agent")
    calibrate.set_defaults(handler=calibrate_command)


def _config(args: argparse.Namespace) -> MasterConfig:
    if args.config is None:
        raise RunDirError(
            "--config FILE is needed: the master file says where the agents connect and "
            "gives the secret"
        )
    return load_master_config(args.config)


def _inventory(args: argparse.Namespace, config: MasterConfig | None) -> Inventory | None:
    if args.inventory is not None:
        return load_inventory(args.inventory)
    if config is not None and config.inventory is not None:
        return load_inventory(config.inventory)
    return None


def status_command(args: argparse.Namespace) -> int:
    """``fleet status``: 0 when every enabled robot answered, else 1."""
    config = _config(args)
    secret = required_secret(config, args.config)
    fleet = _inventory(args, config)
    if not args.json:
        print(f"asking the fleet (waiting up to {args.timeout:.0f} s for the agents)")
    rows = asyncio.run(fleet_status(config, secret, fleet, timeout=args.timeout))
    if args.json:
        print(json.dumps([row.to_json() for row in rows], indent=2))
    else:
        print(format_status(rows))
    return 0 if all(row.reachable for row in rows if row.enabled) else 1


def stop_command(args: argparse.Namespace) -> int:
    """``fleet stop``: 0 when every robot confirmed, 1 when one did not answer."""
    if args.run is not None:
        timeout = STOP_ANSWER_TIMEOUT if args.timeout is None else args.timeout
        event = request_stop(RunDir(args.run), timeout=timeout)
        print(f"the master of {args.run} stopped the robots and paused the run")
        print("stopped (confirmed): " + (", ".join(event.confirmed or []) or "none"))
        print("did not answer: " + (", ".join(event.unanswered or []) or "none"))
        if event.detail:
            print(f"  {event.detail}")
        print(f"let it go on: surprise-master continue {args.run}")
        return 0 if event.accepted else 1
    config = _config(args)
    secret = required_secret(config, args.config)
    fleet = _inventory(args, config)
    timeout = CONNECT_TIMEOUT if args.timeout is None else args.timeout
    print(f"stopping the fleet (waiting up to {timeout:.0f} s for the agents)", flush=True)
    outcome = asyncio.run(fleet_stop(config, secret, fleet, timeout=timeout))
    print(format_stop(outcome))
    return 0 if outcome.complete else 1


def journal_command(address: str, since: str) -> list[str]:
    """The ssh command that prints a robot's journal since ``since`` (ssh joins the remote
    words into one shell line, so each is quoted)."""
    remote = ["journalctl", "--no-pager", "-o", "short-iso", "--since", since]
    for unit in JOURNAL_UNITS:
        remote += ["-u", unit]
    return [
        "ssh",
        "-o",
        "BatchMode=yes",
        "-o",
        f"ConnectTimeout={SSH_CONNECT_TIMEOUT}",
        address,
        " ".join(shlex.quote(word) for word in remote),
    ]


def fleet_logs(fleet: Inventory, since: str, folder: Path) -> dict[str, str | None]:
    """Gather each enabled robot's journal into ``folder/ROBOT.log``; per robot None when it
    worked, else why not (one line). The robots are asked at once."""
    folder.mkdir(parents=True, exist_ok=True)
    robots = [robot for robot in fleet.robots if robot.enabled]

    def one(name: str, address: str) -> str | None:
        try:
            done = subprocess.run(
                journal_command(address, since),
                capture_output=True,
                timeout=SSH_TIMEOUT,
                check=False,
            )
        except FileNotFoundError:
            return "no ssh on this laptop"
        except subprocess.TimeoutExpired:
            return f"no journal within {SSH_TIMEOUT:g} s"
        if done.returncode != 0:
            error = done.stderr.decode(errors="replace").strip().splitlines()
            return f"ssh {address} exited {done.returncode}: {error[-1] if error else ''}"
        (folder / f"{name}.log").write_bytes(done.stdout)
        return None

    with ThreadPoolExecutor(max_workers=max(1, len(robots))) as pool:
        futures = {r.name: pool.submit(one, r.name, r.address) for r in robots}
        return {name: future.result() for name, future in futures.items()}


def logs_command(args: argparse.Namespace) -> int:
    """``fleet logs``: 0 when every enabled robot's journal was gathered, else 1."""
    config = None if args.config is None else load_master_config(args.config)
    fleet = _inventory(args, config)
    if fleet is None:
        raise RunDirError("--inventory FILE (or a master file naming one) lists the robots")
    base = args.run if args.run is not None else args.out
    if args.run is not None:
        RunDir(args.run).path.stat()  # a run directory that is not there is a mistake
    folder = Path(base) / JOURNALS
    outcome = fleet_logs(fleet, args.since, folder)
    for robot, why in outcome.items():
        if why is None:
            print(f"{robot}: {folder / (robot + '.log')}")
        else:
            print(f"{robot}: not gathered: {why}", file=sys.stderr)
    return 0 if all(why is None for why in outcome.values()) else 1


def calibrate_command(args: argparse.Namespace, ask: Any = None) -> int:
    """``surprise-master calibrate``: 0 when the calibration was measured and written. ``ask``:
    how each step waits for the person (default: Enter on the terminal)."""
    from master_service.calibrate import calibrate_robot, format_measured
    from master_service.calibration import write_calibration

    config = _config(args)
    secret = required_secret(config, args.config)
    path = args.inventory if args.inventory is not None else config.inventory
    if path is None:
        raise RunDirError("--inventory FILE (or a master file naming one) lists the robots")
    fleet = load_inventory(path)
    if args.skip_ground and args.video is None:
        raise RunDirError("nothing to measure: --skip-ground and no --video")
    wheels = None if args.video is None else _tracked_drive(args, fleet)

    async def enter(text: str) -> None:
        await asyncio.to_thread(input, f"{text}; then press Enter ")

    print(f"waiting up to {args.timeout:.0f} s for {args.robot}'s agent", flush=True)
    measured = asyncio.run(
        calibrate_robot(
            config,
            secret,
            fleet,
            args.robot,
            ask=enter if ask is None else ask,
            ground=not args.skip_ground,
            wheels=wheels,
            timeout=args.timeout,
        )
    )
    write_calibration(
        path,
        args.robot,
        ground_floor=measured.ground_floor,
        ground_rim=measured.ground_rim,
        wheels=measured.wheels,
    )
    print(format_measured(measured, Path(path)))
    return 0


def _tracked_drive(args: argparse.Namespace, fleet: Inventory) -> Any:
    # What follows the robot's marker in the saved video, from the drive's start flash on.
    import msgspec

    from master_service.calibrate import DRIVE_SECONDS
    from tracking.config import load_tracking_config
    from tracking.video import track_video

    entry = fleet.robot(args.robot)
    if entry is None or entry.marker is None:
        raise RunDirError(f"{args.robot} has no `marker` in the inventory: the camera needs it")
    config = load_tracking_config(args.tracking)
    robots = msgspec.structs.replace(config.robots, ids={args.robot: entry.marker})
    config = msgspec.structs.replace(config, robots=robots)
    return lambda: track_video(str(args.video), config, duration=DRIVE_SECONDS)
