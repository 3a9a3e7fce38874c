"""The arena's physics and sensors as compiled kernels (docs/simulation.md).

Every function of this package is a :func:`minimize_surprise.jit.kernel`: loops over robots and
boxes on plain arrays, compiled by numba. :class:`~simulator.world.World` calls them one step at a
time (the simulated robots of ``surprise-master sim --engine agents``); the engine
(:mod:`simulator.engine`) calls them from its own compiled evaluation loop. One implementation, so
both give the same trajectories bit for bit.

State of one arena (arrays the caller owns): ``pose`` (N, 3) x, y, theta of each robot's wheel
axis centre; ``cmd`` (N, 2) normalised wheel speeds; ``force`` (N,) this step's force value;
``boxes`` (B, 2) box centres; ``pending`` (B,) boxes that may still overlap something. The
constants of a world are in a :class:`Geometry` and a :class:`Sensing` (see
:func:`simulator.world.compile_world`).

Models:

* Motion: the exact arc of constant wheel speeds over one step.
* Contacts, each step: robots push each other apart (half each) and are kept inside the walls;
  then robots push boxes and boxes push boxes, the box farther down a pushing chain giving way. A
  box held by a wall, or wedged between a robot and other boxes, cannot give way: the robot
  pushing it backs off instead. A robot still wedged among boxes stays where it was before the
  step and the boxes settle around it. Overlaps shallower than 10 um are left alone.
* Force: ``force_per_box`` for each box the robot's blade moved this step, directly or through a
  chain of boxes, capped at 1.
* Horizontal IR, two models: ``cone`` (Enki's Thymio II, the real robots' calibration): the
  nearest body or visible wall within a cone of half angle ``ir_aperture`` gives ``c / (d^2 + c)``
  below ``ir_range``; ``ray`` (Webots' Thymio II, the paper's simulation): the first body or
  visible wall on the sensor's axis, at its distance divided by its reflectance
  (``ir_robot_reflectance``, ``ir_wall_reflectance``), looked up in a distance -> value table,
  with Gaussian noise of ``ir_noise`` times the value.
* Ground: ``ground_carpet`` over the carpet, ``ground_outside`` beyond its edge, with Gaussian
  noise of ``ground_noise`` times the value.
* Light: a lamp's fall-off ``centre * (h^2 / (h^2 + r^2))^light_exponent`` from ``light_centre``
  under it to ``light_corner`` at the carpet's corners, or ``light_uniform`` everywhere.
* Noise: Gaussian ``noise`` on every value, from a counter-based generator keyed by (seed, step,
  robot, sensor), so a value never depends on who reads it when; then clipped to [0, 1].

Modules: :mod:`.model` (the constants, sensor geometry, noise), :mod:`.motion` (the step),
:mod:`.contacts` (walls, robots), :mod:`.boxes` (boxes, force), :mod:`.ir` (the IR models),
:mod:`.sensing` (every sensor), :mod:`.grid` (the cells that find neighbours in large swarms).
Everything public is here too: ``physics.sense``, ``physics.step_world``, ...
"""

from __future__ import annotations

from simulator.physics.grid import GRID_ROBOTS, grid_choice
from simulator.physics.ir import IR_CONE, IR_RAY
from simulator.physics.model import (
    GROUND_POSITIONS,
    IR_HEADINGS,
    IR_POSITIONS,
    Geometry,
    Sensing,
    gaussian,
)
from simulator.physics.motion import clamp_commands, step_world
from simulator.physics.sensing import SenseWork, ir_reach, sense, sense_work

__all__ = [
    "GRID_ROBOTS",
    "GROUND_POSITIONS",
    "IR_CONE",
    "IR_HEADINGS",
    "IR_POSITIONS",
    "IR_RAY",
    "Geometry",
    "SenseWork",
    "Sensing",
    "clamp_commands",
    "gaussian",
    "grid_choice",
    "ir_reach",
    "sense",
    "sense_work",
    "step_world",
]
