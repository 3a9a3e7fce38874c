"""The fleet's inventory as an Ansible inventory, for the provisioning playbook (docs/fleet.md).

``surprise-master fleet inventory fleet.yaml`` prints it; ``deploy/ansible/provision`` writes it
to a throw-away file before each run of the playbook, so the fleet file stays the one list and
the Ansible inventory is never edited by hand. Each robot becomes a host named by its robot id,
reached at its ``address``; the groups:

- ``robots``: every enabled robot, swarm and spares (what the playbook provisions: a spare must
  run the same software to be swapped in);
- ``swarm`` and ``spares``: the enabled robots in and out of the swarm;
- ``disabled``: robots away for repair, listed so that ``--limit`` can name them, but in no
  group the playbook targets.

Each host carries its Thymio's node name (``robot_node``, written into a new agent.yaml).
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

import yaml

from master_service.inventory import Inventory, load_inventory

__all__ = ["ansible_inventory", "fleet_inventory_command"]


def ansible_inventory(fleet: Inventory) -> dict[str, Any]:
    """The Ansible inventory (YAML format, as a dict) of ``fleet``."""

    def hosts(names: list[str]) -> dict[str, Any]:
        return {"hosts": {name: None for name in names}} if names else {}

    every: dict[str, Any] = {}
    for robot in fleet.robots:
        every[robot.name] = {"ansible_host": robot.address, "robot_node": robot.node}
    disabled = [r.name for r in fleet.robots if not r.enabled]
    return {
        "all": {
            "hosts": every,
            "children": {
                "robots": {"children": {"swarm": None, "spares": None}},
                "swarm": hosts(fleet.swarm),
                "spares": hosts(fleet.spares),
                "disabled": hosts(disabled),
            },
        }
    }


def fleet_inventory_command(args: argparse.Namespace) -> int:
    """``surprise-master fleet inventory FLEET``: print the Ansible inventory of FLEET."""
    fleet = load_inventory(args.file)
    sys.stdout.write(
        f"# Generated from {args.file} by `surprise-master fleet inventory`: edit that file.\n"
    )
    yaml.safe_dump(ansible_inventory(fleet), sys.stdout, sort_keys=False)
    return 0
