"""The fleet's inventory: one file that lists every robot of the lab (docs/fleet.md).

Each robot has its name (the robot id its agent announces), the address the laptop reaches its Pi
at (a host name or an IP, for ssh), its Thymio's Aseba node name, the id of the ArUco marker on
its top (for ``surprise-master track``), its calibration (optional; filled in later), whether it
is enabled and whether it is a spare. The master file names the inventory (``inventory:
fleet.yaml``); then the master admits the swarm's robots (the enabled ones that are not spares),
the preflight checks those and the enabled spares, and the tracker takes the markers from it.
Nothing else repeats what it lists.

Example::

    robots:
      - name: thymio-1
        address: thymio-1.local
        marker: 10
      - name: thymio-5
        address: 192.0.2.25
        marker: 14
        spare: true            # not in the swarm; ready to be swapped in

Every failure is one :class:`~minimize_surprise.errors.ConfigError` naming the file and the key
(``robots[2].marker``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Final

import msgspec

from drivers.config import PROGRAM_NODE
from minimize_surprise.config import Strict, decode, read_yaml
from minimize_surprise.errors import ConfigError
from minimize_surprise.wire import ROBOT_ID_PATTERN

__all__ = [
    "MAX_WHEEL_SCALE",
    "Calibration",
    "Inventory",
    "Robot",
    "load_inventory",
]

#: The largest wheel scale a calibration may hold: a wheel that needs twice its command to match
#: the other is a broken motor, not one to calibrate around.
MAX_WHEEL_SCALE: Final = 2.0

_RobotId = Annotated[str, msgspec.Meta(pattern=ROBOT_ID_PATTERN)]
# Normalised ground readings, as the agent's safety layer sees them (ground.0, ground.1).
_Unit = Annotated[float, msgspec.Meta(ge=0.0, le=1.0)]
_WheelScale = Annotated[float, msgspec.Meta(gt=0.0, le=MAX_WHEEL_SCALE)]
# A host name (RFC 1123 labels) or an IPv4/IPv6 address; no user@ and no port: ssh takes those
# from its own configuration.
_Address = Annotated[str, msgspec.Meta(pattern=r"^[A-Za-z0-9:.\[\]-]{1,253}$")]


class Calibration(Strict, frozen=True):
    """What one robot measured of its floor and its wheels (``surprise-master calibrate``, or by
    hand): every key optional, a missing one is not measured yet."""

    #: the ground sensors' normalised readings (ground.0, ground.1) on the arena's floor
    ground_floor: tuple[_Unit, _Unit] | None = None
    #: the ground sensors' normalised readings (ground.0, ground.1) on the arena's rim
    ground_rim: tuple[_Unit, _Unit] | None = None
    #: the left wheel's real speed per commanded speed (1: as commanded)
    wheel_left: _WheelScale = 1.0
    #: the right wheel's real speed per commanded speed (1: as commanded)
    wheel_right: _WheelScale = 1.0


class Robot(Strict, frozen=True):
    """One robot of the fleet."""

    #: the robot id: its agent's ``robot_id``, the run's CSV column
    name: _RobotId
    #: where the laptop reaches its Pi (host name or IP address, for ssh)
    address: _Address
    #: the Aseba node name of its Thymio (its agent's ``body.thymio.node``)
    node: Annotated[str, msgspec.Meta(min_length=1, max_length=64)] = PROGRAM_NODE
    #: the id of the ArUco marker on its top, for ``surprise-master track`` (``null``: none)
    marker: Annotated[int, msgspec.Meta(ge=0)] | None = None
    #: its floor's and wheels' measurements (``null``: not calibrated yet)
    calibration: Calibration | None = None
    #: false: out of service (repaired, lent out); the master, the preflight and the tracker
    #: leave it out
    enabled: bool = True
    #: true: not in the swarm, ready to replace one of its robots
    spare: bool = False


class Inventory(Strict, frozen=True):
    """The fleet: every robot of the lab, in the order the tables list them."""

    #: the robots, one entry each
    robots: list[Robot]

    def __post_init__(self) -> None:
        # ValueErrors here are turned into ConfigErrors naming the file; their text starts with
        # the key (as "robots[2].name") so that load_inventory can name it too.
        if not self.robots:
            raise ValueError("robots: the fleet lists no robot")
        names: dict[str, int] = {}
        markers: dict[int, int] = {}
        for index, robot in enumerate(self.robots):
            if robot.name in names:
                raise ValueError(
                    f"robots[{index}].name: '{robot.name}' is listed twice (also robots"
                    f"[{names[robot.name]}])"
                )
            names[robot.name] = index
            # Disabled robots too: a marker card of a robot away for repair still lies around.
            if robot.marker is not None:
                if robot.marker in markers:
                    other = self.robots[markers[robot.marker]].name
                    raise ValueError(
                        f"robots[{index}].marker: marker {robot.marker} is already {other}'s"
                    )
                markers[robot.marker] = index
            if robot.spare and not robot.enabled:
                raise ValueError(
                    f"robots[{index}].spare: {robot.name} is a spare but not enabled; a spare "
                    "must be ready to swap in (enable it, or drop `spare`)"
                )

    @property
    def swarm(self) -> list[str]:
        """The robots that form the swarm: enabled and not spares, in the file's order."""
        return [r.name for r in self.robots if r.enabled and not r.spare]

    @property
    def spares(self) -> list[str]:
        """The enabled spares, in the file's order."""
        return [r.name for r in self.robots if r.enabled and r.spare]

    @property
    def enabled(self) -> list[str]:
        """Every enabled robot, swarm and spares, in the file's order."""
        return [r.name for r in self.robots if r.enabled]

    def markers(self) -> dict[str, int]:
        """Each enabled robot's marker id (robots without one left out)."""
        return {r.name: r.marker for r in self.robots if r.enabled and r.marker is not None}

    def robot(self, name: str) -> Robot | None:
        """The entry named ``name``, None when the fleet has none."""
        return next((r for r in self.robots if r.name == name), None)


def load_inventory(path: str | Path) -> Inventory:
    """Read and check an inventory file; a :class:`ConfigError` names the file and the key."""
    path = Path(path)
    raw = read_yaml(path)
    try:
        return decode(raw, Inventory, file=path)
    except ConfigError as exc:
        # A check of Inventory.__post_init__ comes without a key; its text starts with it.
        key, sep, reason = exc.reason.partition(": ")
        if exc.key is None and sep and (key == "robots" or key.startswith("robots[")):
            raise ConfigError(reason, file=str(path), key=key) from None
        raise
