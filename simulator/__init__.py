"""The simulator that stands in for the hardware: a kinematic arena of Thymio II robots.

* :mod:`simulator.scenarios` - every world parameter (``WorldConfig``) and the named scenarios of
  the paper (``basic``, ``boxes``, ``gradient``) with overrides: ``scenario_config(name, ...)``;
* :mod:`simulator.world` - the vectorised world: motion, contacts, boxes, sensors (``World``);
* :mod:`simulator.body` - the drivers' ``Body`` over a shared world, in lockstep or real time
  (``SimSwarm``, ``SimBody``, ``LockstepClock``);
* :mod:`simulator.metrics` - the paper's behaviour metrics from recorded poses;
* :mod:`simulator.render` - pictures of a world (needs the optional matplotlib);
* :mod:`standins.fake_i2c`, :mod:`standins.fake_medulla` - fake devices behind the real drivers.

Nothing is imported here, so that each part costs only what it uses.
"""
