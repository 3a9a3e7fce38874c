"""The simulator: a kinematic arena of Thymio II robots, and the swarm's compiled engine.

* :mod:`simulator.arenas` - arenas as files (``Arena``: floor, rim, walls, boxes, start, light)
  and the shipped ones (``basic``, ``boxes``, ``gradient``, ``real-objects``): ``load_arena``;
* :mod:`simulator.scenarios` - every world parameter (``WorldConfig``) and the named scenarios of
  the paper (``basic``, ``boxes``, ``gradient``: an arena and its robots) with overrides:
  ``scenario_config(name, ...)``;
* :mod:`simulator.placement` - where robots and boxes start at a reset;
* :mod:`simulator.experiment` - an experiment's world and safety layer in simulation: its
  scenario in its setting (``minimize_surprise.settings`` holds what each setting gives);
* :mod:`simulator.physics` - motion, contacts, boxes and sensors as compiled kernels;
* :mod:`simulator.world` - the world stepped one step at a time (``World``);
* :mod:`simulator.engine` - whole evaluations of a swarm in one compiled loop (``Swarm``);
* :mod:`simulator.events` - what an experiment's events (the light moves, boxes come and go, a
  wall appears, robots leave or join) do to a world, and which an arena refuses;
* :mod:`simulator.body` - the drivers' ``Body`` over a shared world, in lockstep or real time
  (``SimSwarm``, ``SimBody``, ``LockstepClock``);
* :mod:`simulator.battery` - a simulated robot's battery, for the lab's battery pauses;
* :mod:`simulator.metrics` - the paper's behaviour metrics from recorded poses;
* :mod:`simulator.render` - pictures of a world (needs the optional matplotlib);
* :mod:`simulator.warmup` - compiles the kernels a run needs before it starts.

The stand-ins for the lab's hardware (fake medulla, fake I2C chips, served robots) are the
package :mod:`standins`. Nothing is imported here, so that each part costs only what it uses.
"""
