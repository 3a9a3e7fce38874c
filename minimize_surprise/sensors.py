"""Sensor names shared by the configuration, the bodies and the wire protocol.

The canonical order below is the order in which a complete robot reports its sensors. An
experiment chooses a subset by name, in any order; the networks see them in the experiment's order.
"""

from __future__ import annotations

#: Horizontal IR: five front sensors left to right, then the two rear ones (left, right).
IR_SENSORS: tuple[str, ...] = ("ir.f0", "ir.f1", "ir.f2", "ir.f3", "ir.f4", "ir.b0", "ir.b1")
#: Ground IR under the front of the robot, left and right.
GROUND_SENSORS: tuple[str, ...] = ("ground.0", "ground.1")
#: Force sensor behind the pushing blade (object-manipulation robots only).
FORCE_SENSORS: tuple[str, ...] = ("force",)
#: TSL45315 ambient light sensors on top of the robot (gradient arena only).
LIGHT_SENSORS: tuple[str, ...] = ("light.0", "light.1")

#: Every sensor the project knows, in canonical order.
ALL_SENSORS: tuple[str, ...] = IR_SENSORS + GROUND_SENSORS + FORCE_SENSORS + LIGHT_SENSORS


def check_sensor_names(names: list[str] | tuple[str, ...]) -> tuple[str, ...]:
    """Return ``names`` as a tuple after checking each is known and none repeats.

    Raises ``ValueError`` naming the first offending entry.
    """
    seen: set[str] = set()
    for name in names:
        if name not in ALL_SENSORS:
            raise ValueError(f"unknown sensor {name!r}; known sensors: {', '.join(ALL_SENSORS)}")
        if name in seen:
            raise ValueError(f"sensor {name!r} is listed twice")
        seen.add(name)
    return tuple(names)
