"""A simulated robot's battery: a voltage that falls while the robot drives, and a swap.

Not a model of a Li-ion cell: just enough to rehearse what a lab does when a battery runs low
(the master pauses the run and names the robot; a person swaps the battery and continues,
docs/runs.md). The voltage falls by ``drain_v_per_step`` for each control step the robot is
commanded, from ``full_v``; :meth:`SimBattery.swap` puts a full one in.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

__all__ = ["FULL_V", "SimBattery"]

#: A Thymio's Li-ion cell, fully charged.
FULL_V: Final = 4.2


@dataclass
class SimBattery:
    """The voltage of one simulated robot's battery (see the module docstring)."""

    drain_v_per_step: float = 0.0
    full_v: float = FULL_V
    #: the voltage now
    volts: float = FULL_V
    #: batteries put in by :meth:`swap`
    swaps: int = 0

    def __post_init__(self) -> None:
        if self.drain_v_per_step < 0 or self.full_v <= 0:
            raise ValueError("a battery drains by a non-negative amount from a positive voltage")
        self.volts = min(self.volts, self.full_v)

    def step(self) -> None:
        """One control step of driving."""
        self.volts = max(0.0, self.volts - self.drain_v_per_step)

    def swap(self) -> None:
        """A fresh battery."""
        self.volts = self.full_v
        self.swaps += 1
