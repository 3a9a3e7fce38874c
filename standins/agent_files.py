"""The agent configurations ``surprise-sim-robots`` writes, one per served robot.

Each is a ready-to-use ``surprise-agent`` file (docs/separate-processes.md): the robot's id, the
master's address and secret, ``body.thymio`` on that robot's private bus with the settings its
backend needs, the I2C parts and their bridge's socket where the robot carries force or light
sensors (:mod:`standins.i2c_bridge`), safety profile ``stop`` and the reconnection backoff of
the command's options. Each starts with :data:`HEADER`, so that only these files are replaced by
a later server.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import yaml

from minimize_surprise.files import write_atomic

__all__ = [
    "HEADER",
    "PLAYGROUND_THYMIO",
    "RECONNECT_JITTER",
    "ROBOT_ID_PREFIX",
    "SIM_THYMIO",
    "agent_config",
    "robot_id",
    "write_agent_config",
]

#: Robot ids are ``sim-<index>``: they name CSV columns and trace files on the master.
ROBOT_ID_PREFIX = "sim-"
#: The first line of every agent configuration this command writes: only those are replaced.
HEADER = "# Written by surprise-sim-robots"
#: The agents' reconnection jitter, as ``robot_agent.config.BackoffConfig`` defaults it.
RECONNECT_JITTER = 0.25


def robot_id(index: int, ids: Sequence[str] | None = None) -> str:
    """The id of simulated robot ``index``: ``ids[index]`` when given (``--ids``), else
    ``sim-<index>``."""
    return ids[index] if ids else f"{ROBOT_ID_PREFIX}{index}"


def agent_config(
    args: argparse.Namespace,
    index: int,
    bus: str,
    secret_file: Path,
    thymio: dict[str, Any] | None = None,
    parts: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The agent configuration (plain data) of robot ``index`` served on ``bus``; ``thymio``
    adds to its ``body.thymio`` settings, ``parts`` to its ``body`` (the I2C parts and the
    bridge, :meth:`~standins.i2c_bridge.RobotBridges.body`)."""
    thymio = {"bus": bus, "speed_scale": args.speed_scale, **(thymio or {})}
    return {
        "robot_id": robot_id(index, args.ids),
        "master": {
            "host": args.master_host,
            "port": args.master_port,
            "secret_file": str(secret_file),
        },
        "body": {"thymio": thymio, **(parts or {})},
        "safety": {"profile": "stop"},
        "reconnect": {
            "initial": args.reconnect_initial,
            # The agent refuses max < initial; a short --reconnect-initial alone raises max.
            "max": max(args.reconnect_max, args.reconnect_initial),
            "jitter": RECONNECT_JITTER,
        },
    }


#: ``body.thymio`` of the sim backend's agents: no failsafe program, since the simulated Thymio
#: runs no Aseba code, and no medulla to restart.
SIM_THYMIO: dict[str, Any] = {}
#: ``body.thymio`` of the playground backend's agents, as on a lab's robot
#: (deploy/examples/agent-thymio-1.yaml): Playground's Thymios run the failsafe program, and an
#: agent ends a medulla that lost its robot, which the server restarts as systemd would
#: (docs/rehearsal.md).
PLAYGROUND_THYMIO: dict[str, Any] = {"failsafe": True, "restart_medulla": True}


def write_agent_config(
    args: argparse.Namespace,
    directory: Path,
    index: int,
    bus: str,
    secret_file: Path,
    what: str,
    thymio: dict[str, Any],
    parts: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Write robot ``index``'s agent configuration (``what`` the robot is, for its header); the
    robot's entry in robots.json."""
    path = directory / f"agent-{robot_id(index, args.ids)}.yaml"
    header = (
        f"{HEADER} (pid {os.getpid()}): {what}.\n"
        "# Valid while that process runs: the bus and any socket below are its own.\n"
    )
    data = agent_config(args, index, bus, secret_file, thymio, parts)
    text = yaml.safe_dump(data, sort_keys=False)
    # Readers (the tests, a script waiting for robots.json) see the whole file or none.
    write_atomic(path, (header + text).encode("utf-8"), durable=False)
    entry = {"robot_id": robot_id(index, args.ids), "index": index, "bus": bus, "config": str(path)}
    if parts:
        entry["i2c_bridge"] = parts["i2c_bridge"]
    return entry
